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

from services.autotuner.identify.oscillation import Oscillation, fit_ringing
from services.autotuner.parts import Parts, in_turn

MIN_SWINGS = 3  # half-cycles a mode must show to be judged
NOISE_SIGMAS = 4.0  # its amplitude where largest must stand this far out of the noise
# or, where a caller gives a least height (``least``) for the mode: the energy
# the fit explains over the record, in σ² of the noise, with this many half-cycles at
# least. A fit to white noise alone explained at most 20 σ² in 1,000 records of 96–3,000
# samples; a resonance's ringing 4σ tall that keeps 0.86–0.96 of itself a period over 15–30
# periods explained 400–1,100 (random field plants, seed base 13: TL PIs ok at exact gain
# margins 1.5 and 1.8)
SUSTAINED_ENERGY = 100.0
SUSTAINED_SWINGS = 8


@dataclass(frozen=True)
class Ringing:
    decay: float  # amplitude ratio over one period, e^{g·P} (the mode's decay ratio)
    period: float  # s
    amplitude: float  # PV units, at the response's start


def ringing(
    t: np.ndarray,
    y: np.ndarray,
    noise: float,
    scale: float | None = None,
    least: float | None = None,
    parts: Parts = in_turn,
) -> Ringing | None:
    """The oscillatory mode in a response (``t`` s, ``y`` PV units, from its step on; ``noise``:
    σ of the PV's measurement noise; ``scale``: the loop's time scale, s, over a twelfth of
    which the record is smoothed before its turning points are read: the noise's own are then
    too few to fit, and a well-damped response costs no fit); None when none stands out:
    fewer than MIN_SWINGS
    half-cycles, seen for less than 1.5 periods, or its amplitude 1.5 periods on under
    NOISE_SIGMAS σ (a fit to noise alone finds a sinusoid a fraction of σ tall). Given
    ``least`` (PV units), the mode must stand that tall 1.5 periods on, and one under the
    noise's height counts too where it lasts: SUSTAINED_SWINGS half-cycles or more, and the
    fit explaining SUSTAINED_ENERGY σ² of the record or more (a small ringing over many
    periods is as sure as a tall one over a few). ``parts``: how the fit's independent
    starts are computed (``oscillation.fit_ringing``; the same result to the bit)."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.size < 16 or not np.all(np.isfinite(y)):
        return None
    with np.errstate(all="ignore"):  # a trial step of e^{g·t} may overflow: judged below
        osc = fit_ringing(t, y, noise, scale, parts)
    if osc is None or not stands_out(t, y, osc, noise, least):
        return None
    return Ringing(math.exp(min(osc.growth * osc.period, 50.0)), osc.period, osc.amplitude)


def stands_out(
    t: np.ndarray, y: np.ndarray, osc: Oscillation, noise: float, least: float | None = None
) -> bool:
    """Whether a mode fitted to (``t``, ``y``) is judged (``ringing``'s tests): MIN_SWINGS
    half-cycles, seen for 1.5 periods, and out of the noise (or, given ``least``, lasting)."""
    if osc.swings < MIN_SWINGS or not math.isfinite(osc.growth):
        return False
    watched = float(t[-1] - t[0])
    if not 0.0 < osc.period <= watched / 1.5:
        return False
    # still standing out of the noise 1.5 periods on: a mode that sinks into it sooner is
    # judged on a swing or two, and its fitted decay scatters (flow1 under TL PI, 0.061 a
    # period on the plant, read 0.05–0.23 from noisy records)
    seen = osc.amplitude * math.exp(min(osc.growth * 1.5 * osc.period, 50.0))
    if seen < max(1e-9 * float(np.ptp(y)), least or 0.0):
        return False
    return seen >= NOISE_SIGMAS * noise or (least is not None and _lasts(y, osc, noise))


def _lasts(y: np.ndarray, osc: Oscillation, noise: float) -> bool:
    """Whether the fitted mode is sustained: SUSTAINED_SWINGS half-cycles or more, and the
    fit explaining SUSTAINED_ENERGY σ² or more of the record's energy about zero (``y`` a
    residual: the explained part is its mean square less the fit's, over its samples)."""
    if osc.swings < SUSTAINED_SWINGS or not noise > 0.0:
        return False
    explained = y.size * (float(np.mean(np.square(y))) - osc.rms**2)
    return explained >= SUSTAINED_ENERGY * noise**2
