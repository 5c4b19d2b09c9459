"""Ms, gain and phase margins against closed forms."""

import math

import pytest

from services.autotuner.design.robustness import robustness
from shared.control.forms import IsaGains
from shared.control.transfer import DelayedTF
from tests.exact import ultimate_point

THIRD = ([6.0], [1.0, 6.0, 11.0, 6.0], 0.0)
HX = ([1.0], [600.0, 70.0, 1.0], 5.0)


@pytest.mark.parametrize("plant", [THIRD, HX], ids=["third-order", "heat-exchanger"])
@pytest.mark.parametrize("fraction", [0.25, 0.5, 0.8])
def test_gain_margin_of_p_control_is_ku_over_kc(plant, fraction):
    ku, pu = ultimate_point(*plant)
    r = robustness(IsaGains(fraction * ku), DelayedTF.of(*plant))
    assert r.gain_margin == pytest.approx(1 / fraction, rel=1e-6)
    assert 2 * math.pi / r.omega_180 == pytest.approx(pu, rel=1e-6)


def test_integrator_with_p_control():
    """L = k/s: crossover at ω = k with 90° of phase margin, Ms = 1, no phase crossover."""
    r = robustness(IsaGains(3.0), DelayedTF.of([1.0], [1.0, 0.0]))
    assert r.omega_c == pytest.approx(3.0, rel=1e-6)
    assert r.phase_margin_deg == pytest.approx(90.0, abs=1e-6)
    assert r.ms == pytest.approx(1.0, abs=1e-3) and r.gain_margin == math.inf


def test_first_order_with_p_control_ms_closed_form():
    """L = k/(s+1): 1/|1+L| = |jω+1|/|jω+1+k| rises to 1 at high frequency (Ms → 1), and
    the phase margin is 180° − atan(√(k²−1)) at ω_c = √(k²−1)."""
    k = 4.0
    r = robustness(IsaGains(k), DelayedTF.of([1.0], [1.0, 1.0]))
    assert r.omega_c == pytest.approx(math.sqrt(k * k - 1), rel=1e-6)
    assert r.phase_margin_deg == pytest.approx(
        180 - math.degrees(math.atan(math.sqrt(15))), abs=1e-4
    )
    assert r.ms == pytest.approx(1.0, abs=1e-3)


def test_zn_pid_is_less_robust_than_tyreus_luyben():
    """control-references.md: ZN-PID Ms 2.6–3.2 on lag-dominated plants, TL-PID lower."""
    ku, pu = ultimate_point(*HX)
    zn = robustness(IsaGains(0.6 * ku, pu / 2, pu / 8), DelayedTF.of(*HX))
    tl = robustness(IsaGains(ku / 2.2, 2.2 * pu, pu / 6.3), DelayedTF.of(*HX))
    assert zn.ms > tl.ms > 1.0 and zn.ms > 2.0


def test_the_sampled_loop_tends_to_the_continuous_one_with_a_pid():
    """The PID block's backward-difference derivative, forward-Euler integral and the hold
    all converge as T → 0: at 10,000 samples per period the figures agree within 0.1 %."""
    from services.autotuner.design.sampled_loop import sampled_loop_robustness

    ku, pu = ultimate_point(*HX)
    gains = IsaGains(ku / 2.2, 2.2 * pu, pu / 6.3)
    cont = robustness(gains, DelayedTF.of(*HX))
    fine = sampled_loop_robustness(gains, DelayedTF.of(*HX), pu / 10000)
    assert cont.stable is None and fine.stable
    assert fine.ms == pytest.approx(cont.ms, rel=1e-3)
    assert fine.gain_margin == pytest.approx(cont.gain_margin, rel=1e-3)
    assert fine.phase_margin_deg == pytest.approx(cont.phase_margin_deg, rel=1e-3)
