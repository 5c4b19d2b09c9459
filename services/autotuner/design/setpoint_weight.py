"""The setpoint weight β that brings a verified setpoint step's overshoot within its limit,
read off the step measured with the gains' own weight.

Why: a PI or PID on an integrating or lag-dominant process overshoots a setpoint step by
40–60 % however good its margins: its integral must pass the setpoint to give back the error
it gathered on the way up. Such gains were rejected for their overshoot alone and the loop
was left with its old ones. The block's setpoint weight (u = Kc·(β·sp − pv) + I − D) weighs
the setpoint in the proportional action only: the feedback loop, its margins and its
response to a load are the same at any β; only the setpoint's path changes.

With the block's integral (forward Euler, added one sample late, ``shared.control.pid``) the
setpoint reaches the output through Kc·(β + a·z⁻¹/(1 − z⁻¹)), a = Ts/Ti, so the PV's response
to a setpoint step at β is the one measured at β₀ filtered by

    F(z) = (β + (a − β)·z⁻¹) / (β₀ + (a − β₀)·z⁻¹),

exact for the linear loop (the output within its limits throughout), the measurement's noise
filtered with it (F's gain is 1 at rest and about β/β₀ at the fastest). The weight is read on
a grid of 0.05 (what an engineer types), the largest that keeps the predicted overshoot
within ``AIM`` of the limit (the margin for the noise and for a loop not quite linear); the
setpoint step is then made again at that weight and judged as the first was.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from services.autotuner.design.measured_response import measured_setpoint_step

AIM = 0.8  # of the overshoot limit: the predicted overshoot the weight is chosen for
GRID = 0.05  # the weights tried, from the gains' own down to 0


@dataclass(frozen=True)
class Weighting:
    beta: float  # the setpoint weight found
    overshoot: float  # % the step measured at the gains' own weight overshot
    predicted: float  # % the same step is predicted to overshoot at ``beta``


def weighted_response(d: np.ndarray, beta: float, a: float, beta0: float = 1.0) -> np.ndarray:
    """The PV's deviation from its rest, ``d`` (one per sample from before the setpoint's
    step reached the loop), as it would have been with setpoint weight ``beta`` instead of
    ``beta0``; ``a`` = Ts/Ti."""
    return lfilter([beta, a - beta], [beta0, a - beta0], np.asarray(d, dtype=float))


def weights(beta0: float) -> list[float]:
    """The weights tried, largest first: the grid's below ``beta0`` down to 0."""
    n = int(np.floor(beta0 / GRID + 1e-9))
    return [round(k * GRID, 10) for k in range(n, -1, -1) if k * GRID < beta0 - 1e-9]


def weight_for_overshoot(
    t: np.ndarray,
    y: np.ndarray,
    t0: float,
    y0: float,
    target: float,
    ts: float,
    ti: float | None,
    limit: float,
    noise: float = 0.0,
    width: int = 5,
    beta0: float = 1.0,
) -> Weighting | None:
    """The largest weight on the grid below ``beta0`` at which the setpoint step measured
    (``t``, ``y``: the record from the step on, stepped at ``t0`` from rest at ``y0`` toward
    ``target``; figures as ``measured_setpoint_step`` reads them) would overshoot at most
    ``AIM`` × ``limit`` (%); None where none would, or the loop has no integral action (a
    weight then moves where P control leaves the PV, not only how it gets there), or the
    weight cannot be read off it (``beta0`` ≤ a/2: F would not be stable)."""
    t, y = np.asarray(t, dtype=float), np.asarray(y, dtype=float)
    if ti is None or ti <= 0 or ts <= 0 or y.size < 4 or target == y0:
        return None
    a = ts / ti
    if not 0 < a < 2 * beta0:
        return None
    first = measured_setpoint_step(t, y, t0, y0, target, noise=noise, width=width)["overshoot"]
    d = y - y0
    for beta in weights(beta0):
        yb = y0 + weighted_response(d, beta, a, beta0)
        over = measured_setpoint_step(t, yb, t0, y0, target, noise=noise, width=width)["overshoot"]
        if over <= AIM * limit:
            return Weighting(beta, float(first), float(over))
    return None
