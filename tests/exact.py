"""Exact answers for tests, computed independently of the code under test.

The ultimate point of G(s) = num(s)/den(s)·e^{−Ls} is where the phase of G(jω) first reaches
−180°: K_u = 1/|G(jω_u)|, P_u = 2π/ω_u. The phase is unwrapped exactly from the roots, so no
branch of arctan is lost.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq


def phase(num, den, delay, w: float) -> float:
    s = 1j * w
    ph = -w * delay
    ph += sum(np.angle(s - z) for z in np.roots(num)) if len(num) > 1 else 0.0
    ph -= sum(np.angle(s - p) for p in np.roots(den))
    lead_sign = np.sign(num[np.nonzero(num)[0][0]] / den[0])
    return float(ph + (0.0 if lead_sign > 0 else -math.pi))


def magnitude(num, den, delay, w: float) -> float:
    s = 1j * w
    return float(abs(np.polyval(num, s) / np.polyval(den, s)))


def ultimate_point(num, den, delay=0.0) -> tuple[float, float]:
    """(K_u, P_u) at the first phase crossover of −180°."""
    num, den = np.asarray(num, float), np.asarray(den, float)
    grid = np.logspace(-6, 4, 20000)
    f = np.array([phase(num, den, delay, w) + math.pi for w in grid])
    i = int(np.nonzero(f < 0)[0][0])
    wu = brentq(lambda w: phase(num, den, delay, w) + math.pi, grid[i - 1], grid[i], xtol=1e-14)
    return 1.0 / magnitude(num, den, delay, wu), 2 * math.pi / wu


def test_known_answers():
    ku, pu = ultimate_point([6.0], [1, 6, 11, 6])  # Routh: K_u = 10, ω_u = √11 (seed 000)
    assert abs(ku - 10.0) < 1e-9 and abs(pu - 2 * math.pi / math.sqrt(11)) < 1e-9
    # e^{−Ls}/(Ts+1) (Iinoya–Hotta eq. 5): tan(ω L) = −Tω, K_u = √(1+(Tω)²)
    ku, pu = ultimate_point([1.0], [3.0, 1.0], 1.0)
    w = 2 * math.pi / pu
    assert abs(math.tan(w * 1.0) + 3.0 * w) < 1e-9 and abs(ku - math.hypot(1, 3 * w)) < 1e-9
