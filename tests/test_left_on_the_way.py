"""What a run says of a PV it left not at rest: "still on its way back" only where the PV
heads back to where it was. An integrating loop's step test aborted at its allowance, its
output put back at the balance, leaves the level where it is (ipdt 0.1·e^{−s}/s at 1 s: the
PV stays at 74 for 50); it was said to be "still on its way back" (helper trial). A lag's
PV, stepped off and put back, does head back, and is said to."""

from __future__ import annotations

from services.autotuner.commands.tune import format_result
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest


def _run(spec: dict, **request):
    sim = build_plant({"seed": 0, "loops": {"a": {**spec, "pv_range": [0.0, 100.0]}}}, "t")["a"]
    return TuningRun(LocalLoopClient(sim), TuneRequest(loop="a", **request), "t").run()


def test_a_level_left_off_its_rest_is_not_said_to_be_on_its_way_back():
    spec = {"model": "ipdt", "gain": 0.1, "delay": 1.0, "sample_time": 1.0, "noise_std": 0.01}
    r = _run(spec, method="step")
    assert r.status == "aborted" and r.left is not None and not r.left["returned"]
    assert r.left["pv"] - r.left["pv_target"] > 20.0  # the level stays ~24 % up
    assert abs(r.left["drift"]) < 3 * r.left["drift_error"]  # flat at the balance, but noise
    text = format_result(r)
    assert "still on its way back" not in text
    assert "not back where it was, and not moving back" in text


def test_a_lag_left_off_its_rest_is_said_to_be_on_its_way_back():
    """e^{−2s}/(300s + 1), stepped 5 % and aborted at a PV limit 1 above the rest: put back,
    the PV falls back toward 50 with a time constant of 300 s, far longer than the wait."""
    spec = {
        "model": "fopdt",
        "gain": 1.0,
        "time_constant": 300.0,
        "delay": 2.0,
        "sample_time": 0.5,
        "noise_std": 0.01,
    }
    r = _run(spec, method="step", pv_limits=(40.0, 51.0))
    assert r.status == "aborted" and r.left is not None and not r.left["returned"]
    assert r.left["drift"] < 0 < r.left["pv"] - r.left["pv_target"]
    assert "still on its way back (-" in format_result(r)
