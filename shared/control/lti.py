"""Exact zero-order-hold discretisation of a linear system with an input dead time.

For ẋ = A x + B u(t − θ), y = C x + D u(t − θ), with u held constant over each sample
period [kT, (k+1)T) and θ = n·T + f (n whole samples, 0 ≤ f < T), integrating over one period:

    x[k+1] = Φ x[k] + Γ_new u[k−n] + Γ_old u[k−n−1]
    Φ      = e^{AT}
    Γ_new  = ∫₀^{T−f} e^{Aσ} dσ · B
    Γ_old  = e^{A(T−f)} ∫₀^{f} e^{Aσ} dσ · B        (zero when f = 0)

Both integrals come from one matrix exponential of [[A, B], [0, 0]] (Van Loan), so the
samples equal the continuous response exactly (to rounding). The input delay line holds the
last n+2 outputs. PV is read just before the output computed at t_k takes effect, so a
feed-through D sees the output held over the previous period: y[k] = C x[k] + D u[k−1−n]
evaluated as u(t_k⁻ − θ).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

# scipy.linalg is imported where it is used, not here: every `autotune` command loads this
# module, and only a model's discretisation needs it

# A delay within this many sample periods of a whole number is taken as that whole number:
# it only absorbs floating-point error in θ/T (e.g. 0.3/0.1), it never rounds a real fraction.
WHOLE_SAMPLE_TOLERANCE = 1e-9


def split_delay(delay: float, sample_time: float) -> tuple[int, float]:
    """Split ``delay`` into whole samples n and a remainder f in [0, T)."""
    if not math.isfinite(delay) or delay < 0:
        raise ValueError(f"delay must be a finite number ≥ 0 s, got {delay!r}")
    ratio = delay / sample_time
    nearest = round(ratio)
    if abs(ratio - nearest) <= WHOLE_SAMPLE_TOLERANCE * max(1.0, ratio):
        return int(nearest), 0.0
    n = math.floor(ratio)
    return n, delay - n * sample_time


def _zoh_integral(a: np.ndarray, b: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Return (e^{Aτ}, ∫₀^τ e^{Aσ}dσ·B) from one matrix exponential."""
    nx, nu = b.shape
    m = np.zeros((nx + nu, nx + nu))
    m[:nx, :nx] = a
    m[:nx, nx:] = b
    from scipy.linalg import expm

    e = expm(m * tau)
    return e[:nx, :nx], e[:nx, nx:]


@dataclass(frozen=True)
class DiscreteDelaySystem:
    """The sampled system: matrices and the whole/fractional split of the dead time."""

    phi: np.ndarray
    gamma_new: np.ndarray
    gamma_old: np.ndarray
    c: np.ndarray
    d: float
    sample_time: float
    delay_samples: int
    delay_fraction: float

    @property
    def order(self) -> int:
        return self.phi.shape[0]

    def dc_gain(self) -> float:
        """Steady-state gain of the sampled system (inf for an integrating one)."""
        if self.order == 0:
            return self.d
        i_minus_phi = np.eye(self.order) - self.phi
        gamma = self.gamma_new + self.gamma_old
        try:
            return float((self.c @ np.linalg.solve(i_minus_phi, gamma)).item() + self.d)
        except np.linalg.LinAlgError:
            return math.inf

    def response(self, omega: np.ndarray | float) -> np.ndarray:
        """G(e^{jωT}) of the ZOH-sampled system at ω in rad/s, exact (one small linear solve
        per frequency): z^{−n}·[C(zI − Φ)^{−1}(Γ_new + z^{−1}Γ_old) + D·z^{−1}]."""
        omega = np.atleast_1d(np.asarray(omega, dtype=float))
        z = np.exp(1j * omega * self.sample_time)
        zinv = 1.0 / z
        out = self.d * zinv
        if self.order:
            eye = np.eye(self.order)
            b = self.gamma_new[:, 0][None, :] + zinv[:, None] * self.gamma_old[:, 0][None, :]
            x = np.linalg.solve(z[:, None, None] * eye[None] - self.phi[None], b[:, :, None])
            out = out + (x[:, :, 0] @ self.c[0])
        return out * zinv**self.delay_samples


def discretize(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, d: float, sample_time: float, delay: float
) -> DiscreteDelaySystem:
    """ZOH-discretise (A, B, C, D) with input dead time ``delay`` at ``sample_time``."""
    if not math.isfinite(sample_time) or sample_time <= 0:
        raise ValueError(f"sample_time must be a finite number > 0 s, got {sample_time!r}")
    n, f = split_delay(delay, sample_time)
    a = np.atleast_2d(np.asarray(a, dtype=float))
    b = np.asarray(b, dtype=float).reshape(a.shape[0], 1) if a.size else np.zeros((0, 1))
    c = np.asarray(c, dtype=float).reshape(1, a.shape[0]) if a.size else np.zeros((1, 0))
    nx = b.shape[0]
    if nx == 0:
        empty = np.zeros((0, 0))
        return DiscreteDelaySystem(
            empty, np.zeros((0, 1)), np.zeros((0, 1)), c, float(d), sample_time, n, f
        )
    phi, _ = _zoh_integral(a, b, sample_time)
    e_late, gamma_new = _zoh_integral(a, b, sample_time - f)
    if f > 0.0:
        _, int_early = _zoh_integral(a, b, f)
        gamma_old = e_late @ int_early
    else:
        gamma_old = np.zeros_like(gamma_new)
    return DiscreteDelaySystem(phi, gamma_new, gamma_old, c, float(d), sample_time, n, f)


def tf_to_ss(num: list[float], den: list[float]) -> tuple[np.ndarray, ...]:
    """State-space realisation of num/den (descending powers of s); ValueError names the fault."""
    num_a = np.trim_zeros(np.asarray(num, dtype=float), "f")
    den_a = np.trim_zeros(np.asarray(den, dtype=float), "f")
    if den_a.size == 0:
        raise ValueError("den: the denominator is zero")
    if num_a.size == 0:
        num_a = np.zeros(1)
    if num_a.size > den_a.size:
        raise ValueError(
            f"num: degree {num_a.size - 1} exceeds the denominator's {den_a.size - 1} "
            "(the transfer function must be proper)"
        )
    if den_a.size == 1:
        return np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), float(num_a[-1] / den_a[0])
    from scipy.signal import tf2ss  # here: scipy.signal costs 0.25 s of every CLI's start-up

    gain = num_a[0] / den_a[0]
    if num_a.size == 1 and abs(gain) <= 1e-14:
        # scipy warns that such a numerator is "badly conditioned" (it would trim leading
        # zeros, and there are none to trim): the same realisation, scaled, without the
        # warning (a model fit's search passes through gains this small)
        a, b, c, d = tf2ss([1.0], den_a / den_a[0])
        return a, b, c * gain, float(np.asarray(d).item()) * gain
    a, b, c, d = tf2ss(num_a, den_a)
    return a, b, c, float(np.asarray(d).item())


class DelayedLinearSystem:
    """State and delay line of a DiscreteDelaySystem, in deviation variables (rest = 0).

    ``step`` runs once per sample in every loop the plant steps: the arrays it multiplies
    are looked up once here (the very same arrays, so the arithmetic is unchanged to the bit)."""

    def __init__(self, sys: DiscreteDelaySystem):
        self.sys = sys
        self._x = np.zeros(sys.order)
        self._inputs: deque[float] = deque(
            [0.0] * (sys.delay_samples + 2), maxlen=sys.delay_samples + 2
        )
        self._n = sys.delay_samples
        self._phi = sys.phi
        self._g_new = sys.gamma_new[:, 0]
        # without a fractional delay Γ_old is zero: its term adds nothing (but its cost)
        self._g_old = sys.gamma_old[:, 0] if sys.delay_fraction > 0.0 else None
        self._c = sys.c[0]
        self._d = sys.d

    def reset(self) -> None:
        """Back to rest: zero state, zero inputs in the delay line."""
        self._x[:] = 0.0
        for i in range(len(self._inputs)):
            self._inputs[i] = 0.0

    def output(self) -> float:
        """y at the current sample instant (feed-through sees the input held before it)."""
        y = float(self._c @ self._x) if self.sys.order else 0.0
        # After step(u[k]) the line holds u[k] at index 0; u(t_{k+1}⁻ − θ) = u[k−n] is at n.
        return y + self._d * self._inputs[self._n]

    def step(self, u: float) -> float:
        """Hold ``u`` for one sample period; return y at the end of it."""
        inputs, n = self._inputs, self._n
        inputs.appendleft(float(u))
        if self.sys.order:
            x = self._phi @ self._x + self._g_new * inputs[n]
            if self._g_old is not None:
                x = x + self._g_old * inputs[n + 1]
            self._x = x
            return float(self._c @ x) + self._d * inputs[n]
        return 0.0 + self._d * inputs[n]


def simulate(sys: DiscreteDelaySystem, u: np.ndarray) -> np.ndarray:
    """The whole response at once, from rest: y[0] = 0 and y[k+1] the output after holding
    u[k] for a period — the same samples as ``DelayedLinearSystem.step``, via ``lfilter``
    (for fitting models to a record, where thousands of steps run per evaluation)."""
    from scipy.signal import lfilter

    u = np.asarray(u, dtype=float)
    n = sys.delay_samples
    late = np.concatenate((np.zeros(n), u))[: u.size + 1]  # u[k−n] at index k
    early = np.concatenate((np.zeros(n + 1), u))[: u.size + 1]  # u[k−n−1]
    if late.size < u.size + 1:
        late = np.append(late, 0.0)
    y = sys.d * early  # y[k] = C x[k] + D u[k−1−n]; x[k+1] = Φ x[k] + Γ_new u[k−n] + …
    if sys.order:
        den = np.poly(sys.phi)
        for gamma, v in ((sys.gamma_new, late), (sys.gamma_old, early)):
            if not np.any(gamma):
                continue
            num = _numerator(sys.phi, gamma[:, 0], sys.c[0], den)
            y = y + lfilter(num, den, v)
    return y


def _numerator(phi: np.ndarray, gamma: np.ndarray, c: np.ndarray, den: np.ndarray) -> np.ndarray:
    """Numerator of C (zI − Φ)⁻¹ Γ over det(zI − Φ), in powers of z⁻¹ (a leading zero)."""
    # C adj(zI − Φ) Γ = det(zI − Φ + Γ C) − det(zI − Φ) (matrix determinant lemma)
    return np.poly(phi - np.outer(gamma, c)) - den
