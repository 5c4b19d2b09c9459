"""A setpoint step's output against its limits: the time spent at one (``op_limited``, which
says the step's overshoot is the limited loop's) and whether it sat there for a third of the
step or more (``saturated``, a rejection). The verification reads both from the step whose
figures it judges: where the step is made again from a calm loop, from that one, not from
the first (made on the tail of the switch to the new gains, which asks the output for more)."""

from __future__ import annotations

import numpy as np

from services.autotuner.tuning import op_at_limits


def test_time_at_a_limit_counts_samples_at_or_beyond_either_limit():
    u = np.array([50.0, 100.0, 100.0, 80.0, 0.0, 20.0, 30.0, 40.0, 50.0, 60.0])
    limited, saturated = op_at_limits(u, 0.0, 100.0, 0.5)
    assert limited == 3 * 0.5  # two at the top, one at the bottom
    assert saturated is False  # 3 of 10: under a third


def test_a_third_or_more_at_a_limit_is_saturated_and_narrow_limits_count():
    u = np.array([25.0, 25.0, 25.0, 40.0, 50.0, 60.0, 70.0, 75.0, 75.0, 50.0])
    limited, saturated = op_at_limits(u, 25.0, 75.0, 0.1)
    assert np.isclose(limited, 5 * 0.1)
    assert saturated is True


def test_no_step_is_no_time_at_a_limit():
    assert op_at_limits(np.array([]), 0.0, 100.0, 1.0) == (0.0, False)
