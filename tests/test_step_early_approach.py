"""A step test on a process that is nearly all dead time, 2·e^{−20s}/(s + 1) at 0.5 s, stepped
5 %: its PV jumps toward 50 + 2 × 5 = 60 once the 20 s of dead time are over, each sample's
step e^{−0.5} = 0.61 of the one before. Judged on the straight line through its last samples,
extended by the coast (twice the 20 s it took to start moving), it was aborted "would leave
the test's allowance, 25–75 %" at 59.3; the lag's shrinking steps say it ends at 60. Figures
from the plant: K = 2, L = 20 s, T = 1 s."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from services.autotuner.identify.step_test import GEOMETRIC_RATIO, _geometric_left
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

SPEC = {
    "model": "transfer_function",
    "num": [2.0],
    "den": [1.0, 1.0],
    "delay": 20.0,
    "sample_time": 0.5,
    "noise_std": 0.01,
    "pv_range": [0.0, 100.0],
}


@pytest.mark.parametrize("seed", [0, 1])
def test_a_dead_time_process_stepped_is_not_aborted_on_its_lag(seed):
    sim = build_plant({"seed": seed, "loops": {"dd": SPEC}}, "t")["dd"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="dd", method="step"), "t").run()
    assert r.status == "ok", r.reason
    step = r.step
    assert step["gain"] == pytest.approx(2.0, rel=0.01)
    assert step["dead_time"] == pytest.approx(20.0, abs=0.25)  # within half a sample
    assert step["time_constant_63"] == pytest.approx(1.0, rel=0.05)


def test_a_lag_approach_leads_to_its_end_twice_over():
    """Steps of a first-order lag sampled at T/2: ratio e^{−0.5}; what is left after the last
    sample is its step × q/(1 − q), taken twice over."""
    q = math.exp(-0.5)
    y = 60.0 - 10.0 * q ** np.arange(1, 6)
    left = _geometric_left(y, noise=0.0)
    assert left == pytest.approx(2.0 * (60.0 - y[-1]), rel=1e-9)
    assert _geometric_left(60.0 - y, noise=0.0) == pytest.approx(-left, rel=1e-9)


@pytest.mark.parametrize(
    "y",
    [
        np.arange(6) * 1.0,  # steady: an integrator's ramp
        np.arange(6) ** 2 * 1.0,  # speeding up: an S-curve's start, an integrator behind a lag
        60.0 - 10.0 * (GEOMETRIC_RATIO + 0.05) ** np.arange(6),  # slowing, but slowly
        np.array([50.0, 50.1, 50.15, 50.17, 50.18]),  # within 6σ of a noise σ 0.01 a step
        np.array([50.0, 52.0, 53.0, 52.5, 52.3]),  # turned back
    ],
)
def test_only_a_clear_lag_approach_is_judged_on_where_it_leads(y):
    assert _geometric_left(y, noise=0.01) is None


def test_the_tail_does_not_judge_the_engineers_limits():
    """A fast lag beside a slow one, e^{−20s}(31s + 2)/((s + 1)(30s + 1)) at 0.5 s: its steps
    shrink at first as a lone lag's would (0.6 a sample), and its tail missed the slow mode's
    ramp; toward limits at 58.5 the straight line stopped it at 55.07, the tail at 57.78, and
    the PV went on to 58.85 (review, 4 seeds of 8). The tail judges the allowance only."""
    spec = {
        "model": "transfer_function",
        "num": [31.0, 2.0],
        "den": [30.0, 31.0, 1.0],
        "delay": 20.0,
        "sample_time": 0.5,
        "noise_std": 0.01,
        "pv_range": [0.0, 100.0],
    }
    sim = build_plant({"seed": 0, "loops": {"dd": spec}}, "t")["dd"]
    req = TuneRequest(loop="dd", method="step", pv_limits=(40.0, 58.5))
    r = TuningRun(LocalLoopClient(sim), req, "t").run()
    assert r.status == "aborted" and "would leave its limits [40, 58.5]" in r.reason
    assert r.pv_outside is None, r.pv_outside


def test_a_run_recorded_before_rebuilds_without_the_tail():
    """The set-up's flag, unset in a run recorded before, rebuilds the test without it."""
    from services.autotuner.identify.experiments import Settings, Setup
    from services.autotuner.identify.step_test import build

    setup = Setup(sample_time=0.5, op_lo=0.0, op_hi=100.0, pv_lo=0.0, pv_hi=100.0, op_start=50.0)
    assert build(Settings(), setup).config.early_approach is False
    live = dataclasses.replace(setup, step_early_approach=True)
    assert build(Settings(), live).config.early_approach is True
