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

from services.autotuner import experiments, metrics
from services.autotuner.forms import IsaGains, all_forms
from services.autotuner.loop_client import LoopClient
from services.autotuner.ramp import RampTest
from services.autotuner.relay import RelayTest
from services.autotuner.rules import check_rule
from services.autotuner.selection import assessments_dict, select
from services.autotuner.step_test import StepTest
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
VERIFY_SP_FRACTION = 0.02  # of the PV range, verification setpoint step
MAX_CHUNK = 64  # samples per lockstep round trip while the loop runs in auto


class TuneAborted(AutotuneError):
    """The run stopped before a result; the loop has been restored."""


class TuneRefused(AutotuneError):
    """The identification is done but its gains must not be applied (predicted unstable, Ms
    above the bound, or the rule not available); the loop is restored."""


@dataclass
class RunHooks:
    """Where a run reports to, and how it is cancelled."""

    progress: Callable[[TuneProgress], None] = lambda p: None
    event: Callable[[TunerEvent], None] = lambda e: None
    cancelled: threading.Event | None = None


def _seconds(ti: float | None) -> str:
    return "off" if ti is None else f"{ti:.4g} s"


def _json_number(v: object) -> object:
    """Numbers as JSON takes them: infinities (an overdamped trial's growth) become None."""
    if isinstance(v, float | np.floating):
        return float(v) if math.isfinite(v) else None
    return v


def validate_request(req: TuneRequest) -> None:
    """ValueError naming the field when the request cannot be run."""
    if req.rule != "auto":
        try:
            rule = check_rule(req.rule)
        except ValueError as err:
            raise ValueError(f"rule: {err}; or auto") from None
        allowed = {"open": ("step",), "closed": ("relay", "ramp"), "model": ("relay", "step")}
        if req.method not in allowed[rule.kind]:
            need = {
                "open": "a step test (method step)",
                "closed": "K_u and P_u (relay/ramp)",
                "model": "a process model (relay or step)",
            }[rule.kind]
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
        self._reported = 0
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
            "requested_rule": req.rule,
            "previous_gains": before.gains,
            "pv_units": self.info.pv_units,
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
            self._event(
                "request",
                t0,
                {"request": req.model_dump_json(), "info": self.info.model_dump_json()},
            )
            ident = self._experiment()
            result.update(
                ku=ident.ku,
                pu=ident.pu,
                ku_spread=ident.ku_spread,
                pu_spread=ident.pu_spread,
                step=ident.step,
                experiment=ident.experiment or {},
            )
            sel = select(ident, req.rule, req.ms_bound, req.force, self.ts)
            rec = sel.recommended
            result.update(
                rule=sel.rule or req.rule,
                l_over_t=sel.l_over_t,
                gains={name: all_forms(g) for name, g in sel.table.items()},
                robustness=assessments_dict(sel),
                recommended=(
                    {"rule": rec.rule, "reason": rec.reason, "ms": rec.predicted_ms}
                    if rec
                    else None
                ),
                warnings=sel.warnings,
            )
            chosen = sel.chosen
            if chosen is None or (sel.refusal and req.apply):
                raise TuneRefused(sel.refusal or "no gains")
            result["chosen"] = all_forms(chosen)
            self._progress(
                "identified",
                ku=ident.ku,
                pu=ident.pu,
                message=f"{sel.rule}: Kc {chosen.kc:.4g}, Ti {_seconds(chosen.ti)}, "
                f"Td {chosen.td:.4g} s",
            )
            if req.apply:
                result.update(self._apply_and_verify(ident, chosen))
                restored = not result["applied"]
            else:
                self._restore()
                restored = True
            status = "ok" if result.get("applied") or not req.apply else "rejected"
            result.update(status=status, restored=restored)
        except TuneRefused as err:
            restored = self._restore()
            result.update(status="rejected", reason=str(err), restored=restored)
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

    # --- the experiment -------------------------------------------------------------------

    def _setup(self) -> dict:
        """What the live loop contributes to the experiment (logged, so a replay can rebuild
        the same state machine)."""
        req, c, b = self.req, self.client, self.before
        setup = {
            "sample_time": self.ts,
            "op_lo": self.info.op_limits[0],
            "op_hi": self.info.op_limits[1],
            "pv_lo": self.pv_limits[0],
            "pv_hi": self.pv_limits[1],
        }
        if req.method == "ramp":
            lo, hi = self.info.pv_range
            setup.update(
                kc_start=req.kc_start or (0.5 * b.gains.kc if b.gains.kc > 0 else 1.0),
                bump=req.bump or experiments.DEFAULT_BUMP_FRACTION * (hi - lo),
                sp_start=c.sync().pv,
            )
        else:
            st = c.command(ModeCommand(loop=c.loop, mode="manual", source=c.source))
            setup.update(op_start=st.op, direction=1.0 if b.action == "reverse" else -1.0)
        return setup

    def _event(self, kind: str, t: float, data: dict) -> None:
        self.hooks.event(
            TunerEvent(
                run_id=self.run_id,
                loop=self.client.loop,
                t=t,
                kind=kind,
                data={k: _json_number(v) for k, v in data.items()},
            )
        )

    def _experiment(self) -> experiments.Identification:
        """Run the requested experiment on the live loop through its state machine."""
        req, c = self.req, self.client
        setup = self._setup()
        try:
            machine = experiments.build(req.method, req, setup)
        except ValueError as err:
            raise TuneAborted(str(err)) from None
        auto = req.method == "ramp"
        if auto:
            c.command(GainsCommand(loop=c.loop, gains=PidGains(kc=machine.kc), source=c.source))
            c.command(SetpointCommand(loop=c.loop, sp=machine.sp, source=c.source))
            c.command(ModeCommand(loop=c.loop, mode="auto", source=c.source))
            kc, sp = machine.kc, machine.sp
        op = setup.get("op_start")
        first = True
        self._progress("quiet", message="measuring the PV's rest value and noise")
        while not machine.finished:
            self._check_cancel()
            want = None
            for s in c.samples(machine.horizon(MAX_CHUNK) if auto else 1):
                if first:
                    self._event("experiment", s.t, {**setup, "first_seq": s.seq})
                    first = False
                want = experiments.feed(machine, s)
                self._take([s])
                if machine.finished:
                    break
            self._forward_events(machine.events)
            if machine.finished:
                break
            if auto:
                if want.kc != kc:
                    kc = want.kc
                    c.command(GainsCommand(loop=c.loop, gains=PidGains(kc=kc), source=c.source))
                if want.sp != sp:
                    sp = want.sp
                    c.command(SetpointCommand(loop=c.loop, sp=sp, source=c.source))
            elif want != op:
                st = c.command(OutputCommand(loop=c.loop, op=want, t=self._t, source=c.source))
                op = want
                if isinstance(machine, StepTest):
                    # lockstep: held from the present sample; realtime: from the next one
                    t_step = st.t if self.info.clock == "lockstep" else st.t + self.ts
                    machine.step_started(t_step)
                    self._event("step_started", self._t, {"t": t_step})
            self._report(machine)
        self._forward_events(machine.events)
        ident = experiments.identification(machine)
        if ident is None:
            raise TuneAborted(f"{req.method} test: {machine.reason}")
        if auto:
            c.command(ModeCommand(loop=c.loop, mode="manual", source=c.source))
        elif c.last_status.op != setup["op_start"]:
            c.command(OutputCommand(loop=c.loop, op=setup["op_start"], t=self._t, source=c.source))
        return ident

    def _report(self, machine: experiments.Experiment) -> None:
        """Progress once per relay cycle or ramp trial."""
        if isinstance(machine, RelayTest):
            n = len(machine.cycles)
            if n != self._reported and n:
                cyc = machine.cycles[-1]
                self._progress("relay", cycles=n, ku=machine.ku_of(cyc.amplitude), pu=cyc.period)
        elif isinstance(machine, RampTest):
            n = len(machine.trials)
            if n != self._reported and n:
                tr = machine.trials[-1]
                self._progress(
                    "ramp",
                    cycles=n,
                    pu=tr.period,
                    message=f"Kc {tr.kc:.4g}: growth {tr.growth:.3g}/s",
                )
        else:
            n = 1 if machine.t_step is not None else 0
            if n != self._reported and n:
                self._progress("step", message=f"output stepped to {machine.op_target:g} %")
        self._reported = n

    # --- apply and verify -----------------------------------------------------------------

    def _apply_and_verify(self, ident: experiments.Identification, chosen: IsaGains) -> dict:
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

    def _verify(
        self, gains: PidGains, sp0: float, ident: experiments.Identification
    ) -> Verification:
        """A setpoint step, then a load step, with ``gains``; the loop ends at ``sp0``."""
        c = self.client
        scale = max(ident.timescale, 20 * self.ts)
        lo, hi = self.info.pv_range
        step = VERIFY_SP_FRACTION * (hi - lo) * (1 if sp0 < 0.5 * (lo + hi) else -1)
        band = max(0.02 * abs(step), 4 * ident.noise)
        self._progress(
            "verify", message=f"Kc {gains.kc:.4g}, Ti {_seconds(gains.ti)}, Td {gains.td:.4g}"
        )
        self._set_auto(gains, sp0)

        def quiet(t: np.ndarray, y: np.ndarray) -> bool:
            k = max(4, round(scale / self.ts))
            return y.size >= k and metrics.within_band(y[-k:], 2 * band)

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
            load_size = self.req.amplitude or experiments.DEFAULT_RELAY_AMPLITUDE
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
