"""Physical models: rest at the operating point, energy and mass balances, disturbances."""

import math

import numpy as np
import pytest

from services.plant_sim.simulation.physical import (
    FlowLoop,
    HeatExchangerPhysical,
    SensorLag,
    TankLevel,
    TankLevelPumped,
    valve_fraction,
)


def run(model, op, seconds):
    return np.array([model.step(op) for _ in range(round(seconds / model.sample_time))])


def test_heat_exchanger_steady_state_is_the_energy_balance():
    hx = HeatExchangerPhysical(sample_time=0.25)
    t0 = hx.reset()
    q = hx.steam_max * 0.40 * hx.H_FG  # linear valve at 40 %
    assert t0 == pytest.approx(20.0 + q / (2.0 * hx.CP), rel=1e-12)
    final = run(hx, 50.0, 3000)[-1]
    assert final == pytest.approx(20.0 + hx.steam_max * 0.5 * hx.H_FG / (2.0 * hx.CP), rel=1e-6)
    # a colder inlet lowers the outlet by the same amount at rest; more flow lowers the rise
    hx.set_disturbance("inlet_temp", 10.0)
    assert run(hx, 50.0, 3000)[-1] == pytest.approx(final - 10.0, rel=1e-6)
    hx.set_disturbance("flow", 4.0)
    rise = run(hx, 50.0, 3000)[-1] - 10.0
    assert rise == pytest.approx((final - 20.0) / 2.0, rel=1e-6)
    with pytest.raises(ValueError, match="flow"):
        hx.set_disturbance("flow", -1.0)


def test_heat_exchanger_dead_time_is_the_transport_delay():
    hx = HeatExchangerPhysical(sample_time=0.25, delay=5.0, sensor_lag=0.0)
    t0 = hx.reset()
    y = run(hx, 60.0, 10.0)
    assert np.all(y[: round(5.0 / 0.25)] == t0)  # nothing arrives before the delay
    assert y[round(5.0 / 0.25)] > t0


def test_tank_level_follows_the_square_root_law():
    tank = TankLevel(sample_time=1.0)
    h0 = tank.reset()
    assert h0 == pytest.approx(1.5)
    h = run(tank, 60.0, 20000)[-1]
    assert h == pytest.approx(1.5 * (60.0 / 50.0) ** 2, rel=1e-6)  # q ∝ √h at rest
    assert run(tank, 100.0, 20000)[-1] == pytest.approx(3.0)  # overflows at the top, no more


def test_pumped_tank_integrates_the_imbalance():
    tank = TankLevelPumped(sample_time=1.0, delay=0.0)
    tank.reset()
    y = run(tank, 60.0, 100.0)
    rate = 0.02 * 0.10 / 2.0  # 10 % of 0.02 m³/s over 2 m²
    assert y[-1] - 1.5 == pytest.approx(rate * 100.0, rel=1e-9)
    assert run(tank, 0.0, 20000)[-1] == 0.0  # runs dry, not below


def test_flow_loop_gain_and_supply_pressure():
    flow = FlowLoop(sample_time=0.1)
    assert flow.reset() == pytest.approx(50.0)
    assert run(flow, 60.0, 60.0)[-1] == pytest.approx(60.0, rel=1e-9)
    flow.set_disturbance("supply_pressure", 25.0)
    assert run(flow, 60.0, 60.0)[-1] == pytest.approx(30.0, rel=1e-9)  # q ∝ √Δp


def test_valve_characteristics():
    assert valve_fraction(50, "linear", 30) == 0.5
    assert valve_fraction(50, "equal_percentage", 30) == pytest.approx((30**0.5 - 1) / 29)
    assert valve_fraction(25, "quick_opening", 30) == 0.5
    assert valve_fraction(120, "linear", 30) == 1.0


def test_sensor_lag_is_exact_for_a_ramp():
    lag = SensorLag(2.0, 0.5)
    lag.fill(0.0)
    ys = [lag.push(k * 0.5) for k in range(1, 41)]  # input u(t) = t
    t = 20.0
    assert ys[-1] == pytest.approx(t - 2.0 * (1 - math.exp(-t / 2.0)), rel=1e-12)
