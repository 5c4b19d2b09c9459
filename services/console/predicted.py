"""Each rule's predicted setpoint step, as a curve for the page's result panel.

The same loop the tuner judged the rules on (``design/predicted_response.py``): the loop's own
PID block (ISA form, derivative filter N = 10) at the loop's sample time, or coarser where the
curve's span would take more than ``POINTS`` of them (hx1's at 1.09 s for its 0.25 s: a curve
to look at, not the tuner's figures), closing the loop on the identified model discretised
exactly; a unit setpoint step from rest, small enough that
the output limits do not bind, so the curve is the linear loop's, in units of the step.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from services.autotuner.identify.model_fit import ProcessFit
from shared.control.forms import IsaGains
from shared.control.lti import discretize, tf_to_ss
from shared.control.setpoint_steps import setpoint_steps
from shared.control.transfer import DelayedTF

HORIZON = 10.0  # time scales shown (P_u, else the model's delay plus lag)
POINTS = 400  # samples per curve at most: the simulation's step is coarsened to fit
SETTLED = 0.02  # a curve whose last fifth moves less than this (× the step) has settled
SPAN_GROWTH = 4.0  # an unsettled curve is simulated again over this many times its span
LONGEST = 4  # spans tried at most (HORIZON × 4³ = 640 time scales)
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


def step_curves(
    gains: Mapping[str, IsaGains], plant: DelayedTF, timescale: float, sample_time: float
) -> dict[str, tuple[np.ndarray, np.ndarray] | None]:
    """Per candidate, (t in s, PV in units of the setpoint step) over HORIZON time scales, or
    as many times that as it takes to settle (at most LONGEST: a slow one — lambda PI at
    λ = T on a lag-dominant loop, hundreds of its P_u — was cut at a tenth of its rise, and
    its steady climb over the last fifth read as an undamped swing, the curve dropped);
    None when its loop is unstable (the curve would say nothing but that). Those of one span
    are simulated together (``shared.control.setpoint_steps``)."""
    out: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
    left = dict(gains)
    span = HORIZON * timescale
    for attempt in range(LONGEST):
        if not left:
            break
        ts = max(sample_time, span / POINTS)
        sys = discretize(*tf_to_ss(plant.num, plant.den), ts, plant.delay)
        n = int(span / ts)
        # a proportional kick of 10 % at most
        steps = [min(1.0, 10.0 / g.kc) if g.kc > 0 else 1.0 for g in left.values()]
        y, blown = setpoint_steps(list(left.values()), sys, n, steps, 1e3)
        t = ts * np.arange(1, n + 1)
        last = attempt == LONGEST - 1
        for j, name in enumerate(list(left)):
            tail, head = np.ptp(y[j, -(n // 5) :]), np.ptp(y[j, : n // 5])
            if blown[j]:
                out[name] = None
            elif tail <= SETTLED:  # settled within the span
                out[name] = (t, y[j])
            elif last:
                # still swinging at the end as much as at the start: unstable, held only by
                # the output limits (the tuner's own judgement, design/predicted_response.py)
                out[name] = None if tail > 0.5 * (head or 1.0) else (t, y[j])
            else:
                continue
            del left[name]
        span *= SPAN_GROWTH
    return {name: out.get(name) for name in gains}


def step_curve(
    kc: float, ti: float | None, td: float, plant: DelayedTF, timescale: float, sample_time: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """``step_curves`` of one candidate."""
    return step_curves({"": IsaGains(kc, ti, td)}, plant, timescale, sample_time)[""]


def predicted_curves(result: dict[str, Any]) -> dict[str, dict[str, list[float]] | None]:
    """Per rule of a TuneResult (as JSON), its predicted setpoint step ``{"t": [...], "y":
    [...]}`` on the identified model (None: unstable); empty without a model."""
    model = model_of(result.get("experiment") or {})
    sample_time = (result.get("identified_on") or {}).get("sample_time")
    if model is None or not sample_time:
        return {}
    scale = timescale_of(model, result.get("pu"))
    out: dict[str, dict[str, list[float]] | None] = {}
    gains: dict[str, IsaGains] = {}
    for rule, forms in (result.get("gains") or {}).items():
        isa = (forms or {}).get("isa") or {}
        try:
            gains[rule] = IsaGains(float(isa["kc"]), isa.get("ti"), float(isa.get("td") or 0.0))
        except (KeyError, TypeError, ValueError):
            out[rule] = None
    try:
        curves = step_curves(gains, model.transfer, scale, float(sample_time))
    except (TypeError, ValueError, ArithmeticError, np.linalg.LinAlgError):
        curves = dict.fromkeys(gains)
    for rule, curve in curves.items():
        out[rule] = None if curve is None else {"t": curve[0].tolist(), "y": curve[1].tolist()}
    return {rule: out[rule] for rule in (result.get("gains") or {})}
