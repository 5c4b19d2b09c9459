"""A realtime plant that cannot keep its clock's pace says so, and a run on it too.

A model whose step takes 20 ms, at T = 0.1 s and ×20 (5 ms allowed): the plant ran at about
×4, and neither its log nor the run's result said so (helper trial)."""

from __future__ import annotations

import time

import pytest

from services.autotuner.tuning import PACE_KEPT, PACE_WALL, kept_pace

PLANT = """
[loops.s1]
model = "tests.slow_step_model:SlowStep"
sample_time = 0.1
"""


@pytest.mark.integration
def test_a_plant_behind_its_clock_says_so(start_plant):
    plant = start_plant(PLANT, "--clock", "realtime", "--speed", "20", loops=("s1",))
    deadline = time.monotonic() + 20.0
    while "the realtime clock is" not in plant.stderr() and time.monotonic() < deadline:
        time.sleep(0.05)  # a log line is the only sign: read until it comes (bounded)
    err = plant.stderr()
    assert "s of wall time behind at ×20: the loops' steps take longer" in err, err


def test_a_run_says_what_share_of_its_clock_the_plant_kept():
    # ×20 for 10 s of wall time should give 200 s of sim time: 100 s is half
    assert kept_pace("realtime", 20.0, 100.0, 10.0) == pytest.approx(0.5)
    assert kept_pace("realtime", 20.0, 200.0 * PACE_KEPT, 10.0) is None  # kept pace
    assert kept_pace("lockstep", 1.0, 1.0, 10.0) is None  # no clock to keep
    assert kept_pace("realtime", 20.0, 1.0, PACE_WALL / 2) is None  # too short to judge
