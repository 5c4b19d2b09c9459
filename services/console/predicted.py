"""Each rule's predicted setpoint step, as a curve for the page's result panel.

The same loop the tuner judged the rules on (``design/predicted_response.py``): the loop's own
PID block (ISA form, derivative filter N = 10) at the loop's sample time, closing the loop on
the identified model discretised exactly; a unit setpoint step from rest, small enough that
the output limits do not bind, so the curve is the linear loop's, in units of the step.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from services.autotuner.identify.model_fit import ProcessFit
from shared.control.lti import DelayedLinearSystem, discretize, tf_to_ss
from shared.control.pid import PidBlock, PidSettings
from shared.control.transfer import DelayedTF

HORIZON = 10.0  # time scales shown (P_u, else the model's delay plus lag)
POINTS = 400  # samples per curve at most: the simulation's step is coarsened to fit
KINDS = ("fopdt", "sopdt", "ipdt")


def model_of(experiment: dict[str, Any]) -> ProcessFit | None:
    """The identified model of a result's ``experiment`` figures (``model``, ``model_gain``,
    ``model_lag_i``, ``model_delay``); None when the run identified none."""
    kind = experiment.get("model")
    if kind not in KINDS:
        return None
    try:
        lags = tuple(
            float(experiment[f"model_lag_{i}"])
            for i in range(1, 3)
            if experiment.get(f"model_lag_{i}") is not None
        )
        return ProcessFit(
            kind, float(experiment["model_gain"]), lags, float(experiment["model_delay"]), 0.0
        )
    except (KeyError, TypeError, ValueError):
        return None


def timescale_of(model: ProcessFit, pu: float | None) -> float:
    """The closed loop's time scale, s: P_u, else the model's own ultimate period, else its
    delay plus lag (as the tuner's judgement takes it)."""
    if pu is not None and math.isfinite(pu) and pu > 0:
        return pu
    own = model.ultimate_point()
    if own is not None and math.isfinite(own[1]) and own[1] > 0:
        return float(own[1])
    scale = model.delay + model.lag
    return scale if math.isfinite(scale) and scale > 0 else 10.0 * max(model.delay, 1.0)


def step_curve(
    kc: float, ti: float | None, td: float, plant: DelayedTF, timescale: float, sample_time: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """(t in s, PV in units of the setpoint step) over HORIZON time scales; None when the
    loop is unstable (the curve would say nothing but that)."""
    span = HORIZON * timescale
    ts = max(sample_time, span / POINTS)
    sys = DelayedLinearSystem(discretize(*tf_to_ss(plant.num, plant.den), ts, plant.delay))
    pid = PidBlock(PidSettings(kc=kc, ti=ti, td=td), ts, (0.0, 100.0), mode="auto", op=50.0)
    step = min(1.0, 10.0 / kc) if kc > 0 else 1.0  # a proportional kick of 10 % at most
    n = int(span / ts)
    y = np.empty(n)
    pv = 0.0
    for k in range(n):
        pv = sys.step(pid.update(step, pv) - 50.0)  # deviations about the 50 % rest
        y[k] = pv / step
        if not math.isfinite(y[k]) or abs(y[k]) > 1e3:
            return None
    # still swinging at the end as much as at the start: unstable, held only by the output
    # limits (the tuner's own judgement of "stable", design/predicted_response.py)
    if np.ptp(y[-(n // 5) :]) > 0.5 * (np.ptp(y[: n // 5]) or 1.0):
        return None
    return ts * np.arange(1, n + 1), y


def predicted_curves(result: dict[str, Any]) -> dict[str, dict[str, list[float]] | None]:
    """Per rule of a TuneResult (as JSON), its predicted setpoint step ``{"t": [...], "y":
    [...]}`` on the identified model (None: unstable); empty without a model."""
    model = model_of(result.get("experiment") or {})
    sample_time = (result.get("identified_on") or {}).get("sample_time")
    if model is None or not sample_time:
        return {}
    scale = timescale_of(model, result.get("pu"))
    out: dict[str, dict[str, list[float]] | None] = {}
    for rule, forms in (result.get("gains") or {}).items():
        isa = (forms or {}).get("isa") or {}
        try:
            curve = step_curve(
                float(isa["kc"]),
                isa.get("ti"),
                float(isa.get("td") or 0.0),
                model.transfer,
                scale,
                float(sample_time),
            )
        except (KeyError, TypeError, ValueError, ArithmeticError, np.linalg.LinAlgError):
            curve = None
        out[rule] = None if curve is None else {"t": curve[0].tolist(), "y": curve[1].tolist()}
    return out
