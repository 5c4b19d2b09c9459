"""The plant's frequency response at the relay's oscillation, from whole periods of the cycle.

Over a window of whole periods of the limit cycle (period P, ω = 2π/P), the fundamental
Fourier components of the PV and of the output,

    Y₁ = (2/W)∫ y(t) e^{−jωt} dt,   U₁ = (2/W)∫ u(t) e^{−jωt} dt   (W = N·P),

give G(jω) = Y₁/U₁ exactly for a linear plant in a periodic cycle, with no describing-function
approximation (Åström & Hägglund, *Advanced PID Control*, 2006, §2.7; Kaya & Atherton 2001).
The output is piecewise constant (the zero-order hold), so its integral is exact interval by
interval; the PV is known at the samples and is integrated by the trapezoid rule (an error
of order (ωT)²/12, about 1e-4 at 150 samples per period). The same formula at 3ω and 5ω gives
G(j3ω) and G(j5ω) from the relay's odd harmonics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FrequencyPoint:
    omega: float  # rad/s
    g: complex  # G(jω), PV units per %
    # relative uncertainty of ``g`` (magnitude, and radians of phase) that the window's
    # leakage leaves: 0 for a point measured as it is (``relay_model.corrector`` sets it on
    # the points it corrects)
    leak: float = 0.0

    @property
    def magnitude(self) -> float:
        return abs(self.g)

    @property
    def phase_deg(self) -> float:
        """Phase in degrees, in (−360, 0] for a lagging plant."""
        ph = math.degrees(math.atan2(self.g.imag, self.g.real))
        return ph - 360.0 if ph > 0 else ph


def _component_held(t: np.ndarray, u: np.ndarray, t0: float, t1: float, w: float) -> complex:
    """∫ u(t) e^{−jwt} dt over [t0, t1] for u held at u[k] over [t[k], t[k+1])."""
    edges = np.clip(np.append(t, t[-1] + (t[-1] - t[-2])), t0, t1)
    a, b = edges[:-1], edges[1:]
    keep = b > a
    return complex(
        np.sum(u[keep] * (np.exp(-1j * w * a[keep]) - np.exp(-1j * w * b[keep])) / (1j * w))
    )


def _component_sampled(t: np.ndarray, y: np.ndarray, t0: float, t1: float, w: float) -> complex:
    """∫ y(t) e^{−jwt} dt over [t0, t1], y linear between samples (trapezoid)."""
    inside = (t > t0) & (t < t1)
    tt = np.concatenate(([t0], t[inside], [t1]))
    yy = np.concatenate(([np.interp(t0, t, y)], y[inside], [np.interp(t1, t, y)]))
    f = yy * np.exp(-1j * w * tt)
    return complex(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(tt)))


def frequency_points(
    t: np.ndarray,
    pv: np.ndarray,
    op: np.ndarray,
    t_start: float,
    period: float,
    periods: int,
    harmonics: tuple[int, ...] = (1, 3, 5),
) -> list[FrequencyPoint]:
    """G(jkω) for each harmonic k, from ``periods`` whole periods starting at ``t_start``.

    ``op[i]`` is the output held from ``t[i]``. ValueError if the record is too short.
    """
    t, pv, op = (np.asarray(a, dtype=float) for a in (t, pv, op))
    t_end = t_start + periods * period
    slack = 1e-9 * period  # the window's end is a sum of interpolated crossings: rounding
    if t_end > t[-1] and t_end - t[-1] <= slack:
        t_end = t[-1]
    if t_start < t[0] or t_end > t[-1]:
        raise ValueError("the record does not cover the requested whole periods")
    out = []
    for k in harmonics:
        w = 2.0 * math.pi * k / period
        u_k = _component_held(t, op - np.mean(op), t_start, t_end, w)
        if abs(u_k) < 1e-12 * (np.ptp(op) + 1e-300) * (t_end - t_start):
            continue  # an even harmonic of a symmetric relay: no excitation there
        y_k = _component_sampled(t, pv - np.mean(pv), t_start, t_end, w)
        out.append(FrequencyPoint(w, y_k / u_k))
    return out
