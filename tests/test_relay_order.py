"""The relay's two points must agree with a phase that falls with frequency.

A helper's review: e^{−4s}/(20s + 1) with noise σ 1.0, one seed, gave P_u 20.06 s ± 5.3 %, the
exact being 14.88 s. Stage 1 read the plant at 0.333 rad/s, −158° (the plant: −157.8°).
Stage 2 ran at 0.2775 rad/s and read −222°, where the plant has −143°. The "bracket" between
them was built on a point that was not the plant's. Such a pair is now said to contradict
itself, and the spreads are those of stage 1's point alone: they cover the exact figures.
"""

from __future__ import annotations

import cmath
import math

import pytest

from services.autotuner.identify.fourier import FrequencyPoint
from services.autotuner.identify.relay_estimate import order_contradiction, stage_one_spreads
from tests.exact import lag_ultimate


def plant(omega: float) -> complex:
    """e^{−4s}/(20s + 1) at s = jω."""
    s = 1j * omega
    return cmath.exp(-4.0 * s) / (20.0 * s + 1.0)


def point(omega: float, phase_deg: float | None = None) -> FrequencyPoint:
    g = plant(omega)
    if phase_deg is not None:  # as a noisy stage measured it
        g = abs(g) * cmath.exp(1j * math.radians(phase_deg))
    return FrequencyPoint(omega, g)


def test_a_lower_frequency_lagging_more_contradicts_and_widens_the_spreads_to_the_truth():
    one = point(0.333)
    two = point(0.2775, -222.1)
    exact = -math.degrees(math.atan(20.0 * 0.333) + 4.0 * 0.333)  # −157.8°
    assert one.phase_deg == pytest.approx(exact, abs=1e-9)
    lag = order_contradiction(one, two)
    assert lag == pytest.approx(exact - -222.1, abs=1e-9)
    ku_true, pu_true = lag_ultimate(1.0, (20.0,), 4.0)  # 8.50, 14.88 s
    ku, pu = 6.834, 20.06  # what the run printed
    ku_spread, pu_spread = stage_one_spreads(ku, pu, one)
    assert abs(ku_true / ku - 1) <= ku_spread and abs(pu_true / pu - 1) <= pu_spread


def test_points_in_the_plants_own_order_agree():
    """Both stages on the plant itself, either order given, and a small disagreement (under
    ORDER_DEG, the noise's on a good run): no contradiction."""
    one, two = point(0.333), point(0.45)
    assert order_contradiction(one, two) is None and order_contradiction(two, one) is None
    assert order_contradiction(point(0.333), point(0.32, -160.0)) is None
