"""Whether a logger recorded a run: its liveliness tokens watched for the run's length.

A run that no logger recorded is not on record: ``autotune history`` and ``revert`` cannot
know its change of the loop's gains (seen: a logger killed mid-run, the tune ended ok, and
revert answered "no change of hx1's gains on record"). The run's result says so; and when a
logger missed process samples meanwhile (its ``dropped`` count grew: it fell behind, was
paused or starved), that its record may have gaps."""

from __future__ import annotations

import threading
import time

import zenoh

from services.autotuner.loop_client import wait_for_token
from shared import keys, wire
from shared.messages import IncompleteRun, LoggerStatus

ASK = 2.0  # s: a logger's status, asked at the run's start and end
# s: how long a client waits for a logger to finish a run's file once the result is in: a
# logger holds the run open until the plant's last samples catch up with the result, at
# most its RESULT_GRACE (2 s) and a tick (0.25 s) after it
FINISH_WAIT = 4.0
STALL = 1.0  # s: a stall of this tuner's own process that can explain a logger out of sight


class RecorderWatch:
    """The loggers announcing ``<prefix>/logger/*/alive`` from now until ``verdict()``."""

    def __init__(self, session: zenoh.Session, prefix: str):
        self.session, self.key = session, keys.logger_alive(prefix, "*")
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._seen = False  # any logger in sight since the start
        self._gap = False  # all out of sight at some moment after one was seen
        self._sub = session.liveliness().declare_subscriber(self.key, self._on, history=True)
        self._status_key = keys.logger_status(prefix, "*")
        self._before: dict[str, int] = {}
        self._baseline = threading.Thread(target=self._ask_before, daemon=True)
        self._baseline.start()

    def _ask_before(self) -> None:
        self._before = {node: st.dropped for node, st in self._statuses().items()}

    def _statuses(self) -> dict[str, LoggerStatus]:
        """Each logger's status, by node."""
        try:
            answers = wire.query_all(self.session, self._status_key, LoggerStatus, ASK)
        except zenoh.ZError:  # the session closing as the service stops
            return {}
        return {st.node: st for st in answers}

    def _on(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr)
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(name)
                self._seen = True
            else:
                self._alive.discard(name)
                self._gap = self._gap or (self._seen and not self._alive)

    def verdict(self, stalled: float = 0.0, run_id: str | None = None) -> str | None:
        """A warning for the run's result, or None when a logger was in sight throughout;
        ``stalled``: s this tuner's own process did not run during the run (paused, starved),
        long enough for its peers to drop it: then everything went out of its sight, the
        logger with the rest, and that is said rather than blamed on the logger.
        Stops watching, and waits (at most ``ASK``) for the start's question to end: the
        caller may close the session next, and Zenoh refuses to close one a query is still
        using ("Already borrowed", seen in CI on a run that ended within moments). With
        ``run_id``: whether a logger that answers at the end holds the run open (one that
        came up after the run's start never opens it)."""
        self._baseline.join(ASK)
        with self._lock:
            seen, gap, alive = self._seen, self._gap, bool(self._alive)
        if not seen:  # a run that ended within moments of its start: look once more
            seen = alive = wait_for_token(self.session, self.key, 0.5)
        self._sub.undeclare()
        if not seen:
            return (
                f"no logger recorded this run (nothing announced {self.key}): neither the run "
                "nor its change of the loop's gains is on record (`autotune history` and "
                "`revert` will not know it)"
            )
        if gap and stalled >= STALL:
            return (
                f"this tuner's own process did not run for {stalled:.0f} s of the run (paused "
                "or starved), and the logger went out of its sight with the rest of the bus "
                "meanwhile: whether the logger recorded the run throughout, `autotune runs` "
                "shows"
            )
        if gap:
            return (
                "the logger went out of sight during the run (killed, paused or cut off): its "
                f"record of the run may be incomplete{'' if alive else ', and none is back'} "
                "(`autotune runs` shows what was written)"
            )
        statuses = self._statuses()
        after = {node: st.dropped for node, st in statuses.items()}
        if (
            run_id is not None
            and statuses
            and not any(run_id in st.open_runs for st in statuses.values())
        ):
            # a logger in sight throughout, but not recording this run: it came up after the
            # run's start (seen: a tune started as `autotune up` brought the stack up, with no
            # file and no word)
            return (
                f"no logger has this run open ({', '.join(sorted(statuses))} answered): one "
                "that came up after the run started does not record it, nor one that could "
                "not write its file (a full disk: its log says so), so neither the run nor "
                "its change of the loop's gains may be on record (`autotune history` and "
                "`revert` will not know it)"
            )
        if not self._before:  # no logger answered at the start (busy, paused)
            if after:
                return None  # nothing to compare its count with
            # nor at the end: a logger paused throughout is in sight (its token stays up
            # until Zenoh's lease drops it) but records nothing (seen: an ok lockstep run with
            # no file and no word)
            return (
                "no logger answered at the start or the end of the run (paused or starved?): "
                "whether the run is on record is not known (`autotune runs` shows what was "
                "written)"
            )
        if not after:  # answered at the start, not at the end (a logger paused meanwhile)
            return (
                "the logger did not answer at the end of the run (paused or starved?): its "
                "record of the run may be incomplete (`autotune runs` shows what was written)"
            )
        missed = sum(max(0, after[n] - d) for n, d in self._before.items() if n in after)
        if missed:
            return (
                f"the logger missed {missed} process samples during this run (of this loop or "
                "another: it fell behind, paused or starved): its record of the run may have "
                "gaps (`autotune runs` shows what was written)"
            )
        return None


LOOK = 0.5  # s: how long a command looks for a logger's token (one up shows in milliseconds)


def unrecorded_change(session: zenoh.Session, prefix: str, loop: str) -> str | None:
    """A warning for a command that changed ``loop``'s gains while no logger is in sight
    (None: one is): the change is not on record, and a logger that comes up later files it
    as ``unseen``, who not known (seen: a revert with the logger stopped said nothing, and
    the history later blamed no one)."""
    if wait_for_token(session, keys.logger_alive(prefix, keys.ANY), LOOK):
        return None
    return (
        f"warning: no logger is up on {prefix}/: this change of {loop}'s gains is not on "
        "record (a logger that comes up files it as unseen, who not known: `autotune "
        "history`, `revert`)"
    )


def incomplete_record(
    session: zenoh.Session, prefix: str, run_id: str, wait: float = FINISH_WAIT
) -> IncompleteRun | None:
    """A logger's word that run ``run_id``'s file could not be written whole (its status's
    ``incomplete_runs``), asked until no logger that answers holds the run open any more (at
    most ``wait`` s); None when none says so, or none answers. Why: a disk that filled at
    the file's last write, as the run ended, came after the tuner's result and its check of
    the loggers: the client printed the run as recorded, its log alone said otherwise."""
    deadline = time.monotonic() + wait
    while True:
        try:
            statuses = wire.query_all(session, keys.logger_status(prefix, "*"), LoggerStatus, ASK)
        except zenoh.ZError:  # the session closing
            return None
        for st in statuses:
            for run in st.incomplete_runs:
                if run.run_id == run_id:
                    return run
        if not any(run_id in st.open_runs for st in statuses) or time.monotonic() >= deadline:
            return None
        time.sleep(0.05)


def incomplete_line(run: IncompleteRun) -> str:
    """The one line that says run's record is incomplete, and where."""
    if run.on_disk:
        return (
            f"warning: run {run.run_id}'s record is incomplete: the logger could not finish "
            f"its file {run.path} ({run.reason}); what reached the disk: autotune recover "
            f"{run.path} -o FIXED.mcap"
        )
    return (
        f"warning: run {run.run_id} is not on record: the logger could not write its file "
        f"{run.path} ({run.reason}), nothing of it reached the disk"
    )
