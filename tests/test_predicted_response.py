"""The closed-loop prediction against closed forms: a PI controller on a first-order plant
closes a second-order loop with a zero, whose step response is known exactly.

K/(τs+1) with Kc(1 + 1/(Ti s)): T(s) = ω_n²(1 + s/z)/(s² + 2σs + ω_n²), ω_n² = KcK/(Ti τ),
2σ = (1 + KcK)/τ, z = 1/Ti. Its step response is y_std + y_std'/z (y_std the standard
second-order one), so y − 1 = −A·e^{−σt}·cos(ω_d t − ψ): the maxima come every 2π/ω_d and the
decay ratio is e^{−2πσ/ω_d}; the first peak is where tan(ω_d t) = −ω_d/(z − σ).
"""

from __future__ import annotations

import math

import pytest

from services.autotuner.design.predicted_response import predicted_setpoint_step
from shared.control.forms import IsaGains
from shared.control.transfer import DelayedTF
from tests.exact import ultimate_point

K, TAU = 2.0, 10.0


def pi_on_first_order(kc: float, ti: float) -> tuple[float, float]:
    """(overshoot %, decay ratio) of the continuous loop, in closed form."""
    wn2 = kc * K / (ti * TAU)
    sigma = (1 + kc * K) / (2 * TAU)
    wd = math.sqrt(wn2 - sigma**2)
    z = 1 / ti
    tp = (math.pi - math.atan(wd / (z - sigma))) / wd
    y_std = 1 - math.exp(-sigma * tp) * (math.cos(wd * tp) + sigma / wd * math.sin(wd * tp))
    dy_std = wn2 / wd * math.exp(-sigma * tp) * math.sin(wd * tp)
    return 100 * (y_std + dy_std / z - 1), math.exp(-2 * math.pi * sigma / wd)


@pytest.mark.parametrize(("kc", "ti"), [(2.0, 0.5), (1.0, 1.0)])
def test_pi_on_a_first_order_plant_is_the_second_order_closed_form(kc, ti):
    """Kc = 2, Ti = 0.5: ζ ≈ 0.28, overshoot ≈ 50 %; Kc = 1, Ti = 1: ζ ≈ 0.34. Simulated at
    1500 samples per period, the sampled loop is the continuous one within 1 %."""
    overshoot, decay = pi_on_first_order(kc, ti)
    wd = math.sqrt(kc * K / (ti * TAU) - ((1 + kc * K) / (2 * TAU)) ** 2)
    period = 2 * math.pi / wd
    f = predicted_setpoint_step(
        IsaGains(kc, ti),
        DelayedTF.of([K], [TAU, 1.0]),
        period,
        sample_time=period / 1500,
        horizon=10.0,
        max_samples=20_000,
    )
    assert f.stable is True
    assert f.overshoot == pytest.approx(overshoot, rel=0.01)
    assert f.decay_ratio == pytest.approx(decay, rel=0.02)


def test_p_control_offset_is_not_overshoot():
    """Kc·K/(τs + 1 + Kc·K) is first order: it settles at KcK/(1 + KcK) < 1 without passing
    it, so overshoot and decay ratio are 0 although the setpoint is never reached."""
    f = predicted_setpoint_step(IsaGains(2.0), DelayedTF.of([K], [TAU, 1.0]), TAU / 5)
    assert f.overshoot == pytest.approx(0.0, abs=1e-9) and (f.decay_ratio, f.stable) == (0.0, True)


def test_a_gain_beyond_the_ultimate_one_is_unstable():
    """e^{−s}/(5s+1) under P control at twice its K_u (tests.exact): the oscillation grows
    until the 0–100 % output limits hold it, and is called unstable, its crests then
    sustained (a decay ratio of 1 to within 1 %)."""
    ku, pu = ultimate_point([1.0], [5.0, 1.0], 1.0)
    f = predicted_setpoint_step(IsaGains(2 * ku), DelayedTF.of([1.0], [5.0, 1.0], 1.0), pu)
    assert f.stable is False and f.decay_ratio == pytest.approx(1.0, abs=0.01)
