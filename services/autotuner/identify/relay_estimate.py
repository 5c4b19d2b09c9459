"""K_u and P_u from the relay's two stages: where the plant's phase crosses −180°.

Stage 1's cycle gives the describing-function estimate and the exact frequency points
G(jkω₁) (``fourier``); stage 2, re-aimed past −180°, gives G(jω₂) on the other side. A
low-order model fitted to all the points supplies the curvature between the two fundamentals;
its misfit there is interpolated in log ω, so K_u and P_u rest on the measured points. Which
path produced them is said by ``ku_method`` (``KU_METHODS``).
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from services.autotuner.identify.fourier import FrequencyPoint
from services.autotuner.identify.model_fit import ProcessFit, choose, fit_models

Points = tuple[FrequencyPoint, ...]
Corrector = Callable[[ProcessFit], tuple[Points, Points]]

# how K_u and P_u were found (the run's ``experiment.ku_method``)
MODEL_CROSSING = "model crossing"  # the fitted model's −180°, corrected by its misfit at the
# two stages' points: the exact crossing between the stages
LINEAR_CROSSING = "linear crossing"  # phase and log-magnitude linear in log ω between them
FUNDAMENTAL_POINT = "fundamental point"  # stage 1's exact G(jω₁) taken as the crossover
DESCRIBING_FUNCTION = "describing function"  # stage 1's 4d/(π√(a² − ε²)): no exact points
MODEL_ULTIMATE_POINT = "model ultimate point"  # the cycles ran far from −180°: the model's own
NOT_MEASURED = "not measured"  # far from −180° and no model: NaN
KU_METHODS = (
    MODEL_CROSSING,
    LINEAR_CROSSING,
    FUNDAMENTAL_POINT,
    DESCRIBING_FUNCTION,
    MODEL_ULTIMATE_POINT,
    NOT_MEASURED,
)


@dataclass(frozen=True)
class EstimateConfig:
    """The estimator's thresholds."""

    # a measured point this close to −180° makes the crossover "near" (a short interpolation)
    near_deg: float = 25.0
    # the fit weighs the two fundamentals this much more than a harmonic: they carry K_u
    fundamental_weight: float = 10.0
    # passes of the leakage correction (each uses the model the last one improved)
    corrections: int = 2
    # an estimate whose ω lies beyond the measured ω range by more than this factor, or whose
    # K_u beyond the measured 1/|G| range by ``plausible_ku``, comes from a fit gone astray
    plausible_omega: float = 1.3
    plausible_ku: float = 1.5
    # the model crossing is searched this far (in ln ω) beyond the two points
    search_span: float = 0.5


@dataclass(frozen=True)
class StageOne:
    """What stage 1's agreeing cycles measured."""

    ku: float  # describing function
    pu: float
    ku_spread: float
    pu_spread: float
    amplitude: float
    points: Points
    g_scatter: float  # relative cycle-to-cycle scatter of G(jω₁)
    cycles: int
    t_end: float
    window: tuple[float, float, int]  # start, period, periods of the points


@dataclass(frozen=True)
class Refined:
    """K_u and P_u from both stages' exact points."""

    ku: float
    pu: float
    ku_uncertainty: float
    pu_uncertainty: float
    points: Points
    ku_method: str
    model: ProcessFit | None = None
    candidates: tuple[ProcessFit, ...] = ()  # every model fitted to the points


@dataclass(frozen=True)
class Estimate:
    """The relay's final K_u, P_u and how they were found."""

    ku: float
    pu: float
    crossing: str  # "bracketed", "near" or "not reached"
    ku_method: str
    phase_reached_deg: float  # the measured phase closest to −180°


def g_scatter(values: list[complex]) -> float:
    """The largest relative deviation of the per-cycle G(jω) from their mean."""
    if len(values) < 2:
        return 0.0
    g = np.asarray(values)
    return float(np.max(np.abs(g / np.mean(g) - 1.0)))


def spread(values: list[float]) -> float:
    """(max − min)/mean; inf for a zero mean."""
    m = float(np.mean(values))
    return float((max(values) - min(values)) / abs(m)) if m else math.inf


def _fits(
    points: list[FrequencyPoint], p1: FrequencyPoint, p2: FrequencyPoint, cfg: EstimateConfig
) -> list[ProcessFit]:
    weights = [
        cfg.fundamental_weight if p in (p1, p2) else 1.0 / max(1.0, p.omega / p1.omega - 2.0)
        for p in points
    ]
    try:
        return fit_models([p.omega for p in points], [p.g for p in points], weights)
    except ValueError:  # fewer than two points
        return []


def refine(
    s1: StageOne,
    second: Points,
    correct: Corrector | None = None,
    cfg: EstimateConfig = EstimateConfig(),
) -> Refined:
    """K_u and P_u where the phase crosses −180°, from the two stages' exact points.

    A low-order model is fitted to all the points (``model_fit``); its small misfit at the two
    fundamentals is interpolated linearly in log ω between them, so the model only supplies the
    curvature between two exact points a few degrees apart. Without a model, phase and
    log-magnitude are interpolated linearly. The uncertainty is the scatter of the measured
    point (cycle to cycle, over √cycles) plus the difference between the two interpolations
    of the same leakage-corrected points.
    """
    p1, p2 = s1.points[0], (second[0] if second else s1.points[0])
    fits = _fits([*s1.points, *second], p1, p2, cfg)
    model = choose(fits)
    for _ in range(cfg.corrections if correct is not None else 0):
        if model is None:
            break
        first, later = correct(model)  # the transients' leakage taken out, using the model
        if not first or (second and not later):
            break
        p1, p2 = first[0], (later[0] if second else first[0])
        fits = _fits([*first, *later], p1, p2, cfg) or fits
        model = choose(fits) or model
    point = (1.0 / p1.magnitude, 2.0 * math.pi / p1.omega)
    linear, linear_method = (
        (linear_crossing(p1, p2), LINEAR_CROSSING) if second else (point, FUNDAMENTAL_POINT)
    )
    crossing = None
    near = beyond_both(p1, p2) if second else None
    if model is not None:
        # two points far closer together than to −180° (one cycle measured twice): the
        # misfit's slope between them is mostly the two measurements' difference, and
        # carried to −180° it threw the crossing out, implausibly (an FOPDT at 37 samples a
        # period: P_u +3.6 %) or not (a lead-lag with dead time, both points at −190°, 0.03°
        # apart: K_u −30 %); the straight line through them would carry that same
        # difference. The nearer point's misfit held, the model gives the way there (the
        # FOPDT: P_u +0.1 %; the lead-lag: K_u −1.8 %, P_u +1.4 %)
        close = near is not None and abs(p2.phase_deg - p1.phase_deg) < CLOSE * abs(
            near.phase_deg + 180.0
        )
        # else the slope, and the nearer point held where that crossing is implausible
        tries = (
            [(near, near)] if close else [(p1, p2)] + ([(near, near)] if near is not None else [])
        )
        for a, b in tries:
            crossing = model_crossing(model, a, b, cfg)
            if crossing is not None and plausible(crossing, p1, p2, cfg):
                break
            crossing = None
    if not plausible(linear, p1, p2, cfg):
        linear, linear_method = point, FUNDAMENTAL_POINT
    ku, pu = crossing or linear
    scatter = s1.g_scatter / math.sqrt(max(1, s1.window[2]))  # of the mean over the cycles
    ku_far, pu_far = extrapolated(ku, pu, p1, p2) if second else (0.0, 0.0)
    ku_leak, pu_leak = leak_spread(p1, p2 if second else None)
    return Refined(
        ku=ku,
        pu=pu,
        ku_uncertainty=scatter + max(abs(ku / linear[0] - 1.0), ku_far) + ku_leak,
        pu_uncertainty=0.5 * scatter * abs(math.log(p2.omega / p1.omega)) / math.pi
        + max(abs(pu / linear[1] - 1.0), pu_far)
        + pu_leak,
        points=second,
        ku_method=MODEL_CROSSING if crossing else linear_method,
        model=model,
        candidates=tuple(fits),
    )


def leak_spread(p1: FrequencyPoint, p2: FrequencyPoint | None) -> tuple[float, float]:
    """How far (relative) K_u and P_u may move with the leakage each point's correction left
    (``FrequencyPoint.leak``, a relative error of G in any direction): through the two
    points' linear crossing (the worst of eight directions; the two points' shares added in
    quadrature), where carrying the points to −180° sets the sensitivity; where −180° lies
    beyond both further than they lie apart (``beyond_both``), the nearer point's error at
    the steepest slopes a lag chain has there. With stage 1's point alone, its own. Why: a
    correction through a model that is not the plant's leaves the model's own leakage (a
    triple lag sampled 20 times a period: K_u +2.3 % with a spread of 0.16 % before this
    term). (0, 0) for points measured as they are."""
    if p2 is None:
        return p1.leak, 0.0
    near = beyond_both(p1, p2)
    if near is not None:
        return near.leak * (1.0 + KU_PER_RADIAN), near.leak * PU_PER_RADIAN
    errors = (p1.leak, p2.leak)
    base = linear_crossing(p1, p2)
    if not all(math.isfinite(v) and v > 0 for v in base):
        return 0.0, 0.0
    ku_sq = pu_sq = 0.0
    for which, (p, error) in enumerate(zip((p1, p2), errors, strict=True)):
        if not error > 0:
            continue
        error = min(error, 0.5)  # beyond that the point says nothing (the checks on it say so)
        ku_most = pu_most = 0.0
        for k in range(8):
            moved = FrequencyPoint(p.omega, p.g * (1.0 + cmath.rect(error, k * math.pi / 4)))
            ku, pu = linear_crossing(moved, p2) if which == 0 else linear_crossing(p1, moved)
            ku_most = max(ku_most, abs(ku / base[0] - 1.0))
            pu_most = max(pu_most, abs(pu / base[1] - 1.0))
        ku_sq += ku_most**2
        pu_sq += pu_most**2
    return math.sqrt(ku_sq), math.sqrt(pu_sq)


def beyond_both(p1: FrequencyPoint, p2: FrequencyPoint) -> FrequencyPoint | None:
    """The nearer point to −180° where −180° lies beyond both further than they lie apart
    (their slope then says nothing of the way there); None otherwise."""
    d1, d2 = p1.phase_deg + 180.0, p2.phase_deg + 180.0
    if d1 * d2 <= 0 or min(abs(d1), abs(d2)) <= abs(d2 - d1):
        return None
    return p1 if abs(d1) <= abs(d2) else p2


def extrapolated(
    ku: float, pu: float, p1: FrequencyPoint, p2: FrequencyPoint
) -> tuple[float, float]:
    """How far (relative) K_u and P_u lie from the nearer point's 1/|G| and 2π/ω when −180°
    lies further beyond both points than they lie apart: the slope through two points that
    close (one cycle measured twice, when stage 2 switched on stage 1's very samples) is
    their difference, not the plant's, and both interpolations extrapolate it alike; the
    estimate is then no surer than the whole way it was carried. (0, 0) otherwise."""
    near = beyond_both(p1, p2)
    if near is None:
        return 0.0, 0.0
    # the estimate is as far from the plant's point as it is from the nearer measured one
    # plus what the way from there to −180° may cost, at the steepest a lag chain gives
    # there (an estimate that stayed at the point, the slope saying nothing: 1/(s+1)³ at
    # −172.5° gave K_u −19 %, P_u +10 %, with spreads of 0.35 % before; one carried the wrong
    # way, K_u −37 % with a spread of 25 %)
    way = math.radians(abs(near.phase_deg + 180.0))
    return (
        abs(ku * near.magnitude - 1.0) + KU_PER_RADIAN * way,
        abs(pu * near.omega / (2.0 * math.pi) - 1.0) + PU_PER_RADIAN * way,
    )


# two points on one side of −180° whose phases differ by under this share of the nearer one's
# way to it are one cycle measured twice, for the model's crossing (``refine``): their slope
# is set aside (points 20° apart, 23° short, keep theirs: a lead-lag, K_u +0.2 % with it, +1.2
# % without)
CLOSE = 0.25

# degrees: a point at the lower frequency that lags the other by more than this contradicts a
# phase that falls with frequency (``order_contradiction``)
ORDER_DEG = 10.0


def order_contradiction(p1: FrequencyPoint, p2: FrequencyPoint) -> float | None:
    """Degrees by which the lower-frequency point of the two lags the higher one, where that
    is over ``ORDER_DEG``: no plant whose phase falls with frequency gives it, so one of the
    points is not the plant's (noise, σ 1 on e^{−4s}/(20s + 1): stage 2 at 0.2775 rad/s read
    −222° where the plant has −143°, beside stage 1's −158° at 0.333 rad/s, and the
    "bracketed" P_u was 35 % off against a stated ±5.3 %); None otherwise."""
    lo, hi = sorted((p1, p2), key=lambda p: p.omega)
    if lo.omega == hi.omega:
        return None
    lag = hi.phase_deg - lo.phase_deg  # > 0: the lower frequency lags more
    return lag if lag > ORDER_DEG else None


def stage_one_spreads(ku: float, pu: float, p1: FrequencyPoint) -> tuple[float, float]:
    """How far (relative) K_u and P_u may lie from what stage 1's point alone says, where
    stage 2's point cannot be trusted: the estimate's distance from the point's 1/|G| and
    2π/ω plus what the way from its phase to −180° may cost (``KU_PER_RADIAN``,
    ``PU_PER_RADIAN``)."""
    way = math.radians(abs(p1.phase_deg + 180.0))
    return (
        abs(ku * p1.magnitude - 1.0) + KU_PER_RADIAN * way,
        abs(pu * p1.omega / (2.0 * math.pi) - 1.0) + PU_PER_RADIAN * way,
    )


# the most K_u and P_u change (relative) per radian of phase near −180° on the plants a
# relay meets: d ln|G|/dφ = ω_u and d ln P/dφ = (1 + ω_u²)/(n·ω_u) for 1/(s+1)^n, at most
# √3 = 1.73 and 0.77 there (n = 3), less for longer chains and for dead time
KU_PER_RADIAN = 2.0
PU_PER_RADIAN = 1.0


def estimate(
    s1: StageOne,
    refined: Refined | None,
    model: ProcessFit | None,
    cfg: EstimateConfig = EstimateConfig(),
) -> Estimate:
    """The final K_u and P_u: the refined crossing where the stages' points bracket −180° or
    one lies within ``near_deg`` of it; otherwise the process model's own ultimate point."""
    if refined is not None:
        ku, pu, method = refined.ku, refined.pu, refined.ku_method
    else:
        ku, pu, method = s1.ku, s1.pu, DESCRIBING_FUNCTION
    phases = [p.phase_deg for p in (*s1.points[:1], *(refined.points[:1] if refined else ()))]
    closest = min(phases, key=lambda ph: abs(ph + 180.0), default=math.nan)
    # stage 1's point taken as the crossover is one only as near to −180° as it lies itself
    used = phases[:1] if method == FUNDAMENTAL_POINT else phases
    nearest = min(used, key=lambda ph: abs(ph + 180.0), default=math.nan)
    if len(used) == 2 and (used[0] + 180.0) * (used[1] + 180.0) <= 0:
        crossing = "bracketed"
    elif abs(nearest + 180.0) <= cfg.near_deg and math.isfinite(ku):
        crossing = "near"
    else:
        crossing = "not reached"
        up = model.ultimate_point() if model is not None else None
        ku, pu = (float(up[0]), float(up[1])) if up else (math.nan, math.nan)
        method = MODEL_ULTIMATE_POINT if up else NOT_MEASURED
    return Estimate(ku, pu, crossing, method, float(closest))


def plausible(
    estimate: tuple[float, float],
    p1: FrequencyPoint,
    p2: FrequencyPoint,
    cfg: EstimateConfig = EstimateConfig(),
) -> bool:
    """The crossover lies near the two measured points (the cycles ran within tens of degrees
    of −180°); an estimate far outside comes from a fit gone astray, not from the plant."""
    ku, pu = estimate
    if not (math.isfinite(ku) and math.isfinite(pu) and ku > 0 and pu > 0):
        return False
    w = 2.0 * math.pi / pu
    lo, hi = min(p1.omega, p2.omega), max(p1.omega, p2.omega)
    kus = (1.0 / p1.magnitude, 1.0 / p2.magnitude)
    f, k = cfg.plausible_omega, cfg.plausible_ku
    return lo / f <= w <= hi * f and min(kus) / k <= ku <= max(kus) * k


_EXP_MAX = 700.0  # math.exp overflows past about 709.78


def linear_crossing(p1: FrequencyPoint, p2: FrequencyPoint) -> tuple[float, float]:
    """Phase and log-magnitude linear in log ω through the two points, at −180°."""
    x1, x2 = math.log(p1.omega), math.log(p2.omega)
    f1, f2 = p1.phase_deg, p2.phase_deg
    m1, m2 = math.log(p1.magnitude), math.log(p2.magnitude)
    frac = (-180.0 - f1) / (f2 - f1) if abs(f2 - f1) > 1e-9 else 0.0
    xu, mu = x1 + frac * (x2 - x1), m1 + frac * (m2 - m1)
    # two phases a hair apart carry the line anywhere: past a float's range it is out of
    # any plausible bound (``plausible``), not an overflow (a relay whose stage 2 measured
    # its stage-1 cycle again raised "math range error" and the run failed)
    return math.exp(min(-mu, _EXP_MAX)), 2.0 * math.pi / math.exp(min(max(xu, -_EXP_MAX), _EXP_MAX))


def model_crossing(
    model: ProcessFit,
    p1: FrequencyPoint,
    p2: FrequencyPoint,
    cfg: EstimateConfig = EstimateConfig(),
) -> tuple[float, float] | None:
    """The model's crossover, corrected by its misfit at the two points (linear in log ω)."""
    x1, x2 = math.log(p1.omega), math.log(p2.omega)
    span = x2 - x1 if abs(x2 - x1) > 1e-9 else math.inf  # one point: a constant misfit

    def misfit(p: FrequencyPoint) -> complex:
        r = complex(np.log(p.g / model.response(p.omega)))
        return complex(r.real, math.remainder(r.imag, 2.0 * math.pi))

    r1, r2 = misfit(p1), misfit(p2)

    def r_at(x: float) -> complex:
        return r1 + (x - x1) / span * (r2 - r1)

    def excess(x: float) -> float:
        return model.phase(math.exp(x)) + r_at(x).imag + math.pi

    lo, hi = min(x1, x2) - cfg.search_span, max(x1, x2) + cfg.search_span
    if not excess(lo) > 0 > excess(hi):
        return None
    xu = brentq(excess, lo, hi, xtol=1e-12)
    gain = float(abs(model.response(math.exp(xu)))) * math.exp(r_at(xu).real)
    return 1.0 / gain, 2.0 * math.pi / math.exp(xu)
