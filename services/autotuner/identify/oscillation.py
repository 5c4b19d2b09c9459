"""Growth rate and period of an oscillation in a record of samples.

``fit_oscillation`` fits y(t) = c + A·e^{g·t}·sin(ω·t + φ) by least squares, started from the
extrema of the (lightly smoothed) record. The growth rate g (1/s) is negative for a decaying
oscillation, positive for a growing one; the period is 2π/ω. Fitting the whole record rather
than reading peaks keeps both estimates robust to measurement noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares, leastsq

from services.autotuner.parts import Parts, in_turn
from shared.control.signals import extrema, smooth


@dataclass(frozen=True)
class Oscillation:
    growth: float  # g, 1/s
    period: float  # s
    amplitude: float  # A at the start of the window
    offset: float  # c
    rms: float  # residual of the fit
    swings: int  # half-cycles in the window
    # g of the sinusoid alone, where a slow mode fitted beside it replaced it (None: not)
    growth_alone: float | None = None


def fit_oscillation(
    t: np.ndarray,
    y: np.ndarray,
    noise_std: float,
    period_hint: float | None = None,
    parts: Parts = in_turn,
) -> Oscillation | None:
    """Fit a growing/decaying sinusoid to (t, y); None if there is no clear oscillation.
    ``parts``: how the slow mode's fits are computed (``_with_slow_mode``)."""
    start = _start(t, y, noise_std, period_hint)
    if start is None:
        return None
    tt, y, x0, turns = start
    sine = DecayingSine(tt, y)
    span = float(tt[-1])

    def jac(p: np.ndarray) -> np.ndarray:
        # asked where the fit has moved to (a step accepted): a spike at the record's end
        # there is no oscillation of the record, and the fit is given up (``_spike``)
        if _spike(p, span):
            raise _SpikeFit
        return sine.jac(p)

    # a trial step of e^{g·t} may overflow (a fit wandering on a record of noise): judged by
    # the result, not printed on the service's console
    with np.errstate(over="ignore", invalid="ignore"):
        try:
            x, fun, success = levenberg_marquardt(sine.resid, jac, x0, 2000)
        except _SpikeFit:
            return None
        c, a, g, w, _ = x
        if not success or w <= 0 or not np.all(np.isfinite(x)):
            return None
        slow = _with_slow_mode(tt, y, x, float(np.sqrt(np.mean(fun**2))), parts)
    alone = None
    if slow is not None:
        alone = float(g)
        c, a, g, w = slow.x[:4]
        fun = slow.fun
    return Oscillation(
        growth=float(g),
        period=float(2 * math.pi / w),
        amplitude=float(abs(a)),
        offset=float(c),
        rms=float(np.sqrt(np.mean(fun**2))),
        swings=turns - 1,
        growth_alone=alone,
    )


# a fit whose sinusoid has less than one period in its record and grows e^SPIKE_GROWTH
# (5×10⁸) times over it describes the record's last samples, not an oscillation of it
SPIKE_GROWTH = 20.0


class _SpikeFit(Exception):
    """The fit has become a spike at the record's end (``_spike``)."""


def _spike(p: np.ndarray, span: float) -> bool:
    """Whether the sinusoid p = (c, A, g, ω, φ) over a record ``span`` s long is a spike at its
    end: under one period in it, its envelope grown e^SPIKE_GROWTH times across it. Why: a
    fit that gets there crawls on for its 2,000 evaluations and fails (the heat exchanger's
    first ramp trial: A at 10⁻¹¹, growth e^26 over the record, 0.12 s of a 0.6 s phase), and
    its period is past anything a caller takes; of 4,954 fits in 400 random loops' ramp
    tunes, the 24 that got there all crawled on to the limit and failed."""
    g, w = float(p[2]), float(p[3])
    return g * span > SPIKE_GROWTH and abs(w) * span < 2 * math.pi


def stands_out(
    osc: Oscillation, watched: float, level: float, periods: float = 1.5, swing: float = 0.5
) -> bool:
    """Whether the fitted oscillation was seen in its window (``watched`` s from the fit's
    start): the window holds ``periods`` of its periods, and its envelope A·e^{g·t} stands at
    least ``level`` (PV units) over ``swing`` of a period where it is largest (the window's
    start for a decaying one, its end for a growing one): one swing seen out of the noise.

    Why: a fit counts the record's turning points, the noise's among them, and can put a
    sinusoid on a spike of the noise that is gone within a fraction of a period (a ramp
    trial sampled 1,700 times a period read "growth −3.79/s, period 2.11 s" from its noise,
    7σ at its start and under 2σ a sixth of a period on, and its next trials were cut to
    that period); what never swung out of the noise gives neither a period nor a growth rate
    worth acting on. A loop's own oscillation at a low gain decays fast but swings first (a
    dead-time loop's, 0.34 a period from 10σ, is 1.9σ 1.5 periods on: it counts)."""
    if not (0.0 < periods * osc.period <= watched) or not math.isfinite(osc.growth):
        return False
    # the envelope's least over the swing where it is largest
    at = swing * osc.period if osc.growth < 0 else watched - swing * osc.period
    return osc.amplitude * math.exp(min(osc.growth * at, 50.0)) >= level


def fit_ringing(
    t: np.ndarray,
    y: np.ndarray,
    noise_std: float,
    period_hint: float | None = None,
    parts: Parts = in_turn,
) -> Oscillation | None:
    """``fit_oscillation`` with the slow real mode beside the sinusoid from the start: a
    closed loop's step response is its approach to the setpoint (or its recovery from a load)
    and its ringing together, and the sinusoid fitted alone first took a slow approach with
    a small ringing on it for a sinusoid of a period of days. None: no clear oscillation.
    ``parts``: how the slow mode's starts are computed (``_with_slow_mode``)."""
    start = _start(t, y, noise_std, period_hint)
    if start is None:
        return None
    tt, y, x0, turns = start
    sol = _with_slow_mode(tt, y, np.asarray(x0), math.inf, parts)
    if sol is None:
        return None
    c, a, g, w = (float(v) for v in sol.x[:4])
    return Oscillation(
        growth=g,
        period=2 * math.pi / w,
        amplitude=abs(a),
        offset=c,
        rms=float(np.sqrt(np.mean(sol.fun**2))),
        swings=turns - 1,
    )


def _start(
    t: np.ndarray, y: np.ndarray, noise_std: float, period_hint: float | None
) -> tuple[np.ndarray, np.ndarray, list[float], int] | None:
    """Where a fit starts: (s from the record's start, the record's values, the sinusoid's
    (c, A, g, ω, φ) read off its turning points, how many turning points); None for fewer
    than three."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    ext = _turning_points(t, y, noise_std, period_hint)
    if len(ext) < 3:
        return None
    te = np.array([e[0] for e in ext])
    ye = np.array([e[1] for e in ext])
    swings = np.abs(np.diff(ye))
    half = float(np.mean(np.diff(te)))
    w0 = math.pi / half
    mid = 0.5 * (te[:-1] + te[1:])
    g0 = float(np.polyfit(mid - t[0], np.log(swings), 1)[0]) if swings.size >= 2 else 0.0
    c0 = float(np.mean(ye[-2:]))
    a0 = float(swings[0]) / 2.0 / math.exp(g0 * (mid[0] - t[0]))
    # phase: the first extremum is a maximum or a minimum at te[0]
    sign = 1.0 if ye[0] > ye[1] else -1.0
    phi0 = (math.pi / 2 if sign > 0 else -math.pi / 2) - w0 * (te[0] - t[0])
    return t - t[0], y, [c0, a0, g0, w0, phi0], len(ext)


def levenberg_marquardt(
    resid: Callable[[np.ndarray], np.ndarray],
    jac: Callable[[np.ndarray], np.ndarray],
    x0: list[float],
    max_nfev: int,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """(x, residuals at x, converged) of MINPACK's ``lmder`` from ``x0``, with the settings
    of ``least_squares(method='lm')`` (ftol = xtol = gtol = 1e-8, step bound factor 100, the
    scaling from the Jacobian): the same iterations to the bit, through ``leastsq``, which
    calls ``lmder`` without ``least_squares``' wrappers around every evaluation (a third of
    a fit's time). Needs at least as many residuals as parameters."""
    x, _, info, _, ier = leastsq(
        resid,
        np.asarray(x0, dtype=float),
        Dfun=jac,
        full_output=True,
        ftol=1e-8,
        xtol=1e-8,
        gtol=1e-8,
        maxfev=max_nfev,
    )
    return np.asarray(x, dtype=float), info["fvec"], ier in (1, 2, 3, 4)


# scipy's forward-difference step relative to max(1, |x|): √ε (``_numdiff._eps_for_method``)
_FD_STEP = float(np.finfo(np.float64).eps ** 0.5)


class _Residuals:
    """A model's residuals over a record (``tt``: s from its start, ``y``), their factors kept
    for the next call at the same parameters: MINPACK asks for the Jacobian where it has just
    evaluated the residuals. ``_evaluate`` returns the factors, the residual last."""

    def __init__(self, tt: np.ndarray, y: np.ndarray):
        self.tt = tt
        self.y = y
        self._at: bytes | None = None  # the parameters of the factors below
        self._parts: tuple[np.ndarray, ...] = ()

    def _evaluate(self, p: np.ndarray) -> tuple[np.ndarray, ...]:
        raise NotImplementedError

    def _factors(self, p: np.ndarray) -> tuple[np.ndarray, ...]:
        key = p.tobytes()
        if key != self._at:
            self._parts, self._at = self._evaluate(p), key
        return self._parts

    def resid(self, p: np.ndarray) -> np.ndarray:
        return self._factors(np.asarray(p, dtype=float))[-1].copy()


class DecayingSine(_Residuals):
    """Residuals of c + A·e^{g·t}·sin(ω·t + φ) − y over a record, p = (c, A, g, ω, φ), and
    their Jacobian by forward differences: the very numbers scipy's ``'2-point'`` scheme
    gives (its steps, each element by the same operations in the same order), so a fit is
    unchanged to the bit. Why not scipy's: a perturbed parameter changes one factor of the
    model, so the five perturbed residuals cost one exponential and two sines (not five of
    each) and none of the finite-difference machinery — the sinusoid fits were most of a
    ramp trial's wall time."""

    def _evaluate(self, p: np.ndarray) -> tuple[np.ndarray, ...]:
        """e^{g·t}, sin(ω·t + φ), A·e^{g·t}, A·e^{g·t}·sin(ω·t + φ), the residual."""
        c, a, g, w, phi = p
        e = np.exp(g * self.tt)
        s = np.sin(w * self.tt + phi)
        ae = a * e
        aes = ae * s
        return e, s, ae, aes, c + aes - self.y

    def jac(self, p: np.ndarray) -> np.ndarray:
        """∂resid/∂p, (samples × 5), as ``approx_derivative(resid, p, '2-point')``: the
        residual's own expression, c + A·e·s − y, evaluated left to right with one parameter
        stepped, its other factors reused."""
        x = np.asarray(p, dtype=float)
        e, s, ae, aes, f0 = self._factors(x)
        tt, y = self.tt, self.y
        xh = forward_steps(x)
        c, a, _, w, phi = x
        stepped = (
            xh[0] + aes - y,
            c + xh[1] * e * s - y,
            c + a * np.exp(xh[2] * tt) * s - y,
            c + ae * np.sin(xh[3] * tt + phi) - y,
            c + ae * np.sin(w * tt + xh[4]) - y,
        )
        return _quotients(stepped, f0, xh, x)


class DriftingSine(_Residuals):
    """``DecayingSine`` with a slow real mode beside it: c + b·e^{−λ·t} + A·e^{g·t}·sin(ω·t + φ)
    − y, p = (c, A, g, ω, φ, b, λ), for a fit within bounds (``lb``, ``ub``): its forward
    differences are scipy's ``'2-point'`` ones with the steps scipy takes at those bounds."""

    def __init__(self, tt: np.ndarray, y: np.ndarray, lb: np.ndarray, ub: np.ndarray):
        super().__init__(tt, y)
        self.lb = np.asarray(lb, dtype=float)
        self.ub = np.asarray(ub, dtype=float)

    def _evaluate(self, p: np.ndarray) -> tuple[np.ndarray, ...]:
        """e^{−λ·t}, c + b·e^{−λ·t}, e^{g·t}, sin(ω·t + φ), A·e^{g·t}, A·e^{g·t}·sin(ω·t + φ),
        the residual."""
        c, a, g, w, phi, b, lam = p
        drift = np.exp(-lam * self.tt)
        base = c + b * drift
        e = np.exp(g * self.tt)
        s = np.sin(w * self.tt + phi)
        ae = a * e
        aes = ae * s
        return drift, base, e, s, ae, aes, base + aes - self.y

    def jac(self, p: np.ndarray) -> np.ndarray:
        """∂resid/∂p, (samples × 7), as ``approx_derivative(resid, p, '2-point', bounds=…)``."""
        x = np.asarray(p, dtype=float)
        drift, base, e, s, ae, aes, f0 = self._factors(x)
        tt, y = self.tt, self.y
        xh = forward_steps(x, self.lb, self.ub)
        c, a, _, w, phi, b, _ = x
        stepped = (
            xh[0] + b * drift + aes - y,
            base + xh[1] * e * s - y,
            base + a * np.exp(xh[2] * tt) * s - y,
            base + ae * np.sin(xh[3] * tt + phi) - y,
            base + ae * np.sin(w * tt + xh[4]) - y,
            c + xh[5] * drift + aes - y,
            c + b * np.exp(-xh[6] * tt) + aes - y,
        )
        return _quotients(stepped, f0, xh, x)


def forward_steps(
    x: np.ndarray, lb: np.ndarray | None = None, ub: np.ndarray | None = None
) -> list[float]:
    """Each parameter stepped alone, as scipy's ``'2-point'`` scheme steps it: by √ε·max(1,
    |x|) with x's sign, turned back where the step would cross a bound and cut to the
    bound where neither direction fits (``_numdiff._adjust_scheme_to_bounds``, 1-sided)."""
    if lb is None or ub is None or np.all((lb == -np.inf) & (ub == np.inf)):
        # the same operations on plain floats, element by element (a fit asks once an
        # iteration; numpy's fixed cost on five elements was a tenth of it)
        return [
            xi + (_FD_STEP * (1.0 if xi >= 0 else -1.0)) * (abs(xi) if abs(xi) > 1.0 else 1.0)
            for xi in x.tolist()
        ]
    sign = (x >= 0).astype(float) * 2 - 1
    h = _FD_STEP * sign * np.maximum(1.0, np.abs(x))
    h_adjusted = h.copy()
    lower_dist, upper_dist = x - lb, ub - x
    stepped = x + h
    violated = (stepped < lb) | (stepped > ub)
    fitting = np.abs(h) <= np.maximum(lower_dist, upper_dist)
    h_adjusted[violated & fitting] *= -1
    forward = (upper_dist >= lower_dist) & ~fitting
    h_adjusted[forward] = upper_dist[forward]  # num_steps 1
    backward = (upper_dist < lower_dist) & ~fitting
    h_adjusted[backward] = -lower_dist[backward]
    h = h_adjusted
    return [x[i] + h[i] for i in range(x.size)]


def _quotients(
    stepped: tuple[np.ndarray, ...], f0: np.ndarray, xh: list[float], x: np.ndarray
) -> np.ndarray:
    """The Jacobian (samples × parameters) from the residuals with each parameter stepped:
    (f(x + hᵢ) − f(x)) / ((xᵢ + hᵢ) − xᵢ), laid out as scipy returns it."""
    jt = np.empty((len(stepped), f0.size))
    for i, fi in enumerate(stepped):
        jt[i] = (fi - f0) / (xh[i] - x[i])
    return jt.T


def swings(t: np.ndarray, y: np.ndarray, noise_std: float, period_hint: float | None = None) -> int:
    """The half-cycles ``fit_oscillation`` would count in (t, y) (its ``swings`` when it finds
    an oscillation; 0 when it finds none for want of turning points), without the fit: a
    caller that needs so many swings asks this first, and fits only once they are there."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    return max(0, len(_turning_points(t, y, noise_std, period_hint)) - 1)


def _turning_points(
    t: np.ndarray, y: np.ndarray, noise_std: float, period_hint: float | None
) -> list[tuple[float, float]]:
    """The extrema the fit starts from: those of the record smoothed over a twelfth of the
    hinted period, swinging by 4σ of the (smoothed) noise and 2 % of the span; none for
    fewer than 16 samples."""
    if t.size < 16:
        return []
    dt = float(np.median(np.diff(t)))
    width = 1 if noise_std <= 0 else max(1, int((period_hint or 0.0) / dt / 12))
    ys = smooth(y, width)
    span = float(ys.max() - ys.min())
    return extrema(t, ys, max(4.0 * noise_std / math.sqrt(width), 0.02 * span, 1e-12))


class SlowFit(NamedTuple):
    """One start of the slow-mode fit as it ended: its parameters (c, A, g, ω, φ, b, λ), its
    residuals, and its cost (half their sum of squares, as ``least_squares`` gives it)."""

    x: np.ndarray
    fun: np.ndarray
    cost: float


# where the slow mode's λ starts, in turn, per second of the record: each start's fit is
# independent of the other's (computed side by side where ``parts`` allows), the best kept
SLOW_STARTS = (1.0, 4.0)


def _with_slow_mode(
    tt: np.ndarray, y: np.ndarray, p0: np.ndarray, rms0: float, parts: Parts = in_turn
) -> SlowFit | None:
    """Refit with a decaying exponential beside the oscillation, c + b·e^{−λt} + A·e^{gt}·
    sin(ωt + φ): a loop with lags far apart (or a large dead time) has a slow real mode whose
    drift the sinusoid alone would read as damping. Kept only if it clearly fits better.
    ``parts``: how the starts' fits are computed (the tuner's workers: side by side; the
    result is the same to the bit, the best taken in the starts' order)."""
    span = float(tt[-1] - tt[0]) or 1.0
    p = tuple(float(v) for v in p0)
    best = None
    for sol in parts([(_slow_start, (tt, y, p, k / span)) for k in SLOW_STARTS]):
        if sol is not None and (best is None or sol.cost < best.cost):
            best = sol
    if best is None:
        return None
    rms = float(np.sqrt(np.mean(best.fun**2)))
    return best if rms < 0.8 * rms0 else None


def _slow_start(
    tt: np.ndarray, y: np.ndarray, p0: tuple[float, ...], lam0: float
) -> SlowFit | None:
    """The slow-mode fit from the sinusoid ``p0`` = (c, A, g, ω, φ) and λ = ``lam0`` (1/s);
    None where it fails or ends off the finite numbers."""
    c, a, g, w, phi = p0
    span = float(tt[-1] - tt[0]) or 1.0
    b0 = float(y[0] - c - a * math.sin(phi))
    x0 = [c, a, g, w, phi, b0, lam0]
    lo = [-np.inf, -np.inf, -np.inf, 0.5 * w, -np.inf, -np.inf, 0.1 / span]
    hi = [np.inf, np.inf, np.inf, 2.0 * w, np.inf, np.inf, 0.5 * w]
    model = DriftingSine(tt, y, np.array(lo), np.array(hi))
    # (as in ``fit_oscillation``: a trial step of e^{g·t} may overflow, judged by the result)
    with np.errstate(over="ignore", invalid="ignore"):
        try:
            sol = least_squares(model.resid, x0, jac=model.jac, bounds=(lo, hi), max_nfev=400)
        except (ValueError, FloatingPointError):
            return None
    if not np.all(np.isfinite(sol.x)):
        return None
    return SlowFit(sol.x, sol.fun, sol.cost)
