"""Exact ZOH discretisation with dead time, against closed forms and scipy.signal."""

import warnings

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import signal

from services.plant_sim.simulation.models import (
    FirstOrderPlusDeadTime,
    IntegratingPlusDeadTime,
    ModelParamError,
    TransferFunctionModel,
)
from shared.control.lti import (
    DelayedLinearSystem,
    discretize,
    simulate,
    split_delay,
    tf_to_ss,
)

RTOL = 1e-6


def step_samples(model, n: int, size: float = 1.0) -> np.ndarray:
    """PV deviation at t = T, 2T, …, nT after an output step of ``size`` at t = 0."""
    y0 = model.reset()
    return np.array([model.step(model.op0 + size) for _ in range(n)]) - y0


@pytest.mark.parametrize("delay", [0.0, 1.0, 1.3, 0.07, 2.45])
@pytest.mark.parametrize("ts", [0.1, 0.25])
def test_fopdt_step_matches_closed_form(delay, ts):
    k, tau = 2.5, 7.0
    y = step_samples(FirstOrderPlusDeadTime(ts, gain=k, time_constant=tau, delay=delay), 400)
    t = np.arange(1, 401) * ts
    ref = np.where(t >= delay, k * (1.0 - np.exp(-(t - delay) / tau)), 0.0)
    assert_allclose(y, ref, rtol=RTOL, atol=1e-12)


def third_order_closed_form(t: np.ndarray) -> np.ndarray:
    """Unit step of 6/((s+1)(s+2)(s+3)) by partial fractions: 1 − 3e^{−t} + 3e^{−2t} − e^{−3t}."""
    return 1.0 - 3.0 * np.exp(-t) + 3.0 * np.exp(-2 * t) - np.exp(-3 * t)


@pytest.mark.parametrize("delay", [0.0, 0.5, 0.37])
def test_third_order_step_matches_closed_form_and_scipy(delay):
    ts = 0.05
    model = TransferFunctionModel(ts, num=[6.0], den=[1.0, 6.0, 11.0, 6.0], delay=delay)
    y = step_samples(model, 300)
    t = np.arange(1, 301) * ts
    shifted = np.clip(t - delay, 0.0, None)
    assert_allclose(y, third_order_closed_form(shifted), rtol=RTOL, atol=1e-12)
    # scipy.signal's continuous-time simulation of the undelayed plant, shifted by the delay
    h = 0.01  # a grid from 0 through every shifted sample time (all are multiples of h)
    grid = np.arange(0.0, shifted[-1] + h / 2, h)
    _, ref = signal.step(signal.lti([6.0], [1.0, 6.0, 11.0, 6.0]), T=grid)
    assert_allclose(y, ref[np.rint(shifted / h).astype(int)], rtol=RTOL, atol=1e-9)


def test_matches_scipy_cont2discrete_with_whole_sample_delay():
    ts, n_delay = 0.2, 4
    num, den = [0.5, 1.0], [2.0, 3.0, 1.0]
    model = TransferFunctionModel(ts, num=num, den=den, delay=n_delay * ts)
    rng = np.random.default_rng(7)
    u = rng.uniform(-5, 5, 200)
    model.reset()
    y = np.array([model.step(model.op0 + ui) for ui in u]) - model.pv0
    a, b, c, _, _ = signal.cont2discrete(signal.tf2ss(num, den), ts, method="zoh")
    x = np.zeros(a.shape[0])
    ref = []
    u_delayed = np.concatenate((np.zeros(n_delay), u))
    for k in range(200):
        x = a @ x + b[:, 0] * u_delayed[k]
        ref.append(float(c[0] @ x))
    assert_allclose(y, ref, rtol=RTOL, atol=1e-12)


def test_dc_gain_and_dead_time_exact():
    ts, delay = 0.25, 5.0
    model = TransferFunctionModel(ts, num=[1.0], den=[600.0, 70.0, 1.0], delay=delay)
    y = step_samples(model, 20000, size=3.0)
    assert abs(y[-1] / 3.0 - 1.0) < 1e-12
    assert model.discrete.dc_gain() == pytest.approx(1.0, rel=1e-12)
    first_moving = int(np.argmax(np.abs(y) > 0)) + 1  # samples after the step
    assert first_moving * ts == pytest.approx(delay + ts)
    assert np.all(y[: round(delay / ts)] == 0.0)


def test_integrating_plant_ramps_at_its_gain():
    ts, k, delay = 0.5, 0.02, 1.5
    y = step_samples(IntegratingPlusDeadTime(ts, gain=k, delay=delay), 100, size=2.0)
    t = np.arange(1, 101) * ts
    assert_allclose(y, np.where(t >= delay, 2.0 * k * (t - delay), 0.0), rtol=RTOL, atol=1e-12)


def test_sensor_lag_is_folded_in_exactly():
    ts, tau, lag = 0.1, 3.0, 1.0
    y = step_samples(FirstOrderPlusDeadTime(ts, gain=1.0, time_constant=tau, sensor_lag=lag), 200)
    t = np.arange(1, 201) * ts
    ref = 1.0 - (tau * np.exp(-t / tau) - lag * np.exp(-t / lag)) / (tau - lag)
    assert_allclose(y, ref, rtol=RTOL, atol=1e-12)


def test_delay_split_never_rounds_a_real_fraction():
    assert split_delay(0.3, 0.1) == (3, 0.0)  # 0.3/0.1 = 2.9999999999999996 in floating point
    n, f = split_delay(0.3001, 0.1)
    assert n == 3 and f == pytest.approx(0.0001)
    with pytest.raises(ValueError, match="delay"):
        split_delay(-1.0, 0.1)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"num": [1, 2, 3], "den": [1, 1]}, "num"),
        ({"num": [1], "den": [0, 0]}, "den"),
        ({"num": [1], "den": [1, 1], "delay": -2}, "delay"),
        ({"num": [1], "den": [1, float("nan")]}, "den[1]"),
    ],
)
def test_bad_transfer_functions_name_the_field(kwargs, field):
    with pytest.raises(ModelParamError) as err:
        TransferFunctionModel(0.1, **kwargs)
    assert err.value.field == field


@pytest.mark.parametrize(
    ("num", "den", "delay", "ts"),
    [
        ([6.0], [1.0, 6.0, 11.0, 6.0], 0.0, 0.01),
        ([1.0], [600.0, 70.0, 1.0], 5.3, 0.25),  # fractional dead time
        ([1.0], [1.0, 0.0], 1.05, 0.1),  # integrator
        ([-1.0, 1.0], [1.0, 3.0, 3.0, 1.0], 0.37, 0.05),  # right-half-plane zero
        ([2.0, 1.0], [1.0, 1.0], 0.0, 0.1),  # feed-through
    ],
)
def test_vectorised_simulation_matches_the_step_by_step_system(num, den, delay, ts):
    sys = discretize(*tf_to_ss(num, den), ts, delay)
    u = np.random.default_rng(0).standard_normal(2000)
    stepper = DelayedLinearSystem(sys)
    expected = np.array([0.0] + [stepper.step(x) for x in u])
    got = simulate(sys, u)
    assert got.shape == expected.shape
    assert np.max(np.abs(got - expected)) <= 1e-9 * np.max(np.abs(expected))


def test_a_tiny_gain_is_realised_without_scipys_warning():
    """A model fit's search passes through gains far below 1e-14 of the denominator's
    leading coefficient; scipy would warn that the numerator is "badly conditioned" (it has
    nothing to trim). The realisation is the same, scaled, and its DC gain exact."""
    num, den = [3e-12], [1e3, 110.0, 1.0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a, b, c, d = tf_to_ss(num, den)
    dc = float((c @ np.linalg.solve(-a, b)).item()) + d
    assert dc == pytest.approx(3e-12, rel=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = signal.tf2ss(num, den)
    for ours, theirs in zip((a, b, c), ref[:3], strict=True):
        assert_allclose(ours, theirs, rtol=1e-12, atol=0)
