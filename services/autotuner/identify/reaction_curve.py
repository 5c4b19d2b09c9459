"""Process reaction curve: figures of an open-loop step response (seeds 000, 001, 002).

From a step of size Δu in the output at t_s, with the PV at rest at y₀ before and y_∞ after:

* process gain K = (y_∞ − y₀)/Δu;
* the tangent at the inflection point (steepest slope S): its intersection with y₀ gives the
  apparent dead time L (Ziegler–Nichols' lag), its slope per unit step is the reaction rate
  R = S/Δu, and it reaches y_∞ a time T = K/R after L (the tangent time constant);
* the 63 % point: T₆₃ = t₆₃ − t_s − L (Smuts' time constant, seed 001);
* a = R·L and L/T, which the seeds use to judge whether the ZN rules fit (0.15 ≤ L/T ≤ 0.6).

Two ways to the tangent, both reported by ``method``:

* ``data``: on noise-free samples, the steepest secant between neighbours; with noise, the
  slope of a straight line fitted over a window that widens with the noise (Savitzky–Golay),
  its peak refined by a parabola;
* ``model``: with noise, a least-squares fit of K·e^{−θs}/((τ₁s+1)(τ₂s+1)) to the whole response
  (the heat exchanger of seed 002 has this form; FOPDT is τ₂ = 0), with the tangent taken on
  the fitted curve. It is used when the fit explains the data down to the noise
  (residual RMS ≤ 1.25 σ); otherwise the data method is kept.

The dead time is floored at half a sample time (``dead_time_floor``): a digital controller's
zero-order hold adds T/2 of effective delay to any loop it closes, and a tangent figure below
it is not resolved by the data. Seen on the gravity-drain tank (τ ≈ 640 s, 1 s delay, 1 s
samples, σ = 0.002 m): a near-first-order response has its steepest point at its start, so the
tangent meets the baseline at the fitted θ itself; the square-root law makes the early
response faster than one τ fitted to the whole record, which a first-order curve can only match
by starting ≈ 2.5 s early, and θ (bounded at 0) landed on 0: L = 1e-11 s, Kc ≈ 1e15. The
figure as measured stays in ``dead_time_tangent``.

A PV at (or within noise of) an end of the transmitter's range is never taken for rest: the
clipped measurement is flat and noise-free whatever the process does (``range_end``). An
integrating process never comes to rest; ``steady_ramp`` recognises its steady ramp.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from shared.control.rest_window import RESOLUTION
from shared.control.signals import first_crossing, range_end

# scipy.optimize is imported where it is used, not here: it is a third of a second of the
# start of every `autotune` command that loads this module, and most never fit anything


@dataclass(frozen=True)
class ReactionCurve:
    """Figures of one step test. Times in s (from the step), PV in its own units."""

    step_size: float  # Δu, % of output
    pv_before: float  # y₀
    pv_after: float  # y_∞
    gain: float  # K, PV units per %
    dead_time: float  # L, s (tangent ∩ baseline)
    slope: float  # S, PV units per s at the inflection
    reaction_rate: float  # R = S/Δu, PV units per s per %
    time_constant_tangent: float  # T = K/R, s
    time_constant_63: float  # T63 = t63 − L, s
    t_inflection: float  # s after the step
    t_63: float  # s after the step
    a: float  # R·L, PV units per %
    l_over_t: float  # L/T (tangent)
    noise_std: float  # PV noise seen before the step
    smoothing_window: int  # samples in the slope's window (2: a secant between samples)
    method: str  # "data" or "model" (see the module docstring)
    fit_rms: float | None  # RMS residual of the SOPDT fit, PV units (None: no fit)
    dead_time_tangent: float | None = None  # s, the tangent's L before the floor
    dead_time_floor: float = 0.0  # s, half a sample time (see the module docstring)

    def to_dict(self) -> dict[str, float | int | str | None]:
        """The result's ``step`` object (JSON): every field by its name, in this order."""
        return asdict(self)


@dataclass(frozen=True)
class IntegratingCurve:
    """The reaction curve of an integrating process (Ziegler & Nichols' original method, seed
    001): after a step Δu the PV ramps at a steady slope S; R = S/Δu (PV units per s per %)
    is the process's K', and the ramp's line meets the baseline a dead time L after the step
    (lags fold into L, as in the tangent construction). a = R·L feeds the open-loop rules.
    Times in s from the step, PV in its own units."""

    step_size: float  # Δu, % of output
    pv_before: float  # y₀, the rest before the step
    slope: float  # S, PV units per s, of the trailing window when the step ended
    reaction_rate: float  # R = S/Δu = K', PV units per s per %
    reaction_rate_precision: float  # two standard errors of R, relative (0.02: ± 2 %)
    dead_time: float  # L, s (where the ramps' lines meet the rests), floored at half a sample
    dead_time_se: float  # s, its standard error
    a: float  # R·L, PV units per %
    held: float  # s the step was held
    pv_peak: float  # the PV when the step ended (the furthest the test took it, about)
    pv_after: float  # the PV's rest after the equal and opposite pulse (its dead time on)
    returned: bool  # the PV was at rest there (no trend beyond its noise)
    pulse_op: float  # % output of that pulse (the start − the step, or less where limited)
    pulse_held: float  # s it was held (its area equals the step's)
    noise_std: float  # PV noise seen before the step
    window: float  # s, the trailing window over which the slope was steady
    dead_time_tangent: float  # s, L before the floor
    dead_time_floor: float  # s, half a sample time
    method: str = "integrating"
    stopped_by: str = "precision"  # "precision" (R known), or "range" (the PV's allowance)
    # "fit": R and L least-squares fitted to the whole record, step and pulse (the lines of
    # both ramps met with the rests: ``fit_integrator``); "ramp": the trailing ramp's slope and
    # its line met with the baseline (when the fit failed)
    read_by: str = "fit"
    fit_rms: float | None = None  # PV units, the fit's residual RMS
    # PV units per s the level drifted at the output before the step (it does not balance the
    # integrator exactly; "fit" only): the level keeps drifting so after the test
    drift: float = 0.0
    # s: the lag whose slowing the ramps showed (``IntegratorFit.leak``, 1/τ; read with L),
    # None: straight ramps
    slowing_lag: float | None = None

    @property
    def l_over_t(self) -> None:
        """An integrator has no time constant: L/T does not apply."""
        return None

    def drifted(self, seconds: float) -> float | None:
        """PV units the level's own ``drift`` moved it over ``seconds`` (the test's), where
        that is more than 3σ of the noise (``drift_beyond_noise``)."""
        return drift_beyond_noise(self.drift, seconds, self.noise_std)

    def to_dict(self) -> dict[str, float | int | str | None]:
        """The result's ``step`` object (JSON): every field by its name, in this order."""
        return asdict(self)


def drift_beyond_noise(drift: float, seconds: float, noise_std: float) -> float | None:
    """PV units a level drifting at ``drift`` (PV units/s) moves over ``seconds``, where that
    is more than 3σ of its noise: an integrating step test's pulse gives back the step's area,
    not that, so the level ends that far from where it started (None: within the noise, or
    within ``DRIFT_FLOOR``: a noise-free level's fitted drift of −5.3e-13 %/s was said to leave
    it short of where it began)."""
    moved = drift * seconds
    return moved if abs(moved) > max(3.0 * noise_std, DRIFT_FLOOR) else None


# PV units a level's drift must move it by to be told: far below any transmitter's resolution
# (16 bits of a span of 1), far above a noise-free fit's rounding
DRIFT_FLOOR = 1e-9


def _reached(t: np.ndarray, z: np.ndarray, level: float) -> float:
    """``first_crossing`` of the normalised response z, which the analysis needs: ValueError
    if the PV never reached ``level`` of its change."""
    crossed = first_crossing(t, z, level)
    if crossed is None:
        raise ValueError(f"the PV never reached {level:.0%} of its change")
    return crossed


def _window(noise: float, change: float, rise_samples: float) -> int:
    """Derivative window (odd, ≥ 7): 7 samples without noise, wider as noise/change grows."""
    if change == 0 or noise <= 1e-9 * abs(change):
        return 7
    # The slope's noise falls as w^-1.5; aim for ≈ 0.3 % of the change per rise time.
    ratio = noise / abs(change)
    w = round(rise_samples * (ratio / 0.003) ** (2.0 / 3.0) * 0.25)
    w = max(7, min(w, int(rise_samples * 0.5)))
    return w | 1


def analyze_step(
    t: np.ndarray,
    y: np.ndarray,
    t_step: float,
    step_size: float,
    pv_before: float,
    pv_after: float,
    noise_std: float,
    sample_time: float | None = None,
    floor: float = 0.0,
) -> ReactionCurve:
    """Reaction-curve figures from samples (t, y) taken after a step at ``t_step``.

    ``pv_before``/``pv_after`` are the rest values before and after, ``noise_std`` the PV
    noise seen before the step. The dead time is at least half of ``sample_time`` (s; default
    the samples' median spacing): see the module docstring. Raises ValueError when the
    response is too small or short: its change within 5σ of the noise, or within ``floor``
    (PV units: the least move that is a response, ``no_response_floor``)."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if step_size == 0:
        raise ValueError("step_size must not be 0")
    keep = t >= t_step
    t, y = t[keep], y[keep]
    if t.size < 10:
        raise ValueError(f"only {t.size} samples after the step: too few to analyse")
    change = pv_after - pv_before
    if abs(change) <= max(5.0 * noise_std, 1e-12):
        raise ValueError(
            f"PV changed by {change:.4g}, not clear of its noise "
            f"(σ = {noise_std:.3g}): use a larger step"
        )
    if abs(change) <= floor:
        raise ValueError(
            f"the PV did not respond to the step: it changed by {change:.4g}, within "
            f"{floor:.3g} ({RESOLUTION:.0e} of its range; a valve that did not move?)"
        )
    dt = float(np.median(np.diff(t)))
    sign = math.copysign(1.0, change)
    z = (y - pv_before) / change  # normalised response, 0 → 1
    rise_samples = max((_reached(t, z, 0.632) - t_step) / dt, 7.0)
    if noise_std <= 1e-9 * abs(change):
        # Noise-free: the steepest secant between samples, at its midpoint. Exact to O(T²)
        # on a smooth curve, and never overshoots where the slope jumps (a pure dead time).
        w = 2
        ys = y
        secants = np.diff(y) / np.diff(t)
        k = int(np.argmax(sign * secants))
        t_inf, slope = 0.5 * (t[k] + t[k + 1]), float(secants[k])
    else:
        # Noisy: the slope of a straight line over a window that widens with the noise (a
        # local average of the slope: it cannot overshoot), peak refined by a parabola.
        w = _window(noise_std, change, rise_samples)
        if w >= t.size:
            raise ValueError("the response is too short for its noise: record longer")
        # here, not at the top: scipy.signal (and the scipy.stats it loads) is 0.4 s of the
        # start-up of the tuner and of every `autotune tune`, and only a noisy step needs it
        from scipy.signal import savgol_filter

        ys = savgol_filter(y, w, 2, mode="interp")
        dys = savgol_filter(y, w, 2, deriv=1, delta=dt, mode="interp")
        k = int(np.argmax(sign * dys))
        t_inf, slope = t[k], float(dys[k])
        if 0 < k < t.size - 1:
            d0, d1, d2 = dys[k - 1], dys[k], dys[k + 1]
            denom = d0 - 2 * d1 + d2
            if denom != 0 and abs(delta := 0.5 * (d0 - d2) / denom) <= 1:
                t_inf = t[k] + delta * dt
                slope = float(d1 - 0.25 * (d0 - d2) * delta)
    y_at = float(np.interp(t_inf, t, ys))
    if slope == 0:
        raise ValueError("the PV has no slope after the step")
    t_inf -= t_step
    dead_time = t_inf - (y_at - pv_before) / slope
    t63 = _reached(t, (ys - pv_before) / change, 0.632) - t_step
    method, fit_rms = "data", None
    if noise_std > 1e-9 * abs(change):
        fit = fit_sopdt(t - t_step, y - pv_before, change, dead_time, slope)
        if fit is not None:
            fit_rms = fit.rms
            if fit.rms <= 1.25 * noise_std:
                method = "model"
                t_inf, slope, dead_time, t63 = fit.tangent()
    tangent_dead_time = float(dead_time)
    floor = 0.5 * (sample_time if sample_time is not None else dt)
    dead_time = max(tangent_dead_time, floor)
    gain = change / step_size
    reaction_rate = slope / step_size
    tau_tangent = gain / reaction_rate
    return ReactionCurve(
        step_size=step_size,
        pv_before=pv_before,
        pv_after=pv_after,
        gain=gain,
        dead_time=dead_time,
        slope=slope,
        reaction_rate=reaction_rate,
        time_constant_tangent=tau_tangent,
        time_constant_63=t63 - dead_time,
        t_inflection=t_inf,
        t_63=t63,
        a=reaction_rate * dead_time,
        l_over_t=dead_time / tau_tangent,
        noise_std=noise_std,
        smoothing_window=w,
        method=method,
        fit_rms=fit_rms,
        dead_time_tangent=tangent_dead_time,
        dead_time_floor=floor,
    )


@dataclass(frozen=True)
class SopdtFit:
    """K·e^{−θs}/((τ₁s+1)(τ₂s+1)) fitted to a step response (K per whole step, τ₁ ≥ τ₂)."""

    k: float
    tau1: float
    tau2: float
    theta: float
    rms: float

    def response(self, t: np.ndarray) -> np.ndarray:
        return self.k * _sopdt_unit(np.asarray(t, dtype=float) - self.theta, self.tau1, self.tau2)

    def tangent(self) -> tuple[float, float, float, float]:
        """(t_inflection, slope, L, t63) of the fitted curve, times from the step."""
        k, t1, t2, th = self.k, self.tau1, self.tau2, self.theta
        if t2 <= 1e-9 * t1:
            u = 0.0
        elif abs(t1 - t2) <= 1e-6 * t1:
            u = t1
        else:
            u = t1 * t2 * math.log(t1 / t2) / (t1 - t2)
        h = 1e-6 * (t1 + t2)
        slope = (
            float(
                (self.response(np.array([th + u + h])) - self.response(np.array([th + u])))[0] / h
            )
            if u == 0.0
            else float(k * _sopdt_slope(u, t1, t2))
        )
        y_at = float(self.response(np.array([th + u]))[0])
        dead_time = th + u - y_at / slope
        from scipy.optimize import brentq

        t63 = brentq(lambda x: self.response(np.array([x]))[0] - 0.632 * k, th, th + 20 * (t1 + t2))
        return th + u, slope, dead_time, float(t63)


def _sopdt_unit(u: np.ndarray, t1: float, t2: float) -> np.ndarray:
    """Unit-step response of 1/((τ₁s+1)(τ₂s+1)) at times u (0 for u < 0)."""
    u = np.maximum(u, 0.0)
    if t2 <= 1e-9 * t1:
        return 1.0 - np.exp(-u / t1)
    if abs(t1 - t2) <= 1e-6 * t1:
        return 1.0 - (1.0 + u / t1) * np.exp(-u / t1)
    return 1.0 - (t1 * np.exp(-u / t1) - t2 * np.exp(-u / t2)) / (t1 - t2)


def _sopdt_slope(u: float, t1: float, t2: float) -> float:
    if abs(t1 - t2) <= 1e-6 * t1:
        return u / t1**2 * math.exp(-u / t1)
    return (math.exp(-u / t1) - math.exp(-u / t2)) / (t1 - t2)


def fit_sopdt(
    t: np.ndarray, dy: np.ndarray, change: float, dead_time: float, slope: float
) -> SopdtFit | None:
    """Least-squares SOPDT fit of the PV change ``dy`` at times ``t`` after the step.

    Starts from the data method's tangent (L, slope); None if the fit fails.
    """
    tau_t = max(change / slope, 1e-6)
    x0 = np.array([change, 0.7 * tau_t, 0.2 * tau_t, max(dead_time - 0.1 * tau_t, 0.0)])
    scale = np.array([abs(change), tau_t, tau_t, tau_t])

    def resid(p: np.ndarray) -> np.ndarray:
        k, t1, t2, th = p
        a, b = max(t1, t2), min(t1, t2)
        return k * _sopdt_unit(t - th, max(a, 1e-9), max(b, 0.0)) - dy

    from scipy.optimize import least_squares

    lo = [-np.inf, 1e-9, 0.0, 0.0]
    hi = [np.inf, np.inf, np.inf, float(t[-1])]
    try:
        sol = least_squares(resid, x0, bounds=(lo, hi), x_scale=scale, method="trf")
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not sol.success:
        return None
    k, t1, t2, th = sol.x
    rms = float(np.sqrt(np.mean(sol.fun**2)))
    return SopdtFit(float(k), float(max(t1, t2)), float(min(t1, t2)), float(th), rms)


# ``settled``'s band: the drift it allows, and twice the standard error (fraction of the
# change) to which its window's mean must know the rest value
REST_BAND = 0.005
# that standard error's band where the noise puts REST_BAND out of reach in the time allowed
LOOSE_BAND = 0.02
# σ of the noise a step's change must pass for ``settled`` to read a rest at all
MIN_CHANGE_SIGMAS = 5.0


def band_reachable(
    noise_std: float, change: float, sample_time: float, horizon: float, band: float
) -> bool:
    """Whether ``settled`` can know the rest value to ``band``/2 of the ``change`` within
    ``horizon`` s of the step: its window, the last quarter of the record, must hold
    (σ / (band/2 · |change|))² samples, so the record four times as many."""
    if change == 0 or not (sample_time > 0):
        return False
    needed = (noise_std / (0.5 * band * abs(change))) ** 2  # samples in the window
    return 4.0 * needed * sample_time <= horizon


def settled(
    t: np.ndarray,
    y: np.ndarray,
    t_step: float,
    pv_before: float,
    noise_std: float,
    band: float = REST_BAND,
    pv_range: tuple[float, float] | None = None,
    swing: bool = False,
    horizon: float | None = None,
) -> tuple[bool, float]:
    """Has the PV come to rest after the step? Returns (settled, rest value estimate).

    Over the trailing quarter of the time since the step (≥ 20 samples), the PV's trend must
    either be lost in its noise or imply a drift over the next half of that time below
    ``band`` of the change; at least three times the 63 % time must have passed; and the
    window must be long enough for its mean to carry the rest value to within ``band``/2.
    Given the ``horizon`` (s after the step the caller waits at most) and a noise that puts
    that precision beyond it (``band_reachable``), within ``LOOSE_BAND``/2 instead: a step
    of 13σ sampled every 4.4 s needed 16,000 s for it, and a response flat from 600 s on was
    aborted at 7,200 s as "no steady state".
    Given the transmitter's ``pv_range``, a window at or within noise of one of its ends is
    never at rest (the clipped PV is flat whatever the process does). With ``swing``, the
    window's scatter about its line must be noise too, or within ``band`` of the change: an
    underdamped response has no trend over a window of its swing, and was taken for at rest
    mid-oscillation (ζ = 0.1: a gain 46 % low).
    """
    keep = t >= t_step
    t, y = t[keep], y[keep]
    n = t.size
    if n < 40:
        return False, float(y[-1]) if n else pv_before
    m = max(20, n // 4)
    tw, yw = t[-m:], y[-m:]
    rest = float(np.mean(yw))
    change = rest - pv_before
    if abs(change) <= MIN_CHANGE_SIGMAS * noise_std or change == 0:
        return False, rest
    if pv_range is not None and range_end(yw, pv_range, noise_std) is not None:
        return False, rest
    elapsed = t[-1] - t_step
    reached = first_crossing(t, (y - pv_before) / change, 0.632)
    if reached is None:
        return False, rest
    t63 = reached - t_step
    if elapsed < 3.0 * t63:
        return False, rest
    x = tw - tw.mean()
    sxx = float(np.sum(x * x))
    slope = float(np.sum(x * (yw - rest)) / sxx)
    resid = yw - rest - slope * x
    se = float(np.sqrt(np.sum(resid * resid) / max(m - 2, 1) / sxx))
    quiet = abs(slope) <= 2.0 * se
    small = abs(slope) * elapsed * 0.5 <= band * abs(change)
    if swing and float(np.std(resid)) > max(3.0 * noise_std, band * abs(change)):
        return False, rest
    known = band  # the rest value is known to half of it
    if horizon is not None:
        dt = float(tw[-1] - tw[0]) / (m - 1)
        if not band_reachable(noise_std, change, dt, horizon, band):
            known = max(band, LOOSE_BAND)
    precise = noise_std / math.sqrt(m) <= 0.5 * known * abs(change)
    return bool((quiet or small) and precise), rest


RAMP_PRECISION = 0.1  # the slope's change over the window must be resolved to 10 % of it
RAMP_WINDOWS_PER_DEAD_TIME = 10  # the steady window spans at least 10 apparent dead times
RAMP_MIN_SAMPLES = 40
# a change of the slope over the window below this (relative) is none, however well the fit
# resolves it: a noise-free integrator's lag leaves its ramp's slope e^{−W/τ} short, which
# an exact record resolves to 1e-12 (0.05/(s(5s+1))·e^{−s}, stepped 5 %: 8e-5 over its window
# when it neared the allowance, never steady, the step test aborted and the level left 25 %
# of span off: helper trial); a time constant past 200 windows (100 times the time since the
# step) is integration within any record, as the docstring says of 5
RAMP_STEADY_FLOOR = 0.005
RAMP_STEADY_FLOOR_BEFORE = 1e-6  # a run recorded before it (``StepTestConfig.steady_floor``)


@dataclass(frozen=True)
class SteadyRamp:
    """A PV ramping at a constant slope after a step: the mark of an integrating process."""

    slope: float  # PV units per s, at the middle of the window
    dead_time: float  # s from the step to where the ramp's line meets the baseline
    dead_time_se: float  # s, its standard error
    slope_change: float  # relative change of the slope across the window (0: steady)
    slope_change_se: float  # its standard error (relative)
    window: float  # s, the trailing window the ramp was steady over
    elapsed: float  # s since the step
    slope_se: float = math.inf  # PV units per s, the slope's standard error

    @property
    def precision(self) -> float:
        """Two standard errors of the slope, relative to it (0.02: R known to ±2 %)."""
        return 2.0 * self.slope_se / abs(self.slope) if self.slope else math.inf


def steady_ramp(
    t: np.ndarray,
    y: np.ndarray,
    t_step: float,
    pv_before: float,
    noise_std: float,
    windows_per_dead_time: float = RAMP_WINDOWS_PER_DEAD_TIME,
    floor: float = RAMP_STEADY_FLOOR,
) -> SteadyRamp | None:
    """The steady ramp of an integrating process after a step at ``t_step``, or None.

    Over the trailing half of the time since the step (≥ 40 samples) a parabola is fitted;
    its curvature gives the slope's change across the window. An integrating response (after
    its dead time and lags) keeps a constant slope, so: the change must be lost in the noise
    (≤ 3 standard errors) while the fit resolves it to 10 % of the slope (3 se ≤ 10 %); the
    window must span ≥ 10 apparent dead times, so that an S-shaped response is past its
    inflection; the PV must have moved ≥ 10σ over the window; and the ramp's line must meet
    the baseline after the step (within its error), as a delay does. A self-regulating
    response fails: its slope decays (FOPDT: by e^{−W/T} over W), which the window, half the
    time elapsed, resolves long before its 10 % precision is reached, and the chord of its
    decaying curve meets the baseline before the step. A time constant beyond ≈ 5 times the
    time elapsed is indistinguishable from integration, and is called so.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    keep = t >= t_step
    t, y = t[keep], y[keep]
    if t.size < 2 * RAMP_MIN_SAMPLES:
        return None
    elapsed = float(t[-1] - t_step)
    w = t >= t_step + 0.5 * elapsed
    tw, yw = t[w], y[w]
    n = tw.size
    if n < RAMP_MIN_SAMPLES:
        return None
    span = float(tw[-1] - tw[0])
    x = (tw - tw.mean()) / span  # −½ … ½
    a = np.vander(x, 3)  # x², x, 1
    coef, *_ = np.linalg.lstsq(a, yw, rcond=None)
    resid = yw - a @ coef
    s2 = float(resid @ resid) / max(n - 3, 1)
    cov = s2 * np.linalg.inv(a.T @ a)
    c2, c1, c0 = coef
    slope = float(c1) / span
    if slope == 0 or abs(c1) < 10.0 * noise_std:
        return None
    change = 2.0 * float(c2) / float(c1)  # slope(½) − slope(−½), relative to slope(0)
    change_se = 2.0 * math.sqrt(cov[0, 0]) / abs(float(c1))
    steady = abs(change) <= 3.0 * change_se + floor
    if not (steady and 3.0 * change_se <= RAMP_PRECISION):
        return None
    # the ramp's line at the window's middle, back to the baseline
    t_mid = float(tw.mean())
    rise = float(c0) - pv_before
    chord_dead_time = t_mid - rise / slope - t_step
    var_slope = float(cov[1, 1]) / span**2
    chord_se = math.sqrt(float(cov[2, 2]) / slope**2 + (rise / slope**2) ** 2 * var_slope)
    dt = float(np.median(np.diff(t)))
    if chord_dead_time < -(3.0 * chord_se + dt):
        return None  # a decaying curve's chord: it meets the baseline before the step
    if span < windows_per_dead_time * max(chord_dead_time, 0.0):
        return None
    dead_time, dead_time_se = _kink_dead_time(t - t_step, y - pv_before, 0.5 * elapsed)
    return SteadyRamp(
        slope=slope,
        dead_time=float(dead_time),
        dead_time_se=float(dead_time_se),
        slope_change=change,
        slope_change_se=change_se,
        window=span,
        elapsed=elapsed,
        slope_se=math.sqrt(var_slope),
    )


def _kink_dead_time(t: np.ndarray, dy: np.ndarray, longest: float) -> tuple[float, float]:
    """Dead time (s) and its standard error of dy = S·max(t − L, 0) fitted to the whole record.

    The integrating response's line met back at the baseline: the whole record pins it far
    better than extrapolating the trailing window back (lags fold into L, as in a tangent).
    """

    def sse(lag: float) -> float:
        x = np.maximum(t - lag, 0.0)
        xx = float(x @ x)
        return float(dy @ dy) - (float(x @ dy) ** 2 / xx if xx > 0 else 0.0)

    from scipy.optimize import minimize_scalar

    opt = {"xatol": 1e-9 * max(longest, 1.0)}
    lag = float(minimize_scalar(sse, bounds=(0.0, longest), method="bounded", options=opt).x)
    after = t > lag
    x, yy = t[after], dy[after]
    n = x.size
    if n < 3:
        return lag, math.inf
    slope, icpt = np.polyfit(x, yy, 1)
    resid = yy - (slope * x + icpt)
    s2 = float(resid @ resid) / (n - 2)
    sxx = float(np.sum((x - x.mean()) ** 2))
    # L = −intercept/slope where the line meets dy = 0: its variance from the line's
    cross = (float(np.mean(yy)) / slope**2) ** 2 * s2 / sxx
    se = math.sqrt(s2 / n / slope**2 + cross)
    return lag, se


@dataclass(frozen=True)
class IntegratorFit:
    """K'·e^{−Ls}/s fitted to a whole record:
    y = c + d·(t − t₀) + K'·Σ Δu_k·max(t − t_k − L, 0)."""

    rate: float  # K', PV units per s per %
    dead_time: float  # L, s
    level: float  # c, the PV at the record's first sample t₀ (as the fit has it)
    drift: float  # d, PV units per s: the output at rest was not the one that balances
    rate_se: float  # standard errors (linearised)
    dead_time_se: float
    rms: float  # residual RMS, PV units
    # 1/s: the slowing of each ramp, 1/τ of a lag far slower than the record that the record
    # shows (K'·τ(1 − e^{−t/τ}) in place of K'·t: the process is a lag read as an integrator);
    # 0: none shown (an integrator, or a lag the record cannot tell from one)
    leak: float = 0.0


# how far (F statistic, one parameter more) the slowing of the ramps must improve the fit to
# be kept: white noise on an exact integrator passes 25 about once in a million records
LEAK_F = 25.0


def fit_integrator(
    t: np.ndarray,
    y: np.ndarray,
    changes: list[tuple[float, float]],
    longest: float,
    slowing: bool = True,
) -> IntegratorFit | None:
    """Least squares of an integrator with dead time to the record of a known output: the
    output's changes ``(t_k, Δu_k)`` (s, %) each start a ramp L later. Every kink informs L
    (a step and its return pulse: two) and every quiet stretch the level, so this pins L far
    better than one ramp's line met with the baseline. An integrator is at rest only at the
    one output that balances it: any other output at the start is a drift d, which the ramps
    up and down (slopes K'Δu + d and −K'A + d) tell apart from K'. For fixed L it is linear
    in (c, d, K'); L (0 … ``longest`` s) is found by a bounded scalar search. None if the
    record does not determine it.

    A lag far slower than the record also ramps, but each ramp slows: a straight line then
    meets the baseline early, and L comes out short (e^{−10s}/(1000s + 1), a step read as
    integrating over 16 dead times: L 7.8 s, and SIMC's PI on it Ms 2.05 on the plant where
    1.70 was predicted). Where the record shows that slowing (``LEAK_F``), each ramp is
    K'·τ(1 − e^{−t/τ}) (``leak`` = 1/τ, K' still the first slope) and L is read with it
    (``slowing``; False: straight ramps, as a run recorded before was read)."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.size < 4 or not changes:
        return None

    def regressor(lag: float, leak: float = 0.0) -> np.ndarray:
        x = np.zeros_like(t)
        for tk, du in changes:
            run = np.maximum(t - tk - lag, 0.0)
            x += du * (run if leak <= 0.0 else -np.expm1(-leak * run) / leak)
        return x

    t0 = float(t[0])

    def solve(lag: float, leak: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        a = np.column_stack([np.ones_like(t), t - t0, regressor(lag, leak)])
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        return coef, y - a @ coef

    def sse(lag: float, leak: float = 0.0) -> float:
        r = solve(lag, leak)[1]
        return float(r @ r)

    longest = max(longest, 1e-9)
    from scipy.optimize import minimize_scalar

    opt = {"xatol": 1e-10 * max(longest, 1.0)}

    def best_lag(leak: float) -> float:
        # the SSE may have local minima at the sample grid: a grid first, then refined
        grid = np.linspace(0.0, longest, 41)
        best = float(grid[int(np.argmin([sse(g, leak) for g in grid]))])
        step = grid[1] - grid[0]
        lo, hi = max(0.0, best - step), min(longest, best + step)
        found = minimize_scalar(
            lambda g: sse(g, leak), bounds=(lo, hi), method="bounded", options=opt
        )
        return float(found.x)

    lag = best_lag(0.0)
    lag, leak = _with_leak(t, y, sse, best_lag, lag, longest) if slowing else (lag, 0.0)
    (c, d, k), r = solve(lag, leak)
    if not k or not math.isfinite(k):
        return None
    n = t.size
    s2 = float(r @ r) / max(n - 4 - (leak > 0.0), 1)
    d_lag = np.zeros_like(t)  # ∂y/∂L = −K'·Σ Δu_k·e^{−(t − t_k − L)/τ}·[t > t_k + L]
    for tk, du in changes:
        d_lag -= k * du * (t > tk + lag) * np.exp(-leak * np.maximum(t - tk - lag, 0.0))
    jac = np.column_stack([np.ones_like(t), t - t0, regressor(lag, leak), d_lag])
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
        se_k, se_lag = math.sqrt(max(cov[2, 2], 0.0)), math.sqrt(max(cov[3, 3], 0.0))
    except np.linalg.LinAlgError:
        se_k = se_lag = math.inf
    rms = math.sqrt(float(r @ r) / n)
    return IntegratorFit(float(k), lag, float(c), float(d), se_k, se_lag, rms, leak)


def _with_leak(
    t: np.ndarray,
    y: np.ndarray,
    sse: Callable[[float, float], float],
    best_lag: Callable[[float], float],
    lag: float,
    longest: float,
) -> tuple[float, float]:
    """(L, ``IntegratorFit.leak``) of a record: the 1/τ (a thousandth of the record's own
    rate to ten times it, on a log scale) whose best L fits it best, kept with that L where
    it improves on the integrator's fit (L ``lag``) past ``LEAK_F``; else (``lag``, 0). L
    and 1/τ are found together: at the integrator's L, a slowing the drift d half mimics
    fits best (e^{−10s}/(1000s + 1): τ 4,800 s, L 8.3 s), at their own the record's (1,000
    s, 10.0 s)."""
    from scipy.optimize import minimize_scalar

    n = t.size
    base = sse(lag, 0.0)
    # a residual within rounding of none (a noise-free integrator) has no slowing to show:
    # its F would be rounding over rounding
    if n < 8 or base <= n * (1e-9 * float(np.ptp(y))) ** 2:
        return lag, 0.0
    span = max(float(t[-1] - t[0]), longest, 1e-9)
    grid = np.linspace(math.log(1e-3 / span), math.log(10.0 / span), 13)

    def profile(x: float) -> float:
        return sse(best_lag(math.exp(x)), math.exp(x))

    at = int(np.argmin([profile(x) for x in grid]))
    lo, hi = grid[max(at - 1, 0)], grid[min(at + 1, grid.size - 1)]
    x = float(minimize_scalar(profile, bounds=(lo, hi), method="bounded").x)
    leak = math.exp(x)
    lag_leak = best_lag(leak)
    slowed = sse(lag_leak, leak)
    f = (base - slowed) / (slowed / max(n - 5, 1)) if slowed > 0.0 else math.inf
    return (lag_leak, leak) if f > LEAK_F else (lag, 0.0)
