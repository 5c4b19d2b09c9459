"""Before and after, side by side: each verification's setpoint and load steps as
deviations from the setpoint it started at, on a time axis from its setpoint step, and the
figures the tuner measured on them (``Verification``) as rows. Pure."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.logger.gain_text import number
from services.logger.run_marks import VerifyWindow
from shared.messages import Verification


@dataclass(frozen=True)
class VerifyTrace:
    label: str  # "before", "after"
    gains: str
    t: np.ndarray  # s since the setpoint step (the window's start where there was none)
    pv: np.ndarray  # PV − sp0, PV units
    sp: np.ndarray  # setpoint − sp0
    op: np.ndarray  # %
    load_t: float | None  # s since the setpoint step
    load: float | None


def verify_traces(
    t: np.ndarray, pv: np.ndarray, sp: np.ndarray, op: np.ndarray, windows: list[VerifyWindow]
) -> list[VerifyTrace]:
    """The samples of each window, shifted to its setpoint step and its starting setpoint."""
    out = []
    for w in windows:
        sel = (t >= w.start) & (t <= w.end)
        if not np.any(sel):
            continue
        t0 = w.step_t if w.step_t is not None else w.start
        base = w.sp0 if w.sp0 is not None else float(sp[sel][0])
        out.append(
            VerifyTrace(
                w.label,
                w.gains,
                t[sel] - t0,
                pv[sel] - base,
                sp[sel] - base,
                op[sel],
                None if w.load_t is None else w.load_t - t0,
                w.load,
            )
        )
    return out


ROWS = (  # (field of Verification, label, unit; "PV" stands for the PV's units)
    ("sp_step", "setpoint step", "PV"),
    ("overshoot", "overshoot", "%"),
    ("decay_ratio", "decay ratio", ""),
    ("ringing", "ringing a period", ""),
    ("unmodelled_ringing", "fast ring a period, no model", ""),
    ("margin_swing", "swing at Kc × 2, of its step", ""),
    ("margin_ringing", "fast ring a period at Kc × 2", ""),
    ("rise_time", "rise time", "s"),
    # within 2 % of the step, or 3σ of the PV's noise where that is wider (measured_response),
    # the band said beside it: on a level's step 8σ tall it is 37.5 % of the step
    ("settling_time", "settling (2 % or 3σ)", "s"),
    ("settling_band", "settling band", "% step"),
    ("iae_sp", "IAE, setpoint", "PV·s"),
    ("load_step", "load step", "%"),
    ("iae_load", "IAE, load", "PV·s"),
    ("max_deviation_load", "max deviation, load", "PV"),
    ("recovery_time", "recovery time, load", "s"),
    ("op_noise", "output noise σ", "%"),
)


def figures_rows(
    before: Verification | None, after: Verification | None, units: str
) -> list[tuple[str, str, str]]:
    """(label with unit, before, after) for each figure either verification has."""
    rows = []
    for name, label, unit in ROWS:
        a, b = (getattr(v, name, None) if v is not None else None for v in (before, after))
        if a is None and b is None:
            continue
        u = unit.replace("PV", units or "PV")
        factor = getattr(after, "margin_factor", None)
        if factor is not None and factor != 2.0:  # under a --ms-bound past 2 (margin_check)
            label = label.replace("Kc × 2", f"Kc × {factor:.3g}")
        rows.append((f"{label} ({u})" if u else label, number(a), number(b)))
    return rows
