"""An aborted step test of an integrating process: the output put back at the balance, the
level stays where the test took it. The command then waited the whole --timeout (7,200 s of
sim time, two hours at ×1) for a return it cannot make, then said "let it settle" (helper
trial). The wait now ends once the PV rests short of the way back, and says where, and that
it stays there. ipdt 0.1·e^{−s}/s at 1 s, stepped 5 %: the level ramps 0.5 %/s and the test
stops at its allowance (25 % of the range), about 24 above its rest."""

from __future__ import annotations

import pytest

from services.autotuner.identify.step_test import StepTestAborted, StepTestConfig
from services.autotuner.step_run import run_step_test
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant


def test_an_aborted_steps_level_is_said_to_stay_and_not_waited_for_hours():
    spec = {"model": "ipdt", "gain": 0.1, "delay": 1.0, "sample_time": 1.0,
            "noise_std": 0.01, "pv_range": [0.0, 100.0]}  # fmt: skip
    sim = build_plant({"seed": 0, "loops": {"c": spec}}, "t")["c"]
    with pytest.raises(StepTestAborted) as stop:
        run_step_test(LocalLoopClient(sim), StepTestConfig(size=5.0))
    said = str(stop.value)
    assert "step test aborted" in said and "loop restored (manual, 50 %)" in said
    assert "not back where it was (50 before the step): held at this output it stays" in said
    level = float(said.split("the PV came to rest at ")[1].split(" ")[0])
    assert level == pytest.approx(sim.pv, abs=0.05) and level > 70.0
    assert sim.t < 1000.0  # not the 7,200 s of the test's timeout
