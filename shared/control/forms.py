"""PID gains in the forms controllers use, and conversions between them.

* ideal / ISA (``isa``): u = Kc·(e + (1/Ti)∫e dt + Td·de/dt)
* parallel (``parallel``): u = Kp·e + Ki∫e dt + Kd·de/dt;  Kp = Kc, Ki = Kc/Ti, Kd = Kc·Td
* series / interactive (``series``): u = Kc'·(1 + 1/(Ti'·s))·(1 + Td'·s), the form of the old
  pneumatic controllers that Ziegler and Nichols tuned (seed 001). From series to ISA:
  Kc = Kc'(1 + Td'/Ti'), Ti = Ti' + Td', Td = Ti'Td'/(Ti' + Td'). The inverse exists only when
  Ti ≥ 4·Td (Åström & Hägglund, *Advanced PID Control*, 2006, §3.2).

Integral action may be given as a time (s or min) or as a reset rate in repeats per minute
(= 60/Ti with Ti in s), as seed 001 explains. Ti = None (or inf) means no integral action.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class IsaGains:
    """Ideal (ISA) form: Kc in % per PV unit, Ti and Td in s (Ti None: no integral)."""

    kc: float
    ti: float | None = None
    td: float = 0.0

    def __post_init__(self) -> None:
        if not math.isfinite(self.kc) or self.kc < 0:
            raise ValueError(f"kc must be a finite number ≥ 0, got {self.kc}")
        if self.ti is not None and not (self.ti > 0):
            raise ValueError(f"ti must be > 0 s or None, got {self.ti}")
        if not (math.isfinite(self.td) and self.td >= 0):
            raise ValueError(f"td must be a finite number ≥ 0 s, got {self.td}")


@dataclass(frozen=True)
class ParallelGains:
    kp: float
    ki: float  # % per PV unit per s
    kd: float  # % per PV unit · s


@dataclass(frozen=True)
class SeriesGains:
    kc: float
    ti: float | None
    td: float


def to_parallel(g: IsaGains) -> ParallelGains:
    return ParallelGains(g.kc, 0.0 if g.ti is None else g.kc / g.ti, g.kc * g.td)


def from_parallel(p: ParallelGains) -> IsaGains:
    if p.kp <= 0:
        raise ValueError("kp must be > 0 to express the gains in ISA form")
    return IsaGains(p.kp, None if p.ki == 0 else p.kp / p.ki, p.kd / p.kp)


def to_series(g: IsaGains) -> SeriesGains | None:
    """The series form, or None when Ti < 4·Td (no real series equivalent)."""
    if g.ti is None or g.td == 0:  # P, PI, PD: the forms coincide
        return SeriesGains(g.kc, g.ti, g.td)
    disc = 1.0 - 4.0 * g.td / g.ti
    if disc < 0:
        return None
    root = math.sqrt(disc)
    return SeriesGains(g.kc / 2 * (1 + root), g.ti / 2 * (1 + root), g.ti / 2 * (1 - root))


def from_series(s: SeriesGains) -> IsaGains:
    if s.ti is None:
        return IsaGains(s.kc, None, s.td)
    return IsaGains(s.kc * (1 + s.td / s.ti), s.ti + s.td, s.ti * s.td / (s.ti + s.td))


def reset_rate(ti_seconds: float | None) -> float:
    """Repeats per minute for an integral time in seconds (0 for no integral action)."""
    return 0.0 if ti_seconds is None else 60.0 / ti_seconds


def integral_time_from_reset_rate(repeats_per_minute: float) -> float | None:
    return None if repeats_per_minute == 0 else 60.0 / repeats_per_minute


def all_forms(g: IsaGains) -> dict:
    """The gains in every form, JSON-ready (None where a form does not exist)."""
    par = to_parallel(g)
    ser = to_series(g)
    return {
        "isa": {"kc": g.kc, "ti": g.ti, "td": g.td},
        "parallel": {"kp": par.kp, "ki": par.ki, "kd": par.kd},
        "series": None if ser is None else {"kc": ser.kc, "ti": ser.ti, "td": ser.td},
        "ti_min": None if g.ti is None else g.ti / 60.0,
        "td_min": g.td / 60.0,
        "reset_rate_rpm": reset_rate(g.ti),
    }
