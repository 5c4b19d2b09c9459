"""The console's side of the bus: what it watches, and the buttons' work in worker threads.

Watched (nothing written): every loop's samples (its trend), status (faceplate) and info; the
liveliness tokens of the plant_sim, autotuner and logger processes, of the served loops and of
the runs in progress (who is up); every run's progress and result. Samples and statuses arrive
at the loops' rate and are kept, not forwarded: ``tick`` hands the page what changed, a few
times a second. A service that goes away only changes what the page shows; when it comes back
its tokens and samples are seen again (the session stays on the bus throughout).

Messages to the page are plain dicts with a ``type``: ``services``, ``loop``, ``trend``,
``progress``, ``result``, ``action``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pydantic
import zenoh

from services.autotuner.commands.loops import read_loops
from services.autotuner.design.rules import RULES
from services.console import actions
from services.console.predicted import predicted_curves
from services.console.requests import tune_request
from services.console.trends import HISTORY, Trend
from shared import keys, wire
from shared.errors import AutotuneError, ConfigError, DecodeError, one_line
from shared.messages import (
    LoopStatus,
    PidGains,
    ProcessSample,
    ProcessSamples,
    TuneProgress,
    TuneResult,
)

log = logging.getLogger("console")

Emit = Callable[[dict[str, Any]], None]
SERVICES = ("plant_sim", "tuner", "logger")
POLL = 2.0  # s between two reads of every loop's status and info (loops that publish nothing)
ACTION_THREADS = 4  # tunes of different loops, an apply and a revert at once


class Bridge:
    """The bus as the page sees it. ``emit`` (thread-safe) sends one message to every page."""

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        runs: Path,
        emit: Emit,
        history: float = HISTORY,
        user: str | None = None,
    ):
        self.session, self.prefix, self.runs, self.emit = session, prefix, runs, emit
        self.history, self.user = history, user
        self._lock = threading.Lock()
        # the page's direct writes of gains (Revert, a Reject that writes back) one at a time:
        # two Reverts pressed at once both read the loop before either wrote, both passed the
        # check of the gains the page showed, and both said "reverted" (helper trial)
        self._writes = threading.Lock()
        self.alive: dict[str, set[str]] = {s: set() for s in SERVICES}
        self.loops_alive: set[str] = set()
        self.running: set[str] = set()
        self.status: dict[str, dict[str, Any]] = {}
        self.info: dict[str, dict[str, Any]] = {}
        self.trends: dict[str, Trend] = {}
        self.progress: dict[str, dict[str, Any]] = {}
        self.results: dict[str, dict[str, Any]] = {}
        self._dirty: set[str] = set()
        self._new_progress: set[str] = set()
        # what the page must get in order: each change of a run's phase, then its result
        self._outbox: list[dict[str, Any]] = []
        self._stop = threading.Event()
        self._pool = ThreadPoolExecutor(ACTION_THREADS, thread_name_prefix="console-action")
        self._undeclare: list[Any] = []
        self._threads: list[threading.Thread] = []
        any_loop = keys.ANY
        # samples and statuses come at the loops' rate: a ring that drops the oldest never
        # holds the plant back when the page is slow. The samples (one by one on ``pv``, a
        # lockstep advance's as one message on ``pv_batch``) come through one subscriber to
        # the loops' feeds, so in the order they were sent
        for key, handler in (
            (keys.loop_feed(prefix, any_loop), self._on_sample),
            (keys.status(prefix, any_loop), self._on_status),
        ):
            self._listen(
                session.declare_subscriber(key, zenoh.handlers.RingChannel(65536)), handler
            )
        for key, handler in (
            (keys.tune_progress(prefix, any_loop), self._on_progress),
            (keys.tune_result(prefix, any_loop), self._on_result),
        ):
            self._listen(session.declare_subscriber(key, zenoh.handlers.FifoChannel(1024)), handler)
        tokens = [keys.service_alive(prefix, s, keys.ANY) for s in SERVICES]
        tokens += [keys.loop_alive(prefix, any_loop), keys.tune_running(prefix, any_loop)]
        for key in tokens:
            sub = session.liveliness().declare_subscriber(
                key, zenoh.handlers.FifoChannel(1024), history=True
            )
            self._listen(sub, self._on_token)
        self._thread(self._poll)
        self._thread(self._last_results)

    # --- watching -----------------------------------------------------------------------------

    def _listen(self, sub: Any, handler: Callable[[zenoh.Sample], None]) -> None:
        self._undeclare.append(sub)

        def read() -> None:
            for sample in sub:
                try:
                    handler(sample)
                except DecodeError as err:  # someone else's bad message: not ours to stop on
                    log.warning("%s: %s", sample.key_expr, err)

        self._thread(read)

    def _thread(self, target: Callable[[], None]) -> None:
        th = threading.Thread(target=target, daemon=True)
        self._threads.append(th)
        th.start()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if _replayed(sample):
            return  # a replay of a recorded run is not the loop's present
        parsed = keys.parse_loop_key(self.prefix, str(sample.key_expr))
        if parsed is None or parsed[1] not in ("pv", "pv_batch"):
            return  # the loop's status: read by its own subscriber
        if parsed[1] == "pv":
            one = wire.decode_sample(ProcessSample, sample)
            loop, samples = one.loop, [one]
        else:  # a lockstep advance's samples in one message: each to the trend, in order
            batch = wire.decode_sample(ProcessSamples, sample)
            loop, samples = batch.loop, batch.samples
        with self._lock:
            trend = self.trends.get(loop)
            if trend is None:
                trend = self.trends[loop] = Trend(self.history)
            for s in samples:
                trend.add(s.t, s.pv, s.sp, s.op)

    def _on_status(self, sample: zenoh.Sample) -> None:
        if _replayed(sample) or keys.parse_loop_key(self.prefix, str(sample.key_expr)) is None:
            return  # a replayed status showed a recorded run's gains as the loop's (and the
            # page's Revert, sent with them, was refused as stale)
        st = wire.decode_sample(LoopStatus, sample)
        with self._lock:
            self.status[st.loop] = st.model_dump(mode="json")
            self._dirty.add(st.loop)

    def _on_progress(self, sample: zenoh.Sample) -> None:
        p = wire.decode_sample(TuneProgress, sample)
        msg = p.model_dump(mode="json")
        with self._lock:
            last = self.progress.get(p.loop)
            if last is None or (last["run_id"], last["phase"]) != (p.run_id, p.phase):
                self._outbox.append({"type": "progress", **msg})  # however short, shown
            self.progress[p.loop] = msg
            self._new_progress.add(p.loop)

    def _on_result(self, sample: zenoh.Sample) -> None:
        self._pool.submit(self._publish_result, wire.decode_sample(TuneResult, sample))

    def _publish_result(self, r: TuneResult, earlier: bool = False) -> None:
        """``earlier``: a result from before the console started (the page draws it, and
        does not post it as news)."""
        result = r.model_dump(mode="json")
        msg: dict[str, Any] = {"type": "result", "loop": r.loop, "result": result}
        try:
            msg["predicted"] = predicted_curves(result)
        except Exception as err:  # a curve is an extra: the result still goes to the page
            log.warning("predicted responses of run %s: %s", r.run_id, one_line(err))
            msg["predicted"] = {}
        with self._lock:
            first = self.results.get(r.loop)
            if r.applied_from and first and first["result"]["run_id"] == r.applied_from:
                # the apply of a run shown: the run stays, with how its gains went on
                msg = {**first, "applied_by": result}
            self.results[r.loop] = msg
            # after the run's last phase, which came before it
            self._outbox.append({**msg, "earlier": True} if earlier else msg)

    def _last_results(self) -> None:
        """Each loop's last result, kept by the tuner (a console started after a run)."""
        try:
            key = keys.tune_result(self.prefix, keys.ANY)
            for r in wire.query_all(self.session, key, TuneResult, 2.0):
                if r.loop not in self.results:
                    self._publish_result(r, earlier=True)
        except zenoh.ZError as err:  # the session closing under it
            log.info("last results: %s", err)

    def _on_token(self, sample: zenoh.Sample) -> None:
        key, put = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            target: set[str] | None = None
            name: str | None = None
            for service in SERVICES:
                if (node := keys.service_node(self.prefix, service, key)) is not None:
                    target, name = self.alive[service], node
            if (loop := keys.parse_loop_key(self.prefix, key)) is not None:
                target, name = self.loops_alive, loop[0]
                if not put:  # its plant went: what it said last is no longer the loop's
                    self.status.pop(name, None)
                    self.info.pop(name, None)
            if (tune := keys.parse_tune_key(self.prefix, key)) is not None:
                target, name = self.running, tune[0]
            if target is None or name is None:
                return
            (target.add if put else target.discard)(name)
            msg = self._services()
        self.emit(msg)

    def _services(self) -> dict[str, Any]:
        return {
            "type": "services",
            **{s: sorted(v) for s, v in self.alive.items()},
            "loops": sorted(self.loops_alive),
            "running": sorted(self.running),
        }

    def _poll(self) -> None:
        """Every loop's status and info, by query, every POLL s: a lockstep loop nobody
        drives publishes nothing, and its info (units, description) is only had so."""
        while not self._stop.is_set():
            try:
                found = read_loops(self.session, self.prefix, 1.5)
            except (zenoh.ZError, AutotuneError) as err:
                log.info("reading the loops: %s", err)
                found = {}
            with self._lock:
                for loop, (st, info) in found.items():
                    if info is not None and self.info.get(loop) != info.model_dump(mode="json"):
                        self.info[loop] = info.model_dump(mode="json")
                        self._dirty.add(loop)
                    if loop not in self.status:
                        self.status[loop] = st.model_dump(mode="json")
                        self._dirty.add(loop)
            self._stop.wait(POLL)

    # --- what the page gets -------------------------------------------------------------------

    def _loop(self, loop: str) -> dict[str, Any]:
        return {
            "type": "loop",
            "loop": loop,
            "status": self.status.get(loop),
            "info": self.info.get(loop),
        }

    def snapshot(self) -> list[dict[str, Any]]:
        """Everything a page that just connected needs to draw: the form's choices first."""
        hello = {
            "type": "hello",
            "prefix": self.prefix,
            "history": self.history,
            "runs": str(self.runs),
            "rules": [
                {"name": n, "controller": r.controller, "kind": r.kind} for n, r in RULES.items()
            ],
        }
        with self._lock:
            out = [hello, self._services()]
            out += [self._loop(lp) for lp in sorted(self.status)]
            out += [
                {"type": "trend", "loop": lp, "reset": True, **t.snapshot()}
                for lp, t in sorted(self.trends.items())
                if t.rows
            ]
            out += [{"type": "progress", **p} for p in self.progress.values()]
            # marked as what the page finds, not news: it draws them, but does not post them
            # as a result just come (each page load did, stamped with the load's time)
            out += [{**r, "earlier": True} for r in self.results.values()]
        return out

    def tick(self) -> list[dict[str, Any]]:
        """What changed since the last tick: faceplates, trend points, the latest progress."""
        with self._lock:
            out = [self._loop(lp) for lp in sorted(self._dirty)]
            self._dirty.clear()
            for lp, t in sorted(self.trends.items()):
                batch = t.take_new()
                if batch is not None:
                    out.append({"type": "trend", "loop": lp, **batch})
            sent = {(m.get("run_id"), m.get("t")) for m in self._outbox if m["type"] == "progress"}
            out += self._outbox
            out += [  # the latest progress of a phase already shown (its t and figures)
                {"type": "progress", **self.progress[lp]}
                for lp in sorted(self._new_progress)
                if (self.progress[lp]["run_id"], self.progress[lp]["t"]) not in sent
            ]
            self._outbox = []
            self._new_progress.clear()
        return out

    # --- the buttons ----------------------------------------------------------------------------

    def act(self, msg: dict[str, Any], reply: Emit) -> None:
        """Run one request of the page (``tune``, ``cancel``, ``apply``, ``reject``,
        ``revert``) in a worker; ``reply`` gets ``action`` messages with its ``id``: ``ok``
        false and a one-line ``message`` on bad input or refusal."""
        kind, ident = msg.get("type"), msg.get("id")
        work = {
            "tune": self._tune,
            "cancel": self._cancel,
            "apply": self._apply,
            "reject": self._reject,
            "revert": self._revert,
        }.get(str(kind))

        def say(ok: bool, message: str, **extra: Any) -> None:
            reply(
                {
                    "type": "action",
                    "id": ident,
                    "action": kind,
                    "ok": ok,
                    "message": message,
                    **extra,
                }
            )

        if work is None:
            say(False, f"type: {kind!r} is not a request the console takes")
            return

        def job() -> None:
            try:
                work(msg, say)
            except (AutotuneError, ValueError) as err:
                say(False, one_line(err, 500))
            except zenoh.ZError as err:
                say(False, f"the bus: {one_line(err, 300)}")
            except Exception as err:  # a bug: said on the page and logged, the console goes on
                log.exception("%s request", kind)
                say(False, f"internal error (a bug, please report it): {one_line(err, 300)}")

        self._pool.submit(job)

    def _tune(self, msg: dict[str, Any], say: Callable[..., None]) -> None:
        # no fields: the CLI's defaults; fields that are not a form ([], "") are refused, not
        # taken as none (a request with fields [] started a tune that applied its gains)
        req = tune_request(self.prefix, msg.get("loop"), msg.get("fields", {}))

        def accepted(a: Any) -> None:
            say(
                True,
                f"run {a.run_id} on {a.loop} accepted ({a.method}, rule {a.rule})",
                run_id=a.run_id,
                stage="accepted",
            )

        r = actions.run_tune(self.session, self.prefix, req, accepted)
        say(
            r.status in ("ok", "proposed"),
            f"run {r.run_id}: {r.status}" + (f" ({r.reason})" if r.reason else ""),
            run_id=r.run_id,
            stage="done",
        )

    def _cancel(self, msg: dict[str, Any], say: Callable[..., None]) -> None:
        loop = _field(msg, "loop")
        actions.cancel(self.session, self.prefix, loop, msg.get("run_id"))
        say(True, f"cancel sent to {loop}'s run: the tuner restores the loop")

    def _apply(self, msg: dict[str, Any], say: Callable[..., None]) -> None:
        run_id = _field(msg, "run_id")
        rule = _field(msg, "rule") if msg.get("rule") else None
        req = actions.apply_request(self.session, self.prefix, self.runs, run_id, rule)

        def accepted(a: Any) -> None:
            say(
                True,
                f"applying run {run_id}'s {req.rule} gains to {a.loop} (run {a.run_id}, "
                "verified as a tune)",
                run_id=a.run_id,
                stage="accepted",
            )

        r = actions.run_tune(self.session, self.prefix, req, accepted)
        done = "applied and verified" if r.applied else "not applied, the loop restored"
        say(
            r.applied and r.status == "ok",
            f"run {r.run_id}: {r.status}, {done}" + (f" ({r.reason})" if r.reason else ""),
            run_id=r.run_id,
            stage="done",
        )

    def _reject(self, msg: dict[str, Any], say: Callable[..., None]) -> None:
        run_id, loop = _field(msg, "run_id"), _field(msg, "loop")
        with self._lock:
            shown = self.results.get(loop) or {}
        last, by = shown.get("result") or {}, shown.get("applied_by") or {}
        # the change to undo: the run's own (applied when verified), or its later apply's
        changed_by = (
            run_id if last.get("applied") else by.get("run_id") if by.get("applied") else None
        )
        if last.get("run_id") != run_id:  # not the run the page shows: one on record?
            actions.check_run_of(self.runs, self.prefix, loop, run_id)
        if last.get("run_id") == run_id and changed_by:
            with self._writes:
                done = actions.revert(
                    self.session,
                    self.prefix,
                    self.runs,
                    loop,
                    changed_by,
                    self.user,
                    last_only=True,
                )
            say(
                True, f"run {run_id} rejected: {loop}'s gains before it written back", reverted=done
            )
        else:
            say(True, f"run {run_id} rejected: its gains were not applied, {loop} unchanged")

    def _revert(self, msg: dict[str, Any], say: Callable[..., None]) -> None:
        loop = _field(msg, "loop")
        shown = _shown_gains(msg)
        with self._writes:
            done = actions.revert(
                self.session, self.prefix, self.runs, loop, None, self.user, shown=shown
            )
        g = done["after"]
        ti = "off" if g["ti"] is None else f"{g['ti']:.4g} s"
        say(
            True,
            f"{loop} reverted: Kc {g['kc']:.4g}, Ti {ti}, Td {g['td']:.4g} s "
            "(confirmed by the plant)",
            reverted=done,
        )

    def close(self, timeout: float = 5.0) -> None:
        """Stop watching: the subscribers undeclared, the threads joined (bounded), so that
        none is inside a call of the session when it closes. A run the page started goes on
        in its tuner (as after `autotune tune --detach`)."""
        self._stop.set()
        for sub in self._undeclare:
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()
        deadline = time.monotonic() + timeout
        for th in self._threads:
            th.join(max(0.0, deadline - time.monotonic()))
        self._pool.shutdown(wait=False, cancel_futures=True)


def _replayed(sample: zenoh.Sample) -> bool:
    """A message ``autotune replay`` republished from a recording (its attachment says so)."""
    mark = sample.attachment
    return mark is not None and wire.replay_source(mark.to_bytes()) is not None


def _shown_gains(msg: dict[str, Any]) -> PidGains | None:
    """The gains the page showed as the loop's (``gains``, optional); ConfigError naming the
    field when they are not gains."""
    value = msg.get("gains")
    if value is None:
        return None
    try:
        return PidGains.model_validate(value)
    except pydantic.ValidationError as err:
        raise ConfigError(f"gains: {wire.describe_validation_error(err)}") from None


def _field(msg: dict[str, Any], name: str) -> str:
    """A request's text field; ConfigError naming it when it is missing or not text."""
    value = msg.get(name)
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{name}: {value!r} is not a {name.replace('_', ' ')}")
    return value
