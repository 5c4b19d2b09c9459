"""The exact-answer oracle (tests/exact.py) against closed forms derived here by hand.

Every figure below comes from the Routh criterion or from the phase condition written as a sum of
arctangents, never from a run of the code under test. The oracle is what the other tests measure
the relay, the ramp and the model fits against, so it is held to 1e-9.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from tests.exact import lag_ultimate, magnitude, phase, sopdt_tangent, ultimate_point

TOL = 1e-9


def close(a: float, b: float, tol: float = TOL) -> bool:
    return abs(a - b) <= tol * max(1.0, abs(b))


def test_third_order_lag_routh():
    """1/(s+1)³: 3·atan(ω) = π gives ω_u = tan(π/3) = √3, K_u = (1+3)^{3/2} = 8."""
    ku, pu = ultimate_point([1.0], [1, 3, 3, 1])
    assert close(ku, 8.0) and close(pu, 2 * math.pi / math.sqrt(3))


def test_three_distinct_lags_routh():
    """6/((s+1)(s+2)(s+3)): s³+6s²+11s+6(1+K) is marginal at 6·11 = 6(1+K): K_u = 10,
    ω_u² = 11."""
    ku, pu = ultimate_point([6.0], [1, 6, 11, 6])
    assert close(ku, 10.0) and close(pu, 2 * math.pi / math.sqrt(11))


def test_integrator_with_two_lags_routh():
    """1/(s(s+1)(s+2)): s³+3s²+2s+K is marginal at 3·2 = K: K_u = 6, ω_u² = 2 (a pole at the
    origin contributes −π/2 at every frequency)."""
    ku, pu = ultimate_point([1.0], [1, 3, 2, 0])
    assert close(ku, 6.0) and close(pu, 2 * math.pi / math.sqrt(2))


def test_right_half_plane_zero_routh():
    """(1−s)/(s+1)²: s²+(2−K)s+1+K is marginal at K_u = 2, ω_u² = 1+K_u = 3."""
    ku, pu = ultimate_point([-1.0, 1.0], [1, 2, 1])
    assert close(ku, 2.0) and close(pu, 2 * math.pi / math.sqrt(3))


def test_eighth_order_lag_keeps_every_branch():
    """1/(s+1)⁸: 8·atan(ω) = π gives ω_u = tan(π/8), K_u = (1+ω_u²)⁴ = sec⁸(π/8); past it the
    phase runs on towards −4π without wrapping."""
    ku, pu = ultimate_point([1.0], [1, 8, 28, 56, 70, 56, 28, 8, 1])
    wu = math.tan(math.pi / 8)
    assert close(ku, math.cos(math.pi / 8) ** -8) and close(pu, 2 * math.pi / wu)
    assert close(phase([1.0], [1, 8, 28, 56, 70, 56, 28, 8, 1], 0.0, 1e3), -8 * math.atan(1e3))


@pytest.mark.parametrize(
    ("gain", "tau", "delay"), [(1.0, 3.0, 1.0), (2.5, 10.0, 0.5), (0.4, 1.0, 4.0)]
)
def test_first_order_plus_dead_time(gain, tau, delay):
    """K·e^{−Ls}/(Ts+1): atan(ωT) + ωL = π, solved here on (0, π/L) where it changes sign;
    K_u = √(1+(ω_u T)²)/K."""
    wu = brentq(lambda w: math.atan(w * tau) + w * delay - math.pi, 1e-12, math.pi / delay)
    ku, pu = ultimate_point([gain], [tau, 1.0], delay)
    assert close(pu, 2 * math.pi / wu) and close(ku, math.hypot(1.0, wu * tau) / gain)


def test_heat_exchanger_second_order_plus_dead_time():
    """e^{−5s}/((10s+1)(60s+1)): atan(10ω) + atan(60ω) + 5ω = π; K_u = |10jω+1|·|60jω+1|."""
    wu = brentq(lambda w: math.atan(10 * w) + math.atan(60 * w) + 5 * w - math.pi, 1e-9, 1.0)
    ku, pu = ultimate_point([1.0], [600.0, 70.0, 1.0], 5.0)
    assert close(pu, 2 * math.pi / wu)
    assert close(ku, math.hypot(1, 10 * wu) * math.hypot(1, 60 * wu))


def test_lead_lag_with_a_left_half_plane_zero():
    """(0.5s+1)/(s+1)⁴: atan(ω/2) − 4·atan(ω) = −π; K_u = (1+ω_u²)²/√(1+ω_u²/4)."""
    wu = brentq(lambda w: math.atan(w / 2) - 4 * math.atan(w) + math.pi, 0.1, 10.0)
    ku, pu = ultimate_point([0.5, 1.0], [1, 4, 6, 4, 1])
    assert close(pu, 2 * math.pi / wu) and close(ku, (1 + wu**2) ** 2 / math.sqrt(1 + wu**2 / 4))


@pytest.mark.parametrize("w", [0.01, 0.3, 1.0, 7.0])
def test_phase_and_magnitude_of_a_first_order_lag_with_delay(w):
    """2e^{−1.5s}/(4s+1): phase −atan(4ω) − 1.5ω; magnitude 2/√(1+16ω²) (the delay has none)."""
    assert close(phase([2.0], [4.0, 1.0], 1.5, w), -math.atan(4 * w) - 1.5 * w)
    assert close(magnitude([2.0], [4.0, 1.0], 1.5, w), 2.0 / math.hypot(1.0, 4 * w))


def test_a_negative_gain_adds_minus_pi():
    """−1/(s+1) is 1/(s+1) with the sign inverted: its phase is −π − atan(ω), not +π − atan(ω)."""
    assert close(phase([-1.0], [1.0, 1.0], 0.0, 1.0), -math.pi - math.pi / 4)
    assert close(magnitude([-1.0], [1.0, 1.0], 0.0, 1.0), 1 / math.sqrt(2))


@pytest.mark.parametrize(
    ("gain", "lags", "delay"),
    [(1.0, (60.0, 10.0), 5.0), (2.0, (5.0,), 1.0), (0.5, (4.0, 2.0, 1.0), 0.3)],
)
def test_lag_ultimate_agrees_with_the_polynomial_oracle(gain, lags, delay):
    """Two derivations of one answer: Σ atan(τω) + Lω = π, and the roots of the expanded
    denominator unwrapped."""
    den = np.poly1d([1.0])
    for tau in lags:
        den *= np.poly1d([tau, 1.0])
    ku, pu = lag_ultimate(gain, lags, delay)
    ku_o, pu_o = ultimate_point([gain], den.coeffs, delay)
    assert close(ku, ku_o, 1e-8) and close(pu, pu_o, 1e-8)


def test_lag_ultimate_of_an_integrator_with_dead_time():
    """0.5·e^{−2s}/s: −π/2 − 2ω = −π at ω_u = π/4; K_u = ω_u/0.5; the oracle agrees."""
    ku, pu = lag_ultimate(0.5, (), 2.0)
    assert close(ku, math.pi / 2) and close(pu, 8.0)
    ku_o, pu_o = ultimate_point([0.5], [1.0, 0.0], 2.0)
    assert close(ku_o, ku) and close(pu_o, pu)


def test_sopdt_tangent_against_a_numerical_tangent():
    """The inflection tangent of e^{−5s}/((60s+1)(10s+1)), found on a fine grid of the step
    response y(t) = 1 − (60e^{−t/60} − 10e^{−t/10})/50 (t after the delay)."""
    t = np.linspace(0.0, 100.0, 1_000_001)
    y = 1 - (60 * np.exp(-t / 60) - 10 * np.exp(-t / 10)) / 50
    dy = np.gradient(y, t)
    i = int(np.argmax(dy))
    lag, rate = sopdt_tangent(1.0, 60.0, 10.0, 5.0)
    assert rate == pytest.approx(dy[i], rel=1e-8)
    assert lag == pytest.approx(5.0 + t[i] - y[i] / dy[i], rel=1e-6)
