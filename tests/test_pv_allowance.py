"""A relay keeps its PV within the step test's allowance of its rest: 25 % of the
transmitter's range either way. On an integrating loop whose process answers against the
loop's action, 0.05·e^{−2s}/(−s) at 0.2 s under a reverse-acting PID, the relay's push
drained the level to 0 % before the range's end aborted it (helper trial); the step test saw
the wrong sign at once. It now aborts at the allowance, naming the action, and the level is
said to be left where the test took it. Figures here follow from the plant: the level falls
at K'·d = 0.25 %/s under the relay's push. The ramp's trials have no such allowance (its trials
near K_u swing further than that on flow1, a preset), but its calming between trials has: on
the same loop its first trial ran away, and the calming that followed drained the level to
0 %, the abort blaming the bump."""

from __future__ import annotations

import pytest

from services.autotuner.identify.experiments import PV_ALLOWANCE
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

SPAN = 100.0


def _wrong_way(method: str):
    spec = {
        "model": "transfer_function",
        "num": [-0.05],
        "den": [1.0, 0.0],
        "delay": 2.0,
        "sample_time": 0.2,
        "noise_std": 0.01,
        "pv_range": [0.0, SPAN],
    }
    sim = build_plant({"seed": 0, "loops": {"w": spec}}, "t")["w"]
    before = (sim.mode, sim.op, sim.pid.gains)
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="w", method=method), "t").run()
    return r, sim, before


def test_a_wrong_way_integrator_is_stopped_at_the_allowance_not_drained():
    r, sim, before = _wrong_way("relay")
    assert r.status == "aborted"
    assert f"past its allowance of ±{PV_ALLOWANCE * SPAN:.3g}" in r.reason, r.reason
    assert "is the process one for a direct-acting PID?" in r.reason
    # stopped a sample past the allowance, plus what the level falls over the dead time
    # once the output is put back: far from the range's end the PV limits alone allowed
    assert r.left["pv"] > 50.0 - PV_ALLOWANCE * SPAN - 2.5 * 0.25 - 1.0
    assert (sim.mode, sim.op, sim.pid.gains) == before


def test_a_ramp_calming_that_runs_off_stops_at_the_allowance_naming_the_action():
    r, sim, before = _wrong_way("ramp")
    assert r.status == "aborted"
    assert "calming between trials" in r.reason, r.reason
    assert f"past ±{PV_ALLOWANCE * SPAN:.3g}" in r.reason
    assert "is the process one for a direct-acting PID?" in r.reason
    # stopped a sample past the allowance, plus what the level falls over the dead time
    # once the output is put back (the calming's output is a few % off the balance)
    assert r.left["pv"] > 50.0 - PV_ALLOWANCE * SPAN - 1.0
    assert (sim.mode, sim.op, sim.pid.gains) == before


def test_within_the_allowance_nothing_changes_for_a_self_regulating_loop():
    """1/(s+1)³ swings a few % under the relay's ±5 %: the allowance is never near."""
    spec = {
        "model": "transfer_function",
        "num": [1.0],
        "den": [1.0, 3.0, 3.0, 1.0],
        "sample_time": 0.05,
        "noise_std": 0.01,
        "pv_range": [0.0, SPAN],
    }
    sim = build_plant({"seed": 0, "loops": {"a": spec}}, "t")["a"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="a", method="relay"), "t").run()
    assert r.status == "ok", r.reason
    assert r.ku == pytest.approx(8.0, rel=0.05)  # 1/(s+1)³: K_u = 8 at ω = √3
