"""The plant's own ultimate point from the sampled loop's, through a model of the process.

A P-only loop closed by a sampled PID block runs through the zero-order hold, which lags by
about ωT/2 at ω: the loop reaches −180° below the plant's own phase crossover, and its K_u
and P_u differ from the plant's (on a fast loop at 50 samples per period, P_u by 2.5 %). A
P-gain ramp measures the loop's point. A process model fitted to the whole record tells how
far the hold moved it: the ratio of the model's own ultimate point to the ultimate point of
the same model held and sampled at T, applied to the measured point. The ratio rests on the
model's phase and gain slopes near ω_u, fitted on thousands of samples; the model's absolute
point need not be right (a first-order model of a third-order flow loop puts K_u 17 % low,
and still gives the hold's effect within a few tenths of a per cent).

Units: K_u in % of output per PV unit, P_u and T in s, ω in rad/s.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from shared.control.lti import discretize, tf_to_ss
from shared.control.transfer import DelayedTF

GRID_POINTS = 600  # logarithmic grid up to π/T (a root between two points is refined)
MAX_SHIFT = 0.3  # the model's sampled crossover this far from the measured one: not its loop


def sampled_ultimate_point(plant: DelayedTF, sample_time: float) -> tuple[float, float] | None:
    """(K_u, P_u) of the P-only loop around ``plant`` held and sampled at ``sample_time``: the
    first ω ≤ π/T where the phase of G(e^{jωT}) reaches −π, exactly (aliasing included); None
    if it never does below the Nyquist frequency or the continuous phase never reaches −π.

    The sampled phase is the continuous one, unwrapped exactly from poles and zeros, less ωT/2,
    plus what aliasing adds (within ±π of it: read from the exact response)."""
    cont = plant.ultimate_point()
    if cont is None:
        return None
    nyquist = math.pi / sample_time
    sys = discretize(*tf_to_ss(list(plant.num), list(plant.den)), sample_time, plant.delay)
    held = DelayedTF(plant.num, plant.den, plant.delay + 0.5 * sample_time)  # the hold's lag

    def phase(w: np.ndarray) -> np.ndarray:
        smooth = held.phase(w)
        exact = np.angle(sys.response(w))
        return smooth + np.angle(np.exp(1j * (exact - smooth)))

    low = 1e-3 * min(2.0 * math.pi / cont[1], nyquist)  # far below either crossover
    grid = np.logspace(math.log10(low), math.log10(nyquist), GRID_POINTS)
    grid[-1] = nyquist
    f = phase(grid) + math.pi
    below = np.nonzero(f <= 0)[0]
    if below.size == 0 or below[0] == 0:
        return None
    i = int(below[0])
    w = (
        grid[i]
        if f[i] == 0
        else brentq(
            lambda x: float(phase(np.array([x]))[0]) + math.pi, grid[i - 1], grid[i], xtol=1e-14
        )
    )
    gain = float(abs(sys.response(w)[0]))
    if not (gain > 0 and math.isfinite(gain)):
        return None
    return 1.0 / gain, 2.0 * math.pi / w


def through_model(
    ku_loop: float, pu_loop: float, plant: DelayedTF, sample_time: float
) -> tuple[float, float] | None:
    """The plant's (K_u, P_u) from the measured loop's, corrected for the hold as ``plant``
    says (see the module); None when the model cannot say: no ultimate point, or its sampled
    crossover more than ``MAX_SHIFT`` from the measured one (it is not a model of this loop
    near ω_u)."""
    cont = plant.ultimate_point()
    held = sampled_ultimate_point(plant, sample_time)
    if cont is None or held is None:
        return None
    if abs(held[1] / pu_loop - 1.0) > MAX_SHIFT:
        return None
    ku, pu = ku_loop * cont[0] / held[0], pu_loop * cont[1] / held[1]
    if not (math.isfinite(ku) and math.isfinite(pu) and ku > 0 and pu > 0):
        return None
    return ku, pu


def slope_error(s_pts: np.ndarray, l_pts: np.ndarray) -> float:
    """The relative standard error of the slope of the straight line fitted through the
    trials' points (s: closed-loop poles, 1/s; L: the loop's value −1/Kc there), from the
    residuals of the fit; inf for fewer than three points (no residual to judge by). On a
    clean loop the trials give the slope to a few per cent; on a noisy fast loop their growth
    rates scatter by as much as a 1 % change of gain moves them, and the error passes 50 %."""
    n = s_pts.size
    ds = s_pts - s_pts.mean()
    spread = float(np.sum(np.abs(ds) ** 2))
    if n < 3 or spread == 0.0:
        return math.inf
    design = np.column_stack((np.ones_like(s_pts), ds))
    coef, *_ = np.linalg.lstsq(design, l_pts.astype(complex), rcond=None)
    resid = l_pts - design @ coef
    se = math.sqrt(float(np.sum(np.abs(resid) ** 2)) / (n - 2) / spread)
    return se / abs(coef[1]) if coef[1] != 0 else math.inf


def agree(
    point: tuple[float, float], other: tuple[float, float], loop: tuple[float, float]
) -> bool:
    """Two corrections of the loop's (K_u, P_u) agree: each of ``point``'s log-ratios to
    ``loop`` lies within the size of ``other``'s from ``other``'s (the same sign and at most
    twice its size)."""
    for a, b, base in zip(point, other, loop, strict=True):
        da, db = math.log(a / base), math.log(b / base)
        if abs(da - db) > abs(db):
            return False
    return True


def contradicts(
    trials: tuple[float, float] | None,
    model: tuple[float, float] | None,
    loop: tuple[float, float],
) -> bool:
    """Both corrections were made and the model's does not bear the trials' out (``agree``)."""
    return trials is not None and model is not None and not agree(trials, model, loop)


# the share of its own size by which a correction may be off: the trials' is a first-order
# step over the crossover's shift, and sees no aliasing (at 20 samples a period it left a
# fifth to two fifths of the effect on first-order lags with dead time: K_u 2.6–3.4 % high);
# a process model's has its class's slopes near ω_u for the plant's (hx1's second-order
# model: 1.6 times the effect on K_u; hx2's first-order: half; a noisy integrating loop at
# 25 samples a period: two thirds)
OWN_SHARE = 0.5


def uncertainty(
    chosen: str,
    trials: tuple[float, float] | None,
    model: tuple[float, float] | None,
    loop: tuple[float, float],
) -> tuple[float, float] | None:
    """The relative uncertainty (K_u, P_u) the hold's correction adds to the plant's point
    it gave (``chosen``: "trials", "model" or "none"), from the two estimates beside the
    sampled loop's point (None: an estimate not made): ``OWN_SHARE`` of the chosen one's own
    size, or the distance between the two where they disagree (``agree``) and it is more
    (one of them is that far off: seen on noisy loops at 20 to 100 samples a period, the
    trials' K_u 7 to 19 % off where the model's was within 3 %, and the other way round).
    None: no correction made, none added."""

    def gap(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
        return float(abs(a[0] / b[0] - 1.0)), float(abs(a[1] / b[1] - 1.0))

    point = trials if chosen == "trials" else model
    if chosen not in ("trials", "model") or point is None:
        return None
    ku, pu = (OWN_SHARE * g for g in gap(point, loop))
    if contradicts(trials, model, loop):
        apart = gap(trials, model)
        ku, pu = max(ku, apart[0]), max(pu, apart[1])
    return ku, pu


# the most K_u and P_u change (relative) per radian of phase at the crossover, for a point
# the hold's lag moved by an amount not measured: half as much again as the steepest slopes
# seen, an integrator with a lag and dead time's (1/(s(5s+1))·e^{−s}: 2.2 and 1.2 per
# radian; a lag chain's at most 1.7 and 0.8)
HOLD_KU_PER_RADIAN = 3.0
HOLD_PU_PER_RADIAN = 1.5
# how far the plant's log-magnitude slope over the crossover's move (d ln|G|/d ln ω) may lie
# from a process model's: a pure delay's is 0, a lag's −1 past its corner, a resonance's
# steeper (ζ 0.17 at 15 samples a period: K_u moved 14 % where P_u moved 4 %)
SLOPE_UNSURE = 1.0


def unmeasured(
    chosen: str, loop: tuple[float, float], corrected: tuple[float, float], sample_time: float
) -> tuple[float, float] | None:
    """The least relative uncertainty (K_u, P_u) of a plant's point whose hold correction the
    trials did not measure. Left uncorrected (``chosen`` "none"): the hold lags φ = πT/P at
    the loop's crossover, and the plant's own point may lie that much phase away at the
    steepest slopes (``HOLD_KU_PER_RADIAN``, ``HOLD_PU_PER_RADIAN``). Corrected through a
    process model ("model"): K_u moved by the model's own slope over the crossover's move
    (the P_u correction), which the plant's may exceed by ``SLOPE_UNSURE`` per unit of ln ω.
    Why: a lightly damped plant (ζ 0.17) at 15 samples a period, noisy, was corrected through
    a first-order model with next to no slope there: K_u 0.14 % from the loop's where P_u
    moved 11 %, the plant's K_u 14 % away, stated ±0.14 %. None for the trials'."""
    loop_pu = loop[1]
    if chosen == "model":
        moved = abs(math.log(corrected[1] / loop_pu)) if corrected[1] > 0 < loop_pu else 0.0
        return (SLOPE_UNSURE * moved, 0.0) if math.isfinite(moved) else None
    if chosen != "none" or not (loop_pu > 0 and sample_time > 0):
        return None
    phi = math.pi * sample_time / loop_pu
    return HOLD_KU_PER_RADIAN * phi, HOLD_PU_PER_RADIAN * phi
