"""One tuning run on a live loop, the way a DCS auto-tuner does it.

1. Take the loop: snapshot its state and lease it from the plant (whose watchdog restores it
   if this process dies or goes silent).
2. Run the experiment (relay, P-gain ramp or step test) through its pure state machine.
3. Compute the gains of every rule the identification supports; pick the requested one.
4. Apply and verify: a setpoint step and a load step with the new gains (and, when the loop
   was in auto before, with its previous gains to compare). If the new gains are unstable or
   do worse than the old, the previous state is restored.
5. On any abort, error, cancellation or interrupt, the loop's mode, output, setpoint, gains
   and disturbances are put back exactly as they were before the test.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.autotuner import metrics
from services.autotuner.forms import IsaGains, all_forms
from services.autotuner.loop_client import LoopClient
from services.autotuner.ramp import RampConfig, RampTest
from services.autotuner.relay import RelayConfig, RelayTest
from services.autotuner.rules import StepModel, UltimatePoint, apply_rules, check_rule
from services.autotuner.step_test import StepTest, StepTestConfig
from shared.errors import AutotuneError
from shared.messages import (
    DisturbanceCommand,
    GainsCommand,
    LeaseCommand,
    LoopStatus,
    ModeCommand,
    OutputCommand,
    PidGains,
    ProcessSample,
    ReleaseCommand,
    SetpointCommand,
    TuneProgress,
    TuneRequest,
    TuneResult,
    TunerEvent,
    Verification,
)

LEASE_TIMEOUT = 10.0  # s of wall time the plant waits for us before restoring the loop
DEFAULT_RELAY_AMPLITUDE = 5.0  # %
DEFAULT_STEP_SIZE = 5.0  # %
DEFAULT_BUMP_FRACTION = 0.01  # of the PV range, ramp setpoint bump
VERIFY_SP_FRACTION = 0.02  # of the PV range, verification setpoint step
MAX_CHUNK = 64  # samples per lockstep round trip while the loop runs in auto


class TuneAborted(AutotuneError):
    """The run stopped before a result; the loop has been restored."""


@dataclass
class RunHooks:
    """Where a run reports to, and how it is cancelled."""

    progress: Callable[[TuneProgress], None] = lambda p: None
    event: Callable[[TunerEvent], None] = lambda e: None
    cancelled: threading.Event | None = None


@dataclass
class Identification:
    ku: float | None = None
    pu: float | None = None
    ku_spread: float | None = None
    pu_spread: float | None = None
    step: dict | None = None
    step_model: StepModel | None = None
    experiment: dict | None = None
    timescale: float = 0.0  # s: the loop's natural period, for verification windows
    noise: float = 0.0
    rest_pv: float = math.nan


def _json_number(v: object) -> object:
    """Numbers as JSON takes them: infinities (an overdamped trial's growth) become None."""
    if isinstance(v, float | np.floating):
        return float(v) if math.isfinite(v) else None
    return v


def validate_request(req: TuneRequest) -> None:
    """ValueError naming the field when the request cannot be run."""
    try:
        rule = check_rule(req.rule)
    except ValueError as err:
        raise ValueError(f"rule: {err}") from None
    wanted = "open" if req.method == "step" else "closed"
    if rule.kind != wanted:
        need = "a step test (method step)" if rule.kind == "open" else "K_u and P_u (relay/ramp)"
        raise ValueError(f"rule: {req.rule} needs {need}, not method {req.method}")
    if req.pv_limits and not req.pv_limits[0] < req.pv_limits[1]:
        raise ValueError(f"pv_limits: low must be below high, got {list(req.pv_limits)}")
    if req.step_size is not None and not (math.isfinite(req.step_size) and req.step_size != 0):
        raise ValueError("step_size: must be a non-zero number of %")


class TuningRun:
    def __init__(
        self, client: LoopClient, req: TuneRequest, run_id: str, hooks: RunHooks | None = None
    ):
        self.client = client
        self.req = req
        self.run_id = run_id
        self.hooks = hooks or RunHooks()
        self.info = client.info
        self.ts = client.info.sample_time
        self.before: LoopStatus | None = None
        self.pv_limits = tuple(req.pv_limits or client.info.pv_range)
        self._events_sent = 0
        self._t = 0.0

    # --- reporting ------------------------------------------------------------------------

    def _progress(
        self,
        phase: str,
        cycles: int = 0,
        ku: float | None = None,
        pu: float | None = None,
        message: str = "",
    ) -> None:
        self.hooks.progress(
            TuneProgress(
                run_id=self.run_id,
                loop=self.client.loop,
                t=self._t,
                phase=phase,
                cycles=cycles,
                ku=ku,
                pu=pu,
                message=message,
            )
        )

    def _forward_events(self, events: list[tuple[float, str, dict]]) -> None:
        for t, kind, data in events[self._events_sent :]:
            clean = {k: _json_number(v) for k, v in data.items()}
            self.hooks.event(
                TunerEvent(run_id=self.run_id, loop=self.client.loop, t=t, kind=kind, data=clean)
            )
        self._events_sent = len(events)

    def _check_cancel(self) -> None:
        if self.hooks.cancelled is not None and self.hooks.cancelled.is_set():
            raise TuneAborted("cancelled")

    def _take(self, samples: list[ProcessSample]) -> None:
        if samples:
            self._t = samples[-1].t

    # --- the run --------------------------------------------------------------------------

    def run(self) -> TuneResult:
        wall0 = time.monotonic()
        req, c = self.req, self.client
        self.before = before = c.sync()
        self._t = before.t
        t0 = before.t
        result: dict = {
            "run_id": self.run_id,
            "loop": c.loop,
            "method": req.method,
            "rule": req.rule,
            "previous_gains": before.gains,
        }
        lo, hi = self.pv_limits
        if not lo <= before.pv <= hi:
            raise ValueError(
                f"pv_limits: the PV {before.pv:.4g} is already outside [{lo:g}, {hi:g}]"
            )
        c.command(LeaseCommand(loop=c.loop, source=c.source, timeout=LEASE_TIMEOUT, t=t0))
        restored = False
        try:
            self._progress("start", message=f"{req.method} test, rule {req.rule}")
            ident = {"relay": self._relay, "ramp": self._ramp, "step": self._step}[req.method]()
            result.update(
                ku=ident.ku,
                pu=ident.pu,
                ku_spread=ident.ku_spread,
                pu_spread=ident.pu_spread,
                step=ident.step,
                experiment=ident.experiment or {},
                l_over_t=(ident.step or {}).get("l_over_t"),
            )
            ultimate = UltimatePoint(ident.ku, ident.pu) if ident.ku else None
            table = apply_rules(ultimate, ident.step_model)
            result["gains"] = {name: all_forms(g) for name, g in table.items()}
            chosen = table[req.rule]
            result["chosen"] = all_forms(chosen)
            self._progress(
                "identified",
                ku=ident.ku,
                pu=ident.pu,
                message=f"{req.rule}: Kc {chosen.kc:.4g}, Ti {chosen.ti}, Td {chosen.td:.4g}",
            )
            if req.apply:
                result.update(self._apply_and_verify(ident, chosen))
                restored = not result["applied"]
            else:
                self._restore()
                restored = True
            status = "ok" if result.get("applied") or not req.apply else "rejected"
            result.update(status=status, restored=restored)
        except (TuneAborted, AutotuneError) as err:
            restored = self._restore()
            result.update(status="aborted", reason=str(err), restored=restored)
        except BaseException as err:  # Ctrl-C, a bug: the loop must still be restored
            restored = self._restore()
            result.update(
                status="failed",
                restored=restored,
                reason=f"{type(err).__name__}: {err}" if str(err) else type(err).__name__,
            )
            if not isinstance(err, Exception):
                raise
        finally:
            with contextlib.suppress(AutotuneError):  # if the plant is gone, so is the lease
                c.command(ReleaseCommand(loop=c.loop, source=c.source, t=self._t))
        result.update(t=self._t, sim_duration=self._t - t0, wall_time=time.monotonic() - wall0)
        self._progress(
            "done", ku=result.get("ku"), pu=result.get("pu"), message=result.get("reason") or ""
        )
        return TuneResult(**result)

    def _restore(self) -> bool:
        """Put the loop back exactly as it was before the test; False if that failed."""
        b, c = self.before, self.client
        if b is None:
            return False
        try:
            now = c.sync()
            for name, value in b.disturbances.items():
                if now.disturbances.get(name) != value:
                    c.command(
                        DisturbanceCommand(loop=c.loop, name=name, value=value, source=c.source)
                    )
            if now.gains != b.gains:
                c.command(GainsCommand(loop=c.loop, gains=b.gains, source=c.source))
            if now.mode != "manual":
                c.command(ModeCommand(loop=c.loop, mode="manual", source=c.source))
            if b.mode == "manual":
                c.command(OutputCommand(loop=c.loop, op=b.op, source=c.source))
            c.command(SetpointCommand(loop=c.loop, sp=b.sp, source=c.source))
            if b.mode == "auto":
                c.command(ModeCommand(loop=c.loop, mode="auto", source=c.source))
            return True
        except AutotuneError:
            return False

    # --- experiments ----------------------------------------------------------------------

    def _manual_at_present_output(self) -> float:
        c = self.client
        st = c.command(ModeCommand(loop=c.loop, mode="manual", source=c.source))
        return st.op

    def _drive_manual(
        self,
        feed: Callable[[ProcessSample], float],
        finished: Callable[[], bool],
        op: float,
        events: list,
        on_sample: Callable[[], None],
    ) -> None:
        """Per sample: the experiment decides the output to hold (relay, step test)."""
        c = self.client
        while not finished():
            self._check_cancel()
            s = c.next_sample()
            self._take([s])
            want = feed(s)
            if want != op and not finished():
                c.command(OutputCommand(loop=c.loop, op=want, t=s.t, source=c.source))
                op = want
            self._forward_events(events)
            on_sample()
        self._forward_events(events)

    def _relay(self) -> Identification:
        req, b = self.req, self.before
        op = self._manual_at_present_output()
        cfg = RelayConfig(
            amplitude=req.amplitude or DEFAULT_RELAY_AMPLITUDE,
            hysteresis=req.hysteresis,
            cycles=req.cycles,
            tolerance=req.tolerance,
            **({"max_time": req.max_time} if req.max_time else {}),
        )
        try:
            test = RelayTest(
                cfg,
                op,
                tuple(self.info.op_limits),
                self.pv_limits,
                self.ts,
                1.0 if b.action == "reverse" else -1.0,
            )
        except ValueError as err:
            raise TuneAborted(str(err)) from None
        seen = [0]

        def report() -> None:
            if len(test.cycles) != seen[0]:
                seen[0] = len(test.cycles)
                cyc = test.cycles[-1]
                self._progress(
                    "relay", cycles=len(test.cycles), ku=test._ku(cyc.amplitude), pu=cyc.period
                )

        self._progress("quiet", message="measuring the PV's rest value and noise")
        self._drive_manual(
            lambda s: test.feed(s.t, s.pv), lambda: test.finished, op, test.events, report
        )
        if test.result is None:
            raise TuneAborted(f"relay test: {test.reason}")
        r = test.result
        self._restore_output(op)
        return Identification(
            ku=r.ku,
            pu=r.pu,
            ku_spread=r.ku_spread,
            pu_spread=r.pu_spread,
            experiment={
                "relay_amplitude": r.relay_amplitude,
                "amplitude": r.amplitude,
                "hysteresis": r.hysteresis,
                "bias": r.bias,
                "cycles": r.cycles,
                "noise_std": r.noise_std,
                "rest_pv": r.rest_pv,
            },
            timescale=r.pu,
            noise=r.noise_std,
            rest_pv=r.rest_pv,
        )

    def _restore_output(self, op: float) -> None:
        c = self.client
        if c.last_status.op != op:
            c.command(OutputCommand(loop=c.loop, op=op, t=self._t, source=c.source))

    def _step(self) -> Identification:
        req = self.req
        op = self._manual_at_present_output()
        cfg = StepTestConfig(
            size=req.step_size or DEFAULT_STEP_SIZE,
            pv_limits=self.pv_limits,
            **({"timeout": req.max_time} if req.max_time else {}),
        )
        try:
            test = StepTest(cfg, op, tuple(self.info.op_limits), self.pv_limits, self.ts)
        except ValueError as err:
            raise TuneAborted(str(err)) from None
        c = self.client
        self._progress("quiet", message="measuring the PV's rest value and noise")
        while not test.finished:
            self._check_cancel()
            s = c.next_sample()
            self._take([s])
            want = test.feed(s)
            if want != op and not test.finished:
                st = c.command(OutputCommand(loop=c.loop, op=want, t=s.t, source=c.source))
                test.step_started(st.t if self.info.clock == "lockstep" else st.t + self.ts)
                op = want
                self._progress("step", message=f"output stepped to {want:g} %")
        if test.result is None:
            raise TuneAborted(f"step test: {test.reason}")
        self._restore_output(test.op_start)
        rc = test.result
        model = StepModel(rc.gain, rc.dead_time, rc.time_constant_tangent)
        return Identification(
            step=rc.to_dict(),
            step_model=model,
            experiment={"step_size": rc.step_size, "method": rc.method},
            timescale=4 * rc.dead_time + rc.time_constant_63,
            noise=rc.noise_std,
            rest_pv=rc.pv_before,
        )

    def _ramp(self) -> Identification:
        req, b, c = self.req, self.before, self.client
        lo, hi = self.info.pv_range
        kc0 = req.kc_start or (0.5 * b.gains.kc if b.gains.kc > 0 else 1.0)
        bump = req.bump or DEFAULT_BUMP_FRACTION * (hi - lo)
        try:
            cfg = RampConfig(
                kc_start=kc0,
                bump=bump,
                tolerance=min(req.tolerance, 0.02) / 2,
                **({"max_time": req.max_time} if req.max_time else {}),
            )
        except ValueError as err:
            raise TuneAborted(str(err)) from None
        test = RampTest(cfg, self.pv_limits, self.ts)
        st = c.sync()
        demand = test.feed(st.t, st.pv)
        kc, sp = demand.kc, demand.sp
        c.command(GainsCommand(loop=c.loop, gains=PidGains(kc=kc), source=c.source))
        c.command(SetpointCommand(loop=c.loop, sp=sp, source=c.source))
        c.command(ModeCommand(loop=c.loop, mode="auto", source=c.source))
        self._progress("quiet", message="P-only in auto: measuring rest value and noise")
        trials = 0
        while not test.finished:
            self._check_cancel()
            for s in c.samples(test.horizon(MAX_CHUNK)):
                demand = test.feed(s.t, s.pv)
                self._take([s])
                if test.finished:
                    break
            if test.finished:
                break
            if demand.kc != kc:
                kc = demand.kc
                c.command(GainsCommand(loop=c.loop, gains=PidGains(kc=kc), source=c.source))
            if demand.sp != sp:
                sp = demand.sp
                c.command(SetpointCommand(loop=c.loop, sp=sp, source=c.source))
            self._forward_events(test.events)
            if len(test.trials) != trials:
                trials = len(test.trials)
                tr = test.trials[-1]
                self._progress(
                    "ramp",
                    cycles=trials,
                    pu=tr.period,
                    message=f"Kc {tr.kc:.4g}: growth {tr.growth:.3g}/s",
                )
        self._forward_events(test.events)
        if test.result is None:
            raise TuneAborted(f"P-gain ramp: {test.reason}")
        r = test.result
        # back to manual at the present output; the rules' gains are applied next
        self._manual_at_present_output()
        return Identification(
            ku=r.ku,
            pu=r.pu,
            ku_spread=(r.kc_high - r.kc_low) / r.ku,
            pu_spread=None,
            experiment={
                "trials": r.trials,
                "kc_low": r.kc_low,
                "kc_high": r.kc_high,
                "bump": bump,
                "noise_std": r.noise_std,
                "rest_pv": r.rest_pv,
            },
            timescale=r.pu,
            noise=r.noise_std,
            rest_pv=r.rest_pv,
        )

    # --- apply and verify -----------------------------------------------------------------

    def _apply_and_verify(self, ident: Identification, chosen: IsaGains) -> dict:
        b = self.before
        new = PidGains(kc=chosen.kc, ti=chosen.ti, td=chosen.td)
        if not self.req.verify:
            self._set_auto(new, b.sp if b.mode == "auto" else self.client.sync().pv)
            return {"applied": True}
        sp0 = b.sp if b.mode == "auto" else self.client.sync().pv
        before_v = self._verify(b.gains, sp0, ident) if b.mode == "auto" else None
        after_v = self._verify(new, sp0, ident)
        worse = before_v is not None and before_v.stable and after_v.score > before_v.score
        if not after_v.stable or worse:
            why = (
                "unstable"
                if not after_v.stable
                else (
                    f"worse than before (IAE per unit step {after_v.score:.4g} against "
                    f"{before_v.score:.4g})"
                )
            )
            self._restore()
            return {
                "applied": False,
                "before": before_v,
                "after": after_v,
                "reason": f"new gains {why}: previous gains restored",
            }
        self._set_auto(new, sp0)
        return {"applied": True, "before": before_v, "after": after_v}

    def _set_auto(self, gains: PidGains, sp: float) -> None:
        c = self.client
        c.command(GainsCommand(loop=c.loop, gains=gains, source=c.source, t=self._t))
        c.command(SetpointCommand(loop=c.loop, sp=sp, source=c.source, t=self._t))
        if c.last_status.mode != "auto":
            c.command(ModeCommand(loop=c.loop, mode="auto", source=c.source, t=self._t))

    def _record(
        self, seconds: float, done: Callable[[np.ndarray, np.ndarray], bool]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """Run the loop (in auto) up to ``seconds``; stop early when ``done(t, y)``.
        Returns (t, pv, op, within_limits)."""
        c = self.client
        n_max = max(1, round(seconds / self.ts))
        chunk = max(1, min(MAX_CHUNK, n_max // 100))
        t, y, u = [], [], []
        lo, hi = self.pv_limits
        while len(t) < n_max:
            self._check_cancel()
            for s in c.samples(chunk):
                t.append(s.t)
                y.append(s.pv)
                u.append(s.op)
            self._take([c.last_sample] if c.last_sample else [])
            if not all(lo <= v <= hi for v in y[-chunk:]):
                return np.array(t), np.array(y), np.array(u), False
            if len(t) % (chunk * 8) < chunk and done(np.array(t), np.array(y)):
                break
        return np.array(t), np.array(y), np.array(u), True

    def _verify(self, gains: PidGains, sp0: float, ident: Identification) -> Verification:
        """A setpoint step, then a load step, with ``gains``; the loop ends at ``sp0``."""
        c = self.client
        scale = max(ident.timescale, 20 * self.ts)
        lo, hi = self.info.pv_range
        step = VERIFY_SP_FRACTION * (hi - lo) * (1 if sp0 < 0.5 * (lo + hi) else -1)
        band = max(0.02 * abs(step), 4 * ident.noise)
        self._progress("verify", message=f"Kc {gains.kc:.4g}, Ti {gains.ti}, Td {gains.td:.4g}")
        self._set_auto(gains, sp0)

        def quiet(t: np.ndarray, y: np.ndarray) -> bool:
            k = max(4, round(scale / self.ts))
            return y.size >= k and metrics.at_rest(y[-k:], 2 * band)

        _, _, _, ok = self._record(5 * scale, quiet)
        stable = ok
        t0, y0 = self._t, c.last_sample.pv if c.last_sample else sp0
        c.command(SetpointCommand(loop=c.loop, sp=sp0 + step, source=c.source, t=t0))
        t, y, u, ok = self._record(
            15 * scale,
            lambda t, y: (
                t[-1] - t[0] > 2 * scale and quiet(t, y) and abs(y[-1] - sp0 - step) < band
            ),
        )
        sp_m = metrics.setpoint_step(t, y, t0, y0, sp0 + step, noise=ident.noise)
        stable = stable and ok and bool(sp_m["settled"]) and (sp_m["decay_ratio"] or 0) < 1
        op_lo, op_hi = self.info.op_limits
        saturated = bool(np.mean((u <= op_lo) | (u >= op_hi)) > 1 / 3) if u.size else False
        load_size, load_m = None, None
        before = c.sync()
        if stable and "load" in before.disturbances:
            load_size = self.req.amplitude or DEFAULT_RELAY_AMPLITUDE
            base = before.disturbances["load"]
            t1 = self._t
            c.command(
                DisturbanceCommand(
                    loop=c.loop, name="load", value=base + load_size, source=c.source, t=t1
                )
            )
            t, y, u, ok = self._record(
                15 * scale,
                lambda t, y: (
                    t[-1] - t[0] > 2 * scale and quiet(t, y) and abs(y[-1] - sp0 - step) < band
                ),
            )
            load_m = metrics.load_step(t, y, t1, sp0 + step, noise=ident.noise)
            stable = stable and ok and bool(load_m["recovered"])
            c.command(
                DisturbanceCommand(loop=c.loop, name="load", value=base, source=c.source, t=self._t)
            )
        c.command(SetpointCommand(loop=c.loop, sp=sp0, source=c.source, t=self._t))
        if stable:
            self._record(5 * scale, quiet)
        score = sp_m["iae"] / abs(step) + (load_m["iae"] / load_size if load_m else 0.0)
        return Verification(
            gains=gains,
            sp_step=step,
            overshoot=sp_m["overshoot"],
            decay_ratio=sp_m["decay_ratio"],
            rise_time=sp_m["rise_time"],
            settling_time=sp_m["settling_time"],
            iae_sp=sp_m["iae"],
            load_step=load_size,
            iae_load=load_m["iae"] if load_m else None,
            max_deviation_load=load_m["max_deviation"] if load_m else None,
            recovery_time=load_m["recovery_time"] if load_m else None,
            stable=stable,
            saturated=saturated,
            score=score,
        )
