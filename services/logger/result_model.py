"""The process model a run's result states, rebuilt from its plain numbers: the
``experiment`` object's ``model``, ``model_gain``, ``model_lag_i``, ``model_delay`` (relay,
ramp and step tests alike) and ``model_offset`` where the fit had one (the held output's
offset from its balance, %), else the step's reaction curve (K, L and the tangent's T)."""

from __future__ import annotations

import math

from services.autotuner.identify.model_fit import ProcessFit, StepModel, model_of

KINDS = {"fopdt": 1, "sopdt": 2, "ipdt": 0}  # the models the fit knows, and their lags


def _positive(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) and value > 0 else None


def _finite(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def _drift_offset(step: object, gain: float) -> float | None:
    """An integrating step test's held output's offset from its balance (%): the PV's drift
    before the step (PV units/s, ``drift``), which the test's rate is read net of, over the
    rate per % (−drift/K'). The model driven without it climbed off the data by the drift
    times the record (lvl2: 0.015 m by the ramp's end, its fit read 65.9 %: helper trial).
    None where the step is not an integrating one, or states no drift."""
    s = step if isinstance(step, dict) else {}
    drift = _finite(s.get("drift"))
    if s.get("method") != "integrating" or drift is None:
        return None
    return -drift / gain


def result_model(experiment: object, step: object = None) -> ProcessFit | None:
    """The stated model; None where the result has none or its numbers are unusable."""
    e = experiment if isinstance(experiment, dict) else {}
    kind = e.get("model")
    if kind in KINDS:
        gain = _positive(e.get("model_gain"))
        delay = e.get("model_delay")
        lags = [_positive(e.get(f"model_lag_{i}")) for i in range(1, KINDS[kind] + 1)]
        rms = e.get("model_rms")
        if (
            gain is not None
            and None not in lags
            and isinstance(delay, int | float)
            and not isinstance(delay, bool)
            and math.isfinite(delay)
            and delay >= 0
        ):
            fit_rms = (
                float(rms) if isinstance(rms, int | float) and not isinstance(rms, bool) else 0.0
            )
            held = _finite(e.get("model_offset"))
            if held is None and kind == "ipdt":
                held = _drift_offset(step, gain)
            return ProcessFit(kind, gain, tuple(lags), float(delay), fit_rms, offset=held)  # type: ignore[arg-type]
    s = step if isinstance(step, dict) else {}
    gain, lag = _positive(s.get("gain")), _positive(s.get("time_constant_tangent"))
    dead = s.get("dead_time")
    if gain is None or lag is None or not isinstance(dead, int | float) or not dead >= 0:
        return None
    return model_of(StepModel(gain, float(dead), lag))
