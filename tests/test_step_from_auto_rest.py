"""`autotune step` of a loop in auto holds the output the loop averaged, then steps it: only
from a loop at rest. hx1 stepped while its PV still rose to a new setpoint read K = 1.33 for
1.0 and L = 8.2 s for 10.6, exit 0 and no warning (helper trial): the PV's own movement was
read as the step's response. The test now waits for rest as a tune does (on the setpoint,
for a loop that integrates; ten windows at most), and does not start on a loop that does not
come to rest. The expected gain is the plant file's own."""

from __future__ import annotations

import pytest

from services.autotuner.identify.step_test import StepTestAborted, StepTestConfig
from services.autotuner.step_run import run_step_test
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import SetpointCommand
from tests.exact import lag_ultimate

K, T, L, TS = 1.0, 10.0, 2.0, 0.2  # K·e^{−Ls}/(Ts + 1)


def _loop(kc: float, ti: float):
    spec = {
        "model": "fopdt",
        "gain": K,
        "time_constant": T,
        "delay": L,
        "sample_time": TS,
        "noise_std": 0.01,
        "mode": "auto",
        "pid": {"kc": kc, "ti": ti},
    }
    return build_plant({"seed": 3, "loops": {"a": spec}}, "t")["a"]


def test_a_loop_on_its_way_to_a_new_setpoint_is_stepped_once_at_rest():
    sim = _loop(0.5, 10.0)
    client = LocalLoopClient(sim)
    client.command(SetpointCommand(loop="a", sp=55.0, source="test"))  # the PV sets off
    report = run_step_test(client, StepTestConfig(size=5.0), wait_return=False)
    assert report.curve.gain == pytest.approx(K, rel=0.03)
    assert report.curve.dead_time == pytest.approx(L, abs=2 * TS)
    # held at the output that keeps the PV on its new setpoint: (55 − 50)/K + 50
    assert report.op_before == pytest.approx(55.0, abs=0.3)
    assert report.restored and sim.mode == "auto" and sim.sp == 55.0


def test_a_loop_that_does_not_come_to_rest_is_not_stepped():
    """P-only at 0.9 of K_u (the sampled loop's: the hold adds half a sample of dead time):
    the loop rings on, barely damped, through its ten windows."""
    ku, _ = lag_ultimate(K, (T,), L + TS / 2)
    sim = _loop(0.9 * ku, None)
    client = LocalLoopClient(sim)
    client.command(SetpointCommand(loop="a", sp=52.0, source="test"))
    before = (sim.mode, sim.sp, sim.pid.gains)
    with pytest.raises(StepTestAborted, match="not started: the loop in auto is not at rest"):
        run_step_test(client, StepTestConfig(size=5.0), wait_return=False)
    assert (sim.mode, sim.sp, sim.pid.gains) == before
