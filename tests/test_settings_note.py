"""A tune applies its gains with the derivative filter N = 10 and setpoint weight β = 1 its
design, predictions and verification assume, and says so where the loop had other settings:
a loop set up with N 3 and β 0.5 was left at N 10 and β 1, and nothing said so (helper audit).
The plant: 1/(5s + 1)³ at 0.1 s, quick to tune; ZN PID has a derivative, so N applies."""

from __future__ import annotations

import pytest

from services.autotuner.tuning import TuningRun, settings_note
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import PidGains, TuneRequest

SPEC = {
    "model": "transfer_function",
    "num": [1.0],
    "den": [125.0, 75.0, 15.0, 1.0],
    "sample_time": 0.1,
    "pv_range": [0.0, 100.0],
}


def tune(pid: dict) -> object:
    sim = build_plant({"seed": 0, "loops": {"x": {**SPEC, "pid": pid}}}, "t")["x"]
    req = TuneRequest(loop="x", method="relay", rule="tl-pid")
    return TuningRun(LocalLoopClient(sim), req, "t").run()


def test_a_loop_with_its_own_filter_and_weight_is_told_they_were_replaced():
    r = tune({"kc": 1.0, "ti": 20.0, "n": 3.0, "beta": 0.5})
    assert r.status == "ok", r.reason
    assert r.left["gains"]["n"] == 10.0 and r.left["gains"]["beta"] == 1.0
    said = [w for w in r.warnings if w.startswith("the loop's derivative filter")]
    assert said and "N 3 → 10 and setpoint weight β 0.5 → 1" in said[0], r.warnings


def test_a_loop_with_the_design_settings_is_told_nothing():
    r = tune({"kc": 1.0, "ti": 20.0})
    assert r.status == "ok", r.reason
    assert not [w for w in r.warnings if w.startswith("the loop's")], r.warnings


@pytest.mark.parametrize(
    ("before", "applied", "weighted", "said"),
    [
        (PidGains(kc=1, ti=9, n=3), PidGains(kc=2, ti=8), False, None),  # PI: N does nothing
        (PidGains(kc=1, n=3), PidGains(kc=2, td=1), False, "derivative filter N 3 → 10:"),
        (PidGains(kc=1, beta=1), PidGains(kc=2, beta=0.6), True, None),  # its own note says
        (PidGains(kc=1, beta=0.4), PidGains(kc=2), False, "setpoint weight β 0.4 → 1:"),
    ],
)
def test_only_what_changed_and_matters_is_said(before, applied, weighted, said):
    note = settings_note(before, applied, weighted)
    assert note is None if said is None else said in note


def test_gains_applied_unverified_are_not_said_verified():
    note = settings_note(PidGains(kc=1, n=3), PidGains(kc=2, td=1), verified=False)
    assert "designed and predicted with N 10" in note and "verified" not in note
