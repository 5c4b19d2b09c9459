"""A test begun on a PV still drifting says so (``identify.rest_drift``).

Closed forms: a straight line fitted to n samples of white noise σ over W s has a slope whose
standard error is σ·√12/(W·√n) (n ≫ 1); a drift of D per s carried over a test of T s is D·T.
"""

from __future__ import annotations

import math

import pytest

from services.autotuner.identify.rest_drift import drift_note
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

# e^{−5s}/((100s + 1)(5s + 1)), 30 s into its settling from an output 1.5 % off (sampled at
# 0.2 s, σ 0.02): the rest check's 40 samples (8 s) pass it
SETTLING = {
    "model": "tests.disturbed_plant:SineDisturbed",
    "sample_time": 0.2,
    "noise_std": 0.02,
    "den": [500.0, 105.0, 1.0],
    "delay": 5.0,
    "sin_amp": 0.0,
    "settling": 1.5,
    "age": 30.0,
}


def test_a_drift_within_the_fits_noise_or_small_over_the_test_says_nothing():
    se = 0.02 * math.sqrt(12 / 40) / 8.0  # σ 0.02 over 40 samples of 0.2 s
    assert drift_note(3.9 * se, 0.02, 8.0, 0.2, 800.0, 1.0) is None  # within 4 SE
    small = 4.5 * se
    assert drift_note(small, 0.02, 8.0, 0.2, 800.0, 10 * small * 800.0 * 1.01) is None
    note = drift_note(-small, 0.02, 8.0, 0.2, 800.0, 5.0, "u")
    assert note is not None and "still drifting" in note
    assert f"{small * 800.0:.3g} u" in note  # the drift carried over the test
    assert f"{100 * small * 800.0 / 5.0:.0f} %" in note


@pytest.mark.parametrize("method", ["step", "relay"])
def test_a_process_still_settling_when_the_test_began_is_said(method):
    """e^{−5s}/((100s + 1)(5s + 1)) 30 s into settling from an output 1.5 % off: the rest
    check's 40 samples (8 s) pass it, and the step test read its static gain 0.83 for 1.0
    (helper trial); the result now says why its figures may be off."""
    spec = dict(SETTLING)
    sim = build_plant({"seed": 1, "loops": {"x": spec}}, "t")["x"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method=method), "t").run()
    said = [w for w in r.warnings if "still drifting" in w]
    assert said, (r.status, r.reason, r.warnings)
    # the same plant at rest: nothing said
    spec.update(settling=0.0, age=0.0)
    sim = build_plant({"seed": 1, "loops": {"x": spec}}, "t")["x"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method=method), "t").run()
    assert not [w for w in r.warnings if "still drifting" in w], r.warnings


def test_analyze_gives_the_drift_note_as_the_live_result_does(tmp_path):
    """`analyze` gives the live result's warnings, in order: the drift note too, from the
    rest the result recorded and the test's own samples (review)."""
    from services.logger.analysis import analyze_file
    from tests.recorded_run import record_in_process

    spec = dict(SETTLING)
    path, live = record_in_process(
        tmp_path, "drift", {"seed": 1, "loops": {"x": spec}}, "x", "step", apply=False
    )
    said = [w for w in live.warnings if "still drifting" in w]
    assert said, live.warnings
    a = analyze_file(path)
    assert a.warnings == live.warnings[: len(a.warnings)] and said[0] in a.warnings
