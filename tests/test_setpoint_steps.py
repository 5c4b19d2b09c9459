"""Many candidates' setpoint steps simulated together equal, to the bit, each candidate's loop
stepped alone with the plant's own blocks (``PidBlock`` and ``DelayedLinearSystem``): the
design's predictions did not move when they were batched, and cannot drift from the loop the
plant runs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.autotuner.design.predicted_response import (
    predicted_setpoint_step,
    predicted_setpoint_steps,
)
from services.autotuner.design.rules import UltimatePoint, apply_rules
from shared.control.forms import IsaGains
from shared.control.lti import DelayedLinearSystem, discretize, tf_to_ss
from shared.control.pid import PidBlock, PidSettings
from shared.control.setpoint_steps import setpoint_step, setpoint_steps
from shared.control.transfer import ultimate_point

LIMIT = 1e6


def alone(gains: IsaGains, sys, samples: int, step: float) -> np.ndarray:
    """The reference: one loop, the plant's own blocks, stopped where it leaves ±LIMIT."""
    plant = DelayedLinearSystem(sys)
    pid = PidBlock(
        PidSettings(kc=gains.kc, ti=gains.ti, td=gains.td),
        sys.sample_time,
        (0.0, 100.0),
        mode="auto",
        op=50.0,
    )
    y, pv = [], 0.0
    for _ in range(samples):
        pv = plant.step(pid.update(step, pv) - 50.0)
        y.append(pv / step)
        if not math.isfinite(y[-1]) or abs(y[-1]) > LIMIT:
            break
    return np.array(y)


PLANTS = {
    # heat exchanger's two lags and delay; a delay-dominated first order; an integrator
    # (a level); a pure gain with a fractional delay (order 0)
    "sopdt": ([1.0], [48.7 * 10.7, 48.7 + 10.7, 1.0], 5.0, 0.5),
    "fopdt": ([2.0], [4.0, 1.0], 9.3, 0.7),
    "ipdt": ([0.05], [1.0, 0.0], 2.0, 0.25),
    "gain": ([1.5], [1.0], 1.3, 0.4),
}


@pytest.mark.parametrize("name", list(PLANTS))
def test_every_rule_and_an_unstable_gain_equal_their_loops_alone(name):
    num, den, delay, ts = PLANTS[name]
    sys = discretize(*tf_to_ss(num, den), ts, delay)
    point = ultimate_point(num, den, delay)
    ku, pu = point if point else (5.0, 10.0 * delay)
    gains = list(apply_rules(UltimatePoint(ku, pu), None).values())
    gains += [IsaGains(2.0 * ku), IsaGains(0.5 * ku, 0.3 * pu, 0.4 * pu)]
    steps = [min(1.0, 10.0 / g.kc) for g in gains]
    # twice K_u grows until the output limits hold it: tens of PV units, past LIMIT steps of
    # 1e-8, so that this loop stops early in both
    steps[-2] = 1e-8
    samples = int(30 * pu / ts)
    y, blown = setpoint_steps(gains, sys, samples, steps, LIMIT)
    assert blown[-2] and not blown[-1]
    for j, g in enumerate(gains):
        ref = alone(g, sys, samples, steps[j])
        stopped = ref.size < samples
        assert bool(blown[j]) == stopped, (name, g)
        assert np.array_equal(y[j, : ref.size], ref), (name, g)
        # one candidate alone in float arithmetic (the verification's model response): the
        # same samples to the bit, None where the loop left ±LIMIT
        one = setpoint_step(g, sys, samples, steps[j], LIMIT)
        assert (one is None) == stopped, (name, g)
        assert one is None or np.array_equal(one, ref), (name, g)


def test_saturating_steps_wind_up_as_the_block_does():
    """Steps of 30–60 % of span with strong gains: the output sits at its limits and the
    anti-windup holds the integral, in the batch as in the block."""
    sys = discretize(*tf_to_ss([1.0], [10.0, 1.0]), 0.2, 1.0)
    gains = [IsaGains(8.0, 3.0, 0.5), IsaGains(3.0, 1.0), IsaGains(20.0, 50.0, 2.0)]
    steps = [30.0, -40.0, 60.0]
    y, blown = setpoint_steps(gains, sys, 600, steps, LIMIT)
    assert not blown.any()
    for j, g in enumerate(gains):
        assert np.array_equal(y[j], alone(g, sys, 600, steps[j]))
    assert np.max(np.abs(y[0])) > 0  # moved


def test_the_batch_of_predictions_is_each_prediction():
    """``predicted_setpoint_steps`` of a table gives each rule's ``predicted_setpoint_step``."""
    from shared.control.transfer import DelayedTF

    plant = DelayedTF.of([1.0], [48.7 * 10.7, 48.7 + 10.7, 1.0], 5.0)
    ku, pu = plant.ultimate_point()
    table = apply_rules(UltimatePoint(ku, pu), None)
    together = predicted_setpoint_steps(table, plant, pu, 0.5)
    assert together == {k: predicted_setpoint_step(g, plant, pu, 0.5) for k, g in table.items()}
    assert predicted_setpoint_steps({}, plant, pu, 0.5) == {}


def test_gains_a_block_refuses_are_refused():
    sys = discretize(*tf_to_ss([1.0], [10.0, 1.0]), 0.2, 1.0)
    with pytest.raises(ValueError, match="ti"):
        setpoint_steps([IsaGains(1.0, -2.0)], sys, 10, [1.0], LIMIT)
