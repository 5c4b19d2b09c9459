"""The change history of every loop's gains (seed 001: "make note of the previous controller
settings, the new settings, and the date and time of change").

Kept by the logger, append-only, in ``<runs>/history.jsonl`` beside the run files: one JSON
object per line, written and flushed as it happens, so it survives restarts. Two records:

* ``change``: the gains of a loop differ from those it had; the plant's status says who caused
  it (``by_source``, the command's label, and ``by_user``, the Zenoh user its key names: the
  sender's identity as the bus knows it, verified by the router in a secure deployment) and
  what (``cause``: ``gains``, ``release``…). Changes under a tuning run's lease are the
  experiment's and are not changes of the loop's settings: the run's net change is recorded
  when it lets the loop go (the release), against the gains in force before it took it.
  ``run_id`` names the run (a ``tuner:<run id>`` source), ``before`` and ``after`` are the
  whole gains (``kc``, ``ti``, ``td``, ``n``, ``beta``). A loop first seen is learned, not a
  change. A plant that (re)starts with other gains than the last known is a change with
  ``cause`` ``start`` (tuned gains lost with the plant's restart show here); after this
  logger's own restart the last gains on record are the baseline, and a loop whose gains
  moved meanwhile gets a change with ``cause`` ``unseen`` (who is not known); so does a change
  first seen on a status that does not change gains (a setpoint's, a sync's: the change was
  missed, the logger paused or its messages lost), not charged to that status's sender, with
  the ``run_id`` of the run whose result applied exactly those gains, if one was seen.
* ``tune``: a run's result, applied or not (its status, rule, the gains it chose and the
  previous ones, its verification before and after): ``autotune history`` shows a change
  with the verification of the run that made it, and ``autotune apply`` what a run
  recommended.

Times: ``utc`` (ISO 8601, when the logger saw it) and ``t`` (the loop's sim time, s). Every
record names its bus's ``prefix``: one runs directory may serve several (a loop id is a loop
only within its prefix).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pydantic

from shared import keys
from shared.history_file import HISTORY_FILE, RUN_SOURCE, read_history, run_of
from shared.messages import LoopStatus, TuneResult

log = logging.getLogger("logger")

# the status reasons that change a loop's gains (a command's, a lease's end, the plant's
# restore): a change first seen on any other status was made where this logger missed it
GAIN_CAUSES = frozenset({"gains", "release", "watchdog"})


# the words of the selection's warning that the run's model misses the plant
# (``design.selection``): its measured ultimate point, or its record
MODEL_MISSES = ("model misses the plant", "model misses its record")


def model_misses(warnings: list[str] | None) -> str | None:
    """The run's warning that its model misses the plant, if it gave one."""
    return next((w for w in warnings or [] if any(m in w for m in MODEL_MISSES)), None)


@dataclass
class _Loop:
    node: str
    # in force outside any lease: the baseline of the next change (None: first heard under
    # a run's lease, the gains before it not known to this logger)
    gains: dict[str, Any] | None
    leased: bool


class ChangeHistory:
    """Watches the loops' statuses and the runs' results; appends records to the file."""

    def __init__(
        self,
        runs_dir: Path,
        prefix: str,
        now: Callable[[], datetime] = lambda: datetime.now(UTC),
        bus: str | None = None,
    ):
        self.path = Path(runs_dir) / HISTORY_FILE
        self.prefix = prefix
        # the bus its records name: the prefix, under the Zenoh namespace if there is one
        self.bus = bus or prefix
        self.now = now
        self.loops: dict[str, _Loop] = {}
        self.written = 0
        self.invalid = 0
        # the last gains on record per loop (and the node they were of): a restart's baseline
        self._on_record: dict[str, tuple[str | None, dict[str, Any]]] = {}
        # per loop, the last run whose result says it applied gains, and those gains
        self._applied: dict[str, tuple[str, dict[str, Any]]] = {}
        # per loop first heard under a lease: the run whose release was heard (its result
        # not yet), and the last result heard (its release not yet): the run's change is
        # its result's, whichever comes second
        self._released: dict[str, str | None] = {}
        self._results: dict[str, TuneResult] = {}
        # loops with evidence of a new plant instance whose status has not been heard since:
        # the next one (the service asks for it) is the new instance's start
        self._restarted: set[str] = set()
        for rec in read_history(self.path):  # this bus's (prefix's) loops only
            if (
                rec.get("record") == "change"
                and isinstance(rec.get("after"), dict)
                and rec.get("prefix", self.bus) == self.bus
            ):
                self._on_record[str(rec.get("loop"))] = (rec.get("node"), rec["after"])

    def handle(self, key: str, payload: bytes) -> None:
        """One live message from the bus (statuses and results; the rest is ignored)."""
        if not key.endswith(("/status", "/result")):  # every sample passes here: cheaply out
            return
        loop_key = keys.parse_loop_key(self.prefix, key)
        tune_key = keys.parse_tune_key(self.prefix, key)
        try:
            if loop_key is not None and loop_key[1] == "status":
                self._status(LoopStatus.model_validate_json(payload))
            elif tune_key is not None and tune_key[1] == "result":
                self._result(TuneResult.model_validate_json(payload))
        except pydantic.ValidationError:
            self.invalid += 1  # the recorder counts and logs invalid messages already

    def learn(self, key: str, payload: bytes) -> None:
        """A loop's status asked for at the logger's start: taken only for a loop no live
        status has taught yet (a live one may be newer than this answer)."""
        loop_key = keys.parse_loop_key(self.prefix, key)
        if loop_key is None or loop_key[1] != "status" or loop_key[0] in self.loops:
            return
        self.handle(key, payload)

    def plant_restarted(self, loop: str) -> None:
        """Evidence of a new plant instance of ``loop`` (the recorder's: its samples' number
        or sim time went back, another node, a status ``start``): the loop's next status is
        taken as the new instance's start, its gains against the last known (cause
        ``start``). Why: the plant puts its ``start`` status as its session opens, and
        it is lost where this logger is not yet reached (the killed plant held the bus's
        rendezvous port: the logger connects again a moment later); in realtime no other
        status comes until a command, so a restart that lost tuned gains was filed late, as
        ``unseen``, or not at all (helper trial: `history hx1` still showed the set's Kc 2.5
        while the restarted plant ran Kc 2)."""
        if loop in self.loops:
            self._restarted.add(loop)

    def restart_status(self, key: str, payload: bytes) -> None:
        """The status asked of a loop on evidence of its plant's restart: taken only if no
        live status has been heard since (it is the newer)."""
        loop_key = keys.parse_loop_key(self.prefix, key)
        if loop_key is None or loop_key[1] != "status" or loop_key[0] not in self._restarted:
            return
        self.handle(key, payload)

    def awaits_restart_status(self, loop: str) -> bool:
        """Is the status of ``loop``'s new plant instance still awaited?"""
        return loop in self._restarted

    # --- what changed -----------------------------------------------------------------------

    def _status(self, st: LoopStatus) -> None:
        gains = st.gains.model_dump()
        known = self.loops.get(st.loop)
        restarted = st.loop in self._restarted
        self._restarted.discard(st.loop)
        if known is None or known.node != st.node or st.reason == "start" or restarted:
            self._first_seen(st, gains, known, restarted)
            return
        if st.leased_by is not None:  # a supervisor's experiment: its changes are not settings
            known.leased = True
            return
        known.leased = False
        if known.gains is None:  # first heard under a lease that has now ended
            known.gains = gains
            run = run_of(st.by_source) if st.reason == "release" else None
            heard = self._results.pop(st.loop, None)
            if heard is not None and run is not None and heard.run_id == run:
                self._change_from_result(heard, st.node)
            else:
                self._released[st.loop] = run
            return
        if gains != known.gains:
            if st.reason in GAIN_CAUSES:  # the change this status reports, by its sender
                by, user, cause, run = st.by_source, st.by_user, st.reason, run_of(st.by_source)
            else:  # missed (this logger paused, or its messages lost): not this sender's
                run = self._applied_by(st.loop, gains)
                by, user, cause = None, None, "unseen"
            self._change(st.loop, st.node, st.t, st.mode, known.gains, gains, cause, by, user, run)
            known.gains = gains

    def _applied_by(self, loop: str, gains: dict[str, Any]) -> str | None:
        """The run whose result (seen by this logger) applied exactly ``gains`` to ``loop``,
        the last such: what a missed release most likely was."""
        run, chosen = self._applied.get(loop, (None, None))
        if run is None or not chosen:
            return None
        same = all(gains.get(k) == v for k, v in chosen.items() if k in gains)
        return run if same else None

    def _first_seen(
        self, st: LoopStatus, gains: dict[str, Any], known: _Loop | None, restarted: bool = False
    ) -> None:
        """Learn a loop, or a new plant instance of it (``restarted``: the first status heard
        since evidence of one). Gains that differ from the last known are recorded: a plant
        (re)started with its configured gains (``start``), another
        plant node serving the loop (``another plant``), or a change made while this logger
        was not running (``unseen``; the last gains on record are its baseline)."""
        leased = st.leased_by is not None
        node, on_record = self._on_record.pop(st.loop, (None, None))
        if known is not None:
            prev = known.gains
        else:
            prev = on_record if node == st.node or st.reason == "start" else None
        if st.reason == "start":
            cause = "start"
        elif known is not None and known.node != st.node:
            cause = "another plant"
        elif restarted:
            cause = "start"
        else:
            cause = "unseen"
        if prev is not None and prev != gains and not leased:
            self._change(st.loop, st.node, st.t, st.mode, prev, gains, cause)
        # under a lease with nothing on record, the gains in force are the experiment's, not
        # the loop's: taken as the baseline, a rejected run's restore was filed as its change
        # and `autotune revert` put the rejected gains back (helper trial: a logger that came
        # up as the run went on)
        baseline = prev if leased else gains
        self.loops[st.loop] = _Loop(st.node, baseline, leased)

    def _result(self, r: TuneResult) -> None:
        known = self.loops.get(r.loop)
        if known is not None and known.gains is None:  # its release not heard yet
            self._results[r.loop] = r
        elif self._released.get(r.loop, "") == r.run_id and known is not None:
            del self._released[r.loop]
            self._change_from_result(r, known.node)
        chosen = (r.chosen or {}).get("isa")
        if r.applied and isinstance(chosen, dict):
            self._applied[r.loop] = (r.run_id, chosen)
        self._append(
            {
                "record": "tune",
                "utc": self._utc(),
                "t": r.t,
                "prefix": self.bus,
                "loop": r.loop,
                "run_id": r.run_id,
                "status": r.status,
                "reason": r.reason,
                "method": r.method,
                "rule": r.rule,
                "applied": r.applied,
                "recommended": (r.recommended or {}).get("rule"),
                "previous_gains": r.previous_gains.model_dump() if r.previous_gains else None,
                "chosen": chosen,
                "verification_before": r.before.model_dump() if r.before else None,
                "verification_after": r.after.model_dump() if r.after else None,
                "applied_from": r.applied_from,
                # what autotune apply needs of a run that did not apply its gains: every rule's
                # ISA gains, whether each is within the safety envelope and its predicted
                # overshoot, K_u, and the loop it identified (to check it is still that one)
                "gains": {k: v.get("isa") for k, v in r.gains.items()},
                "robustness": {
                    k: {
                        "within_envelope": v.get("within_envelope"),
                        "overshoot_pct": v.get("overshoot_pct"),
                        "ms": v.get("ms"),
                    }
                    for k, v in r.robustness.items()
                },
                "ku": r.ku,
                # the watch's T_u where no tuner remembers the run (one restarted since)
                "pu": r.pu,
                # the PV's units: `history` gives the verification's IAE in them
                "pv_units": r.pv_units,
                "identified_on": r.identified_on,
                "timescale": r.timescale,
                "noise": r.noise,
                # the --ms-bound the gains were judged within: `autotune apply` verifies them
                # within it (without it here, an apply of a run tuned with --ms-bound 3 had
                # its gains checked at Kc × 2, not the 1.5 that bound admits)
                "ms_bound": r.ms_bound,
                # the --max-op-noise the run's recommendation and verification held its
                # gains to: `autotune apply` holds them to it too (without it, a run tuned
                # with --max-op-noise 60 proposed SIMC PI at 36 % predicted, and its apply
                # rejected it at the default 10 %)
                "max_op_noise": r.max_op_noise,
                # and its other acceptance limits, where asked (``TuneResult``)
                "max_overshoot": r.max_overshoot,
                "max_decay_ratio": r.max_decay_ratio,
                "overshoot_miss": r.overshoot_miss,
                # why none of them may be applied (``autotune apply`` refuses the run)
                "contradiction": r.contradiction,
                # the run's model misses the plant, as its warning says: ``autotune apply
                # --no-verify`` refuses its gains, as the run itself would have
                "model_misses": model_misses(r.warnings),
            }
        )

    def late_result(self, payload: bytes) -> None:
        """A run's result this logger missed on the bus and asked its tuner for (it was paused
        or cut off as the run ended, ``LoggerService._ask_late_results``): its ``tune``
        record, and the run's net change, which its release status said where this logger
        could not hear it, from the gains the result says the run left (cause ``release``,
        the run named). Without it a paused logger filed the run's gains later as ``unseen``,
        who not known, and ``autotune revert --to RUN`` found no change by the run (helper
        trial)."""
        try:
            r = TuneResult.model_validate_json(payload)
        except pydantic.ValidationError:
            self.invalid += 1
            return
        self._result(r)
        left = (r.left or {}).get("gains")
        known = self.loops.get(r.loop)
        # only while the last status heard was under a lease (the run's, or a next run's):
        # one heard since outside any lease already says the loop's gains, and a change
        # written then (an operator's after the run) would be charged to the run (review)
        if known is None or not known.leased or not isinstance(left, dict):
            return
        if known.gains is None:  # first heard under this run's lease: the result says all
            self._results.pop(r.loop, None)
            self._change_from_result(r, known.node)
            known.gains = left
            return
        if left == known.gains:
            return  # nothing changed: a rejected run put the gains back
        mode = (r.left or {}).get("mode")
        by = f"{RUN_SOURCE}{r.run_id}"
        late = "from the run's result: its release status was not heard"
        self._change(
            r.loop, known.node, r.t, mode, known.gains, left, "release", by, run=r.run_id, late=late
        )
        known.gains = left

    def _change_from_result(self, r: TuneResult, node: str) -> None:
        """The change a run that applied its gains made, from its result alone (its previous
        gains, and those it left): for a loop this logger first heard under the run's lease,
        whose gains before it were never heard. A run that did not apply its gains changed
        nothing."""
        left = (r.left or {}).get("gains")
        before = r.previous_gains.model_dump() if r.previous_gains is not None else None
        if not (r.applied and isinstance(left, dict) and before is not None and left != before):
            return
        self._change(
            r.loop,
            node,
            r.t,
            (r.left or {}).get("mode"),
            before,
            left,
            "release",
            f"{RUN_SOURCE}{r.run_id}",
            run=r.run_id,
            late="this logger first heard the loop under the run's lease: the gains before "
            "it are the run's result's",
        )

    def _change(
        self,
        loop: str,
        node: str,
        t: float,
        mode: str | None,
        before: dict[str, Any],
        after: dict[str, Any],
        cause: str,
        by: str | None = None,
        user: str | None = None,
        run: str | None = None,
        **more: Any,
    ) -> None:
        """A ``change`` record of ``loop``'s gains (of plant ``node``) from ``before`` to
        ``after``, at sim time ``t`` in ``mode``: its ``cause``, sender (``by``, ``user``),
        run and any ``more`` fields."""
        self._append(
            {
                "record": "change",
                "utc": self._utc(),
                "t": t,
                "prefix": self.bus,
                "loop": loop,
                "node": node,
                "by_source": by,
                "by_user": user,
                "cause": cause,
                "run_id": run,
                "mode": mode,
                "before": before,
                "after": after,
                **more,
            }
        )

    # --- the file ---------------------------------------------------------------------------

    def _utc(self) -> str:
        return self.now().isoformat().replace("+00:00", "Z")

    def _append(self, record: dict[str, Any]) -> None:
        line = json.dumps(record, separators=(",", ":"), allow_nan=False)
        data = memoryview((line + "\n").encode("utf-8"))
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            end = os.lseek(fd, 0, os.SEEK_END)
            try:
                while data:
                    data = data[os.write(fd, data) :]
            except OSError:  # a full disk: the part written taken back, so that the next
                # record starts a line of its own (it was joined to the cut one and lost too:
                # helper trial of a full disk)
                with contextlib.suppress(OSError):
                    os.ftruncate(fd, end)
                raise
        finally:
            os.close(fd)
        self.written += 1
        if record["record"] == "change":
            log.info(
                "loop %s: gains changed by %s (%s)",
                record["loop"],
                record["by_source"] or "someone unseen",
                record["cause"],
            )
