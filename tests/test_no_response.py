"""A loop whose PV does not answer its output (a valve stuck in its deadband, a dead
transmitter) is never tuned: a noise-free PV that moves 2e-7 of its range for a 5 % step
read as a gain of 4e-8 (step test) or a K_u of 2.6e8 (relay), and the verification put a
PI of Kc 1e8–1e9 on the loop before rejecting it. Each experiment now ends at no response
(a move within ``rest_window.RESOLUTION`` of the range), before any gain is designed.

In process, lockstep (``LocalLoopClient``), a noise-free FOPDT of gain 4e-8.
"""

import math

import pytest

from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.control.signals import no_response_floor
from shared.messages import TuneRequest

DEAD = {
    "model": "fopdt",
    "gain": 4e-8,  # PV units per %: 2e-7 for a 5 % step, within 1e-5 of the 0–100 range
    "time_constant": 15.0,
    "delay": 2.0,
    "sample_time": 0.1,
    "noise_std": 0.0,
    "pv0": 50.0,
    "pv_range": [0.0, 100.0],
}


def test_the_floor_is_a_hundred_thousandth_of_the_range():
    assert no_response_floor((0.0, 100.0)) == pytest.approx(1e-3, rel=1e-12)
    assert no_response_floor((2.0, -2.0)) == pytest.approx(4e-5, rel=1e-12)
    assert no_response_floor((0.0, float("inf"))) == 0.0


@pytest.mark.parametrize("method", ["relay", "step"])
def test_no_response_aborts_before_any_gain_is_designed_or_applied(method):
    loop = build_plant({"seed": 1, "loops": {"x": DEAD}})["x"]
    before = (loop.pid.mode, loop.pid.op, loop.pid.gains.kc)
    r = TuningRun(
        LocalLoopClient(loop), TuneRequest(loop="x", method=method), "t", RunHooks()
    ).run()
    assert r.status == "aborted" and not r.applied and not r.gains
    assert "did not respond to the" in r.reason, r.reason
    assert (loop.pid.mode, loop.pid.op, loop.pid.gains.kc) == before


class Stuck:
    """A valve stuck shut in its deadband: the PV holds at 50 % whatever the output."""

    pv_units = "%"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time: float, op0: float = 50.0):
        self.sample_time, self.op0 = sample_time, op0

    def reset(self) -> float:
        return 50.0

    def step(self, op: float) -> float:
        return 50.0

    def disturbance_names(self) -> tuple[str, ...]:
        return ()

    def set_disturbance(self, name: str, value: float) -> None:
        raise KeyError(name)


def test_a_relay_whose_push_moves_nothing_says_so_when_its_time_runs_out():
    """The relay never switches: its time budget ran out with "a slower process needs a
    longer one" (helper trial, a dead valve); it says the PV did not respond."""
    spec = {"model": f"{__name__}:Stuck", "sample_time": 0.1, "noise_std": 0.0}
    loop = build_plant({"seed": 1, "loops": {"s": spec}})["s"]
    req = TuneRequest(loop="s", method="relay", max_time=60.0)
    r = TuningRun(LocalLoopClient(loop), req, "t", RunHooks()).run()
    assert r.status == "aborted" and not r.gains
    assert "the PV did not respond to the relay's push in 60" in r.reason
    assert "(it stayed within 0.001 of 50: a valve that does not move?)" in r.reason
    assert "a slower process" not in r.reason and "after 0 cycles" not in r.reason


def test_a_tiny_but_real_gain_grows_the_relay_above_the_resolution():
    """0.001·6/((s+1)(s+2)(s+3)) on a 0–100 range, noise-free: a relay of 5 % cycles by
    20/(π·10,000) = 6.4e-4, within the 1e-3 a transmitter resolves, and was aborted as no
    response where the step test read its gain (helper trial). The cycle rides on the
    resolution as on a hysteresis: d grows, and the ultimate point is read (K_u = 10,000,
    P_u = 2π/√11, the closed form of 6/((s+1)(s+2)(s+3)) scaled)."""
    spec = {
        "model": "transfer_function",
        "num": [0.006],
        "den": [1.0, 6.0, 11.0, 6.0],
        "delay": 0.0,
        "sample_time": 0.02,
        "noise_std": 0.0,
        "pv_range": [0.0, 100.0],
    }
    loop = build_plant({"seed": 1, "loops": {"t": spec}})["t"]
    events = []
    req = TuneRequest(loop="t", method="relay")
    r = TuningRun(LocalLoopClient(loop), req, "t", RunHooks(event=events.append)).run()
    # read, and its gains not applied: every rule asks more than 1000 %/% of this loop,
    # whose output moves the PV over 0.1 % of its range (test_gain_limit)
    assert r.status == "rejected" and not r.applied and r.restored, r.reason
    assert "Kc above the 1000 % of output per % of span" in r.reason
    (grown,) = [e.data for e in events if e.kind == "amplitude"]
    assert "within the transmitter's resolution" in grown["reason"]
    assert r.ku == pytest.approx(10_000.0, rel=0.01)
    assert r.pu == pytest.approx(2 * math.pi / math.sqrt(11.0), rel=0.005)
