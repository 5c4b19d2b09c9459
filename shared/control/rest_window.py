"""How long the tuner watches a loop for rest before a test, and what rest allows: the window
and the resolution are the tuner's check's (``services.autotuner.identify.rest``), and
``autotune model check`` uses them with ``rest_allowance`` (3σ, at least the resolution, as
that check judges a straight-line trend) to say beforehand whether a model that drifts at
op0 will ever let a tune start.

The window is at least ``MIN_SAMPLES`` samples and at least the loop's integral time (a tuned
loop's Ti is of the order of its process lag), capped at ``MAX_WINDOW`` s. A straight-line
trend over it within 3σ of the noise, or within ``RESOLUTION`` of the PV's span (what no
transmitter resolves), is rest.
"""

from __future__ import annotations

import math

MIN_SAMPLES = 40
MAX_WINDOW = 900.0  # s: the longest window watched (a slow level loop's Ti can be hours)
# of the PV's span: a move within it is no move (a 17-bit converter's step; a test's swing is
# 1–10 % of span, 1,000 times more)
RESOLUTION = 1e-5


def rest_window(sample_time: float, ti: float | None, requested: float | None = None) -> float:
    """Seconds of PV to watch for a drift: ``requested`` (at least ``MIN_SAMPLES`` samples),
    else the loop's integral time ``ti`` within [``MIN_SAMPLES`` samples, ``MAX_WINDOW``]."""
    if requested is not None:
        return max(requested, MIN_SAMPLES * sample_time)
    slow = ti if ti is not None and math.isfinite(ti) else 0.0
    return max(MIN_SAMPLES * sample_time, min(slow, MAX_WINDOW))


def rest_allowance(noise_std: float, span: float) -> float:
    """PV units a window's trend may move and still be rest: 3σ of the noise, and at least
    ``RESOLUTION`` of the span."""
    return max(3.0 * noise_std, RESOLUTION * span if math.isfinite(span) else 0.0)
