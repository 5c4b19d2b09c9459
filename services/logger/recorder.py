"""Turn the tuning traffic into one MCAP file per run (no Zenoh in here).

A run starts with its first TuneProgress (phase ``start``) and ends with its TuneResult: at
once when the file already holds the run's samples up to the result's sim time, else once a
sample of that time is written or ``RESULT_GRACE`` s after the result (the result travels
from the tuner, the samples from the plant: the result can overtake the last of them). A
run whose tuner is gone ends "tuner lost": when the run's liveliness token
(``<prefix>/tune/<loop>/running``) vanished and no result followed within ``RESULT_GRACE``
s, or when the plant's watchdog restored the loop (status reason ``watchdog``) while no
token of the run was there. A watchdog status that still names a lease holder of the run,
or that comes while the run's token is alive (the tuner lives and will end its run with a
result), closes nothing. Should the tuner's result come after all (a tuner paused past the
grace, then resumed), the file is rewritten with it (``mcap_io.amend_run``): the tuner's
status, and ``late_result`` in the metadata.

A run's start while another run on the loop is open (live) waits: a tuner's run starts, and
waits for the loop's rest, before it asks for the lease, and a second tuner's run is refused
the lease while the first holds it. The waiting run is recorded from its start once the open
run ends, or once the plant's status shows the waiting run holding the loop (the open one
then ends "superseded", unless its result follows within ``RESULT_GRACE`` s); one that ends
before either has no file (``unrecorded_runs``).

Everything on the loop's keys in between goes into the file: process samples (those a
lockstep advance sends as one batch on ``pv_batch``, each as its own ``pv`` message, as the
plant would have sent it), status, every command, the tuner's progress, events and result.
Messages are validated against their model first; one that is not valid is counted and left
out (a batch whole).

**One run, one file.** A file holds only its run's messages, from the plant instance the run
tuned:

* The tuner's messages (progress, events, result) of other runs are left out.
* Plant instances are told apart by evidence, never by one sign alone: a status with reason
  ``start`` (a plant publishes it as it comes up), a status from another plant ``node``, a
  sample number or sim time that goes back (for a status, on the lockstep clock only: in
  realtime statuses and samples come from two threads and may cross). The loop's liveliness
  token vanishing (``<prefix>/plant/<loop>/alive``) drops the context kept so far; when the
  plant comes back, the first message either continues the numbering (the same plant,
  reached again) or shows a new instance. Once the plant instance changes, no more plant
  messages or commands go into a run that tuned the old one.
* A few recent messages are kept per loop because a sample can overtake the run's first
  progress message on another link; at the start they go into the file if they are of the
  present plant instance, came after the loop's previous run ended, and are not older (in
  sim time) than the run's start. A sample already written (its number not past the last
  one) is never written again.
* Replayed traffic (``autotune replay`` marks every message with the attachment
  ``{"replay": "<file name>"}``) is not recorded unless ``record_replays``; then each replay
  is its own stream, never mixed with live traffic, and its file says so in its metadata
  (``replay``) and its name (``…_<run id>_replay.mcap``, ``…_replay-2.mcap`` for another
  within the same second). A run id the logger already recorded live opens no second file.
  A replay has no liveliness token: its file is closed ``incomplete`` once nothing of it has
  come for ``REPLAY_SILENCE`` s of wall time (a replay cut short by Ctrl-C or a kill).
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import pydantic

from services.logger.mcap_io import RunWriter, amend_run, log_time_zero
from services.logger.record_form import recorded_payload
from shared import json_text, keys, wire
from shared.errors import ConfigError, one_line
from shared.messages import (
    COMMANDS,
    MAX_INCOMPLETE,
    IncompleteRun,
    LeaseCommand,
    LoopInfo,
    LoopStatus,
    Message,
    ProcessSample,
    ProcessSamples,
    TuneProgress,
    TuneResult,
    TunerEvent,
)

log = logging.getLogger("logger")

BUFFER = 4096  # recent messages kept per loop (pre-run context)
# kept instead while the loop is leased and no run on it has started here: a logger that fell
# behind (paused through a lockstep run) takes the run's samples from the plant's link before
# the run's start from the tuner's, thousands of them (4,683 seen, lost past BUFFER)
LEASED_BUFFER = 65536
RESULT_GRACE = 2.0  # s of wall time a run's result may trail the withdrawal of its token
# s of wall time without a message of a recorded replay's run that end its file, incomplete:
# a replay interrupted (Ctrl-C, a kill) left its file open and listed "recording" until the
# logger stopped (helper trial: 5.5 min). Beyond any pause of a replay: ``autotune replay``
# sends a message at least every sample time over its --rate, and waits at most its --wait
REPLAY_SILENCE = 60.0
FILE_METHODS = ("relay", "ramp", "step", "apply")  # what a run file's name may say
REMEMBERED_RUNS = 4096  # finished run ids kept, so that a repeated start opens no new file
# the latest live runs whose file could not be written whole, said in the logger's status (the
# client that ran one asks as its run ends: the latest are enough, and the status stays small)
INCOMPLETE_KEPT = 100

TUNER_MESSAGES = (TuneProgress, TunerEvent, TuneResult)
PLANT_MESSAGES = (ProcessSample, LoopStatus)
# what is recorded of a loop's keys, by their last chunk (besides its commands)
PLANT_LEAVES: dict[str, type[Message]] = {"pv": ProcessSample, "status": LoopStatus}
TUNE_LEAVES: dict[str, type[Message]] = {
    "progress": TuneProgress,
    "event": TunerEvent,
    "result": TuneResult,
}


def prepare_runs_dir(path: Path | str) -> Path:
    """The ``--runs`` directory, created (with its parents) if missing, and writable.

    ConfigError in one line naming ``--runs`` and the reason otherwise: a file there, a
    parent that is a file, no permission.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"--runs {path}: not a directory (a file of that name exists)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ConfigError(f"--runs {path}: cannot create it (a parent is a file)") from None
    except OSError as err:
        raise ConfigError(f"--runs {path}: cannot create it ({err.strerror or err})") from None
    try:
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as err:
        raise ConfigError(f"--runs {path}: cannot write there ({err.strerror or err})") from None
    return path


@dataclass
class Item:
    key: str
    model: type[Message]
    payload: bytes
    msg: Message
    t: float  # sim time, s: the message's own, else that of the loop's last timed message
    instance: int  # the plant instance it came from or went to (see Stream.instance)


@dataclass
class OpenRun:
    run_id: str
    loop: str
    method: str
    rule: str
    writer: RunWriter
    t_start: float
    started: str
    instance: int  # the plant instance this run tunes
    replay: str = ""  # the replayed file's name, "" for a live run
    request: str = ""
    info: str = ""
    samples: int = 0
    first_seq: int | None = None
    last_seq: int | None = None
    gaps: int = 0
    left_out: int = 0  # messages on the loop's keys that were not this run's (or repeated)
    plant_node: str = ""
    plant_changed: str = ""  # why the plant instance changed under the run, if it did
    lease_holders: set[str] = field(default_factory=set)
    lost: str = ""  # "token" (the run's token vanished) or "watchdog" (the plant restored)
    lost_at: float = 0.0  # wall clock (monotonic) of ``lost``
    last_t: float | None = None  # sim time of the last sample written
    ending: TuneResult | None = None  # the result, in the file, while samples catch up to it
    ending_at: float = 0.0  # wall clock (monotonic) the result came
    # wall clock (monotonic) the plant showed the run that waited behind this one holding
    # the loop: this one's result, if it comes within RESULT_GRACE, still closes its file
    superseded_at: float | None = None
    held: bool = False  # a plant status showed this run holding the loop
    heard_at: float | None = None  # wall clock (monotonic) of its last message written
    opened_at: float | None = None  # wall clock (monotonic) the run's file was opened
    ts: float | None = None  # the loop's sample time, s, from the run's request (its info)
    # samples left out as not the plant's: their sim time is not their number × ts
    inconsistent: int = 0


@dataclass
class Stream:
    """One loop's traffic: live, or one replayed file's (kept apart)."""

    loop: str
    replay: str = ""
    recent: deque[Item] = field(default_factory=lambda: deque(maxlen=BUFFER))
    run: OpenRun | None = None
    t: float = 0.0
    instance: int = 0  # plant instance counter: +1 on each piece of evidence of a new one
    node: str | None = None
    last_seq: int | None = None  # highest number of a sample or status (they share it)
    last_sample_seq: int | None = None
    last_sample: bytes = b""  # payload of the last sample (a repeat of it is a duplicate)
    last_t: float | None = None  # of the last sample
    plant_alive: bool | None = None  # the loop's liveliness token (None: not seen yet)
    run_token: bool | None = None  # the run's liveliness token (None: not seen yet)
    # the start of a run that came while another was open (live only): opened once that one
    # ends, or once the plant shows this one holding the loop (``_waiting_run``)
    waiting: Item | None = None


def _size_buffer(stream: Stream, status: LoopStatus) -> None:
    """The pre-run buffer: LEASED_BUFFER messages while the loop is leased with no run open
    (a run whose start has not come yet), BUFFER otherwise (its latest kept)."""
    size = LEASED_BUFFER if status.leased_by and stream.run is None else BUFFER
    if stream.recent.maxlen != size:
        stream.recent = deque(stream.recent, maxlen=size)


def _seq_at(t: float, ts: float) -> int:
    """The number of the plant's sample at sim time ``t`` (s), its sample time ``ts``: sample
    ``seq`` is at t = seq·T (the small slack: t read back from a float product)."""
    return math.floor(t / ts + 1e-6)


def _missed_head(t_start: float, first: ProcessSample) -> int:
    """Samples of a run's beginning missing before ``first``, the first of its samples
    written: those after the sample at its start's sim time ``t_start`` (a plant's sample
    ``seq`` is at t = seq·T). Why: a logger that fell behind (paused through a lockstep run)
    took thousands of the run's samples before its start message, the oldest left the
    pre-run buffer uncounted, and the file said 0 dropped."""
    if first.seq <= 0 or first.t <= 0:
        return 0
    ts = first.t / first.seq
    return max(0, first.seq - (_seq_at(t_start, ts) + 1))


def _sample_time(run: OpenRun) -> float | None:
    """The loop's sample time (s): from the run's samples (a plant's sample ``seq`` is at
    t = seq·T), else from the loop's info in the run's request; None if neither says."""
    if run.last_seq and run.last_t:
        return run.last_t / run.last_seq
    try:
        return LoopInfo.model_validate_json(run.info).sample_time
    except pydantic.ValidationError:
        return None


def replay_silence(run: OpenRun) -> float:
    """Wall s without a message that end a recorded replay's run: ``REPLAY_SILENCE``, or ten
    of its samples' gaps at the pace it has come at so far (a replay at --rate 1e-3 of a 1 s
    loop sends a sample every 1,000 s)."""
    ts = _sample_time(run)
    sim = (run.last_t or 0.0) - run.t_start
    wall = (run.heard_at or 0.0) - (run.opened_at or 0.0)
    if ts is None or sim <= 0 or wall <= 0:
        return REPLAY_SILENCE
    return max(REPLAY_SILENCE, 10.0 * ts * wall / sim)


def _missed_tail(run: OpenRun, result: TuneResult) -> int:
    """Samples of a run up to its result's sim time that never reached its file: those after
    the last one written (none written: after the sample at the run's start). Why: in a
    user's trial a lockstep run that a paused plant ended was recorded with its commands and
    none of the 7,800 samples its tuner took (not reproduced in 15 tries), and the file said
    0 dropped. Not counted where the plant instance changed under the run (its numbering is
    another's)."""
    if run.plant_changed:
        return 0
    ts = _sample_time(run)
    if ts is None or not math.isfinite(result.t / ts):
        return 0
    last = run.last_seq if run.last_seq is not None else _seq_at(run.t_start, ts)
    return max(0, round(result.t / ts) - last)


def _encoded(sample: ProcessSample) -> bytes:
    """A sample's JSON as the plant puts it on ``pv`` (``wire.encode``: the model's dump)."""
    return wire.encode(sample)


_SPACE = (b" ", b"\n", b"\t", b"\r")
_FIELDS = 7  # of a ProcessSample, each required: its JSON has exactly this many keys


def batch_elements(payload: bytes, n: int) -> list[bytes] | None:
    """The JSON texts of the ``n`` samples of a valid ProcessSamples ``payload``, each as the
    batch carries it (the plant's: what it puts on ``pv``), cut out of the payload rather
    than encoded again (a sixth of the logger's time per sample); None where the cut is not
    sure, for them to be encoded instead. Sure for a compact payload (no whitespace) with one
    key per field (2 + 7·n keys, counted by ``":``): the batch is valid, so every key is a
    field's, every string a loop id or a mode (no brace, bracket or colon in any: a
    duplicate key's dropped value, which pydantic does not check, would add keys), its one
    array is ``samples``, and ``},{`` appears in it only between two samples; there being
    n − 1 of them, each cut is at one."""
    if any(c in payload for c in _SPACE) or payload.count(b'":') != 2 + _FIELDS * n:
        return None
    start, end = payload.find(b"["), payload.rfind(b"]")
    if start < 0 or end <= start:
        return None
    parts = payload[start + 1 : end].split(b"},{")
    if len(parts) != n:
        return None
    if n == 1:
        return parts
    return [parts[0] + b"}", *(b"{" + p + b"}" for p in parts[1:-1]), b"{" + parts[-1]]


def model_for(prefix: str, key: str) -> tuple[str, type[Message]] | None:
    """(loop, model) of a key the logger records, or None."""
    plant = keys.parse_loop_key(prefix, key)
    if plant is not None:
        model = PLANT_LEAVES.get(plant[1])
        return (plant[0], model) if model is not None else None
    command = keys.parse_command(prefix, key)  # with or without the sender's user
    if command is not None and command[1] in COMMANDS:
        return command[0], COMMANDS[command[1]]
    tune = keys.parse_tune_key(prefix, key)
    if tune is not None:
        model = TUNE_LEAVES.get(tune[1])
        return (tune[0], model) if model is not None else None
    return None


class Recorder:
    """The logger's state: one Stream per loop (and per replayed file), one open file per run.

    ``clock`` (monotonic seconds) times the grace a run's result gets after its token
    vanished; tests pass their own.
    """

    def __init__(
        self,
        runs_dir: Path,
        prefix: str,
        flush_interval: float = 1.0,
        record_replays: bool = False,
        clock: Callable[[], float] = time.monotonic,
        namespace: str = "",
    ):
        self.runs_dir = prepare_runs_dir(runs_dir)
        self.prefix = prefix
        self.namespace = namespace  # the session's Zenoh namespace (keys are read without it)
        self.flush_interval = flush_interval
        self.record_replays = record_replays
        self.clock = clock
        self.streams: dict[tuple[str, str], Stream] = {}
        self.counts: Counter[str] = Counter()
        self.finished: list[Path] = []
        self._recorded: OrderedDict[str, None] = OrderedDict()  # live run ids with a file
        # live runs closed "tuner lost": their files, should the tuner's result come after all
        self._lost: OrderedDict[str, Path] = OrderedDict()
        self._lost_loop: dict[str, str] = {}  # their loops (``lost_runs``)
        # finished live runs whose file could not be written whole (``incomplete_runs``)
        self._incomplete: OrderedDict[str, IncompleteRun] = OrderedDict()
        self._replays_seen: set[str] = set()
        # told the loop id of each new live plant instance (evidence of a restart, after the
        # loop's previous one was heard): the service files its gains in the change history
        self.on_new_instance: Callable[[str], None] | None = None

    def lost_runs(self) -> list[tuple[str, str]]:
        """(run id, loop) of the live runs closed "tuner lost" whose result has not come: the
        service asks their tuners for it (a logger cut off, or paused past Zenoh's lease, as
        the result was published never hears it: an ok run stayed "tuner lost")."""
        return list(self._lost_loop.items())

    # --- input ------------------------------------------------------------------------------

    def handle(self, key: str, payload: bytes, replay: str | None = None) -> None:
        """Take one message from the bus; ``replay``: the replayed file it came from, if any."""
        self.counts["received"] += 1
        if replay is not None and not self.record_replays:
            self.counts["replayed_ignored"] += 1
            if replay not in self._replays_seen:
                self._replays_seen.add(replay)
                log.info("not recording the replay of %s (--record-replays does)", replay)
            return
        found = model_for(self.prefix, key)
        if found is None:
            if (batch := keys.parse_loop_key(self.prefix, key)) and batch[1] == "pv_batch":
                self._batch(batch[0], payload, replay)
            else:
                self.counts["ignored"] += 1
            return
        loop_id, model = found
        try:
            msg = model.model_validate_json(payload)
        except pydantic.ValidationError:
            self.counts["invalid"] += 1
            return
        self._take(key, loop_id, model, payload, msg, replay)

    def _batch(self, loop_id: str, payload: bytes, replay: str | None) -> None:
        """A lockstep advance's samples in one message (``pv_batch``): each taken as if it had
        come on its own on ``pv``, its payload what the plant puts there (the same JSON), so
        the file holds one ``pv`` message per sample as always. Not valid: counted, left out
        whole (its samples then show as a gap)."""
        try:
            batch = ProcessSamples.model_validate_json(payload)
        except pydantic.ValidationError:
            self.counts["invalid"] += 1
            return
        if batch.loop != loop_id:
            self.counts["invalid"] += 1
            return
        key = keys.pv(self.prefix, loop_id)
        samples = batch.samples
        texts = batch_elements(payload, len(samples)) or [_encoded(s) for s in samples]
        self.counts["received"] += len(samples) - 1  # as many as came on their own
        self._take(key, loop_id, ProcessSample, texts[0], samples[0], replay)
        rest = self._run_samples(self._stream(loop_id, replay or ""), key, samples, texts)
        for sample, text in zip(samples[rest:], texts[rest:], strict=True):
            self._take(key, loop_id, ProcessSample, text, sample, replay)

    def _run_samples(
        self, stream: Stream, key: str, samples: list[ProcessSample], texts: list[bytes]
    ) -> int:
        """A batch's samples after its first, taken as ``_take`` takes each, where nothing
        but their writing is left to decide (the first taken already; the index of the first
        not taken): a run open and not ending, the first written, and these numbered on from
        it (the batch's validation says they are) at sim times that never go back — neither
        a duplicate nor a new plant instance can be among them. Why: the per-message checks
        were a quarter of the logger's time per sample, and a lockstep run's samples come as
        batches of up to 256."""
        run = stream.run
        first = samples[0]
        if (
            run is None
            or run.ending is not None
            or stream.instance != run.instance
            or run.last_seq != first.seq
            or stream.last_sample_seq != first.seq
        ):
            return 1
        last_t = first.t
        end = 1
        for sample in samples[1:]:
            if sample.t < last_t:
                break
            last_t = sample.t
            end += 1
        if end == 1:
            return 1
        taken = samples[1:end]
        instance, t = stream.instance, stream.t
        recent = stream.recent
        payload = b""
        written: list[tuple[bytes, float]] = []
        for sample, payload in zip(taken, texts[1:end], strict=True):
            t = sample.t
            recent.append(Item(key, ProcessSample, payload, sample, t, instance))
            written.append((recorded_payload(sample, payload), t))
        run.writer.write_many(key, ProcessSample, written)
        last = taken[-1]
        stream.t = t
        stream.last_sample = payload
        stream.last_sample_seq, stream.last_t = last.seq, last.t
        stream.last_seq = max(stream.last_seq or 0, last.seq)
        run.last_seq, run.last_t = last.seq, last.t
        run.samples += len(taken)
        self.counts["written"] += len(taken)
        return end

    def _take(
        self,
        key: str,
        loop_id: str,
        model: type[Message],
        payload: bytes,
        msg: Message,
        replay: str | None,
    ) -> None:
        """One valid message of a loop: into its stream's context and its run's file."""
        stream = self._stream(loop_id, replay or "")
        if isinstance(msg, TuneResult) and not replay and msg.run_id in self._lost:
            self._late_result(key, model, payload, msg)
            return
        if isinstance(msg, ProcessSample):
            if self._not_the_plants(stream.run, msg):
                return
            if msg.seq == stream.last_sample_seq and payload == stream.last_sample:
                self.counts["duplicates"] += 1  # the same sample delivered again
                return
            stream.last_sample = payload
        if isinstance(msg, PLANT_MESSAGES):
            self._plant_evidence(stream, msg)
        t = getattr(msg, "t", None)
        stream.t = t if t is not None else stream.t
        item = Item(key, model, payload, msg, stream.t, stream.instance)
        if isinstance(msg, LoopStatus):
            _size_buffer(stream, msg)
        stream.recent.append(item)
        run = stream.run
        if isinstance(msg, TuneProgress) and msg.phase == "start":
            if run is not None and run.run_id == msg.run_id:
                self._write(run, item)
                return
            if stream.waiting is not None and stream.waiting.msg.run_id == msg.run_id:
                return  # its start again, still waiting
            if run is not None and run.ending is not None:  # its result is in: it ended
                self._end(stream)  # (which opens a run that waited behind it)
                stream.recent.append(item)
                run = stream.run
            if run is not None and not stream.replay:
                self._wait_behind(stream, run, item)
                return
            if run is not None:  # a replay's new run: the old one's file ends here
                self._close(stream, status="superseded", result=None)
                # (a replay's stream ends with its run: a new one for the new run)
                stream = self._stream(stream.loop, stream.replay)
                stream.recent.append(item)
            if not stream.replay and msg.run_id in self._recorded:
                self.counts["repeated_runs"] += 1
                log.warning("run %s on %s: already recorded, not again", msg.run_id, loop_id)
                return
            self._open(stream, msg)
            return
        if stream.waiting is not None and self._waiting_run(stream, item):
            return
        run = stream.run
        if run is None:
            return
        if run.superseded_at is not None and not isinstance(msg, TUNER_MESSAGES):
            return  # the loop is the waiting run's now: kept for its file (``recent``)
        if self._belongs(run, stream, item):
            self._write(run, item)
        else:
            run.left_out += 1
            return
        if isinstance(msg, TuneResult):
            self._result_in(stream, run, msg)
        elif run.ending is not None:
            if isinstance(msg, ProcessSample) and msg.t >= run.ending.t:
                self._end(stream)
        elif isinstance(msg, LoopStatus):
            self._status(stream, run, msg)

    def plant_token(self, loop_id: str, alive: bool) -> None:
        """The loop's liveliness token appeared or vanished (live traffic only)."""
        stream = self._stream(loop_id, "")
        if not alive and stream.plant_alive is not False:
            # whatever comes next is checked against what came before (seq, node); the
            # context kept from before the interruption is never a later run's
            stream.recent.clear()
            log.info("loop %s: its plant's token vanished", loop_id)
            if stream.run is not None and stream.run.ending is not None:
                self._end(stream)  # the samples its result waits for are not coming
        stream.plant_alive = alive

    def run_token(self, loop_id: str, alive: bool) -> None:
        """The loop's run token (``<prefix>/tune/<loop>/running``) appeared or vanished."""
        stream = self._stream(loop_id, "")
        stream.run_token = alive
        run = stream.run
        if run is None or run.ending is not None:  # no run, or its result is in
            return
        if alive:
            if run.lost == "token":  # back (a reconnection): the tuner still runs it
                run.lost = ""
        elif run.lost == "watchdog":  # restored by the plant and now gone: it is over
            self._close(stream, status="tuner lost", result=None)
        else:  # the result may still be on its way on another path: wait RESULT_GRACE
            run.lost, run.lost_at = "token", self.clock()

    def tick(self) -> None:
        """Close the runs whose token vanished ``RESULT_GRACE`` s ago without a result, and
        those whose result came that long ago (their last samples are not coming); flush the
        open files that are due (called about every 0.25 s)."""
        now = self.clock()
        for stream in list(self.streams.values()):
            run = stream.run
            if run is None:
                continue
            if run.ending is not None:
                if now - run.ending_at >= RESULT_GRACE:
                    self._end(stream)
            elif run.lost == "token" and now - run.lost_at >= RESULT_GRACE:
                self._close(stream, status="tuner lost", result=None)
            elif run.superseded_at is not None and now - run.superseded_at >= RESULT_GRACE:
                status = "tuner lost" if run.lost else "superseded"
                self._close(stream, status=status, result=None)
            elif (
                stream.replay
                and run.heard_at is not None
                and now - run.heard_at >= (silence := replay_silence(run))
            ):
                log.warning(
                    "run %s on %s: nothing of its replay of %s for %.3g s: its file ends "
                    "incomplete (the replay was interrupted)",
                    run.run_id,
                    run.loop,
                    stream.replay,
                    silence,
                )
                self._close(stream, status="incomplete", result=None)
        self.flush_due()

    def _wait_behind(self, stream: Stream, run: OpenRun, start: Item) -> None:
        """A run's start while ``run`` is open: it is recorded once ``run`` ends, or once the
        plant shows it holding the loop (``_waiting_run``). Why: a tuner's run starts, and
        waits for the loop's rest, before it asks for the lease; a second tuner's run on a
        loop the first one is tuning is then refused, and its start had closed the first
        run's file "superseded" (it went on to end ok, its result on no record)."""
        if stream.waiting is not None:
            log.warning(
                "run %s on %s: not recorded (run %s started after it, still behind run %s)",
                stream.waiting.msg.run_id,
                stream.loop,
                start.msg.run_id,
                run.run_id,
            )
        stream.waiting = start
        log.info(
            "run %s on %s: started while run %s is open; recorded once the plant shows it "
            "holding the loop, or once run %s ends",
            start.msg.run_id,
            stream.loop,
            run.run_id,
            run.run_id,
        )

    def _waiting_run(self, stream: Stream, item: Item) -> bool:
        """A message about the run that waits behind the open one: its own (kept in the
        recent messages for its file, if it opens), or the plant's status that shows it
        holding the loop. True when ``item`` is done with here."""
        waiting, msg = stream.waiting, item.msg
        assert waiting is not None
        run_id = waiting.msg.run_id
        run = stream.run  # (open: a run waits only behind an open one)
        if isinstance(msg, TUNER_MESSAGES) and msg.run_id == run_id:
            if isinstance(msg, TuneResult) and run is not None and run.superseded_at is not None:
                # it held the loop, and it is over: so is the open run (its file ends, this
                # one opens from its start, this result in it: ``recent``)
                self._close(stream, status="tuner lost" if run.lost else "superseded", result=None)
                if stream.run is not None and stream.run.run_id == run_id:
                    self._result_in(stream, stream.run, msg)
            elif isinstance(msg, TuneResult):  # refused, or ended, before it held the loop
                stream.waiting = None
                self._unrecorded(run_id, stream.loop, msg.status, run.run_id if run else None)
            return True
        # the plant shows it holding the loop: the open run let the loop go, and its result,
        # still on its way, may yet close its file (``tick``); else it was superseded
        held = isinstance(msg, LoopStatus) and msg.leased_by == f"tuner:{run_id}"
        if held and run is not None and run.superseded_at is None:
            run.superseded_at = self.clock()
        return False

    def _result_in(self, stream: Stream, run: OpenRun, msg: TuneResult) -> None:
        """The run's result, written: its file closes now, or once the plant's samples have
        caught up with it. Now also where the plant's token has vanished before the result
        came: its samples are not coming (a killed plant's run waited ``RESULT_GRACE`` for
        them, and the client that waits for the file with it: a fault test's 4 s bound
        was missed by 0.24 s in CI)."""
        gone = stream.plant_alive is False
        if run.last_t is None or run.last_t >= msg.t or run.plant_changed or gone:
            self._close(stream, status=msg.status, result=msg)
        else:  # the plant's last samples are still on their way
            run.ending, run.ending_at = msg, self.clock()

    def _end(self, stream: Stream) -> None:
        """Close the stream's run with the result it already wrote."""
        result = stream.run.ending if stream.run is not None else None
        if result is not None:
            self._close(stream, status=result.status, result=result)

    # --- evidence ---------------------------------------------------------------------------

    def _stream(self, loop_id: str, replay: str) -> Stream:
        stream = self.streams.get((loop_id, replay))
        if stream is None:
            stream = self.streams[(loop_id, replay)] = Stream(loop_id, replay)
        return stream

    def _plant_evidence(self, stream: Stream, msg: ProcessSample | LoopStatus) -> None:
        """Start a new plant instance on evidence of one; then track its numbering.

        Samples and statuses share one numbering, but only samples are published in that
        order always (in realtime one thread paces the samples while another answers
        commands: a status can trail the samples by a few numbers, or run ahead of them).
        So the samples' own numbering is checked always, a status's against everything only
        on the lockstep clock (one thread publishes both), and never a watchdog's (its own
        thread)."""
        why = ""
        if isinstance(msg, LoopStatus):
            if msg.reason == "start":
                why = "the plant started (status 'start')"
            elif stream.node is not None and msg.node != stream.node:
                why = f"another plant node ({stream.node!r} → {msg.node!r})"
            elif (
                msg.clock == "lockstep"
                and msg.reason != "watchdog"
                and stream.last_seq is not None
                and msg.seq < stream.last_seq
            ):
                why = f"the loop's sample number went back ({stream.last_seq} → {msg.seq})"
        elif stream.last_sample_seq is not None and msg.seq < stream.last_sample_seq:
            why = f"the sample number went back ({stream.last_sample_seq} → {msg.seq})"
        elif stream.last_sample_seq is not None and msg.seq == stream.last_sample_seq:
            why = f"sample {msg.seq} came again, with other values"
        elif stream.last_t is not None and msg.t < stream.last_t:
            why = f"the sim time went back ({stream.last_t:g} → {msg.t:g} s)"
        if why:
            self._new_instance(stream, why)
        if isinstance(msg, LoopStatus):
            stream.node = msg.node
        else:
            stream.last_sample_seq, stream.last_t = msg.seq, msg.t
        stream.last_seq = msg.seq if stream.last_seq is None else max(stream.last_seq, msg.seq)

    def _new_instance(self, stream: Stream, why: str) -> None:
        had_history = stream.last_seq is not None or stream.node is not None
        stream.instance += 1
        stream.recent.clear()
        stream.node = None
        stream.last_seq = stream.last_sample_seq = stream.last_t = None
        if not had_history:
            return
        self.counts["plant_instances"] += 1
        run = stream.run
        log.info("loop %s%s: a new plant instance: %s", stream.loop, _replay_note(stream), why)
        if self.on_new_instance is not None and not stream.replay:
            self.on_new_instance(stream.loop)
        if run is not None and not run.plant_changed:
            run.plant_changed = why
            log.warning(
                "run %s on %s: %s; the new instance's messages are left out of its file",
                run.run_id,
                run.loop,
                why,
            )

    def _belongs(self, run: OpenRun, stream: Stream, item: Item) -> bool:
        """Is ``item`` this run's message: its tuner's, or its plant instance's?"""
        msg = item.msg
        if isinstance(msg, TUNER_MESSAGES):
            return msg.run_id == run.run_id
        if item.instance != run.instance:  # another plant instance's samples and commands
            return False
        # a sample already written (a duplicate) is not written again
        return not (
            isinstance(msg, ProcessSample) and run.last_seq is not None and msg.seq <= run.last_seq
        )

    def _not_the_plants(self, run: OpenRun | None, msg: ProcessSample) -> bool:
        """A sample whose sim time is not its number × the loop's sample time (the plant's
        always is): a forged or garbled one, left out of the run and of the stream's evidence
        and counted (one with seq 1e9 made a run's file say 999,757,179 samples dropped, and
        its loop's next samples read as a new plant instance's: helper trial). Known only
        once a run's request told the sample time."""
        if run is None or run.ts is None:
            return False
        if abs(msg.t - msg.seq * run.ts) <= 1e-6 * max(1.0, abs(msg.t)):
            return False
        run.inconsistent += 1
        self.counts["inconsistent"] += 1
        if run.inconsistent == 1:
            log.warning(
                "run %s on %s: a sample whose sim time %g s is not its number %d × the loop's "
                "sample time %g s is not the plant's: left out (others counted)",
                run.run_id,
                run.loop,
                msg.t,
                msg.seq,
                run.ts,
            )
        return True

    def _status(self, stream: Stream, run: OpenRun, msg: LoopStatus) -> None:
        """A status of the run's loop: the watchdog's restore ends a run whose tuner is gone."""
        if msg.reason != "watchdog" or self._lease_held(run, msg):
            return
        if stream.run_token and run.lost != "token":
            # the tuner lives (its token is there): it learns the lease is gone and ends
            # its run with a result; if it does not, its token's vanishing closes the file
            run.lost, run.lost_at = "watchdog", self.clock()
            return
        self._close(stream, status="tuner lost", result=None)

    @staticmethod
    def _lease_held(run: OpenRun, msg: LoopStatus) -> bool:
        """Does ``msg`` show the run's lease still held? Before the run's lease command is
        seen, any holder counts (a lease on a run's loop is the run's: leases are exclusive)."""
        if msg.leased_by is None:
            return False
        holders = run.lease_holders | {f"tuner:{run.run_id}"}
        return msg.leased_by in holders or len(run.lease_holders) == 0

    # --- files ------------------------------------------------------------------------------

    def _open(self, stream: Stream, start: TuneProgress) -> None:
        wall_ns = time.time_ns()  # the run's start on the wall clock: its log times' origin
        now = datetime.fromtimestamp(wall_ns / 1e9, UTC)
        # the method, as the tuner's start message names it: a known one, else "run" (the
        # message is any client's text: a forged one put a newline and U+202E in a name)
        said = start.message.split(" ")[0] if start.message else ""
        method = said if said in FILE_METHODS else "run"
        tail = "_replay" if stream.replay else ""
        name = f"{now:%Y%m%dT%H%M%SZ}_{stream.loop}_{method}_{start.run_id}{tail}.mcap"
        path = self.runs_dir / name
        n = 1
        while path.exists():  # the same run replayed twice within a second
            n += 1
            path = path.with_name(f"{name[: -len('.mcap')]}-{n}.mcap")
        run = OpenRun(
            start.run_id,
            stream.loop,
            method,
            "",
            RunWriter(path, self.flush_interval, log_time_zero(wall_ns, start.t)),
            start.t,
            now.isoformat(),
            instance=stream.instance,
            replay=stream.replay,
            plant_node=stream.node or "",
        )
        run.opened_at = self.clock()
        stream.run = run
        if stream.run_token is False and not stream.replay:
            run.lost, run.lost_at = "token", self.clock()  # its token is not there (yet)
        self.counts["runs"] += 1
        log.info(
            "run %s on %s%s: recording to %s",
            start.run_id,
            stream.loop,
            _replay_note(stream),
            path,
        )
        for item in stream.recent:  # what came just before, the start message included
            if item.t >= start.t and self._belongs(run, stream, item):
                self._write(run, item)

    def _write(self, run: OpenRun, item: Item) -> None:
        run.heard_at = self.clock()
        msg = item.msg
        if isinstance(msg, ProcessSample):
            if run.last_seq is not None and msg.seq != run.last_seq + 1:
                run.gaps += max(0, msg.seq - run.last_seq - 1)
            if run.first_seq is None and (head := _missed_head(run.t_start, msg)):
                run.gaps += head
                log.warning(
                    "run %s on %s: its first %d samples did not reach the file (they came "
                    "before its start, more than are kept for a run not yet started: the "
                    "logger was behind)",
                    run.run_id,
                    run.loop,
                    head,
                )
            run.first_seq = msg.seq if run.first_seq is None else run.first_seq
            run.last_seq = msg.seq
            run.last_t = msg.t
            run.samples += 1
        elif isinstance(msg, LoopStatus):
            run.plant_node = run.plant_node or msg.node
            run.held = run.held or msg.leased_by == f"tuner:{run.run_id}"
        elif isinstance(msg, LeaseCommand):
            run.lease_holders.add(msg.source)
        elif isinstance(msg, TunerEvent) and msg.kind == "request":
            run.request = str(msg.data.get("request", ""))
            run.info = str(msg.data.get("info", ""))
            try:
                run.ts = LoopInfo.model_validate_json(run.info).sample_time
            except pydantic.ValidationError:
                run.ts = None
            try:
                request = json_text.loads(run.request)
                run.rule = request.get("rule", "")
                run.method = request.get("method", run.method)
            except (json.JSONDecodeError, AttributeError):
                pass
        run.writer.write(item.key, item.model, recorded_payload(msg, item.payload), item.t)
        self.counts["written"] += 1

    def _close(self, stream: Stream, status: str, result: TuneResult | None) -> None:
        run = stream.run
        if run is None:
            return
        stream.run = None
        # what came before this close is never a later run's context, but for a run that
        # waited behind this one: its messages since its start
        waiting, stream.waiting = stream.waiting, None
        kept = [i for i in stream.recent if i.t >= waiting.t] if waiting is not None else []
        stream.recent = deque(kept, maxlen=BUFFER)
        if stream.replay:  # a replay's stream ends with its run (memory stays bounded)
            self.streams.pop((stream.loop, stream.replay), None)
        if _never_held(run, result):
            # refused the loop another run held: no file, whichever of the two started first
            # (it had one when it started first, none when it started behind the other: one
            # rule now, the README's)
            run.writer.discard()
            self._unrecorded(run.run_id, run.loop, status, waiting.msg.run_id if waiting else None)
        else:
            self._finish(stream, run, status, result)
        if waiting is not None:
            if waiting.msg.run_id in self._recorded:
                log.warning(
                    "run %s on %s: already recorded, not again", waiting.msg.run_id, run.loop
                )
            else:
                self._open(stream, waiting.msg)

    def _unrecorded(self, run_id: str, loop: str, status: str, holder: str | None) -> None:
        """A run that ended without ever holding the loop while ``holder``'s run did: counted
        and said, no file."""
        self.counts["unrecorded_runs"] += 1
        log.warning(
            "run %s on %s: ended (%s) without ever holding the loop while run %s did: not recorded",
            run_id,
            loop,
            status,
            holder or "?",
        )

    def _finish(self, stream: Stream, run: OpenRun, status: str, result: TuneResult | None) -> None:
        """The run's file finished with its metadata, and the run remembered as recorded."""
        if result is not None and (tail := _missed_tail(run, result)):
            run.gaps += tail
            log.warning(
                "run %s on %s: %d of its samples, up to its result's sim time %g s, did not "
                "reach the file (%s): counted as dropped",
                run.run_id,
                run.loop,
                tail,
                result.t,
                "none of its samples came" if run.last_seq is None else "its last ones",
            )
        meta = {
            "run_id": run.run_id,
            "loop": run.loop,
            "method": run.method,
            "rule": run.rule,
            "status": status,
            "started": run.started,
            "finished": datetime.now(UTC).isoformat(),
            "prefix": self.prefix,
            "namespace": self.namespace,
            "samples": str(run.samples),
            "first_seq": str(run.first_seq),
            "last_seq": str(run.last_seq),
            "dropped": str(run.gaps),
            "messages": str(run.writer.messages),
            "request": run.request,
            "info": run.info,
            "result": result.model_dump_json() if result else "",
            "ku": "" if result is None or result.ku is None else repr(result.ku),
            "pu": "" if result is None or result.pu is None else repr(result.pu),
            "replay": run.replay,
            "plant_node": run.plant_node,
            "plant_changed": run.plant_changed,
            "left_out": str(run.left_out),
        }
        end = result.t if result is not None else (run.last_t or run.t_start)
        # the messages of the bus it holds (the run's record, written with the metadata, is
        # the file's own: counted apart, so that the runs' counts add up to ``written``)
        bus_messages = run.writer.messages
        run.writer.finish(meta, keys.tune_run_record(self.prefix, run.loop), max(end, run.t_start))
        self.finished.append(run.writer.path)
        if not run.replay:
            self._recorded[run.run_id] = None
            while len(self._recorded) > REMEMBERED_RUNS:
                self._recorded.popitem(last=False)
            if status == "tuner lost":
                self._lost[run.run_id] = run.writer.path
                self._lost_loop[run.run_id] = run.loop
                while len(self._lost) > REMEMBERED_RUNS:
                    self._lost_loop.pop(self._lost.popitem(last=False)[0], None)
        self.counts["dropped"] += run.gaps
        if run.writer.error is not None:  # cut short where it could no longer be written
            why = run.writer.error.strerror or one_line(run.writer.error)
            path = run.writer.path
            if not run.replay:  # said in the status: the client that ran it asks
                self._incomplete[run.run_id] = _incomplete(run)
                while len(self._incomplete) > INCOMPLETE_KEPT:
                    self._incomplete.popitem(last=False)
            what = (
                f"its file {path} is cut short ({why}): its recording stopped after "
                f"{bus_messages} of its messages, some of them lost with the chunk in progress"
                if path.exists()
                else f"not recorded: its file {path} could not be written ({why})"
            )
            log.error(
                "run %s on %s%s: %s, but %s",
                run.run_id,
                run.loop,
                _replay_note(stream),
                status,
                what,
            )
            return
        log.info(
            "run %s on %s%s: %s, %d messages and its run record, %d samples, %d dropped, "
            "%d left out → %s",
            run.run_id,
            run.loop,
            _replay_note(stream),
            status,
            bus_messages,
            run.samples,
            run.gaps,
            run.left_out,
            run.writer.path,
        )

    def _late_result(
        self, key: str, model: type[Message], payload: bytes, result: TuneResult
    ) -> None:
        """The result of a run whose file was closed "tuner lost" (its tuner paused or cut
        off past the grace, then back): the file is rewritten with the result in it and the
        tuner's status, and says that its tuner was lost for a while (``late_result``)."""
        path = self._lost.pop(result.run_id)
        self._lost_loop.pop(result.run_id, None)
        meta = {
            "status": result.status,
            "late_result": "the run's result came after the file was closed 'tuner lost' (its "
            "tuner, or this logger, paused or cut off meanwhile)",
            "result": result.model_dump_json(),
            "ku": "" if result.ku is None else repr(result.ku),
            "pu": "" if result.pu is None else repr(result.pu),
        }
        try:
            amend_run(
                path,
                key,
                model,
                recorded_payload(result, payload),
                result.t,
                meta,
                keys.tune_run_record(self.prefix, result.loop),
            )
        except Exception as err:  # a file moved or damaged since: the result is not lost
            self.counts["late_results_lost"] += 1
            log.warning(
                "run %s on %s: its late result (%s) could not go into %s: %s",
                result.run_id,
                result.loop,
                result.status,
                path,
                one_line(err),
            )
            return
        self.counts["late_results"] += 1
        log.info(
            "run %s on %s: its tuner's result came late (%s): into %s, closed 'tuner lost'",
            result.run_id,
            result.loop,
            result.status,
            path,
        )

    def flush_due(self) -> None:
        for stream in self.streams.values():
            if stream.run is not None:
                stream.run.writer.flush_if_due()

    def close_all(self, status: str = "incomplete") -> None:
        """Finish every open file (on SIGTERM or Ctrl-C): nothing received is lost; a run
        whose result is in keeps its status."""
        for stream in list(self.streams.values()):
            run = stream.run
            if run is not None and run.ending is not None:
                self._end(stream)
            else:
                self._close(stream, status=status, result=None)

    def incomplete_runs(self) -> list[IncompleteRun]:
        """The live runs whose file could not be written whole: those still open whose file
        failed (the rest of the run is not recorded), then the latest finished ones, the
        last write of their end among them (a full disk as the file was finished: the tuner
        had published its result, and its client printed the run as recorded)."""
        failed = [
            _incomplete(s.run)
            for s in self.streams.values()
            if s.run is not None and not s.run.replay and s.run.writer.error is not None
        ]
        return (failed + list(self._incomplete.values()))[:MAX_INCOMPLETE]

    def open_runs(self) -> list[str]:
        """The runs being recorded; not one whose file could no longer be written (a full
        disk): its tuner then says the run is not on record, rather than nothing."""
        return [
            s.run.run_id
            for s in self.streams.values()
            if s.run is not None and s.run.writer.error is None
        ]


def _incomplete(run: OpenRun) -> IncompleteRun:
    """What the status says of a run whose file failed (``run.writer.error`` set)."""
    err = run.writer.error
    assert err is not None
    return IncompleteRun(
        run_id=run.run_id,
        loop=run.loop,
        path=str(run.writer.path.absolute()),
        reason=err.strerror or one_line(err),
        on_disk=run.writer.path.exists(),
    )


def _replay_note(stream: Stream) -> str:
    return f" (replay of {stream.replay})" if stream.replay else ""


def _never_held(run: OpenRun, result: TuneResult | None) -> bool:
    """A run that ended untouched, never holding the loop, while a run that started behind
    it was seen holding it: refused the lease another supervisor had."""
    return (
        result is not None
        and bool(result.untouched)
        and not run.held
        and run.superseded_at is not None
        and not run.replay
    )
