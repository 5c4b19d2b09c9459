"""How a closed loop rings: the oscillatory mode of a verification's response, fitted.

The decay ratio read off a setpoint step's first two peaks misses a lightly damped mode that
the step barely excites. Seen: e^{−0.5s}/(s² + 0.6s + 1) under ZN PI from a ramp test's
model, no overshoot and the step's ripples at 0.85, 0.92 and 0.96 of it on the way up, while
the loop's dominant poles ring at ζ 0.086, each period 0.58 of the one before (Ms 3.1 on the
plant), and the run ended ``ok``. The response from the step on is fitted with a decaying
sinusoid beside a slow real mode (``oscillation.fit_ringing``: the approach to the
setpoint, or the recovery from a load, is that slow mode); the sinusoid's decay over one
period, e^{g·P}, is the mode's decay ratio whatever its share of the response.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.autotuner.identify.oscillation import fit_ringing

MIN_SWINGS = 3  # half-cycles a mode must show to be judged
NOISE_SIGMAS = 4.0  # its amplitude where largest must stand this far out of the noise


@dataclass(frozen=True)
class Ringing:
    decay: float  # amplitude ratio over one period, e^{g·P} (the mode's decay ratio)
    period: float  # s
    amplitude: float  # PV units, at the response's start


def ringing(
    t: np.ndarray, y: np.ndarray, noise: float, scale: float | None = None
) -> Ringing | None:
    """The oscillatory mode in a response (``t`` s, ``y`` PV units, from its step on; ``noise``:
    σ of the PV's measurement noise; ``scale``: the loop's time scale, s, over a twelfth of
    which the record is smoothed before its turning points are read: the noise's own are then
    too few to fit, and a well-damped response costs no fit); None when none stands out:
    fewer than MIN_SWINGS
    half-cycles, seen for less than 1.5 periods, or its amplitude 1.5 periods on under
    NOISE_SIGMAS σ (a fit to noise alone finds a sinusoid a fraction of σ tall)."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.size < 16 or not np.all(np.isfinite(y)):
        return None
    with np.errstate(all="ignore"):  # a trial step of e^{g·t} may overflow: judged below
        osc = fit_ringing(t, y, noise, scale)
    if osc is None or osc.swings < MIN_SWINGS or not math.isfinite(osc.growth):
        return None
    watched = float(t[-1] - t[0])
    if not 0.0 < osc.period <= watched / 1.5:
        return None
    # still standing out of the noise 1.5 periods on: a mode that sinks into it sooner is
    # judged on a swing or two, and its fitted decay scatters (flow1 under TL PI, 0.061 a
    # period on the plant, read 0.05–0.23 from noisy records)
    seen = osc.amplitude * math.exp(min(osc.growth * 1.5 * osc.period, 50.0))
    if seen < max(NOISE_SIGMAS * noise, 1e-9 * float(np.ptp(y))):
        return None
    return Ringing(math.exp(min(osc.growth * osc.period, 50.0)), osc.period, osc.amplitude)
