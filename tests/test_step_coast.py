"""A step test stops short of its allowance on the PV's trend, extended by the time the PV
keeps moving once the output is restored. An integrator behind a lag, 0.2·e^{−s}/(s(5s + 1))
at 0.1 s, coasts its dead time and its lag (6 s at the rate it has reached), which the time
it took to start moving (1.2 s) does not show: stepped 5 %, it was stopped 2.8 s short of the
allowance's 75 % and went on to 78.7 % (helper trial). The trend's line, where it crosses the
rest before the step, reads the coast. Figures from the plant: the rate K'·Δu = 0.2 × 5 = 1 %/s,
and the coast at that rate over L + T = 6 s is 6 %."""

from __future__ import annotations

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

SPEC = {
    "model": "transfer_function",
    "num": [0.2],
    "den": [5.0, 1.0, 0.0],
    "delay": 1.0,
    "sample_time": 0.1,
    "pv_range": [0.0, 100.0],
}


def test_an_integrator_behind_a_lag_is_stopped_for_its_coast():
    sim = build_plant({"seed": 0, "loops": {"il": SPEC}}, "t")["il"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="il", method="step"), "t").run()
    assert r.status == "aborted" and "would leave the test's allowance, 25–75 %" in r.reason
    # its coast read off the trend: about the dead time and lag (6 s), not 2.8 s
    within = float(r.reason.split("within ")[1].split(" s")[0])
    assert 5.0 < within < 7.0, r.reason
    for _ in range(300):  # 30 s on, the output at its balance: the coast is over
        sim.advance()
    # where it came to rest: at the allowance's edge (the coast read from a rate still
    # rising a little), not 3.7 % past it
    assert sim.status("n", "lockstep", "q", 0).pv < 75.0 + 1.0
