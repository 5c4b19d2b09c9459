"""The exact ultimate point of a linear plant model, from its frequency response.

K_u = 1/|G(jω_u)| and P_u = 2π/ω_u where the phase of G(jω) = num/den·e^{−Ls} first reaches
−180°, the phase unwrapped exactly from the poles and zeros. Used to show the exact values
beside the measured ones when the plant's model is known (the demo, benchmarks).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq


def _phase(zeros: np.ndarray, poles: np.ndarray, sign: float, delay: float, w: float) -> float:
    s = 1j * w
    return float(
        np.sum(np.angle(s - zeros))
        - np.sum(np.angle(s - poles))
        - w * delay
        + (0.0 if sign > 0 else -math.pi)
    )


def ultimate_point(
    num: list[float], den: list[float], delay: float = 0.0
) -> tuple[float, float] | None:
    """(K_u, P_u) of num/den·e^{−delay·s}, or None if the phase never reaches −180°."""
    num_a = np.trim_zeros(np.asarray(num, dtype=float), "f")
    den_a = np.trim_zeros(np.asarray(den, dtype=float), "f")
    if num_a.size == 0 or den_a.size == 0:
        return None
    zeros, poles = np.roots(num_a), np.roots(den_a)
    sign = float(np.sign(num_a[0] / den_a[0]))
    grid = np.logspace(-6, 5, 4000)
    f = np.array([_phase(zeros, poles, sign, delay, w) + math.pi for w in grid])
    below = np.nonzero(f < 0)[0]
    if below.size == 0 or below[0] == 0:
        return None
    i = int(below[0])
    wu = brentq(
        lambda w: _phase(zeros, poles, sign, delay, w) + math.pi,
        grid[i - 1],
        grid[i],
        xtol=1e-14,
        rtol=1e-14,
    )
    gain = abs(np.polyval(num_a, 1j * wu) / np.polyval(den_a, 1j * wu))
    return 1.0 / gain, 2.0 * math.pi / wu


def model_ultimate_point(model: object) -> tuple[float, float] | None:
    """The exact ultimate point of a plant_sim linear model (None for others)."""
    num, den = getattr(model, "num", None), getattr(model, "den", None)
    if num is None or den is None:
        return None
    lag = getattr(model, "sensor_lag", 0.0)
    full = list(np.polymul(den, [lag, 1.0])) if lag else den
    return ultimate_point(num, full, getattr(model, "delay", 0.0))
