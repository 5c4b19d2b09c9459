"""A transfer function with dead time, G(s) = num(s)/den(s)·e^{−Ls}, and its exact ultimate
point.

K_u = 1/|G(jω_u)| and P_u = 2π/ω_u where the phase of G(jω) first reaches −180°, the phase
unwrapped exactly from the poles and zeros. ``DelayedTF`` is the one type every module uses
for a plant's frequency response: the fitted process models, the benchmark's plants, the
robustness and closed-loop predictions, the exact answers shown beside measured ones.
Coefficients in descending powers of s; time in seconds; gain in PV units per % of output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# scipy.optimize is imported where it is used, not here: it is a third of a second of the
# start of every `autotune` command that loads this module, and most never fit anything


@dataclass(frozen=True)
class DelayedTF:
    """num(s)/den(s)·e^{−delay·s}; ``delay`` in s."""

    num: tuple[float, ...]
    den: tuple[float, ...]
    delay: float = 0.0

    @classmethod
    def of(cls, num, den, delay: float = 0.0) -> DelayedTF:
        """From any sequences of coefficients (lists, arrays, tuples)."""
        return cls(tuple(float(c) for c in num), tuple(float(c) for c in den), float(delay))

    def response(self, omega: np.ndarray | float) -> np.ndarray:
        """G(jω) at ω in rad/s."""
        s = 1j * np.asarray(omega, dtype=float)
        return np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay)

    def phase(self, omega: np.ndarray) -> np.ndarray:
        """The continuous phase of G(jω) at every ω of ``omega`` (rad/s), rad, unwrapped
        exactly from the poles, zeros and dead time (as ``ultimate_point`` follows it)."""
        num = np.trim_zeros(np.asarray(self.num, dtype=float), "f")
        den = np.trim_zeros(np.asarray(self.den, dtype=float), "f")
        sign = float(np.sign(num[0] / den[0]))
        w = np.atleast_1d(np.asarray(omega, dtype=float))
        return _phases(np.roots(num), np.roots(den), sign, self.delay, w)

    def ultimate_point(self) -> tuple[float, float] | None:
        """(K_u, P_u in s), or None if the phase never reaches −180°."""
        return ultimate_point(list(self.num), list(self.den), self.delay)

    def with_lag(self, lag: float) -> DelayedTF:
        """This times 1/(lag·s + 1): a first-order sensor lag in series (lag in s)."""
        if not lag:
            return self
        return DelayedTF.of(self.num, np.polymul(self.den, [lag, 1.0]), self.delay)


def _phase(zeros: np.ndarray, poles: np.ndarray, sign: float, delay: float, w: float) -> float:
    s = 1j * w
    return float(
        np.sum(np.angle(s - zeros))
        - np.sum(np.angle(s - poles))
        - w * delay
        + (0.0 if sign > 0 else -math.pi)
    )


def _phases(
    zeros: np.ndarray, poles: np.ndarray, sign: float, delay: float, w: np.ndarray
) -> np.ndarray:
    """``_phase`` at every ω of ``w`` at once (the same sums, term by term, in the same order)."""
    s = 1j * w[:, None]
    return (
        np.sum(np.angle(s - zeros[None, :]), axis=1)
        - np.sum(np.angle(s - poles[None, :]), axis=1)
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
    f = _phases(zeros, poles, sign, delay, grid) + math.pi
    below = np.nonzero(f < 0)[0]
    if below.size == 0 or below[0] == 0:
        return None
    i = int(below[0])
    from scipy.optimize import brentq

    wu = brentq(
        lambda w: _phase(zeros, poles, sign, delay, w) + math.pi,
        grid[i - 1],
        grid[i],
        xtol=1e-14,
        rtol=1e-14,
    )
    gain = abs(np.polyval(num_a, 1j * wu) / np.polyval(den_a, 1j * wu))
    return 1.0 / gain, 2.0 * math.pi / wu


def model_transfer(model: object) -> DelayedTF | None:
    """The transfer function of a plant_sim linear model, its sensor lag included (None for a
    model without ``num`` and ``den`` as coefficient sequences: physical and user models)."""
    num, den = getattr(model, "num", None), getattr(model, "den", None)
    if num is None or den is None:
        return None
    try:
        tf = DelayedTF.of(num, den, getattr(model, "delay", 0.0))
        return tf.with_lag(getattr(model, "sensor_lag", 0.0))
    except (TypeError, ValueError, OverflowError):
        # a user's class whose own ``num`` and ``den`` are something else (a tube count and a
        # density: "'int' object is not iterable", exit 70 from `model check`: helper review)
        return None


def model_ultimate_point(model: object) -> tuple[float, float] | None:
    """The exact ultimate point of a plant_sim linear model (None for others), of the loop
    its controller closes: a process whose gain is negative (its lowest-order coefficients'
    ratio: the static gain, or an integrator's) is under a direct-acting controller, which
    closes the loop around −G (whose phase, not G's, starts at 0° and crosses −180°)."""
    tf = model_transfer(model)
    if tf is None:
        return None
    if _low_order_sign(tf) < 0:
        tf = DelayedTF(tuple(-c for c in tf.num), tf.den, tf.delay)
    return tf.ultimate_point()


def _low_order_sign(tf: DelayedTF) -> float:
    """The sign of the ratio of the lowest-order nonzero coefficients of num and den."""
    num = [c for c in tf.num if c != 0.0]
    den = [c for c in tf.den if c != 0.0]
    return float(np.sign(num[-1] / den[-1])) if num and den else 1.0
