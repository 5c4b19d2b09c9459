"""A PV clipped at an end of the transmitter's range is not a measurement of the process.

2e^{−2s}/(10s + 1) over a range of 49–51 (a relay of 5 % swings it ±10 units): the relay's
cycles had flat tops at 49 and 51, agreed to 0.13 %, and gave K_u 5.667 against the exact
4.251 (+33 %); the gains then went on the loop for their verification. Now the first sample
at an end of the range aborts the test, saying so, and the loop is restored."""

from __future__ import annotations

from dataclasses import replace

from services.autotuner.identify import methods
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest
from tests.exact import ultimate_point

TIGHT = {
    "model": "fopdt",
    "gain": 2.0,
    "time_constant": 10.0,
    "delay": 2.0,
    "sample_time": 0.1,
    "pv_range": [49.0, 51.0],
    "noise_std": 0.01,
}


def _relay(monkeypatch=None, recorded_before: bool = False):
    if recorded_before:  # as a run recorded before the check: the relay measured on
        relay = methods.METHODS["relay"]
        old = {"pv_clip": None, "pv_allowance": None}  # neither was in such a run
        before = replace(relay, build=lambda st, setup: relay.build(st, replace(setup, **old)))
        monkeypatch.setitem(methods.METHODS, "relay", before)
    sim = build_plant({"seed": 11, "loops": {"t": TIGHT}})["t"]
    # limits of the whole range, the engineer's: the relay's allowance (a quarter of the
    # range either way from rest, ``test_pv_allowance``) would stop it first, and this is
    # the check at the range's ends
    req = TuneRequest(loop="t", method="relay", pv_limits=(49.0, 51.0))
    return TuningRun(LocalLoopClient(sim), req, "clip").run()


def test_without_limits_of_the_engineers_the_allowance_stops_it_first():
    sim = build_plant({"seed": 11, "loops": {"t": TIGHT}})["t"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="t", method="relay"), "clip").run()
    assert (r.status, r.restored, r.applied) == ("aborted", True, False)
    assert "past its allowance of ±0.5 (25 % of the transmitter's range" in r.reason
    # the amplitude that keeps the cycle within it, or limits of the engineer's own
    assert "so --amplitude " in r.reason and "or --pv-limits of your own" in r.reason


def test_a_relay_whose_pv_reaches_the_end_of_its_range_aborts_there():
    r = _relay()
    assert (r.status, r.restored, r.applied) == ("aborted", True, False)
    assert (r.left["mode"], r.left["op"]) == ("manual", 50.0)  # as it was
    assert r.reason.startswith("relay test: PV 51 at an end of the transmitter's range [49, 51]")
    assert "clipped there" in r.reason and "--amplitude" in r.reason
    # at the first clipped sample: within the relay's first half-cycles, not after its cycles
    assert r.sim_duration < 60.0


def test_recorded_before_it_measured_the_clipped_cycles(monkeypatch):
    r = _relay(monkeypatch, recorded_before=True)
    ku, _ = ultimate_point([2.0], [10.0, 1.0], 2.0)
    assert r.ku is not None and r.ku > 1.2 * ku  # the flat tops read as a smaller swing
