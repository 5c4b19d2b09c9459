"""autotuner over Zenoh: tunes loops it does not own, several at once.

Requests arrive on the queryable ``<prefix>/tuner/<node>/tune`` (a TuneRequest); the reply is
a TuneAccepted, or an error naming the field at fault. Each run holds the liveliness token
``<prefix>/tune/<loop>/running`` (the plant's watchdog restores the loop if it vanishes),
publishes progress, events and a result under ``<prefix>/tune/<loop>/``, and is cancelled by
a put on ``<prefix>/tune/<loop>/cancel``. Stopping the service cancels every run, which
restores its loop before the process ends.

Every loop a run left tuned (``ok``, gains applied) is then watched in normal operation: its
samples (whatever advances them; the tuner never commands it) feed a ``monitor.Watcher``, and
every window a ``LoopMonitor`` goes out on ``<prefix>/monitor/<loop>``. Samples while a test
holds the loop's lease, or while this tuner runs on it, are not normal operation: left out.
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
import uuid
from dataclasses import dataclass

import zenoh

from services.autotuner.compute_pool import ComputePool, inline, preload
from services.autotuner.design.request_check import validate_request
from services.autotuner.identify.experiments import (
    DEFAULT_STEP_SIZE,
    limits_problem,
    run_pv_limits,
    start_gain_problem,
)
from services.autotuner.loop_client import (
    LEASE_TIMEOUT,
    LoopClient,
    wait_for_loop,
    wait_for_token,
)
from services.autotuner.monitor.assessment import (
    Watcher,
    choose_period,
    gains_note,
    loop_watcher,
)
from services.autotuner.recorder_watch import RecorderWatch
from services.autotuner.stall_watch import stall_watch
from services.autotuner.tuning import RunHooks, TuningRun
from shared import keys, wire
from shared.cli import add_common_arguments, check_ids, setup_logging
from shared.control.forms import span_or_none
from shared.errors import AutotuneError, ConfigError, DecodeError
from shared.identity import auth_user
from shared.messages import (
    ANSWERED_LATE,
    APPLIED_STATUSES,
    LoopInfo,
    LoopMonitor,
    LoopStatus,
    ProcessSample,
    ProcessSamples,
    TuneAccepted,
    TuneRequest,
    TuneResult,
)
from shared.reject_log import RejectLog
from shared.service_shell import ServiceShell, run_until_stopped
from shared.session import settings_from_args

log = logging.getLogger("autotuner")

HELP = "run the autotuner service"
DEFAULT_WORKERS = min(4, os.cpu_count() or 1)
# s a request waits for a loop's liveliness token (within the request's own timeout, 10 s
# and more, at the client)
ANNOUNCE_WAIT = 4.0


@dataclass
class Watched:
    """A loop a run left tuned, watched in normal operation."""

    watcher: Watcher
    pv_units: str
    leased: bool = False  # a test holds the loop: its samples are not normal operation
    # the loop's gains (kc, ti, td) as its last status showed them: changed since the run
    # (`autotune set`), its windows say so (they went on flagging "degraded" against the tune
    # for an operator's Kc 14, and the report put them under the run's change: helper trial)
    gains: tuple[float, float | None, float] | None = None


def watched(result: TuneResult, info: LoopInfo, status: LoopStatus) -> Watched | None:
    """What to watch after ``result`` (None unless ok with its gains applied): T_u from the
    run's P_u (else the loop's Ti), the loop's ranges, action and integral action as the run
    left them (``status``), its verification as the baseline."""
    if result.status not in APPLIED_STATUSES or not result.applied:
        return None
    pu = result.pu
    if pu is None and result.applied_from and result.method in ("relay", "ramp"):
        # an apply identifies nothing: the P_u of the run it applied, which a relay or ramp
        # run's time scale is (after the console's Apply the monitor took Ti for T_u, 96 s
        # against hx1's P_u of 43.7 s, and read its 46 s oscillation as 92 s: helper trial)
        pu = result.timescale
    period, source = choose_period(None, pu, status.gains.ti, info.sample_time)
    g = status.gains
    return Watched(
        loop_watcher(period, source, info, status, result.model_dump()),
        info.pv_units,
        gains=(g.kc, g.ti, g.td),
    )


@dataclass
class ActiveRun:
    run_id: str
    request: TuneRequest
    cancel: threading.Event
    thread: threading.Thread


def stale_by(req: TuneRequest, now: float | None = None) -> float | None:
    """How many seconds past its ``answer_by`` (wall clock) ``req`` is read; None: in time,
    or no bound asked. The machines' clocks are taken to agree to well under the client's
    wait (10 s; NTP keeps them to milliseconds)."""
    if req.answer_by is None:
        return None
    late = (time.time() if now is None else now) - req.answer_by
    return late if late > 0 else None


def _check_step_size(req: TuneRequest, status: LoopStatus) -> None:
    """A step test's output step that cannot fit the loop's output limits, refused when the
    request arrives (ValueError naming ``step_size``), not after the wait for rest (600 s on
    lvl1) as an aborted run. A manual loop steps from its output now; an auto loop from its
    controller's mean output, not known yet: refused only when no output could take it."""
    if req.method != "step":
        return
    size = req.step_size or DEFAULT_STEP_SIZE
    lo, hi = status.op_limits
    if status.mode == "manual" and not lo <= status.op + size <= hi:
        raise ValueError(
            f"step_size {size:+g} %: the output would go from {status.op:g} to "
            f"{status.op + size:g} %, outside the loop's limits [{lo:g}, {hi:g}] %"
        )
    if abs(size) > hi - lo:
        raise ValueError(
            f"step_size {size:+g} %: more than the loop's whole output range [{lo:g}, {hi:g}] %"
        )


def _check_limits(req: TuneRequest, status: LoopStatus) -> None:
    """Settings the loop's PV limits cannot take, refused when the request arrives
    (ValueError naming the field, exit 2 at the client): a relay hysteresis of half their
    width or more (it could never switch within them), and limits the PV is already outside.
    The run checks the same (``TuningRun``); here its client hears it as the bad input it is,
    not as a run that ``failed`` (exit 1, its reason among the result's lines)."""
    if req.apply_from:
        return
    limits = run_pv_limits(req.pv_limits, status.pv_range)
    why = limits_problem(req.method, req.hysteresis, status.pv, limits, bump=req.bump)
    why = why or start_gain_problem(req.method, req.kc_start, span_or_none(status.pv_range))
    if why is not None:
        raise ValueError(why)


class TunerService:
    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        node: str,
        loop_timeout: float = 10.0,
        lease_timeout: float = LEASE_TIMEOUT,
        user: str | None = None,
        workers: int = DEFAULT_WORKERS,
        pool: ComputePool | None = None,
    ):
        self.session = session
        self.user = user
        # the runs' heavy pure steps (the relay's fits, the design) in worker processes, so
        # that tunes at once use every core (0: in each run's own thread); ``pool``: one
        # made already (``run``'s, its workers forked at start-up)
        self.pool = pool or (ComputePool(workers) if workers > 0 else None)
        self.lease_timeout = lease_timeout
        self.prefix = prefix
        self.node = node
        self.loop_timeout = loop_timeout
        self.lock = threading.Lock()
        self.active: dict[str, ActiveRun] = {}
        self.results: dict[str, TuneResult] = {}  # the last result per loop (queryable)
        self.rejected = 0
        self.monitor_rejected = 0  # a watched loop's samples that were not valid
        self._log_reject = RejectLog(log)  # a flood of them logged 137,000 lines in seconds
        self.monitors: dict[str, Watched] = {}  # the loops left tuned, watched (monitor)
        self.shell: ServiceShell | None = None

    def _start(self, req: TuneRequest) -> TuneAccepted:
        validate_request(req)
        key = keys.loop_alive(self.prefix, req.loop)
        # a liveliness subscriber's history, not a query: a tuner just restarted, busy
        # meeting its peers, missed a query's answers and refused a loop that was there (and
        # among 600 loops' tokens a peer's query was seen never to end)
        if not wait_for_token(self.session, key, ANNOUNCE_WAIT):
            raise ValueError(f"loop: no plant serves {req.loop!r} (nothing announces {key})")
        status = wire.query_one(self.session, keys.status(self.prefix, req.loop), LoopStatus, 2.0)
        if status is not None and status.leased_by is not None:
            raise ValueError(
                f"loop: {req.loop} is held by {status.leased_by!r} for another test; "
                "try again when it is released"
            )
        if status is not None:
            _check_step_size(req, status)
            _check_limits(req, status)
        late = stale_by(req)
        if late is not None:  # the checks above outlasted the client's wait (this tuner
            # starved): its client has asked another tuner, whose run is to be the only one
            raise ValueError(
                f"the request for {req.loop} was checked {late:.3g} s {ANSWERED_LATE} (this tuner "
                "was paused or starved): not started"
            )
        with self.lock:
            if req.loop in self.active:
                raise ValueError(
                    f"loop: {req.loop} is already being tuned (run {self.active[req.loop].run_id})"
                )
            run_id = uuid.uuid4().hex[:12]
            cancel = threading.Event()
            th = threading.Thread(
                target=self._run, args=(req, run_id, cancel), daemon=True, name=f"tune-{req.loop}"
            )
            self.active[req.loop] = ActiveRun(run_id, req, cancel, th)
        if self.pool is not None:  # not forked at start-up (``run``): started with the
            # first run, in the background: ready by the end of its relay, as a rule
            threading.Thread(target=self.pool.warm, daemon=True, name="compute-pool").start()
        th.start()
        return TuneAccepted(run_id=run_id, loop=req.loop, t=0.0, method=req.method, rule=req.rule)

    def _run(self, req: TuneRequest, run_id: str, cancel: threading.Event) -> None:
        p, s = self.prefix, self.session
        token = s.liveliness().declare_token(keys.tune_running(p, req.loop))
        try:  # whether a logger records the run: said in its result, never in its way
            recorders: RecorderWatch | None = RecorderWatch(s, p)
        except zenoh.ZError as err:
            log.warning("run %s on %s: its recording is not watched: %s", run_id, req.loop, err)
            recorders = None
        started = time.monotonic()
        seen: tuple[LoopInfo, LoopStatus] | None = None  # the loop as the run left it
        hooks = RunHooks(
            progress=lambda m: wire.put(s, keys.tune_progress(p, req.loop), m),
            event=lambda m: wire.put(s, keys.tune_event(p, req.loop), m),
            cancelled=cancel,
            compute=self.pool.call if self.pool is not None else inline,
        )
        ran = False  # the run itself began: before it, nothing can have been sent to the loop
        try:
            wait_for_loop(s, p, req.loop, self.loop_timeout)
            with LoopClient(
                s,
                p,
                req.loop,
                source=f"tuner:{run_id}",
                lease_timeout=self.lease_timeout,
                user=self.user,
            ) as client:
                ran = True
                result = TuningRun(client, req, run_id, hooks).run()
                seen = client.info, client.last_status
        except Exception as err:  # whatever happens, the run ends with a result
            expected = isinstance(err, AutotuneError | ValueError)
            if expected:  # the run could not go on: its reason, and where it came from
                log.warning("run %s on %s failed: %s", run_id, req.loop, err, exc_info=err)
            else:  # a bug: never let one run take the service down
                log.exception("run %s on %s failed", run_id, req.loop)
            result = TuneResult(
                run_id=run_id,
                loop=req.loop,
                t=0.0,
                method=req.method,
                rule=req.rule,
                status="failed",
                reason=str(err) if expected else repr(err),
                wall_time=time.monotonic() - started,
                # a loop whose plant never answered (its token up, its info not: a paused
                # plant, a token of another client) was said "may not have been restored"
                untouched=not ran,
            )
        finally:
            with self.lock:
                self.active.pop(req.loop, None)
        try:
            stalled = stall_watch().stalled(started)
            # a run that sent nothing has nothing for a logger to hold open (one that never
            # took the loop while another run held it is not recorded, by design): not said as
            # "no logger has this run open … came up after the run started"
            mine = None if result.untouched else run_id
            unrecorded = recorders.verdict(stalled, mine) if recorders is not None else None
        except Exception:  # a failure here never withholds the run's result
            log.exception(
                "run %s on %s: whether a logger recorded it is not known", run_id, req.loop
            )
            unrecorded = None
        if unrecorded is not None:
            result = result.model_copy(update={"warnings": [*result.warnings, unrecorded]})
        with self.lock:
            self.results[req.loop] = result
        if seen is not None and result.status in APPLIED_STATUSES and result.applied:
            self._monitor(req.loop, result, *seen)
        wire.put(s, keys.tune_result(p, req.loop), result)
        token.undeclare()
        log.info(
            "run %s on %s: %s%s (K_u %s, P_u %s) in %.2f s",
            run_id,
            req.loop,
            result.status,
            f", {result.reason}" if result.reason else "",
            result.ku,
            result.pu,
            result.wall_time,
        )

    def _monitor(self, loop: str, result: TuneResult, info: LoopInfo, left: LoopStatus) -> None:
        """Watch ``loop`` from now on (a run left it tuned): its samples and status to
        ``_on_loop``, one subscriber per loop for the process's life. A failure here is
        logged: it never changes the run's result."""
        try:
            watch = watched(result, info, left)
        except (ValueError, TypeError):
            log.exception("monitor of %s: not started", loop)
            return
        if watch is None:
            return
        with self.lock:
            known = loop in self.monitors
            self.monitors[loop] = watch
        if not known and self.shell is not None:
            self.shell.subscribe(
                keys.loop_feed(self.prefix, loop), lambda x: self._on_loop(loop, x), 1 << 16
            )

    def _on_loop(self, loop: str, sample: zenoh.Sample) -> None:
        """A watched loop's sample (to its watcher; a LoopMonitor at each window's end) or
        status (whether a test holds it)."""
        leaf = keys.leaf(str(sample.key_expr))
        mark = sample.attachment
        with self.lock:
            watch = self.monitors.get(loop)
            busy = loop in self.active
        if (
            watch is None
            or leaf not in ("pv", "pv_batch", "status")
            or (mark is not None and wire.replay_source(mark.to_bytes()) is not None)
        ):
            return
        try:
            if leaf == "status":
                status = wire.decode_sample(LoopStatus, sample)
                watch.leased = status.leased_by is not None
                g = status.gains
                watch.gains = (g.kc, g.ti, g.td)
                return
            if busy or watch.leased:
                return
            if leaf == "pv":
                samples = [wire.decode_sample(ProcessSample, sample)]
            else:  # a lockstep advance's samples in one message: each in turn
                samples = wire.decode_sample(ProcessSamples, sample).samples
        except DecodeError as err:  # counted; logged at most 10 lines in 10 s
            self.monitor_rejected += 1
            self._log_reject("monitor", f"monitor of {loop}: {err}")
            return
        w = watch.watcher
        for s in samples:
            w.feed(s.t, s.sp, s.pv, s.op, s.mode == "auto")
            start = w.window_start
            if start is not None and s.t - start >= w.settings.window:
                assessment = w.report()
                if (note := gains_note(watch.gains, w.baseline)) is not None:
                    assessment.notes.append(note)
                report = assessment.to_dict()
                msg = LoopMonitor(loop=loop, node=self.node, pv_units=watch.pv_units, **report)
                wire.put(self.session, keys.monitor(self.prefix, loop), msg)
                log.info("monitor of %s at t = %g s: %s", loop, msg.t, ", ".join(msg.flags) or "ok")

    def _on_request(self, query: zenoh.Query) -> None:
        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            req = wire.decode(TuneRequest, payload, str(query.encoding) if query.encoding else None)
            late = stale_by(req)
            if late is not None:
                self.rejected += 1
                why = (
                    f"the request for {req.loop} came {late:.3g} s {ANSWERED_LATE} (this tuner was "
                    "paused or starved): not started"
                )
                log.warning("request refused: %s", why)
                query.reply_err(why.encode())
                return
            accepted = self._start(req)
            wire.reply(query, str(query.key_expr), accepted)
            log.info(
                "run %s: tuning %s by %s, rule %s",
                accepted.run_id,
                req.loop,
                req.method,
                req.rule,
            )
        except (DecodeError, ValueError) as err:
            self.rejected += 1
            log.warning("request refused: %s", err)
            query.reply_err(str(err).encode())

    def _on_results_query(self, query: zenoh.Query) -> None:
        """The last result per loop, for a client that was cut off when it was published;
        and an error reply per loop with a run going, naming it: a client that has a result
        for that run from the bus was not given it by this tuner (``commands.tune``)."""

        def asked(loop: str) -> bool:
            return query.key_expr.intersects(zenoh.KeyExpr(keys.tune_result(self.prefix, loop)))

        with self.lock:
            found = [
                (keys.tune_result(self.prefix, loop), r)
                for loop, r in self.results.items()
                if asked(loop)
            ]
            going = [(loop, a.run_id) for loop, a in self.active.items() if asked(loop)]
        for key, r in found:
            wire.reply(query, key, r)
        for loop, run_id in going:
            query.reply_err(f"run {run_id} on {loop} is still going".encode())

    def _on_cancel(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse_tune_key(self.prefix, str(sample.key_expr))
        if parsed is None:
            return
        loop = parsed[0]
        with self.lock:
            run = self.active.get(loop)
        if run is not None:
            log.info("run %s on %s: cancel requested", run.run_id, loop)
            run.cancel.set()

    def run(self, stop: threading.Event) -> None:
        p, shell = self.prefix, ServiceShell(self.session, log)
        self.shell = shell
        requests = shell.queryable(keys.tuner_request(p, self.node), self._on_request, 256)
        shell.subscribe(keys.tune_cancel(p, keys.ANY), self._on_cancel, 256)
        results = shell.queryable(keys.tune_result(p, keys.ANY), self._on_results_query, 256)
        shell.announce(keys.tuner_alive(p, self.node))
        log.info("autotuner %s ready at %s", self.node, keys.tuner_request(p, self.node))
        try:
            shell.wait(stop, 0.5)
        finally:
            shell.undeclare(requests, results)  # no new run; cancels still heard
            with self.lock:
                runs = list(self.active.values())
            for run in runs:
                run.cancel.why = (  # type: ignore[attr-defined]
                    "cancelled: the autotuner service is stopping (SIGTERM or Ctrl-C; under "
                    "`autotune up`, also when another of its services died)"
                )
                run.cancel.set()
            for run in runs:  # each restores its loop, the plant still up
                run.thread.join(timeout=30.0)
            shell.undeclare()
            shell.withdraw()
            shell.join(2.0)
            if self.pool is not None:
                self.pool.close()
            log.info("stopped")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--node", default="tuner", help="this process's id on the bus (default: %(default)s)"
    )
    parser.add_argument(
        "--lease-timeout",
        type=float,
        default=LEASE_TIMEOUT,
        metavar="S",
        help="s of wall time without a word from this tuner after which the plant takes a "
        "leased loop back and restores it (default: %(default)g; 1–3600)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=DEFAULT_WORKERS,
        metavar="N",
        help="worker processes for the runs' model fits and design, so that tunes at once "
        "use every core (default: %(default)s, the cores here, at most 4; 0: in each run's "
        "thread)",
    )
    add_common_arguments(parser)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.verbose + 1, "autotuner")
    check_ids(args.prefix, node=args.node)
    if not 1.0 <= args.lease_timeout <= 3600.0:  # also refuses NaN
        raise ConfigError(f"--lease-timeout {args.lease_timeout:g}: must be 1–3600 s")
    if not 0 <= args.workers <= 64:
        raise ConfigError(f"--workers {args.workers}: must be 0–64")
    settings = settings_from_args(args)
    preload()  # what every run computes with, at start-up, not in the first run
    # the workers forked now, before the session's threads exist: up before the first run
    # (``ComputePool.fork_now``), else started with it from the fork server
    pool = ComputePool(args.workers) if args.workers > 0 else None
    if pool is not None:
        pool.fork_now()  # False (said in its log line): the fork server's, with the first run
    run_until_stopped(
        settings,
        lambda session: TunerService(
            session,
            args.prefix,
            args.node,
            lease_timeout=args.lease_timeout,
            user=auth_user(settings),
            workers=args.workers,
            pool=pool,
        ),
    )
    return 0
