"""A loop's figures over a window of normal operation, read off its samples.

Arrays of one window: sample times t (s), setpoint sp and PV pv (PV units), output op (% of
output), and ``auto`` (the loop was in auto at that sample). Only samples in auto count: a
loop in manual is not being controlled. The control error is e = sp − pv.

- ``iae_rate``: IAE per unit time, (1/T)·∫|e| dt = the mean |e|, PV units;
- ``error_mean``, ``error_std``: the error's mean and standard deviation about it, PV units;
- ``saturation``: % of the time the output sat at one of its limits;
- ``travel``: Σ|Δop| over the window, % of output, and ``travel_rate`` per hour of auto;
- ``reversals``: the output's changes of direction beyond ``deadband`` % of output, and per
  hour, read on the output averaged over ``smoothing`` samples (the caller's: a quarter of
  T_u): a zigzag, a turning point counting once the averaged output has come back
  ``deadband`` from it. White noise of σ on the output is σ/√smoothing after the average, and
  the deadband is at least REVERSAL_NOISE_SIGMAS times that: over a long window the noise's
  own extremes reach ±4σ or so, so a deadband of a few σ would count noise;
- ``op_noise``: σ(Δop)/√2, the output's white-noise σ (% of output): what the tune's
  verification measured at rest with its gains; ``pv_noise`` likewise for the PV.
"""

from __future__ import annotations

import math

import numpy as np

from shared.control.signals import extrema, smooth

REVERSAL_DEADBAND = 0.5  # % of output: the least swing of the output counted as a reversal
REVERSAL_NOISE_SIGMAS = 10.0  # … and this many σ of the averaged output's white noise


# σ of a normal variable over its median absolute deviation
MAD_SIGMA = 1.482602218505602


def white_noise(y: np.ndarray) -> float:
    """σ(Δy)/√2 (``y``'s units): the white noise on ``y``, a trend or a slow swing hardly
    counted; σ(Δy) read from the median absolute deviation of Δy, so that the few large
    changes of a setpoint change and its settling are not taken for noise (a flow loop's
    step of 2 after a cancelled test read as noise σ 0.624 against 0.182 at its tune, and
    the loop was flagged degraded: helper trial); 0 for fewer than 3 samples."""
    return white_noise_of(np.diff(y)) if y.size > 2 else 0.0


def white_noise_of(d: np.ndarray) -> float:
    """``white_noise`` from the sample-to-sample changes ``d`` themselves; their standard
    deviation where most of them are nil (a quantised PV, an output held: the median
    absolute deviation is 0 there whatever the rest do, review)."""
    mad = float(MAD_SIGMA * np.median(np.abs(d - np.median(d))))
    return (mad if mad > 0 else float(np.std(d))) / math.sqrt(2.0)


def performance(
    t: np.ndarray,
    sp: np.ndarray,
    pv: np.ndarray,
    op: np.ndarray,
    auto: np.ndarray,
    op_limits: tuple[float, float],
    smoothing: int = 1,
) -> dict[str, float | int | None]:
    """The window's figures (see the module); those that need samples in auto are None
    without two of them. ``smoothing``: samples the output is averaged over for reversals."""
    t, sp, pv, op = (np.asarray(x, float) for x in (t, sp, pv, op))
    auto = np.asarray(auto, bool)
    n, m = int(t.size), int(np.count_nonzero(auto))
    out: dict[str, float | int | None] = {
        "samples": n,
        "auto_fraction": m / n if n else 0.0,
        "duration": float(t[-1] - t[0]) if n > 1 else 0.0,
    }
    keys = (
        "iae_rate", "error_mean", "error_std", "saturation", "travel",
        "travel_rate", "reversals", "reversal_rate", "reversal_deadband", "op_noise", "pv_noise",
    )  # fmt: skip
    out.update(dict.fromkeys(keys))
    if m < 2:
        return out
    dt = float(np.median(np.diff(t))) if n > 1 else 0.0
    e = (sp - pv)[auto]
    u = op[auto]
    hours = m * dt / 3600.0
    lo, hi = op_limits
    # consecutive samples both in auto: the output's moves the controller made
    pair = auto[1:] & auto[:-1]
    moves = np.abs(np.diff(op))[pair]
    op_noise = white_noise_of(np.diff(op)[pair]) if moves.size > 1 else 0.0
    width = max(1, smoothing) | 1
    deadband = max(REVERSAL_DEADBAND, REVERSAL_NOISE_SIGMAS * op_noise / math.sqrt(width))
    reversals = 0
    for run in _runs(auto):
        reversals += len(extrema(t[run], smooth(op[run], width), deadband))
    out.update(
        iae_rate=float(np.mean(np.abs(e))),
        error_mean=float(np.mean(e)),
        error_std=float(np.std(e)),
        saturation=100.0 * float(np.mean((u <= lo) | (u >= hi))),
        travel=float(np.sum(moves)),
        travel_rate=float(np.sum(moves)) / hours if hours > 0 else None,
        reversals=reversals,
        reversal_rate=reversals / hours if hours > 0 else None,
        reversal_deadband=deadband,
        op_noise=op_noise,
        pv_noise=white_noise(pv[auto]),
    )
    return out


def _runs(mask: np.ndarray) -> list[slice]:
    """The stretches of consecutive True in ``mask``, as slices."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    return [slice(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]
