"""Build an experiment's state machine from a request and its set-up, and read its result.

The live tuner and the offline analysis of a recorded run both go through here: given the same
set-up (published as the run's ``experiment`` event) and the same samples, they reach the
same K_u, P_u or reaction curve, to the bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from services.autotuner.design.rules import StepModel, model_of
from services.autotuner.identify.model_fit import ProcessFit
from services.autotuner.identify.ramp import RampConfig, RampTest
from services.autotuner.identify.relay import RelayConfig, RelayTest
from services.autotuner.identify.step_test import StepTest, StepTestConfig
from shared.messages import ProcessSample, TuneRequest

DEFAULT_RELAY_AMPLITUDE = 5.0  # %
DEFAULT_STEP_SIZE = 5.0  # %
DEFAULT_BUMP_FRACTION = 0.01  # of the PV range, ramp setpoint bump

Experiment = RelayTest | RampTest | StepTest


@dataclass
class Identification:
    """What an experiment found, in the terms the rules and the verification need."""

    ku: float | None = None
    pu: float | None = None
    ku_spread: float | None = None
    pu_spread: float | None = None
    step: dict | None = None
    step_model: StepModel | None = None
    model: ProcessFit | None = None  # the process model fitted to the test (relay, step)
    experiment: dict | None = None
    timescale: float = 0.0  # s: the loop's natural period, for verification windows
    noise: float = 0.0
    rest_pv: float = math.nan
    # evidence of integration in the record: True when the PV ramps under a constant output,
    # False when it settles, None when the experiment did not tell (``model_check`` then
    # accepts an integrating model only if it reproduces the measured ultimate point)
    integrating: bool | None = None
    notes: list[str] = field(default_factory=list)  # what the engineer must know (warnings)
    # False when the experiment did not pin the model's static gain (a relay without bias: its
    # mean output never moves, so K is extrapolated from points near ω_u): the rules that
    # scale with 1/K (AMIGO, SIMC) are then offered but not recommended
    static_gain_known: bool = True


def _frequency_fields(points) -> dict[str, float]:
    """The exact frequency points of a relay test, flat for JSON: omega_k (rad/s),
    g_k_magnitude (PV units per %) and g_k_phase_deg, k = 1, 3, 5."""
    out: dict[str, float] = {}
    previous = 0.0
    for p in points:
        k = round(p.omega / points[0].omega)
        phase = p.phase_deg
        while phase > previous:  # unwrapped: the lag grows with frequency
            phase -= 360.0
        previous = phase
        out[f"omega_{k}"] = p.omega
        out[f"g_{k}_magnitude"] = p.magnitude
        out[f"g_{k}_phase_deg"] = phase
    return out


def build(method: str, req: TuneRequest, setup: dict[str, Any]) -> Experiment:
    """The state machine for ``method``; ValueError naming the setting that cannot work.

    ``setup`` holds what the live loop contributed: sample_time, op_start, op_lo/op_hi,
    pv_lo/pv_hi, and direction (relay), kc_start, bump and sp_start (ramp); with time_scale
    (s, the drift check's window) the budgets before a first period are bounded by it:
    relay 100, ramp trial 30, step 200 time scales (and 400 samples at least).
    """
    ts = setup["sample_time"]
    op_limits = (setup["op_lo"], setup["op_hi"])
    pv_limits = (setup["pv_lo"], setup["pv_hi"])
    budget = {"max_time": req.max_time} if req.max_time else {}
    # the loop's slowest known dynamics (the drift check's window, s) bound the phases that
    # run before the test has seen a period of its own; a request's max_time overrides
    scale = setup.get("time_scale")
    if method == "relay":
        if scale and not req.max_time:
            budget = {"max_time": min(RelayConfig.max_time, max(100 * scale, 400 * ts))}
        cfg = RelayConfig(
            amplitude=req.amplitude or DEFAULT_RELAY_AMPLITUDE,
            hysteresis=req.hysteresis,
            cycles=req.cycles,
            tolerance=req.tolerance,
            low_ratio=1.0 - (req.relay_bias or 0.0),
            **budget,
        )
        return RelayTest(cfg, setup["op_start"], op_limits, pv_limits, ts, setup["direction"])
    if method == "ramp":
        first = (
            {"first_trial_time": min(RampConfig.first_trial_time, max(30 * scale, 200 * ts))}
            if scale
            else {}
        )
        cfg = RampConfig(
            kc_start=setup["kc_start"],
            bump=setup["bump"],
            tolerance=min(req.tolerance, 0.02) / 2,
            **first,
            **budget,
        )
        return RampTest(cfg, pv_limits, ts, sp_start=setup["sp_start"], op_limits=op_limits)
    if method == "step":
        cfg = StepTestConfig(
            size=req.step_size or DEFAULT_STEP_SIZE,
            pv_limits=pv_limits,
            **(
                {"timeout": req.max_time}
                if req.max_time
                else {"timeout": min(StepTestConfig.timeout, max(200 * scale, 400 * ts))}
                if scale
                else {}
            ),
        )
        pv_range = (setup["pv_range_lo"], setup["pv_range_hi"]) if "pv_range_lo" in setup else None
        return StepTest(
            cfg,
            setup["op_start"],
            op_limits,
            pv_limits,
            ts,
            pv_range=pv_range,
            pv_units=str(setup.get("pv_units", "")),
        )
    raise ValueError(f"method: unknown method {method!r}")


def feed(machine: Experiment, s: ProcessSample) -> Any:
    """Give the machine one sample; return what it wants held (an output or a Demand)."""
    if isinstance(machine, StepTest):
        return machine.feed(s)
    if isinstance(machine, RampTest):
        return machine.feed(s.t, s.pv, s.op)
    return machine.feed(s.t, s.pv)


def identification(machine: Experiment) -> Identification | None:
    """The machine's findings once it is done (None if it has none)."""
    if isinstance(machine, RelayTest):
        r = machine.result
        if r is None:
            return None
        measured = r.crossing != "not reached"
        notes = []
        if not measured:
            notes.append(
                f"the relay's cycle ran at {r.phase_reached_deg:.0f}°, far from −180° (the "
                f"hysteresis the noise needs, {r.hysteresis:.3g}, is as large as the cycle): "
                "K_u and P_u were not measured, so the rules that need them are not offered"
                + (
                    f"; the model's own ultimate point is K_u ≈ {r.ku:.4g}, P_u ≈ {r.pu:.4g} s"
                    if math.isfinite(r.ku)
                    else ""
                )
            )
        return Identification(
            static_gain_known=r.static_gain is not None,
            ku=r.ku if measured else None,
            pu=r.pu if measured else None,
            ku_spread=r.ku_spread if measured else None,
            pu_spread=r.pu_spread if measured else None,
            notes=notes,
            experiment={
                "crossing": r.crossing,
                "phase_reached_deg": r.phase_reached_deg,
                **({} if measured else {"ku_model": r.ku, "pu_model": r.pu}),
                "relay_amplitude": r.relay_amplitude,
                "amplitude": r.amplitude,
                "hysteresis": r.hysteresis,
                "bias": r.bias,
                "cycles": r.cycles,
                "noise_std": r.noise_std,
                "rest_pv": r.rest_pv,
                "ku_describing_function": r.ku_df,
                "pu_describing_function": r.pu_df,
                "stage_one_cycles": r.stage_one_cycles,
                **_frequency_fields(r.frequency),
                **{f"stage2_{k}": v for k, v in _frequency_fields(r.second).items()},
                **(r.model.to_dict() if r.model else {}),
                **({"static_gain": r.static_gain} if r.static_gain is not None else {}),
            },
            timescale=r.pu if math.isfinite(r.pu) else r.cycle_period,
            noise=r.noise_std,
            rest_pv=r.rest_pv,
            model=r.model,
        )
    if isinstance(machine, RampTest):
        r = machine.result
        if r is None:
            return None
        return Identification(
            ku=r.ku,
            pu=r.pu,
            ku_spread=(r.kc_high - r.kc_low) / r.ku,
            experiment={
                "trials": r.trials,
                "ku_sampled_loop": r.ku_loop,
                "pu_sampled_loop": r.pu_loop,
                **(r.model.to_dict() if r.model else {}),
                "kc_low": r.kc_low,
                "kc_high": r.kc_high,
                "bump": machine.config.bump,
                "bump_final": machine.bump,
                "noise_std": r.noise_std,
                "rest_pv": r.rest_pv,
            },
            timescale=r.pu,
            noise=r.noise_std,
            rest_pv=r.rest_pv,
            model=r.model,
        )
    rc = machine.result
    if rc is None:
        return None
    step_model = StepModel(rc.gain, rc.dead_time, rc.time_constant_tangent)
    fitted = machine.process_model()
    return Identification(
        step=rc.to_dict(),
        step_model=step_model,
        model=fitted or model_of(step_model),
        integrating=False,  # it settled
        experiment={
            "step_size": rc.step_size,
            "method": rc.method,
            **(fitted.to_dict() if fitted else {}),
        },
        timescale=4 * rc.dead_time + rc.time_constant_63,
        noise=rc.noise_std,
        rest_pv=rc.pv_before,
    )
