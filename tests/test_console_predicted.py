"""The rules' predicted setpoint steps the console draws: the closed loop of the loop's PID
block on the identified model, against closed forms."""

from __future__ import annotations

import math

import pytest

from services.console.predicted import model_of, predicted_curves, step_curve, timescale_of
from shared.control.transfer import DelayedTF
from tests.exact import lag_ultimate

K, TAU, L = 2.0, 10.0, 1.0  # K·e^{−Ls}/(τs + 1)
FOPDT = {"model": "fopdt", "model_gain": K, "model_lag_1": TAU, "model_delay": L}


def test_p_control_settles_at_its_static_offset():
    """P only: the closed loop's static gain is Kc·K/(1 + Kc·K), exactly, sampled or not."""
    kc = 1.5
    t, y = step_curve(kc, None, 0.0, DelayedTF.of([K], [TAU, 1.0], L), 20.0, 0.1)
    assert y[-1] == pytest.approx(kc * K / (1 + kc * K), rel=1e-6)
    assert t[0] > 0 and t[-1] == pytest.approx(10 * 20.0, rel=0.01)


def test_integral_action_removes_the_offset():
    t, y = step_curve(1.0, 8.0, 0.0, DelayedTF.of([K], [TAU, 1.0], L), 20.0, 0.1)
    assert y[-1] == pytest.approx(1.0, abs=1e-4)
    assert y[t < L].max() == 0.0  # nothing before the dead time


def test_a_slow_lambda_curve_is_drawn_until_it_settles():
    """Lambda PI (λ = T) on e^{−s}/(100s + 1): the closed loop e^{−Ls}/((λ + L)s + e^{−Ls})
    is λs + 1 to first order in Ls, its 63 % at t = L + λ = 101 s, while 10 P_u is 39 s: the
    curve was cut at a third of its rise, and its climb over the last fifth, as steep as over
    the first, read as an undamped swing (no curve)."""
    tau, lam, delay = 100.0, 100.0, 1.0
    _ku, pu = lag_ultimate(1.0, (tau,), delay)
    assert 10 * pu < 0.5 * (lam + delay)
    plant = DelayedTF.of([1.0], [tau, 1.0], delay)
    curve = step_curve(tau / (lam + delay), tau, 0.0, plant, pu, 0.05)
    assert curve is not None
    t, y = curve
    assert y[-1] == pytest.approx(1.0, abs=0.02) and t[-1] > 4 * (lam + delay)
    t63 = float(t[next(k for k, v in enumerate(y) if v >= 1 - math.exp(-1))])
    assert t63 == pytest.approx(delay + lam, rel=0.03)


def test_beyond_the_ultimate_gain_the_loop_diverges_and_gives_no_curve():
    ku, pu = lag_ultimate(K, (TAU,), L)
    plant = DelayedTF.of([K], [TAU, 1.0], L)
    assert step_curve(0.8 * ku, None, 0.0, plant, pu, 0.01) is not None
    assert step_curve(1.5 * ku, None, 0.0, plant, pu, 0.01) is None


def test_every_rule_of_a_result_gets_its_curve_on_the_result_s_model():
    ku, pu = lag_ultimate(K, (TAU,), L)
    result = {
        "pu": pu,
        "experiment": FOPDT,
        "identified_on": {"sample_time": 0.1},
        "gains": {
            "zn-p": {"isa": {"kc": 0.5 * ku, "ti": None, "td": 0.0}},
            "too-much": {"isa": {"kc": 2.0 * ku, "ti": None, "td": 0.0}},
        },
    }
    curves = predicted_curves(result)
    assert curves["too-much"] is None
    kc = 0.5 * ku
    assert curves["zn-p"]["y"][-1] == pytest.approx(kc * K / (1 + kc * K), rel=1e-4)


def test_the_model_and_time_scale_read_from_a_result():
    m = model_of(FOPDT)
    assert (m.kind, m.gain, m.lags, m.delay) == ("fopdt", K, (TAU,), L)
    assert model_of({"model": "none"}) is None and model_of({"model": "sopdt"}) is None
    assert timescale_of(m, 42.0) == 42.0
    assert timescale_of(m, None) == pytest.approx(lag_ultimate(K, (TAU,), L)[1], rel=1e-6)
    assert predicted_curves({"experiment": {}, "gains": {}}) == {}
    assert math.isfinite(timescale_of(model_of({**FOPDT, "model": "ipdt"}), None))
