"""The fitted model against the recorded data: the model, driven by the recorded output
from the rest the experiment started at, simulated over the record (exact ZOH
discretisation, ``model_fit.response_to``) beside the measured PV. The window runs from the
experiment's first sample to the first load step (a disturbance the model does not know) or
the record's end; the closed loop of a ramp or a verification does not matter, since the
model maps output to PV whoever sets the output. Pure."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.autotuner.identify.model_fit import ProcessFit, response_to

REST_SAMPLES = 40  # the relay's and the ramp's quiet period, the step's baseline (defaults)


@dataclass(frozen=True)
class Overlay:
    t: np.ndarray  # s
    pv: np.ndarray  # the recorded PV, PV units
    model_pv: np.ndarray  # the model's, PV units
    rest_pv: float  # where both start, PV units
    op_start: float  # %, the output the deviations are taken from
    fit_percent: float  # 100·(1 − ‖y − ŷ‖/‖y − ȳ‖): 100 a perfect fit, 0 no better than the mean
    rms: float  # of y − ŷ, PV units
    hole: float | None = None  # s: where the record has a hole, at which the overlay stops

    @property
    def end(self) -> float:
        return float(self.t[-1])


def model_overlay(
    t: np.ndarray,
    pv: np.ndarray,
    op: np.ndarray,
    model: ProcessFit,
    sample_time: float,
    start: int,
    end: int,
) -> Overlay | None:
    """The overlay on samples ``start`` … ``end - 1``; ``op[k]`` the output held from sample
    k. The model starts from the rest the experiments measure first: the mean PV and output
    over the first ``REST_SAMPLES`` samples, and is driven, as it was fitted, by the output
    less its fitted offset from the balance (``ProcessFit.offset``: an integrator's, which
    a ramp of the PV shows over a long record: without it the line drifted off the data).
    None for a window shorter than that or a model that cannot be simulated."""
    t, pv, op = (np.asarray(a, dtype=float)[start:end] for a in (t, pv, op))
    if t.size <= REST_SAMPLES or not (math.isfinite(sample_time) and sample_time > 0):
        return None
    r, u0 = float(np.mean(pv[:REST_SAMPLES])), float(np.mean(op[:REST_SAMPLES]))
    try:
        with np.errstate(all="ignore"):
            y_hat = r + response_to(model, sample_time, op - u0 - (model.offset or 0.0))
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(y_hat)):
        return None
    err = pv - y_hat
    spread = float(np.linalg.norm(pv - pv.mean()))
    fit = 100.0 * (1.0 - float(np.linalg.norm(err)) / spread) if spread > 0 else math.nan
    return Overlay(t, pv, y_hat, r, u0, fit, float(np.sqrt(np.mean(err**2))))
