"""The step test on a live loop: lease, manual, the step, always the restore, then the
bounded wait for the PV's return to rest (``StepTest`` and ``ReturnWatch`` decide; this
module only drives the loop client)."""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

from services.autotuner.identify.experiments import snapped
from services.autotuner.identify.reaction_curve import IntegratingCurve, ReactionCurve
from services.autotuner.identify.repeated_steps import RepeatedSteps, Spread
from services.autotuner.identify.rest import RestCheck, rest_window
from services.autotuner.identify.step_test import (
    ReturnWatch,
    StepTest,
    StepTestAborted,
    StepTestConfig,
    return_timeout,
)
from services.autotuner.loop_client import CommandRefused, LeaseLost, LoopClient
from shared.control.forms import pv_span, step_percent
from shared.errors import AutotuneError
from shared.messages import (
    MAX_BATCH,
    LeaseCommand,
    LoopStatus,
    ModeCommand,
    OutputCommand,
    ProcessSample,
    ReleaseCommand,
    SetpointCommand,
)


class StepInterrupted(KeyboardInterrupt):
    """A signal (Ctrl-C) stopped the test once it held the loop; the loop was then put back
    as it was (``restored``: confirmed; else not, and the plant asked to on release): what the
    client says as it leaves (it said only "interrupted", the loop restored: helper trial)."""

    def __init__(self, loop: str, restored: bool, mode: str, op: float, by: str = ""):
        super().__init__(loop)
        self.loop, self.restored, self.mode, self.op, self.by = loop, restored, mode, op, by

    def summary(self) -> str:
        if self.restored:
            return (
                f"step test of {self.loop} interrupted; loop restored ({self.mode}, output "
                f"{self.op:g} %{self.by})"
            )
        return (
            f"step test of {self.loop} interrupted; its restore to {self.mode}, output "
            f"{self.op:g} % NOT confirmed: check the loop"
        )


@dataclass(frozen=True)
class StepTestReport:
    loop: str
    model: str
    pv_units: str
    mode_before: str
    op_before: float
    t_step: float
    t_end: float
    samples: int
    curve: ReactionCurve | IntegratingCurve
    restored: bool
    returned_to_rest: bool | None = None  # None: not waited for (--no-wait, or not restored)
    pv_end: float | None = None  # PV units: the rest after the return, else the last PV seen
    t_return: float | None = None  # s, sim time the wait for the return ended
    # repeated tests (``--repeat``): every test's curve (``curve`` is then their mean), each
    # figure's spread, and what the engineer must know of it; empty for one test
    tests: tuple[ReactionCurve | IntegratingCurve, ...] = ()
    spreads: dict[str, Spread] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    pv_range: tuple[float, float] | None = None  # the transmitter's, PV units

    @property
    def percent(self) -> dict[str, float | None] | None:
        """The process gains K, R and a in % of span (``forms.step_percent``); None without
        a usable range."""
        try:
            span = pv_span(self.pv_range)
        except ValueError:
            return None
        return None if span is None else step_percent(self.curve.to_dict(), span)

    def to_dict(self) -> dict:
        return {
            "loop": self.loop,
            "model": self.model,
            "pv_units": self.pv_units,
            "mode_before": self.mode_before,
            "op_before": self.op_before,
            "op_step": self.op_before + self.curve.step_size,
            "t_step": self.t_step,
            "t_end": self.t_end,
            "samples": self.samples,
            "restored": self.restored,
            "returned_to_rest": self.returned_to_rest,
            "pv_end": self.pv_end,
            "t_return": self.t_return,
            "pv_range": list(self.pv_range) if self.pv_range else None,
            "step_percent": self.percent,
            **self.curve.to_dict(),
            **(
                {
                    "tests": [c.to_dict() for c in self.tests],
                    "spreads": {k: dataclasses.asdict(v) for k, v in self.spreads.items()},
                    "notes": list(self.notes),
                }
                if self.tests
                else {}
            ),
        }


def run_step_test(
    client: LoopClient,
    config: StepTestConfig,
    progress: Callable[[StepTest | RepeatedSteps, ProcessSample], None] | None = None,
    wait_return: bool = True,
    repeat: int = 1,
    auto: bool = False,
) -> StepTestReport:
    """Run the step test on a live loop; restore its mode and output afterwards, always.

    ``repeat`` > 1 (or ``auto``): repeated tests, up and down in turn, each from rest
    (``RepeatedSteps``). With ``wait_return``, after a completed test it then follows the PV
    until it is back at rest (``ReturnWatch``, at most ``return_timeout``), so that whatever
    runs next does not identify on a recovering PV; ``progress`` keeps being called meanwhile.
    """
    before = client.sync()
    info = client.info
    pv_limits = config.pv_limits or tuple(info.pv_range)
    where = {"pv_range": tuple(info.pv_range), "pv_units": info.pv_units}

    def make(op_start: float) -> StepTest | RepeatedSteps:
        """The test from the output held at ``op_start`` (StepTestAborted where it cannot)."""
        args = (config, op_start, tuple(info.op_limits), pv_limits, info.sample_time)
        try:
            if repeat > 1 or auto:
                return RepeatedSteps(*args, **where, repeat=repeat, auto=auto)
            return StepTest(*args, **where)
        except ValueError as err:
            raise StepTestAborted(f"loop {client.loop}: {err}") from None

    if before.fault is not None:
        # a faulted loop is held in manual and refuses the output: refused before the lease,
        # as a tune is (it took the lease, then failed "output refused … loop restored":
        # helper review)
        raise StepTestAborted(
            f"loop {client.loop}: not started: the loop is faulted ({before.fault})"
        )
    lo, hi = pv_limits
    if config.pv_limits is not None and not lo <= before.pv <= hi:
        # limits the PV is already outside (another loop's, or in other units): refused
        # before the lease, as a tune refuses them (`step lvl1 --pv-limits 45 55` of a level
        # at 1.5 m took the loop and aborted "left its limits" a second in: user trial)
        raise StepTestAborted(
            f"loop {client.loop}: not started: --pv-limits [{lo:g}, {hi:g}]: the PV "
            f"{before.pv:.4g}{' ' + info.pv_units if info.pv_units else ''} is already outside "
            "them"
        )
    test = make(before.op)  # refused before the lease where the settings cannot work
    hold = before.op  # the output held for the test (a loop in auto: its mean, below)
    restored = False
    try:  # under a lease: if this client dies, the plant's watchdog puts the loop back
        client.command(
            LeaseCommand(
                loop=client.loop,
                source=client.source,
                timeout=client.lease_timeout,
                # realtime: the plant restores the loop itself at a PV outside them
                pv_limits=pv_limits if info.clock == "realtime" else None,
            )
        )
    except CommandRefused as err:
        raise StepTestAborted(f"not started: {err}") from None
    lost: LeaseLost | None = None
    failed: AutotuneError | None = None
    interrupted = False
    try:
        if before.mode != "manual":
            # held at the controller's mean output, not at its last sample's, which carries
            # the noise the gains feed back (hx1 under TL PID held at 38.79 % against a mean
            # near 40.2: K read 0.76 for 1.0, the PV still drifting from the hold when it was
            # stepped; lvl2 held at 55.3 % drained 0.43 m before any step)
            hold = _mean_output(
                client,
                before,
                _cap(info.clock),
                lambda s: progress and progress(test, s),
            )
            test = make(hold)
            client.command(ModeCommand(loop=client.loop, mode="manual", source=client.source))
            client.command(OutputCommand(loop=client.loop, op=hold, source=client.source))
        op = want = hold
        # lockstep: a batch up to the test's next decision (``horizon``, ``band``), fed one
        # by one, is the test fed a sample at a time, in a round trip instead of one each;
        # realtime: a sample at a time, as they come (a sample lost on the way must not put a
        # timed decision inside a batch counted in samples)
        cap = _cap(info.clock)
        while not test.finished:
            n = test.horizon(cap)
            batch = client.samples(n, test.band()) if n > 1 else client.samples(1)
            if not batch:
                raise AutotuneError(f"loop {client.loop}: no sample came")
            for s in batch:
                want = test.feed(s).op
                if progress:
                    progress(test, s)
                if test.finished:
                    break
            if want != op and not test.finished:
                status = client.command(
                    OutputCommand(
                        loop=client.loop,
                        op=snapped(want, client.info.op_limits),
                        t=s.t,
                        source=client.source,
                    )
                )
                # Lockstep: applied at the present sample. Realtime: latched at the next one.
                test.step_started(
                    status.t if info.clock == "lockstep" else status.t + info.sample_time
                )
                op = want
    except LeaseLost as err:
        lost = err
    except KeyboardInterrupt:  # restored below, then said so
        interrupted = True
    except StepTestAborted:  # its own words say what was left
        raise
    except AutotuneError as err:  # the plant silent or gone: said with what was left, below
        failed = err
    finally:
        taken: LeaseLost | None = None  # the plant took the loop back as the test let go
        if client.holding:
            try:
                restored = _restore(client, before.mode, before.op, before.sp)
            except LeaseLost as err:  # realtime: the PV past the lease's limits, say
                taken, restored = err, True
            else:
                with contextlib.suppress(AutotuneError):  # unconfirmed: the plant puts it back
                    client.command(
                        ReleaseCommand(loop=client.loop, source=client.source, restore=not restored)
                    )
        else:  # the plant took the loop back (and restored it) or is gone
            restored = lost is not None
    if interrupted:
        by = f", by the plant: {taken}" if taken is not None else ""
        raise StepInterrupted(client.loop, restored, before.mode, before.op, by)
    if lost is not None:
        raise StepTestAborted(
            f"{lost}; the plant restored the loop ({before.mode}, {before.op:g} %)"
        )
    if failed is not None:  # a plant paused mid-test said nothing of the loop (helper trial)
        left = (
            f"loop restored ({before.mode}, {before.op:g} %)"
            if restored
            else f"the loop was NOT confirmed restored ({before.mode}, {before.op:g} % before "
            "the test): the plant, if it runs, puts it back itself once this test's lease "
            "lapses (check it with autotune loops)"
        )
        raise StepTestAborted(f"{failed}; {left}")
    if taken is not None and info.clock == "lockstep":  # no lease: the loop cannot be stepped
        wait_return = False
    if test.phase == "aborted" or test.result is None:
        back = ""
        # a single test's (the repeated tests' own records end where each did)
        last = test if isinstance(test, StepTest) and test.t_step is not None else None
        if wait_return and restored and last is not None and before.mode == "manual":
            # the output is back, but the PV answers it only after its dead time and lag: a
            # test started at once measured a PV still on its way (K = −1.43 for +1, at
            # rest by a window shorter than the dead time); waited for as after a test
            pv_before = last.pv_before_step
            watch = ReturnWatch(
                last.t[-1] + (0.0 if info.clock == "lockstep" else info.sample_time),
                last.pv[-1],
                last.noise_std,
                # the PV goes on past where the test stopped for its dead time and lags
                # before it turns back (hx1: 45 s, and minutes to come back): as long as the
                # test itself may take, at most; it ends when the PV is back at rest
                config.timeout,
                tuple(info.pv_range),
                pv_back=pv_before,
                settle_off=True,
            )
            _follow_return(client, watch, cap, lambda s: progress(test, s) if progress else None)
            back = (
                f"; the PV back at rest at {watch.rest:.4g}"
                if watch.at_rest
                else f"; the PV came to rest at {watch.rest_off:.4g} {info.pv_units}, not back "
                f"where it was ({pv_before:.4g} before the step): held at this output it stays "
                "there (a level, an integrating process, does), so bring it back in auto or by "
                "hand before the next test"
                if math.isfinite(watch.rest_off)
                else f"; the PV not yet back at rest ({watch.pv_end:.4g} {info.pv_units}, "
                f"{pv_before:.4g} before the step): let it settle before the next test"
            )
        by = f", by the plant: {taken}" if taken is not None else ""
        raise StepTestAborted(
            f"loop {client.loop}: step test aborted: {test.reason}; "
            f"{'loop restored' if restored else 'LOOP NOT RESTORED'} "
            f"({before.mode}, {before.op:g} %{by}){back}"
        )
    last = test.done[-1] if isinstance(test, RepeatedSteps) else test
    first = test.done[0] if isinstance(test, RepeatedSteps) else test
    t_step, t_end = first.t_step or 0.0, last.t[-1]
    returned, pv_end, t_return = None, None, None
    if isinstance(last.result, IntegratingCurve):  # the test itself watched the level's return
        returned, pv_end, t_return = last.result.returned, last.result.pv_after, t_end
    elif wait_return and restored:
        lag = 0.0 if info.clock == "lockstep" else info.sample_time
        watch = ReturnWatch(
            t_end + lag,
            last.result.pv_after,
            last.result.noise_std,
            return_timeout(config, last.t_step or 0.0, t_end),
            tuple(info.pv_range),
            pv_back=last.result.pv_before,
        )
        _follow_return(client, watch, cap, lambda s: progress(test, s) if progress else None)
        returned = watch.at_rest
        pv_end = watch.pv_end if watch.pv else test.pv[-1]
        t_return = watch.t[-1] if watch.t else t_end
    return StepTestReport(
        client.loop,
        info.model,
        info.pv_units,
        before.mode,
        hold,
        t_step,
        t_end,
        sum(len(t.t) for t in test.done) if isinstance(test, RepeatedSteps) else len(test.t),
        test.result,
        restored,
        returned,
        pv_end,
        t_return,
        *(
            (tuple(test.curves()), test.spreads(), tuple(test.notes()))
            if isinstance(test, RepeatedSteps)
            else ((), {}, ())
        ),
        tuple(info.pv_range),
    )


def _cap(clock: str) -> int:
    """Samples per request: lockstep, a batch up to the test's next decision; realtime, one
    at a time, as they come."""
    return MAX_BATCH if clock == "lockstep" else 1


def _mean_output(
    client: LoopClient, status: LoopStatus, cap: int, seen: Callable[[ProcessSample], object]
) -> float:
    """The output a loop in auto holds on average over a rest window (its integral time, 40
    samples at least, ``rest.rest_window``), within the output's limits: where to hold it in
    manual for the test. Only from a loop at rest (``RestCheck``, as a tune waits for it: on
    its setpoint where it integrates), watched ten windows at most; else StepTestAborted,
    nothing changed. Why: hx1 stepped while its PV still rose to a new setpoint read K 1.33
    for 1.0 and L 8.2 s for 10.6, exit 0 (helper trial)."""
    info = client.info
    ts = info.sample_time
    lo, hi = info.op_limits
    pv_lo, pv_hi = info.pv_range
    integrating = bool(status.gains.ti) and lo < status.op < hi
    check = RestCheck(
        ts,
        rest_window(ts, status.gains.ti),
        (pv_lo, pv_hi),
        target=status.sp if integrating else None,
        band=max(4.0 * max(info.noise_std, 0.0), 0.001 * (pv_hi - pv_lo)),
    )
    ops: list[float] = []
    while not check.done:  # a window first, then a quarter of one at a time (its checks)
        want = check.samples if not ops else max(1, check.samples // 4)
        batch = client.samples(min(cap, want))
        if not batch:
            raise AutotuneError(f"loop {client.loop}: no sample came")
        for s in batch:
            check.feed(s.t, s.pv)
            ops.append(s.op)
            seen(s)
            if check.done:
                break
    if not check.at_rest:
        raise StepTestAborted(
            f"loop {client.loop}: not started: the loop in auto is not at rest: {check.reason}; "
            "a step now would read that movement as the process's response (it was left in "
            "auto as it was: step it once it has settled)"
        )
    n = check.samples
    return min(max(math.fsum(ops[-n:]) / n, lo), hi)


def _follow_return(
    client: LoopClient, watch: ReturnWatch, cap: int, seen: Callable[[ProcessSample], None]
) -> None:
    """Samples to ``watch`` until it is done (in batches up to its next check); a failure or
    Ctrl-C meanwhile ends the wait (the loop is restored: it is reported not back at rest)."""
    try:
        while not watch.done:
            batch = client.samples(watch.horizon(cap, client.info.sample_time))
            if not batch:
                raise AutotuneError(f"loop {client.loop}: no sample came")
            for s in batch:
                done = watch.feed(s.t, s.pv)
                seen(s)
                if done:
                    break
    except (KeyboardInterrupt, AutotuneError):
        pass


def _restore(client: LoopClient, mode: str, op: float, sp: float) -> bool:
    """Put the loop back to ``mode`` at output ``op`` and setpoint ``sp`` (bumpless into
    auto); LeaseLost when the plant has taken the loop back (and restored it itself). A loop
    that tracks its PV with its setpoint (``sp_track``) moved its setpoint with the PV while
    the test held it in manual: it is written back once in auto, where it stays (restored
    "auto" at the tracked setpoint, the loop held the PV where the step had taken it)."""
    try:
        status = client.sync()
        if status.mode == "manual" and status.op != op:
            client.command(OutputCommand(loop=client.loop, op=op, source=client.source))
        if status.sp != sp:
            status = client.command(SetpointCommand(loop=client.loop, sp=sp, source=client.source))
        if mode != status.mode:
            status = client.command(ModeCommand(loop=client.loop, mode=mode, source=client.source))
        if status.sp != sp and status.mode == "auto":  # tracked again before the switch
            status = client.command(SetpointCommand(loop=client.loop, sp=sp, source=client.source))
        return status.sp == sp or status.mode == "manual"
    except LeaseLost:
        raise
    except AutotuneError:
        return False
