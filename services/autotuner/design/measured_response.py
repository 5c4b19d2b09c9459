"""Closed-loop response figures: a setpoint step and a load step.

Setpoint step from y₀ to r, z = (y − y₀)/(r − y₀), read with the noise averaged over a few
samples: overshoot = max(z) − 1 (in %), decay ratio
= second overshoot over the first (the quarter-decay aim of Ziegler–Nichols is 0.25), rise
time 10 → 90 %, settling time to stay within ±``band`` of the step, IAE = ∫|r − y| dt. Load
step: IAE, the largest deviation from the setpoint and the time to return within a tenth of
it (or the noise band).
"""

from __future__ import annotations

import math

import numpy as np

from services.autotuner.identify.oscillation import extrema, smooth


def _trapz(y: np.ndarray, t: np.ndarray) -> float:
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(t))) if t.size > 1 else 0.0


def _crossing(t: np.ndarray, z: np.ndarray, level: float) -> float | None:
    i = np.nonzero(z >= level)[0]
    if i.size == 0:
        return None
    k = int(i[0])
    if k == 0:
        return float(t[0])
    return float(t[k - 1] + (level - z[k - 1]) / (z[k] - z[k - 1]) * (t[k] - t[k - 1]))


def setpoint_step(
    t: np.ndarray,
    y: np.ndarray,
    t0: float,
    y0: float,
    target: float,
    band: float = 0.02,
    noise: float = 0.0,
    width: int = 5,
) -> dict[str, float | bool | None]:
    """``width``: samples the noise is averaged over (odd; a small part of the period, so
    that the averaging leaves a peak's height alone while it takes the noise off it)."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    delta = target - y0
    z = (y - y0) / delta
    # the peaks are read on the response with the noise averaged (σ/√width), and a turning
    # point must clear 8σ of it, so a noisy crest is one peak, not two
    rel_noise = noise / abs(delta)
    zs = smooth(z, width) if rel_noise > 0 and z.size >= 2 * width else z
    over = float(np.max(zs) - 1.0)
    ext = extrema(t, zs - 1.0, max(0.02, 8 * rel_noise))
    peaks = [v for _, v in ext if v > 0]
    decay = peaks[1] / peaks[0] if len(peaks) >= 2 and peaks[0] > 0 else None
    t10, t90 = _crossing(t, z, 0.1), _crossing(t, z, 0.9)
    tol = max(band, 3 * noise / abs(delta))
    outside = np.nonzero(np.abs(z - 1.0) > tol)[0]
    settled = outside.size == 0 or int(outside[-1]) < t.size - 1
    t_settle = None
    if settled:
        t_settle = 0.0 if outside.size == 0 else float(t[int(outside[-1]) + 1] - t0)
    return {
        "overshoot": 100.0 * max(over, 0.0),
        "decay_ratio": decay,
        "rise_time": None if t10 is None or t90 is None else t90 - t10,
        "settling_time": t_settle,
        "iae": _trapz(np.abs(target - y), t),
        "settled": settled,
    }


def load_step(
    t: np.ndarray, y: np.ndarray, t0: float, sp: float, noise: float = 0.0
) -> dict[str, float | bool | None]:
    t, y = np.asarray(t, float), np.asarray(y, float)
    dev = np.abs(y - sp)
    peak = float(dev.max())
    tol = max(0.1 * peak, 3 * noise)
    outside = np.nonzero(dev > tol)[0]
    recovered = outside.size == 0 or int(outside[-1]) < t.size - 1
    rec = None
    if recovered:
        rec = 0.0 if outside.size == 0 else float(t[int(outside[-1]) + 1] - t0)
    return {
        "iae": _trapz(dev, t),
        "max_deviation": peak,
        "recovery_time": rec,
        "recovered": recovered,
    }


def within_band(y: np.ndarray, band: float) -> bool:
    """The record barely moves: its spread is within ``band``."""
    return y.size > 0 and float(np.ptp(y)) <= band and math.isfinite(float(y[-1]))
