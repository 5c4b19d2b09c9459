"""Many PID blocks executed at once, as arrays: each element exactly as ``PidBlock`` does it.

The same floating-point operations in the same order as ``pid.PidBlock`` (its module has the
equations), elementwise over numpy arrays, so every element equals a ``PidBlock``'s value to the
bit: numpy's elementwise ``*``, ``+``, ``/`` and ``minimum``/``maximum`` round as Python's float
operations do. Used where many loops step together — the plant's linear batch
(``services/plant_sim/simulation/linear_batch.py``) and the design's predicted setpoint steps
(``setpoint_steps``) — so neither holds a second copy of the block's arithmetic.

Units as ``PidBlock``: gains Kc % per PV unit, times in s, outputs and terms in % of output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PidGainArrays:
    """The blocks' settings, one element per block: ``sign`` +1 reverse, −1 direct; ``ti``
    any positive number where ``integral`` is False (no integral action); ``tf`` = Td/N (s);
    ``lo``, ``hi`` the output limits (%)."""

    sign: np.ndarray
    kc: np.ndarray
    ti: np.ndarray
    td: np.ndarray
    tf: np.ndarray
    beta: np.ndarray
    integral: np.ndarray  # bool
    lo: np.ndarray
    hi: np.ndarray
    sample_time: float  # s, shared by every block


@dataclass(frozen=True)
class Coefficients:
    """The products of settings that every execution uses, each formed as ``PidBlock`` forms
    it (so the same value to the bit): computed once where the settings stay fixed."""

    rate_keep: np.ndarray  # Tf/(Tf + T)
    rate_span: np.ndarray  # Tf + T, s
    p_gain: np.ndarray  # s·Kc
    d_gain: np.ndarray  # −s·Kc·Td
    i_gain: np.ndarray  # s·Kc·T/Ti


def coefficients(g: PidGainArrays) -> Coefficients:
    """The execution's products of ``g``'s settings, as they are now."""
    t = g.sample_time
    return Coefficients(
        g.tf / (g.tf + t), g.tf + t, g.sign * g.kc, -g.sign * g.kc * g.td, g.sign * g.kc * t / g.ti
    )


def filtered_rate(
    g: PidGainArrays,
    dpv: np.ndarray,
    pv: np.ndarray,
    pv_prev: np.ndarray,
    has_prev: np.ndarray,
    k: Coefficients | None = None,
) -> np.ndarray:
    """The filtered dPV/dt after this sample (PV units/s): 0 for a block's first sample;
    ``k``: ``coefficients(g)`` if already at hand."""
    k = k or coefficients(g)
    rate = k.rate_keep * dpv + (pv - pv_prev) / k.rate_span
    return np.where(has_prev, rate, 0.0)


@dataclass(frozen=True)
class Execution:
    """One execution's result per block: the output to hold (%), its P and D terms, and the
    integral term for the next sample (held where the block would wind up, or integrates not)."""

    op: np.ndarray
    p: np.ndarray
    d: np.ndarray
    i_next: np.ndarray


def execute(
    g: PidGainArrays,
    sp: np.ndarray,
    pv: np.ndarray,
    i: np.ndarray,
    dpv: np.ndarray,
    k: Coefficients | None = None,
) -> Execution:
    """``PidBlock.update`` for every block: ``dpv`` already filtered with this sample's PV;
    ``k``: ``coefficients(g)`` if already at hand."""
    k = k or coefficients(g)
    p = k.p_gain * (g.beta * sp - pv)
    d = k.d_gain * dpv
    v = p + i + d
    u = np.minimum(np.maximum(v, g.lo), g.hi)
    step = k.i_gain * (sp - pv)
    winding = ((v >= g.hi) & (step > 0)) | ((v <= g.lo) & (step < 0))
    i_next = i + step
    off = k.p_gain * (g.beta - 1.0) * sp  # P at zero error: I's bounds are the limits less it
    hi, lo = g.hi - off, g.lo - off
    i_next = np.where((step > 0) & (i_next > hi), np.maximum(i, hi), i_next)
    i_next = np.where((step < 0) & (i_next < lo), np.minimum(i, lo), i_next)
    return Execution(u, p, d, np.where(g.integral & ~winding, i_next, i))
