"""Exact answers for tests, computed independently of the code under test.

The ultimate point of G(s) = num(s)/den(s)·e^{−Ls} is where the phase of G(jω) first reaches
−180°: K_u = 1/|G(jω_u)|, P_u = 2π/ω_u. The phase is unwrapped exactly from the roots, so no
branch of arctan is lost.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq


def _phase_of(num, den, delay):
    """ω ↦ the unwrapped phase of G(jω) (scalar or array): each root's angle is taken on its
    own, so the sum never wraps, and a negative leading gain adds −π."""
    num, den = np.asarray(num, float), np.asarray(den, float)
    zeros = np.roots(num) if len(num) > 1 else np.array([])
    poles = np.roots(den)
    offset = 0.0 if np.sign(num[np.nonzero(num)[0][0]] / den[0]) > 0 else -math.pi

    def ph(w):
        s = 1j * np.asarray(w, float)[..., None]
        return (
            -np.asarray(w, float) * delay
            + np.angle(s - zeros).sum(axis=-1)
            - np.angle(s - poles).sum(axis=-1)
            + offset
        )

    return ph


def phase(num, den, delay, w: float) -> float:
    return float(_phase_of(num, den, delay)(w))


def magnitude(num, den, delay, w: float) -> float:
    s = 1j * w
    return float(abs(np.polyval(num, s) / np.polyval(den, s)))


def ultimate_point(num, den, delay=0.0) -> tuple[float, float]:
    """(K_u, P_u) at the first phase crossover of −180°."""
    num, den = np.asarray(num, float), np.asarray(den, float)
    ph = _phase_of(num, den, delay)
    grid = np.logspace(-6, 4, 20000)
    i = int(np.nonzero(ph(grid) + math.pi < 0)[0][0])
    wu = brentq(lambda w: float(ph(w)) + math.pi, grid[i - 1], grid[i], xtol=1e-14)
    return 1.0 / magnitude(num, den, delay, wu), 2 * math.pi / wu


def lag_ultimate(gain: float, lags: tuple[float, ...], delay: float) -> tuple[float, float]:
    """K·e^{−Ls}/Π(τs+1): Σ atan(τω) + Lω = π at ω_u, K_u = Π√(1+(τω_u)²)/K; an integrator
    (no lags) adds 90°: ω_u = π/(2L), K_u = ω_u/K."""
    if not lags:
        wu = math.pi / (2 * delay)
        return wu / gain, 2 * math.pi / wu
    wu = brentq(lambda w: sum(math.atan(t * w) for t in lags) + delay * w - math.pi, 1e-9, 1e6)
    return math.prod(math.hypot(1.0, t * wu) for t in lags) / gain, 2 * math.pi / wu


def sopdt_tangent(k: float, t1: float, t2: float, theta: float) -> tuple[float, float]:
    """(L, R per unit step) of the inflection tangent of k·e^{−θs}/((t1 s+1)(t2 s+1)), in
    closed form: the inflection is where y'' = 0, the tangent meets the baseline at L."""
    u = t1 * t2 * math.log(t1 / t2) / (t1 - t2)  # inflection: y'' = 0
    slope = k * (math.exp(-u / t1) - math.exp(-u / t2)) / (t1 - t2)
    y = k * (1 - (t1 * math.exp(-u / t1) - t2 * math.exp(-u / t2)) / (t1 - t2))
    return theta + u - y / slope, slope


def isa_ms(num, den, delay: float, ts: float, isa: dict) -> float:
    """Sensitivity peak of the ISA PID ``isa`` (kc, ti, td; derivative filter Td/10) on the
    plant num/den·e^{−delay·s}, the sampling's zero-order hold taken as half a sample of delay
    (the usual approximation), on a grid up to the Nyquist frequency."""
    w = np.logspace(-6, math.log10(math.pi / ts), 80000)
    s = 1j * w
    g = np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * (delay + ts / 2))
    kc, ti, td = isa["kc"], isa["ti"], isa["td"]
    c = kc * (1 + (1 / (ti * s) if ti else 0) + td * s / (1 + td * s / 10))
    return float(np.max(1 / np.abs(1 + c * g)))
