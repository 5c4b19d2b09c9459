"""Robustness of a PID on a linear plant model: maximum sensitivity, gain and phase margins.

Loop transfer L(jω) = C(jω)·G(jω) with the plant G = num/den·e^{−Ls} (a ``DelayedTF``) and
the ISA PID C = Kc·(1 + 1/(Ti·s) + Td·s/(1 + Td·s/N)) as the loop's PID block runs it. On a
dense logarithmic grid refined around each extremum:

* Ms = max |1/(1 + L(jω))| (Åström & Hägglund 2006, §4.6: 1.2–2.0 is the usual range);
* gain margin 1/|L(jω₁₈₀)| at the first frequency where the unwrapped phase of L reaches
  −180° (inf if it never does; for P control it equals K_u/Kc);
* phase margin 180° + arg L(jω_c) at the first frequency where |L| falls to 1.

This is the continuous loop: it ignores the zero-order hold and the PID block's discrete
integral and derivative. ``sampled_loop`` gives the same figures for the loop as it runs at
its sample time T (and its stability by the Nyquist count), to which these tend as T → 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq, minimize_scalar

from shared.control.forms import IsaGains
from shared.control.transfer import DelayedTF


@dataclass(frozen=True)
class Robustness:
    ms: float
    gain_margin: float
    phase_margin_deg: float
    omega_180: float | None  # rad/s
    omega_c: float | None  # rad/s
    # the sampled loop's (``sampled_loop``): its stability by the Nyquist count, the sample
    # time, and how many closed-loop poles lie outside the unit circle; None in continuous time
    stable: bool | None = None
    sample_time: float | None = None
    unstable_poles: int | None = None


def nearest_crossing(
    w: np.ndarray, phase: np.ndarray, mag: np.ndarray, first: float | None, tol: float = 1e-9
) -> tuple[int, float] | None:
    """The crossing of −180° + k·360° (any k, either way) on the grid ``w`` where the loop's
    gain ``mag`` is largest — the nearest to −1, so the least gain margin — other than the
    ``first`` one (ω, already found): (the grid index it lies after, the crossed phase in
    rad); None if there is no other. A filtered derivative keeps the gain up at high
    frequency while a delay's phase turns on, so a later crossing can be the nearer (seen:
    e^{−10s}/(2s + 1), ZN PID: 1.37 at the first, 1.03 at the next). Only where the grid
    resolves the phase (steps below π)."""
    x = (phase + math.pi) / (2.0 * math.pi)
    turns = np.floor(x + tol)
    resolved = np.abs(np.diff(phase)) < math.pi
    idx = np.nonzero((np.diff(turns) != 0) & resolved)[0]
    if first is not None:
        idx = idx[~((w[idx] <= first) & (first <= w[idx + 1]))]
    if idx.size == 0:
        return None
    i = int(idx[np.argmax(np.maximum(mag[idx], mag[idx + 1]))])
    return i, 2.0 * math.pi * max(turns[i], turns[i + 1]) - math.pi


def loop_response(gains: IsaGains, plant: DelayedTF, n: float, w: np.ndarray) -> np.ndarray:
    """L(jω) = C(jω)·G(jω) at ω in rad/s; ``n`` the derivative filter (Tf = Td/n)."""
    s = 1j * np.asarray(w, dtype=float)
    c = gains.kc * (1.0 + (0.0 if gains.ti is None else 1.0 / (gains.ti * s)))
    if gains.td > 0:
        c = c + gains.kc * gains.td * s / (1.0 + gains.td * s / n)
    # G in a named array, not a temporary: numpy multiplies into a temporary in place, by
    # another loop whose last bit can differ (the figures must not move)
    g = plant.response(w)
    return c * g


def robustness(
    gains: IsaGains,
    plant: DelayedTF,
    n: float = 10.0,
    w_min: float = 1e-5,
    w_max: float = 1e4,
) -> Robustness:
    """Ms, margins and crossover frequencies of ``gains`` on ``plant`` over ω in [w_min,
    w_max] rad/s (see the module)."""
    w = np.logspace(math.log10(w_min), math.log10(w_max), 20000)
    lw = loop_response(gains, plant, n, w)
    phase = np.unwrap(np.angle(lw))
    # the unwrapped phase may start a multiple of 2π off: anchor it at the low-frequency end
    phase -= 2 * math.pi * round((phase[0] - np.angle(lw[0])) / (2 * math.pi))
    sens = 1.0 / np.abs(1.0 + lw)
    k = int(np.argmax(sens))
    lo, hi = w[max(k - 1, 0)], w[min(k + 1, w.size - 1)]
    best = minimize_scalar(
        lambda x: -1.0 / abs(1.0 + loop_response(gains, plant, n, np.array([x]))[0]),
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 1e-12},
    )
    ms = max(float(sens[k]), -float(best.fun))

    def interp_root(values: np.ndarray, target: float) -> float | None:
        idx = np.nonzero(np.diff(np.sign(values - target)))[0]
        if idx.size == 0:
            return None
        i = int(idx[0])
        return brentq(lambda x: np.interp(math.log(x), np.log(w), values) - target, w[i], w[i + 1])

    w180 = interp_root(phase, -math.pi)
    gm = (
        math.inf if w180 is None else 1.0 / abs(loop_response(gains, plant, n, np.array([w180]))[0])
    )
    other = nearest_crossing(w, phase, np.abs(lw), w180)
    if other is not None:  # the least margin over every crossing, not the first's alone
        i, crossed = other
        wo = brentq(lambda x: np.interp(math.log(x), np.log(w), phase) - crossed, w[i], w[i + 1])
        go = 1.0 / abs(loop_response(gains, plant, n, np.array([wo]))[0])
        if go < gm:
            gm, w180 = go, wo
    wc = interp_root(np.log(np.abs(lw)), 0.0)
    pm = math.inf
    if wc is not None:
        pm = 180.0 + math.degrees(float(np.interp(math.log(wc), np.log(w), phase)))
    return Robustness(ms, gm, pm, w180, wc)
