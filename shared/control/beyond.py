"""A PV that left its limits, printed so that it reads outside them."""

from __future__ import annotations


def beyond(pv: float, lo: float, hi: float, digits: int = 4) -> str:
    """``pv`` to ``digits`` significant digits, more where that many would print it on or
    inside the limits it left (59.7953 below [59.8, 60.2] read "PV 59.8 left its limits"),
    as the limits are printed beside it too (``:g``)."""
    shown = (float(f"{lo:g}"), float(f"{hi:g}"))
    for n in range(digits, 17):
        text = f"{pv:.{n}g}"
        if not lo <= float(text) <= hi and not shown[0] <= float(text) <= shown[1]:
            return text
    return repr(pv)
