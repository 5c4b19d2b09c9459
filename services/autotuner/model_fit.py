"""Low-order process models fitted to measured frequency points.

The relay test measures G(jω) exactly at a handful of frequencies (its two stages'
fundamentals and their harmonics). Three classic models are fitted to them by least squares on
the complex logarithm (log-magnitude and phase errors, in nepers and radians, weighted):

    FOPDT  K·e^{−Ls}/(Ts + 1)
    SOPDT  K·e^{−Ls}/((T₁s + 1)(T₂s + 1)),  T₁ ≥ T₂
    IPDT   K·e^{−Ls}/s           (integrating, e.g. a tank level)

and the one that fits best is chosen, a model with more parameters only when it fits clearly
better (its residual at most half the simpler one's). The model gives what the points alone do
not: the static gain, L/T for the rules' guidance, model-based rules (AMIGO, SIMC) and the
robustness (Ms) of candidate gains.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from services.autotuner.frequency import ultimate_point


@dataclass(frozen=True)
class ProcessFit:
    kind: str  # "fopdt" | "sopdt" | "ipdt"
    gain: float  # K: PV units per % (IPDT: PV units per % per second)
    lags: tuple[float, ...]  # time constants, s (none for IPDT)
    delay: float  # L, s
    rms: float  # weighted rms of the log residual (nepers ≈ radians)

    @property
    def num(self) -> list[float]:
        return [self.gain]

    @property
    def den(self) -> list[float]:
        if self.kind == "ipdt":
            return [1.0, 0.0]
        den = np.array([1.0])
        for tau in self.lags:
            den = np.polymul(den, [tau, 1.0])
        return [float(c) for c in den]

    @property
    def lag(self) -> float:
        """T: the dominant lag (FOPDT's T; SOPDT's T₁ + T₂; inf for an integrator)."""
        return float(sum(self.lags)) if self.lags else math.inf

    @property
    def normalised_delay(self) -> float:
        """L/T (0 for an integrator)."""
        return self.delay / self.lag if self.lags else 0.0

    def response(self, omega: np.ndarray | float) -> np.ndarray:
        s = 1j * np.asarray(omega, dtype=float)
        return np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay)

    def phase(self, omega: float) -> float:
        """The continuous (unwrapped) phase of G(jω), rad."""
        ph = -omega * self.delay - sum(math.atan(omega * tau) for tau in self.lags)
        return ph - (0.5 * math.pi if self.kind == "ipdt" else 0.0)

    def ultimate_point(self) -> tuple[float, float] | None:
        return ultimate_point(self.num, self.den, self.delay)

    def to_dict(self) -> dict[str, float | str]:
        out: dict[str, float | str] = {
            "model": self.kind,
            "model_gain": self.gain,
            "model_delay": self.delay,
            "model_rms": self.rms,
        }
        for i, tau in enumerate(self.lags, start=1):
            out[f"model_lag_{i}"] = tau
        return out


def _shape(kind: str, x: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """log G(jω) of the model with parameters x = (ln K, ln T…, L)."""
    s = 1j * omega
    log_g = x[0] - s * x[-1]
    if kind == "ipdt":
        return log_g - np.log(s)
    for ln_tau in x[1:-1]:
        log_g = log_g - np.log1p(s * math.exp(ln_tau))
    return log_g


def _fit_one(kind: str, omega: np.ndarray, g: np.ndarray, weights: np.ndarray) -> ProcessFit | None:
    log_g = np.log(np.abs(g)) + 1j * np.angle(g)

    def residual(x: np.ndarray) -> np.ndarray:
        d = _shape(kind, x, omega) - log_g
        # the phase residual wrapped to (−π, π]: the model's own branch is continuous
        d = d.real + 1j * (np.mod(d.imag + math.pi, 2 * math.pi) - math.pi)
        return np.concatenate([d.real * weights, d.imag * weights])

    w0 = float(omega[0])
    starts = []
    n_lags = {"fopdt": 1, "sopdt": 2, "ipdt": 0}[kind]
    for lag_scale in (0.3, 3.0):
        for delay_scale in (0.1, 1.0):
            taus = [lag_scale / w0, 0.3 * lag_scale / w0][:n_lags]
            mag = abs(g[0]) * np.prod([math.hypot(1.0, w0 * t) for t in taus])
            if kind == "ipdt":
                mag = abs(g[0]) * w0
            starts.append(np.array([math.log(mag), *map(math.log, taus), delay_scale / w0]))
    # bounds keep the search finite: lags within 1e-4…1e5 of 1/ω, delay up to 20/ω
    lo = np.array([-60.0] + [math.log(1e-4 / w0)] * n_lags + [0.0])
    hi = np.array([60.0] + [math.log(1e5 / w0)] * n_lags + [20.0 / w0])
    best = None
    for x0 in starts:
        try:
            sol = least_squares(
                residual, np.clip(x0, lo, hi), bounds=(lo, hi), x_scale="jac", max_nfev=200
            )
        except (ValueError, FloatingPointError, OverflowError):
            continue
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None or not np.all(np.isfinite(best.x)):
        return None
    x = best.x
    lags = tuple(sorted((math.exp(v) for v in x[1:-1]), reverse=True))
    rms = math.sqrt(2.0 * best.cost / max(1.0, float(np.sum(weights**2)) * 2.0))
    return ProcessFit(kind, math.exp(x[0]), lags, float(x[-1]), rms)


def fit_models(
    omega: Sequence[float], g: Sequence[complex], weights: Sequence[float] | None = None
) -> list[ProcessFit]:
    """Every model that could be fitted to the points, best fit first."""
    om = np.asarray(omega, dtype=float)
    gg = np.asarray(g, dtype=complex)
    if om.size < 2 or om.size != gg.size:
        raise ValueError("points: need at least two frequency points")
    order = np.argsort(om)
    om, gg = om[order], gg[order]
    wt = np.ones_like(om) if weights is None else np.asarray(weights, dtype=float)[order]
    fits = [f for kind in ("fopdt", "ipdt", "sopdt") if (f := _fit_one(kind, om, gg, wt))]
    return sorted(fits, key=lambda f: f.rms)


def choose(fits: Sequence[ProcessFit]) -> ProcessFit | None:
    """The simplest model whose fit is not clearly beaten: more parameters must halve the
    residual (an rms below 1e-3 counts as exact)."""
    if not fits:
        return None
    simple = [f for f in fits if f.kind in ("fopdt", "ipdt")]
    best_simple = min(simple, key=lambda f: f.rms) if simple else None
    sopdt = next((f for f in fits if f.kind == "sopdt"), None)
    if best_simple is None:
        return sopdt
    if sopdt is None or best_simple.rms <= max(2.0 * sopdt.rms, 1e-3):
        return best_simple
    return sopdt
