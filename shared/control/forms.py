"""PID gains in the forms controllers use, and conversions between them.

* ideal / ISA (``isa``): u = Kc·(e + (1/Ti)∫e dt + Td·de/dt)
* parallel (``parallel``): u = Kp·e + Ki∫e dt + Kd·de/dt;  Kp = Kc, Ki = Kc/Ti, Kd = Kc·Td
* series / interactive (``series``): u = Kc'·(1 + 1/(Ti'·s))·(1 + Td'·s), the form of the old
  pneumatic controllers that Ziegler and Nichols tuned (seed 001). From series to ISA:
  Kc = Kc'(1 + Td'/Ti'), Ti = Ti' + Td', Td = Ti'Td'/(Ti' + Td'). The inverse exists only when
  Ti ≥ 4·Td (Åström & Hägglund, *Advanced PID Control*, 2006, §3.2).

Integral action may be given as a time (s or min) or as a reset rate in repeats per minute
(= 60/Ti with Ti in s), as seed 001 explains. Ti = None (or inf) means no integral action.

Normalised figures (% of span, seed 001: industrial controllers work on 0–100 % signals). The
output is already in %; the PV is in engineering units over the transmitter's range (lo, hi),
span = hi − lo. Then

* a controller gain (or K_u) in % per PV unit becomes Kc·span/100 in % per % (dimensionless);
* the proportional band is PB = 100/Kc(%/%) in % of span (None for Kc = 0);
* a process gain K in PV units per % becomes K·100/span in % of span per % (an integrating
  process's K' in PV units per s per %: K'·100/span in % of span per s per %);
* Ti and Td are times: unchanged (s).
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


def pv_span(pv_range: tuple[float, float] | None) -> float | None:
    """The span hi − lo of a transmitter range (PV units); None without a range. ValueError
    unless lo < hi and the span is finite (no % of span figure can be had of such a range)."""
    if pv_range is None:
        return None
    lo, hi = pv_range
    span = hi - lo
    if not (math.isfinite(lo) and math.isfinite(hi) and math.isfinite(span) and span > 0):
        raise ValueError(f"pv_range must be two finite numbers lo < hi, got {list(pv_range)}")
    return float(span)


def span_or_none(pv_range: tuple[float, float]) -> float | None:
    """``pv_span``, or None for a range that has none (not two finite numbers lo < hi): no
    figure in % of span then."""
    try:
        return pv_span(pv_range)
    except ValueError:
        return None


# % of output per % of span: a proportional band of 0.1 %, the most any write of gains may ask
# (above it a 0.1 % error drives the output across its range: a slip, not a tuning)
MAX_KC_PERCENT = 1000.0
# % of output per % of span: the least gain a ramp test starts from, a proportional band of
# 100,000 % (below it the loop's output hardly answers the PV, and the ramp, which doubles
# its gain toward the ultimate point, spent a day of sim time from 1e-300: helper trial)
MIN_RAMP_KC_PERCENT = 1e-3
# % of output: the smallest output step a test takes (1e-9 % on a noise-free loop read K
# −26 %/% off the PV's rounding; 1e-300 % left the output where it was and waited past its
# timeout, the loop held: helper review)
MIN_STEP = 0.01


def unit(units: str | None) -> str:
    """A PV's units as a factor of a compound unit: in ( ) where they are a quotient or a
    product themselves ("%/(m3/h)", not "%/m3/h", which reads as % per m3 per hour); "PV
    unit" where none are given."""
    if not units:
        return "PV unit"
    return f"({units})" if any(c in units for c in "/·*") else units


def kc_percent(kc: float | None, span: float) -> float | None:
    """A controller gain or K_u in % per PV unit as % of output per % of span (Kc·span/100)."""
    return None if kc is None else kc * span / 100.0


def kc_over_limit(kc: float, span: float | None) -> str | None:
    """Why a controller gain ``kc`` (% of output per PV unit) is more than any write of gains
    may ask on a PV ``span`` wide (above ``MAX_KC_PERCENT`` % of output per % of span), else
    None (None also without a span: no % of span to judge by). `autotune set` and `apply`
    refuse such a gain, and so does a tune: its rules gave TL PI 4,700 %/% (a proportional
    band of 0.02 %) on e^{−0.02s}/(200s + 1) at 0.01 s, and a noise-free loop passed it."""
    pct = kc_percent(kc, span) if span else None
    if pct is None or not pct > MAX_KC_PERCENT:
        return None
    return (
        f"Kc {kc:.4g} is {pct:.4g} % of output per % of span (a proportional band of "
        f"{100.0 / pct:.2g} %), above the {MAX_KC_PERCENT:g} % per % any write of gains may ask "
        "(a 0.1 % error would drive the output across its range)"
    )


def kc_problem(kc: float, span: float) -> str | None:
    """Why a controller gain ``kc`` (% of output per PV unit) is no control at all on a PV
    ``span`` wide, else None: Kc 0, in ideal (ISA) form the factor of every term, so that a
    loop in auto holds its output whatever the PV does (an operator's slip, not a tuning), or
    a gain so small that its proportional band (100/Kc % of span) is not a number."""
    if not kc > 0:
        return (
            "no control at all: in ideal form Kc multiplies every term, and a loop in auto "
            "would hold its output whatever the PV does (Kc must be > 0 % of output per PV unit)"
        )
    pct = kc * span / 100.0
    if pct == 0.0 or not math.isfinite(100.0 / pct):
        return (
            f"{pct:g} % of output per % of span, a proportional band too wide to be a number: "
            "no control at all"
        )
    return None


def process_gain_percent(k: float | None, span: float) -> float | None:
    """A process gain in PV units per % (or PV units per s per %: K', R) as % of span per %
    (or % of span per s per %): K·100/span."""
    return None if k is None else k * 100.0 / span


def proportional_band(kc_pct: float) -> float | None:
    """PB = 100/Kc in % of span, Kc in % per %; None for Kc = 0 (no proportional action)."""
    return None if kc_pct <= 0 else 100.0 / kc_pct


@dataclass(frozen=True)
class PercentGains:
    """ISA gains on normalised signals: Kc in % of output per % of span, PB = 100/Kc in % of
    span (None for Kc = 0), Ti and Td in s as in engineering units (Ti None: no integral)."""

    kc: float
    ti: float | None
    td: float
    pb: float | None

    def to_dict(self) -> dict[str, float | None]:
        """The result's ``isa_percent`` object."""
        return {"kc": self.kc, "ti": self.ti, "td": self.td, "pb": self.pb}


def to_percent(g: IsaGains, span: float) -> PercentGains:
    """``g`` (Kc in % per PV unit) on a PV of ``span`` PV units, normalised."""
    kc = g.kc * span / 100.0
    return PercentGains(kc, g.ti, g.td, proportional_band(kc))


# the reaction curve's figures (the result's ``step`` keys) that scale with 1/span, and their
# units once normalised; the other keys (times, sizes in %, the PV's own levels) do not
STEP_PERCENT = {
    "gain": "% of span per %",
    "reaction_rate": "% of span per s per %",
    "a": "% of span per %",
}


def step_percent(step: dict[str, Any] | None, span: float) -> dict[str, float | None] | None:
    """The result's ``step_percent`` object: the reaction curve's process gains (K, R, a = R·L;
    an integrating curve's R = K' and a) as % of span (STEP_PERCENT); None without a step."""
    if step is None:
        return None
    return {k: process_gain_percent(step[k], span) for k in STEP_PERCENT if step.get(k) is not None}


@dataclass(frozen=True)
class GainForms:
    """One set of gains in every form a controller may take (``all_forms``): ISA, parallel,
    series (None where Ti < 4·Td: it has none), and the ISA times in minutes and the reset
    rate, as controllers' faceplates show them; given the PV's span, the ISA gains also in %
    of span (``isa_percent``)."""

    isa: IsaGains
    parallel: ParallelGains
    series: SeriesGains | None
    ti_min: float | None  # Ti in min (None: no integral action)
    td_min: float  # Td in min
    reset_rate_rpm: float  # repeats per minute (0: no integral action)
    isa_percent: PercentGains | None = None  # None: the PV's span was not given

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, the result's ``gains``/``chosen`` object (None where a form lacks;
        ``isa_percent`` only where the span was given)."""
        isa, par, ser = self.isa, self.parallel, self.series
        out: dict[str, Any] = {
            "isa": {"kc": isa.kc, "ti": isa.ti, "td": isa.td},
            "parallel": {"kp": par.kp, "ki": par.ki, "kd": par.kd},
            "series": None if ser is None else {"kc": ser.kc, "ti": ser.ti, "td": ser.td},
            "ti_min": self.ti_min,
            "td_min": self.td_min,
            "reset_rate_rpm": self.reset_rate_rpm,
        }
        if self.isa_percent is not None:
            out["isa_percent"] = self.isa_percent.to_dict()
        return out


def all_forms(g: IsaGains, span: float | None = None) -> GainForms:
    """The gains ``g`` in every form; with the PV's ``span`` (PV units), in % of span too."""
    return GainForms(
        isa=g,
        parallel=to_parallel(g),
        series=to_series(g),
        ti_min=None if g.ti is None else g.ti / 60.0,
        td_min=g.td / 60.0,
        reset_rate_rpm=reset_rate(g.ti),
        isa_percent=None if span is None else to_percent(g, span),
    )
