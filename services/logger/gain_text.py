"""Controller gains as an engineer reads them: Kc with its units (% of output per PV unit),
as % of output per % of span and as the proportional band PB = 100/Kc% (% of span), Ti and
Td in s. Pure text from the result's plain numbers (``shared.control.forms`` does the
arithmetic)."""

from __future__ import annotations

import math

from shared.control.forms import kc_percent, proportional_band, pv_span, unit


def number(value: object, spec: str = ".4g", suffix: str = "") -> str:
    """A recorded number formatted, or "—" where there is none (or not a finite number)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return "—"
    return f"{value:{spec}}{suffix}"


def span_of(pv_range: object) -> float | None:
    """The PV's span (PV units) from a recorded range, None where it is missing or unusable."""
    try:
        lo, hi = pv_range  # type: ignore[misc]
        return pv_span((float(lo), float(hi)))
    except (TypeError, ValueError):
        return None


def kc_forms(kc: object, span: float | None) -> tuple[float | None, float | None]:
    """(Kc in % per % of span, PB in % of span) of a Kc in % per PV unit; Nones without a
    span or a usable Kc."""
    if span is None or isinstance(kc, bool) or not isinstance(kc, int | float):
        return None, None
    pct = kc_percent(float(kc), span)
    return pct, (proportional_band(pct) if pct is not None else None)


def kc_text(kc: object, units: str, span: float | None) -> str:
    """``Kc 6.973 %/degC = 10.46 %/% (PB 9.56 %)``; the % figures only with a span."""
    text = f"Kc {number(kc)} %/{unit(units)}"
    pct, pb = kc_forms(kc, span)
    if pct is not None:
        same = span == 100 and units == "%"  # a PV in % of a 0–100 span: Kc is already %/%
        text += (
            f" (PB {number(pb, '.3g')} %)"
            if same
            else f" = {number(pct)} %/% (PB {number(pb, '.3g')} %)"
        )
    return text


def gains_text(isa: object, units: str, span: float | None) -> str:
    """ISA gains on one line: Kc (units, %/%, PB), Ti (or off), Td."""
    if not isinstance(isa, dict):
        return "—"
    ti = isa.get("ti")
    ti_s = "off" if ti is None else number(ti, ".4g", " s")
    return (
        f"{kc_text(isa.get('kc'), units, span)}  Ti {ti_s}  Td {number(isa.get('td'), '.4g', ' s')}"
    )
