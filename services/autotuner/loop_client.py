"""Drive one plant_sim loop over Zenoh: read it, command it, step its clock.

Samples and status arrive on one subscriber whose callback (Zenoh's receiving thread, order
kept) puts them on a queue (a lockstep advance's batch, ``pv_batch``, as its samples one by
one), so every wait is bounded: a silent plant becomes ``PlantLost``,
never a hang. The loop's liveliness token is watched too: a plant that dies or is cut off is
``PlantLost`` at once. While the client holds the loop's lease, every status the plant
publishes says who holds it: one that no longer names this client (the plant's watchdog
restored the loop, the plant restarted) is ``LeaseLost`` at once, and so is a refusal because
the lease lapsed.
"""

from __future__ import annotations

import itertools
import logging
import math
import queue
import re
import secrets
import threading
import time
from collections import Counter, deque
from collections.abc import Callable

import zenoh

from services.autotuner.identify.driver import until_band
from services.autotuner.identify.experiments import Band
from services.autotuner.stall_watch import StallWatch, stall_watch
from shared import keys, wire
from shared.errors import AutotuneError, DecodeError
from shared.messages import (
    COMMANDS,
    AdvanceCommand,
    CalmStop,
    Command,
    LeaseCommand,
    LoopInfo,
    LoopStatus,
    Message,
    ProcessSample,
    ProcessSamples,
    RecordStops,
    ReleaseCommand,
    SyncCommand,
)
from shared.session import unreached

log = logging.getLogger("autotuner")

LEASE_TIMEOUT = 10.0  # s of wall time without a command before the plant restores the loop
RENEW_EVERY = 2.0  # s of wall time between lease-keeping syncs in realtime, at most
RESEND_EVERY = 1.0  # s: a sync whose answer is late is sent again (lost while reconnecting)
_GONE = "<gone>"  # inbox marker: the loop's liveliness token vanished
# a wait that ends this long past its deadline did not run: this process was paused or
# starved (SIGSTOP, a suspended VM), and what the plant sent meanwhile may still be coming in
OVERSLEPT = 1.0  # s
RESUMED_WAIT = 2.0  # s: then waited for once more, so the cause is the plant's word
# s: a stall of this process within this long before the plant's token vanished is why
CUT_OFF_WINDOW = 30.0


def stalled_before(watch: StallWatch, born: float, gone: float) -> float:
    """Seconds this process did not run within ``CUT_OFF_WINDOW`` before ``gone`` (when the
    plant's token vanished) and since ``born`` (when the client began), monotonic times."""
    return watch.stalled(max(gone - CUT_OFF_WINDOW, born)) - watch.stalled(gone)


class PlantLost(AutotuneError):
    """The plant stopped answering."""


class CommandRefused(AutotuneError):
    """The loop refused a command; the message is the plant's reason."""


class LoopFaulted(AutotuneError):
    """The loop's model failed (its status carries ``fault``): the plant holds it in manual
    at its last output and refuses output, auto-mode and disturbance commands (its setpoint
    and gains it still takes)."""


class ForgedCommand(AutotuneError):
    """The plant applied a command in this client's name that this client did not send:
    another client on the bus writes as it (a bus without credentials cannot tell them
    apart)."""


class ForgedSample(AutotuneError):
    """A sample of the loop numbered as one already received: a second publisher on the
    loop's key (a bus without credentials cannot tell it from the plant)."""


# command kinds whose status names the sender (``by_source``): each of ours is answered by
# one, so one more than this client sent came from elsewhere
MOVING_KINDS = ("output", "mode", "gains", "setpoint", "disturbance")
# and a lease: one in this client's name that it did not send names the PV limits at which
# the plant restores the loop by itself (realtime), so it is counted the same way (a forged
# lease of limits ±1e300 took away that safety net, and the run went on to `ok`)
NAMED_KINDS = (*MOVING_KINDS, "lease")


# how a refusal in a run's name of a command it did not send is said (its reason, or a
# warning of its result)
NOT_SENT_REFUSED = "refused command(s) in this run's name that it did not send"


def refused_kind(reason: str | None) -> str | None:
    """The command kind a plant's refusal names first ("setpoint: sp … is outside the PV
    range", "advance refused: …"); None if it names none."""
    m = re.match(r"([a-z_]+)(?::| refused)", reason or "")
    return m.group(1) if m is not None and m.group(1) in COMMANDS else None


def split_refusals(new: int, possible: Counter[str], last: str | None) -> tuple[int, int]:
    """Of ``new`` refusals counted in this client's name since its last sync's answer, how
    many can be its own and how many it did not send: (own, forged). ``possible``: per kind,
    its commands since then that could have been refused (sent, and not answered by a status
    of them applied); ``last``: the plant's reason for the last of them (it names only the
    last). More than it could have had refused, or a last one of a kind it did not send, is
    another client's in its name: a setpoint forged outside the PV range was refused in a
    run's name, and the run, which sent no setpoint, blamed itself (helper trial)."""
    if new <= 0:
        return 0, 0
    forged = max(0, new - sum(possible.values()))
    kind = refused_kind(last)
    if kind is not None and possible[kind] <= 0:
        forged = max(forged, 1)
    return new - forged, forged


# how a lease the plant ended is said (``_lost_why``): a run's reason that says it is not
# told again that the plant restored the loop
PLANT_RESTORED = "restored the loop to its state before the test"


class LeaseLost(AutotuneError):
    """The plant no longer lets this client hold the loop (it restored it, or restarted)."""


ABANDON_POLL = 0.25  # s between a wait's looks at whether it should go on


def wait_for_token(
    session: zenoh.Session,
    key_expr: str,
    timeout: float,
    abandon: Callable[[], bool] | None = None,
) -> bool:
    """Block until a liveliness token matching ``key_expr`` is seen; False after ``timeout``,
    or as soon as ``abandon()`` (asked every ``ABANDON_POLL`` s) says the wait is pointless."""
    events: queue.Queue[zenoh.Sample] = queue.Queue()
    sub = session.liveliness().declare_subscriber(
        key_expr, zenoh.handlers.FifoChannel(16), history=True
    )
    reader = threading.Thread(target=lambda: [events.put(s) for s in sub], daemon=True)
    reader.start()
    deadline = time.monotonic() + timeout
    try:
        while True:
            left = max(0.0, deadline - time.monotonic())
            try:
                sample = events.get(timeout=left if abandon is None else min(left, ABANDON_POLL))
            except queue.Empty:
                if abandon is None or time.monotonic() >= deadline or abandon():
                    return False
                continue
            if sample.kind == zenoh.SampleKind.PUT:
                return True
    finally:
        sub.undeclare()


LISTED = 20  # loop ids a one-line message names at most (600 made a line of 4,000 characters)


def listed(ids: list[str]) -> str:
    """``ids`` for a one-line message: the first ``LISTED``, and how many there are."""
    if len(ids) <= LISTED:
        return ", ".join(ids)
    return f"{', '.join(ids[:LISTED])}, … ({len(ids)} in all: `autotune loops` lists them)"


def wait_for_loop(session: zenoh.Session, prefix: str, loop: str, timeout: float) -> None:
    """Block until the loop's liveliness token is seen, or raise PlantLost after ``timeout``."""
    if not wait_for_token(session, keys.loop_alive(prefix, loop), timeout):
        present = live_loops(session, prefix)
        there = (
            f"; the loops on the bus under {prefix!r} are {listed(present)}"
            if present
            else " (is `autotune plant` running, reachable and serving that loop?)"
        )
        raise PlantLost(
            f"loop {loop!r} not found: nothing announces {keys.loop_alive(prefix, loop)} "
            f"after {timeout:g} s{there}{unreached(session)}"
        )


TOKENS_QUIET = 0.2  # s without a new token that ends the gathering of the tokens up


def live_loops(session: zenoh.Session, prefix: str, timeout: float = 1.0) -> list[str]:
    """The ids of the loops whose liveliness tokens are up under ``prefix``, sorted: from a
    liveliness subscriber's history, gathered until ``TOKENS_QUIET`` s bring no new one (at
    most ``timeout`` s). Not a liveliness query: among 600 loops' tokens a peer's query was
    seen never to end, and the session's close waited on it (`loops` hung)."""
    found: set[str] = set()
    came = threading.Event()

    def on_token(sample: zenoh.Sample) -> None:
        parsed = keys.parse_loop_key(prefix, str(sample.key_expr))
        if parsed is not None and parsed[1] == "alive" and sample.kind == zenoh.SampleKind.PUT:
            found.add(parsed[0])
            came.set()

    sub = session.liveliness().declare_subscriber(
        keys.loop_alive(prefix, keys.ANY), on_token, history=True
    )
    try:
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            came.clear()
            if not came.wait(min(TOKENS_QUIET, left)):
                break
    finally:
        sub.undeclare()
    return sorted(found)


class LoopClient:
    """One driver's view of a loop. Use as a context manager."""

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        loop: str,
        *,
        source: str = "autotune",
        timeout: float = 5.0,
        lease_timeout: float = LEASE_TIMEOUT,
        user: str | None = None,
    ):
        self.session = session
        self.prefix = prefix
        self.loop = loop
        self.source = source
        self.timeout = timeout
        self.lease_timeout = lease_timeout  # what this client asks for when it leases
        self.user = user  # its authenticated Zenoh user, named in its command keys
        self._renew_every = min(RENEW_EVERY, lease_timeout / 4)
        # a silence this long (this process paused, its link re-forming) may have cost the
        # lease: it is confirmed before anything is written
        self._suspect_after = 0.4 * lease_timeout
        # every client on the bus sees every loop status: tokens start at random so that no
        # client takes another's barrier for its own (0 is the lease keeper's, never awaited)
        self._tokens = itertools.count(secrets.randbits(40) + 1)
        self._last_sent = time.monotonic()
        self._stalls = stall_watch()
        self._born = time.monotonic()  # a stall before this client began is not its loss's
        self._gone_at: float | None = None  # monotonic: when the plant's token vanished
        # refusals in our name so far (from the plant's sync answers); None before the first,
        # which is the baseline: the plant counts by source, and a fixed one (`autotune set`'s,
        # the console's) carries every earlier client's refusals, none of them this one's
        self._refused: int | None = None
        # of them, the ones that can be this client's own, and the ones it did not send
        # (``split_refusals``)
        self._own_refused = 0
        self._own_reject: str | None = None
        self.forged_refused = 0
        self.forged_reject: str | None = None  # the plant's reason for the last, if told
        # commands sent since the last sync's answer that are not of NAMED_KINDS (whose
        # applied status names their sender) nor syncs (never refused): an advance, a release
        self._sent_unnamed: Counter[str] = Counter()
        self._loop_refused = 0
        self.holding = False  # this client holds the loop's lease (confirmed by the plant)
        self.gone = False  # the plant's liveliness token vanished since this client began
        self.fault: str | None = None  # the loop's fault, once a status carried one
        # messages on the loop's keys that could not be read (not JSON, not the schema, a
        # batch of another loop): rejected, counted and logged, never acted on
        self.rejected = 0
        self.last_rejected: str | None = None
        # commands of NAMED_KINDS sent and not yet answered by a status in this client's name
        self._unanswered: Counter[str] = Counter()
        # Zenoh's receiving thread puts each message straight on the inbox, in order: no
        # reader thread of ours runs per message, and the waiting run is woken once per
        # batch of samples it waits for (``_want``), or at once by anything else
        # (key, payload, encoding); a batch's samples go in one by one, already decoded
        self._inbox: deque[tuple[str, bytes | ProcessSample, str]] = deque()
        self._ready = threading.Condition()
        self._want = 1  # samples the run waits for before it is woken
        self._others = 0  # messages in the inbox that are not samples
        self._pv_key = keys.pv(prefix, loop)
        self._batch_key = keys.pv_batch(prefix, loop)
        # lockstep: samples asked for by advances and not yet received; those received while
        # waiting for a sync's answer (in realtime, every one) are held back for the next
        # taker, in order
        self._flight = 0
        self._held: deque[ProcessSample] = deque()
        self._sub = session.declare_subscriber(keys.loop_feed(prefix, loop), self._read)
        self._alive = session.liveliness().declare_subscriber(
            keys.loop_alive(prefix, loop), zenoh.handlers.FifoChannel(64)
        )
        threading.Thread(target=self._watch_alive, daemon=True).start()
        self._status_key = keys.status(prefix, loop)
        self.info = self._query_info()
        self.last_sample: ProcessSample | None = None
        self.last_status: LoopStatus = self.sync()
        # the plant's sim time (s) at which the last command this client had confirmed was
        # applied (the confirming sync's): a sample at or before it ran under what the loop
        # held before (``TuningRun._record`` leaves such samples out of a record; None: none)
        self.applied_t: float | None = None

    def _read(self, s: zenoh.Sample) -> None:
        mark = s.attachment
        if mark is not None and wire.replay_source(mark.to_bytes()) is not None:
            return  # `autotune replay` of a recorded run: not this loop's present
        key, payload, enc = str(s.key_expr), s.payload.to_bytes(), str(s.encoding)
        if key == self._batch_key:  # a lockstep advance's samples: each its own, in order
            try:
                batch = wire.decode(ProcessSamples, payload, enc)
            except DecodeError:  # kept as it came: read in turn, it raises its reason
                batch = None
            if batch is None or batch.loop != self.loop:
                self._put((key, payload, enc))
                return
            with self._ready:
                self._inbox.extend((self._pv_key, x, "") for x in batch.samples)
                if len(self._inbox) >= self._want:
                    self._ready.notify()
            return
        self._put((key, payload, enc))

    def _put(self, item: tuple[str, bytes, str]) -> None:
        with self._ready:
            self._inbox.append(item)
            if item[0] != self._pv_key:
                self._others += 1
                self._ready.notify()
            elif len(self._inbox) >= self._want:
                self._ready.notify()

    def _get(self, timeout: float, want: int) -> tuple[str, bytes | ProcessSample, str] | None:
        """The inbox's first message; with it empty, wait (at most ``timeout`` s) until
        ``want`` samples or any other message are in. None if nothing came."""
        with self._ready:
            if not self._inbox:
                self._want = max(1, want)
                try:
                    self._ready.wait_for(
                        lambda: self._others or len(self._inbox) >= self._want, timeout
                    )
                finally:
                    self._want = 1
                if not self._inbox:
                    return None
            item = self._inbox.popleft()
            if item[0] != self._pv_key:
                self._others -= 1
            return item

    def _reject(self, key: str, why: str) -> None:
        """A message on the loop's ``key`` that cannot be read: counted, logged (the first
        few, then every hundredth) and dropped. Why not an abort: any client on a bus without
        credentials can put such a payload there, and a malformed message ended a healthy
        run with pydantic's complaint as its reason (helper trial); a real sample lost this
        way leaves a lockstep advance short, which its bounded wait reports, naming these."""
        self.rejected += 1
        self.last_rejected = f"{key}: {why}"
        if self.rejected <= 3 or self.rejected % 100 == 0:
            log.warning(
                "loop %s: rejected message %d on %s: %s", self.loop, self.rejected, key, why
            )

    def _watch_alive(self) -> None:
        """The plant's token vanishing (killed, or this client cut off from it) ends the wait
        at once: Zenoh tells in milliseconds what a timeout would in seconds."""
        for s in self._alive:
            if s.kind == zenoh.SampleKind.DELETE:
                if self._gone_at is None:
                    self._gone_at = time.monotonic()
                self.gone = True
                self._put((_GONE, b"", ""))

    def close(self) -> None:
        self._sub.undeclare()
        self._alive.undeclare()

    def __enter__(self) -> LoopClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def query_status(self, timeout: float) -> LoopStatus | None:
        """The loop's status by a query: reads, sends no command (what a client that lost
        the plant may still do, to say how the loop was left once it is back in reach)."""
        return wire.query_one(
            self.session, keys.status(self.prefix, self.loop), LoopStatus, timeout
        )

    def query_info(self, timeout: float) -> LoopInfo | None:
        """The loop's info by a query (None: no answer within ``timeout`` s): its plant's
        ``instance`` tells a plant started anew from the one the run began on."""
        return wire.query_one(self.session, keys.info(self.prefix, self.loop), LoopInfo, timeout)

    def _query_info(self) -> LoopInfo:
        info = wire.query_one(
            self.session, keys.info(self.prefix, self.loop), LoopInfo, self.timeout
        )
        if info is None:
            raise PlantLost(
                f"loop {self.loop!r}: no plant answered "
                f"{keys.info(self.prefix, self.loop)} within {self.timeout:g} s"
            )
        return info

    def _next(self, wait: float | None = None, want: int = 1) -> Message | None:
        """The next sample or status on the loop's feed (others' too). With ``wait``, None
        when nothing comes within it; else PlantLost after ``timeout`` s of silence.
        ``want``: samples expected (an advance's); with the inbox empty, the wait ends when
        that many are in, or anything else is (a status, the plant gone)."""
        while True:
            started = time.monotonic()
            got = self._get(self.timeout if wait is None else wait, want)
            if got is None and wait is None:
                # a wait that ran late, or one through which this process did not run
                paused = max(
                    time.monotonic() - started - self.timeout, self._stalls.stalled(started)
                )
                if paused > OVERSLEPT:  # this process did not run: hear what came meanwhile
                    got = self._get(RESUMED_WAIT, want)
                if got is None:
                    if paused > OVERSLEPT:
                        why = f" (this process did not run for {paused:.0f} s: paused or starved)"
                    elif not self.gone:  # not "the plant": what is known of it
                        why = (
                            "; its liveliness token is still up, so it is silent, not known "
                            "gone: paused or starved, held up publishing to a subscriber "
                            "that stopped reading (a paused logger), or cut off from this process"
                        )
                    else:
                        why = ""
                    if self.rejected:  # a sample may have been among them
                        why += (
                            f"; {self.rejected} message(s) on the loop's keys were rejected "
                            f"as unreadable during the run (the last: {self.last_rejected})"
                        )
                    raise PlantLost(
                        f"loop {self.loop!r}: no message from the plant for {self.timeout:g} s"
                        + why
                    )
            if got is None:
                return None
            key, payload, enc = got
            if key == _GONE:
                self.gone = True
                self.check_plant()
            if key == self._pv_key:
                if isinstance(payload, ProcessSample):
                    self.last_sample = payload
                    return payload
                try:
                    sample = wire.decode(ProcessSample, payload, enc)
                except DecodeError as err:
                    self._reject(key, str(err))
                    continue
                last = self.last_sample
                if self.holding and last is not None and sample.seq <= last.seq:
                    # one plant numbers its samples one after the other: a number again (or
                    # back) is another publisher's (a forged sample shadowing each real one
                    # got a realtime tune to `ok` on a K_u 10 % low: helper trial G)
                    raise ForgedSample(
                        f"loop {self.loop}: a sample numbered {sample.seq} (t = {sample.t:.6g} "
                        f"s, PV {sample.pv:.6g}) came after sample {last.seq} (PV "
                        f"{last.pv:.6g}): another client publishes samples as this loop's "
                        "plant (a bus without credentials cannot tell them apart: see Security)"
                    )
                self.last_sample = sample
                return sample
            if key == self._batch_key:  # one that could not be taken (see ``_read``)
                try:
                    batch = wire.decode(ProcessSamples, payload, enc)
                    why = f"loop: {batch.loop!r} in a batch of loop {self.loop!r}"
                except DecodeError as err:
                    why = str(err)
                self._reject(key, why)
                continue
            if key == self._status_key:
                try:
                    status = wire.decode(LoopStatus, payload, enc)
                except DecodeError as err:
                    self._reject(key, str(err))
                    continue
                self.last_status = status
                if status.fault is not None and self.fault is None:
                    # the model failed: the experiment has no process left to act on (told
                    # once: what follows, the restore, goes on against the faulted loop)
                    self.fault = status.fault
                    if self.holding:
                        # the fault says when it came; the status, when it was said (at the end
                        # of the lockstep part it came in: "faulted at t = 102.8 s (… at t =
                        # 90.1 s)" read as two faults, helper trial)
                        raise LoopFaulted(
                            f"loop {self.loop}: the plant faulted it ({status.fault}; said in its "
                            f"status at t = {status.t:.6g} s): it holds the loop in manual at the "
                            "output it last had, and the model is not called again"
                        )
                if self.holding and status.leased_by != self.source:
                    self.holding = False
                    raise LeaseLost(self._lost_why(status))
                if status.by_source == self.source and status.reason in NAMED_KINDS:
                    if self._unanswered[status.reason] > 0:
                        self._unanswered[status.reason] -= 1
                    elif self.holding:
                        raise ForgedCommand(
                            f"loop {self.loop}: at t = {status.t:.6g} s the plant applied "
                            f"{'an' if status.reason[0] in 'aeiou' else 'a'} {status.reason} "
                            "command in this run's name that it did not send "
                            f"(now {status.mode}, OP {status.op:.4g} %, SP {status.sp:.6g}): "
                            "another client on the bus writes as this run (a bus without "
                            "credentials cannot tell them apart: see Security)"
                        )
                return status

    def _lost_why(self, status: LoopStatus) -> str:
        if status.reason == "watchdog":
            why = f"the plant's watchdog {PLANT_RESTORED}"
            if status.ended:  # a lease timeout, a lost run token, the PV past its limits
                why += f": {status.ended}"
        elif status.leased_by is not None:
            why = f"the plant says {status.leased_by!r} holds it"
        elif status.reason == "start":
            why = "the plant restarted"
        else:
            why = "the plant no longer holds it for this run"
        return f"loop {self.loop}: lease lost at t = {status.t:.6g} s: {why}"

    def send(self, cmd: Command) -> None:
        """Put ``cmd`` on the loop's command key, in this client's name (its ``source``: the
        plant renews a lease and counts refusals by it). Holding the lease after a silence
        of 40 % of its timeout (this process paused, its link re-forming), the lease is
        confirmed first: LeaseLost rather than a write to a loop the plant took back. Once
        the plant's token has vanished nothing more is sent: a plant that comes back is a new
        instance that never granted this client anything."""
        if self.gone:
            raise PlantLost(
                f"loop {self.loop!r}: the plant was lost (its liveliness token vanished: the "
                f"plant stopped, or this process was cut off or paused); {cmd.kind} not sent"
            )
        if (
            self.holding
            and not isinstance(cmd, SyncCommand)
            and time.monotonic() - self._last_sent > self._suspect_after
        ):
            self.sync()
        update: dict = {}
        if cmd.source != self.source:
            update["source"] = self.source
        if cmd.t is None and (now := self._sim_time()) is not None:
            update["t"] = now  # every message carries sim time: the last this client saw
        if update:
            cmd = cmd.model_copy(update=update)
        if cmd.kind in NAMED_KINDS:  # counted before it can be answered
            self._unanswered[cmd.kind] += 1
        elif not isinstance(cmd, SyncCommand):
            self._sent_unnamed[cmd.kind] += 1
        wire.put(self.session, keys.command(self.prefix, self.loop, cmd.kind, self.user), cmd)
        self._last_sent = time.monotonic()

    def check_plant(self) -> None:
        """PlantLost if the plant's token has vanished (``_watch_alive``), without waiting for
        a message: a run busy with a long step ends at once."""
        if self.gone:
            self.holding = False
            # a link's lease (Zenoh: 10 s) outlived by this process's own stall cut it off:
            # a stall within the window before the token vanished and since this client
            # began (one before the run blamed the tuner for a plant killed mid-run: helper)
            gone = self._gone_at if self._gone_at is not None else time.monotonic()
            paused = stalled_before(self._stalls, self._born, gone)
            why = (
                f"this process was cut off from it: it did not run itself for "
                f"{paused:.0f} s (paused or starved)"
                if paused > OVERSLEPT
                else "the plant stopped, or this process was cut off from it"
            )
            raise PlantLost(
                f"loop {self.loop!r}: lost the plant (its liveliness token "
                f"{keys.loop_alive(self.prefix, self.loop)} vanished: {why})"
            )

    def _sim_time(self) -> float | None:
        """The loop's latest sim time this client has seen (s): its last sample's, status's
        or (before the first sync's answer) its info's; None before any."""
        last = [getattr(self, k, None) for k in ("info", "last_sample", "last_status")]
        seen = [m.t for m in last if m is not None]
        return max(seen) if seen else None

    def renew_lease(self) -> None:
        """Renew a held lease if nothing was sent for a renewal interval: a run that waits on
        its own bounded computation in lockstep (the plant does not move meanwhile) is still
        at work, and a slow step on a busy machine must not look like a tuner gone."""
        if self.holding and not self.gone:
            self._keep_lease()

    def _keep_lease(self) -> None:
        """In realtime a run may send nothing for minutes (a relay half-cycle, a verification
        step): a sync every few seconds of wall time keeps the plant's lease on the loop
        alive (any command from the holder renews it), and asks for no answer."""
        if time.monotonic() - self._last_sent > self._renew_every:
            self.send(SyncCommand(loop=self.loop, token=0, source=self.source))

    def sync(self) -> LoopStatus:
        """Barrier: return the loop's status once every command sent so far is applied.

        Bounded by ``timeout`` s of wall time whatever else arrives (samples keep coming in
        realtime); a sync lost on the way (a link re-forming) is sent again every
        RESEND_EVERY s, and any of its answers will do."""
        tokens: set[int] = set()
        started = time.monotonic()
        deadline = started + self.timeout
        resend = 0.0
        resumed = False
        while True:
            now = time.monotonic()
            if now > deadline:
                # a wait through which this process did not run (paused, starved): hear
                # what came meanwhile once more, then say so (the plant's restore followed)
                paused = self._stalls.stalled(started)
                if paused > OVERSLEPT and not resumed:
                    resumed, deadline = True, now + RESUMED_WAIT
                    continue
                own = (
                    f" (this process did not run for {paused:.0f} s: paused or starved)"
                    if paused > OVERSLEPT
                    else ""
                )
                if self.user is not None and not self.gone and not own:
                    # its token there, its commands unanswered: in a secure deployment the
                    # router drops, silently, what this user may not write (an operator's
                    # `autotune set` read as a dead plant: helper 52)
                    own = (
                        f" (the plant's token is there: the router may not let user "
                        f"{self.user!r} write to this loop; in the secure deployment only the "
                        "tuner's credentials do)"
                    )
                raise PlantLost(
                    f"loop {self.loop!r}: no answer to a sync within {self.timeout:g} s" + own
                )
            if now >= resend:
                token = next(self._tokens)
                tokens.add(token)
                self.send(SyncCommand(loop=self.loop, token=token, source=self.source))
                resend = now + RESEND_EVERY
            msg = self._next(wait=max(0.0, min(resend, deadline) - time.monotonic()))
            if isinstance(msg, ProcessSample) and self._flight > 0:  # asked for: kept
                self._flight -= 1
                self._held.append(msg)
            elif isinstance(msg, ProcessSample) and self.info.clock == "lockstep":
                if self.holding:  # none asked for: the loop was advanced by someone else
                    raise ForgedSample(
                        f"loop {self.loop}: sample {msg.seq} (t = {msg.t:.6g} s) came beyond "
                        "every advance this run asked for: another client advanced the loop "
                        "in this run's name (a bus without credentials cannot tell them "
                        "apart: see Security), the plant stepping it without this run's stops "
                        "or PV limits"
                    )
            elif isinstance(msg, ProcessSample):
                # realtime: the loop went on while the sync waited; its samples are the
                # run's as much as any (an experiment that missed them would decide on a
                # record with holes, and a replay of the file, which has them, otherwise)
                self._held.append(msg)
            if isinstance(msg, LoopStatus) and msg.sync_token in tokens:
                self._loop_refused = msg.rejected
                forged = self._count_refusals(msg)
                # the plant takes a sender's commands in order and answers each (applied or
                # refused) before this: what is still counted was refused or lost, and must
                # not stand for a command in this client's name that comes later
                self._unanswered.clear()
                self._sent_unnamed.clear()
                if forged and self.holding:
                    raise ForgedCommand(
                        f"loop {self.loop}: by t = {msg.t:.6g} s the plant {NOT_SENT_REFUSED} "
                        f"({forged}; the last: {self.forged_reject}): another client on the "
                        "bus writes as this run (a bus without credentials cannot tell them "
                        "apart: see Security)"
                    )
                return msg

    def _count_refusals(self, answer: LoopStatus) -> int:
        """A sync's ``answer``: the refusals in this client's name since the last one split
        into its own and ones it did not send (``split_refusals``); how many of the latter."""
        if answer.sync_rejected is None:  # a plant that does not count by sender
            return 0
        before, self._refused = self._refused, answer.sync_rejected
        if before is None:  # sent before this client began (it sends nothing before it)
            return 0
        new = answer.sync_rejected - before
        possible = self._unanswered + self._sent_unnamed
        last = answer.sync_last_reject
        own, forged = split_refusals(new, possible, last)
        # the plant names its last refusal only: another's if none was ours, or of a kind
        # this client did not send
        kind = refused_kind(last)
        theirs = forged > 0 and (own == 0 or (kind is not None and possible[kind] <= 0))
        if own:
            self._own_refused += own
            self._own_reject = (
                last
                if not theirs
                else "its reason not told (the plant names only its last refusal in this "
                f"client's name, of a command it did not send: {last})"
            )
        if forged:
            self.forged_refused += forged
            self.forged_reject = (
                last if theirs else "not told: the plant names only its last, this client's own"
            )
            log.warning(
                "loop %s: %d refusal(s) in this client's name (%s) of commands it did not send "
                "(the last: %s)",
                self.loop,
                forged,
                self.source,
                self.forged_reject,
            )
        return forged

    def command(self, cmd: Command) -> LoopStatus:
        """Send ``cmd`` and confirm it was applied; CommandRefused carries the plant's reason.
        The plant counts refusals per sender (a sync's answer carries ours), so another
        client's refused commands are never taken for ours."""
        before, loop_before = self._own_refused, self._loop_refused
        if isinstance(cmd, ReleaseCommand):
            self.holding = False  # its own release's status must not read as a lost lease
        self.send(cmd)
        status = self._confirmed(before, loop_before)
        self.applied_t = status.t
        if isinstance(cmd, LeaseCommand):
            self.holding = status.leased_by == self.source
            if not self.holding:
                raise CommandRefused(f"loop {self.loop}: lease not granted")
        if isinstance(cmd, ReleaseCommand) and status.leased_by == self.source:
            # not taken, though no refusal was counted as ours (a payload the plant could not
            # read names no sender: a plant of an earlier version refused the release as
            # malformed, and an ok run said nothing while its watchdog undid the gains)
            raise CommandRefused(
                f"loop {self.loop}: the plant still shows the loop held by this client after "
                f"its release ({status.last_reject or 'no reason given'})"
            )
        return status

    def _confirmed(self, before: int, loop_before: int) -> LoopStatus:
        """A sync's status, once the commands sent since the counts ``before`` (this client's
        refusals) and ``loop_before`` (the loop's) were read are applied; CommandRefused with
        the plant's reason if any of them was refused."""
        status = self.sync()
        if status.sync_rejected is None:  # a plant that does not count by sender: the loop's
            if status.rejected > loop_before:
                raise CommandRefused(f"loop {self.loop}: {status.last_reject}")
        elif self._own_refused > before:  # refusals it did not send are not its own
            raise CommandRefused(f"loop {self.loop}: {self._own_reject}")
        return status

    def command_all(self, *cmds: Command) -> LoopStatus:
        """Send ``cmds`` in order and confirm they were applied (CommandRefused names the
        last refusal). In lockstep they go at once and one sync confirms them all: the loop
        does not move between commands (no sim time passes without an advance), so a refusal
        is known before it runs a sample under any of them. Unlike one at a time, the commands
        after a refused one are still applied (the setpoint after refused gains, say): the
        caller, told of the refusal, restores the loop before it advances. In realtime the
        loop runs on meanwhile, so each is confirmed before the next is sent (``command``).
        Not for a lease or its release (``command``)."""
        if not cmds:
            raise ValueError("command_all: none given")
        if self.info.clock != "lockstep" or len(cmds) == 1:
            for cmd in cmds:
                status = self.command(cmd)
            return status
        if any(isinstance(cmd, LeaseCommand | ReleaseCommand) for cmd in cmds):
            raise ValueError("command_all: a lease or a release is sent with command()")
        before, loop_before = self._own_refused, self._loop_refused
        for cmd in cmds:
            self.send(cmd)
        status = self._confirmed(before, loop_before)
        self.applied_t = status.t
        return status

    # --- lockstep samples: asked for by advances, taken in order ------------------------------

    def _ask(self, steps: int) -> None:
        """Lockstep: ask the plant for ``steps`` more periods (their samples come later)."""
        s = self.last_sample
        t = s.t if s is not None else self.last_status.t
        self.send(AdvanceCommand(loop=self.loop, steps=steps, source=self.source, t=t))
        self._flight += steps

    def _take(self, want: int = 1) -> ProcessSample:
        """Lockstep: the next sample in order (one held back by a sync first); ``want``: how
        many are expected, so that the wait is woken once for them all."""
        if self._held:
            return self._held.popleft()
        while True:
            msg = self._next(want=max(1, min(want, self._flight)))
            if isinstance(msg, ProcessSample):
                self._flight = max(0, self._flight - 1)
                return msg

    def _take_ready(self, limit: int) -> list[ProcessSample]:
        """Lockstep: up to ``limit`` samples of a batch already in (decoded as it came), in
        order, under one lock: the samples of an advance are taken together, not one wait
        each. Empty when the next message is anything else, or nothing is in: ``_take``."""
        out: list[ProcessSample] = []
        if self._held:
            return out
        with self._ready:
            inbox, pv_key = self._inbox, self._pv_key
            while inbox and len(out) < limit:
                key, payload, _ = inbox[0]
                if key != pv_key or not isinstance(payload, ProcessSample):
                    break
                inbox.popleft()
                out.append(payload)
        if out:
            self.last_sample = out[-1]
            self._flight = max(0, self._flight - len(out))
        return out

    def _give_back(self, samples: list[ProcessSample]) -> None:
        """Put taken samples back at the head of the inbox, in order (not this advance's)."""
        with self._ready:
            self._inbox.extendleft((self._pv_key, s, "") for s in reversed(samples))

    def advance(self, steps: int) -> list[ProcessSample]:
        """Lockstep: the next ``steps`` samples (those already asked for first), the rest
        asked for in one round trip."""
        out: list[ProcessSample] = []
        while self._held and len(out) < steps:
            out.append(self._held.popleft())
        missing = steps - len(out) - self._flight
        if missing > 0:
            self._ask(missing)
        while len(out) < steps:
            ready = self._take_ready(steps - len(out))
            out += ready if ready else [self._take(steps - len(out))]
        return out

    def samples(
        self, steps: int, band: Band | None = None, record: RecordStops | None = None
    ) -> list[ProcessSample]:
        """The next ``steps`` samples, advancing the clock in lockstep, waiting in realtime;
        with ``band``, ending with the first whose PV leaves it (``advance_within``); in
        lockstep with ``record`` (the samples are a verification record from its first), also
        where its judging would stop it (the plant judges as it steps)."""
        if self.info.clock == "lockstep":
            if band is None and record is None:
                return self.advance(steps)
            whole = band if band is not None else Band(-math.inf, math.inf)
            return self.advance_within(steps, whole, record)
        return until_band(self.next_sample, steps, band)

    def advance_within(
        self, steps: int, band: Band, record: RecordStops | None = None
    ) -> list[ProcessSample]:
        """Lockstep: up to ``steps`` samples in one round trip, the plant stopping after the
        first whose PV leaves ``band`` (the advance's ``stop_below``/``stop_above``) or, with
        ``record``, where the record's judging stops it; this client tells that sample by the
        same test, so it knows the advance has ended. With samples of an earlier advance still
        to take: the next one alone (a record's judging counts from its first sample: none)."""
        if self._held or self._flight:
            return self.advance(1)
        below, above = band.stops()
        op_below, op_above = band.op_stops()
        s = self.last_sample
        cmd = AdvanceCommand(
            loop=self.loop,
            steps=steps,
            source=self.source,
            t=s.t if s is not None else self.last_status.t,
            stop_below=below,
            stop_above=above,
            stop_op_below=op_below,
            stop_op_above=op_above,
            calm=CalmStop.of(band.calm) if band.calm is not None else None,
            record=record,
        )
        self.send(cmd)
        self._flight += steps
        out: list[ProcessSample] = []
        ends = cmd.stop_test()
        while self._flight > 0:
            for j, s in enumerate(got := self._take_ready(self._flight) or [self._take()]):
                if ends(s.pv, s.op):
                    out += got[: j + 1]
                    if j + 1 < len(got):  # the plant stopped at s: these came after it
                        self._give_back(got[j + 1 :])
                    self._flight = 0  # the plant stopped here: nothing more is coming
                    break
            else:
                out += got
        return out

    def hold_arrived(self) -> list[ProcessSample]:
        """Realtime: the samples that came since the run last read, kept for it in order (it
        reads them next) and returned to be watched meanwhile; a status on the way is heeded
        as any (LeaseLost). Does not wait."""
        new: list[ProcessSample] = []
        while (msg := self._next(wait=0.0)) is not None:
            if isinstance(msg, ProcessSample):
                self._held.append(msg)
                new.append(msg)
        return new

    def next_sample(self) -> ProcessSample:
        """The next sample: in lockstep, advance the loop one period first."""
        if self.info.clock == "lockstep":
            return self.advance(1)[0]
        if self._held:  # those that came while a command was confirmed, in order
            return self._held.popleft()
        while True:
            self._keep_lease()
            msg = self._next()
            if isinstance(msg, ProcessSample):
                return msg
