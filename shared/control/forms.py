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
from typing import Any


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


@dataclass(frozen=True)
class GainForms:
    """One set of gains in every form a controller may take (``all_forms``): ISA, parallel,
    series (None where Ti < 4·Td: it has none), and the ISA times in minutes and the reset
    rate, as controllers' faceplates show them."""

    isa: IsaGains
    parallel: ParallelGains
    series: SeriesGains | None
    ti_min: float | None  # Ti in min (None: no integral action)
    td_min: float  # Td in min
    reset_rate_rpm: float  # repeats per minute (0: no integral action)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, the result's ``gains``/``chosen`` object (None where a form lacks)."""
        isa, par, ser = self.isa, self.parallel, self.series
        return {
            "isa": {"kc": isa.kc, "ti": isa.ti, "td": isa.td},
            "parallel": {"kp": par.kp, "ki": par.ki, "kd": par.kd},
            "series": None if ser is None else {"kc": ser.kc, "ti": ser.ti, "td": ser.td},
            "ti_min": self.ti_min,
            "td_min": self.td_min,
            "reset_rate_rpm": self.reset_rate_rpm,
        }


def all_forms(g: IsaGains) -> GainForms:
    """The gains ``g`` in every form."""
    return GainForms(
        isa=g,
        parallel=to_parallel(g),
        series=to_series(g),
        ti_min=None if g.ti is None else g.ti / 60.0,
        td_min=g.td / 60.0,
        reset_rate_rpm=reset_rate(g.ti),
    )
