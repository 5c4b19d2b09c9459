"""A noise-free loop re-tuned after a test: its PV still creeps back by a few 1e-5 of its
range, which the tuner's rest check (``rest.RESOLUTION`` of the range: no transmitter
resolves it) calls rest, and the experiment's own check before its first step (3σ of a σ of
1e-7) called a drift: every step, relay or ramp after another test aborted "the PV is not at
rest before the test (it keeps drifting)" (helper trial). Now each experiment counts a drift
within the same resolution as rest, where the run's set-up says so (``Setup.resolution``).

In process, lockstep: 1.2·e^{−2s}/(15s + 1), 0.1 s samples, no noise; its exact ultimate
point (tests.exact) is what the relay reads after the other tests.
"""

import pytest

from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest
from tests.exact import ultimate_point

SPEC = {
    "model": "fopdt",
    "gain": 1.2,
    "time_constant": 15.0,
    "delay": 2.0,
    "sample_time": 0.1,
    "noise_std": 0.0,
    "pv0": 50.0,
    "pv_range": [0.0, 100.0],
}


def test_each_experiment_after_another_finds_rest_on_a_noise_free_loop():
    loop = build_plant({"seed": 1, "loops": {"x": SPEC}})["x"]
    client = LocalLoopClient(loop)
    results = {}
    for method in ("ramp", "step", "relay"):
        req = TuneRequest(loop="x", method=method)
        results[method] = r = TuningRun(client, req, method, RunHooks()).run()
        assert r.status == "ok", (method, r.reason)
    ku, pu = ultimate_point([1.2], [15.0, 1.0], 2.0)
    assert results["relay"].ku == pytest.approx(ku, rel=0.01)
    assert results["relay"].pu == pytest.approx(pu, rel=0.01)
