"""The relay on the realtime clock: a switch decided at a sample holds from the next one (the
plant latches the output at each sample), and each sample carries the output held from it.
Recorded as the samples give it (``outputs_from_samples``, the live run's set-up on that
clock), the relay's ultimate point is the process's, within 1 % of the closed form as in
lockstep; recorded as its own decisions, every switch a sample early, it is not."""

from __future__ import annotations

import pytest

from services.autotuner.identify.driver import drive
from services.autotuner.identify.experiments import Demand, Setup
from services.autotuner.identify.relay import RelayTest, Settings, build
from services.offline.local_loop import Reading
from services.plant_sim.simulation.models import TransferFunctionModel
from tests.exact import ultimate_point

# the heat exchanger e^{−5s}/((10s+1)(60s+1)) sampled as the hx1 preset is (0.25 s: 174
# samples per ultimate period), where a sample of extra delay is 2° of phase at ω_u
HX = ([1.0], [600.0, 70.0, 1.0], 5.0, 0.25)


class RealtimePort:
    """A model on the realtime clock, as plant_sim runs it: at each sample the output latched
    for the period to come is the last one commanded before it; the sample carries that
    output; a command sent in answer to a sample so holds from the next one. The realtime
    tuner takes the samples one at a time."""

    def __init__(self, model: TransferFunctionModel, sample_time: float, op: float):
        self.model, self.ts = model, sample_time
        self.held = self.commanded = op
        self.k = 0

    def samples(self, n: int, band=None) -> list[Reading]:
        pv = self.model.step(self.held)  # the period just ended, at the output latched for it
        self.k += 1
        self.held = self.commanded  # latched at this sample, for the period to come
        return [Reading(self.k * self.ts, pv, self.held)]

    def apply(self, demand: Demand, before: Demand) -> None:
        self.commanded = demand.op

    def hold_time(self) -> float:
        return (self.k + 1) * self.ts


def relay_on_realtime(
    num: list[float], den: list[float], delay: float, ts: float, direction: float, **setup
) -> RelayTest:
    """The relay, as a live run builds it, on num/den·e^{−delay·s} sampled every ``ts`` s on
    the realtime clock (``RealtimePort``); ``direction`` −1: a direct-acting loop (the
    process's gain negative), whose outputs the relay records mirrored, in the loop's own
    sense; ``setup``: the set-up's other fields (``outputs_from_samples``, …)."""
    model = TransferFunctionModel(ts, num=[direction * c for c in num], den=den, delay=delay)
    model.reset()
    limits = {"op_lo": 0.0, "op_hi": 100.0, "pv_lo": -1e6, "pv_hi": 1e6}
    st = Setup(sample_time=ts, **limits, op_start=50.0, direction=direction, **setup)
    test = build(Settings(), st)
    drive(test, RealtimePort(model, ts, 50.0))
    return test


def _relay_on_realtime(outputs_from_samples: bool, direction: float) -> RelayTest:
    """The relay on the heat exchanger, recording from the samples or from its decisions."""
    test = relay_on_realtime(*HX, direction, outputs_from_samples=outputs_from_samples or None)
    assert test.outputs_from_samples is outputs_from_samples
    return test


@pytest.mark.parametrize("direction", [1.0, -1.0], ids=["reverse", "direct"])
def test_recorded_from_the_samples_the_ultimate_point_is_the_processs(direction):
    ku, pu = ultimate_point(*HX[:3])
    r = _relay_on_realtime(True, direction).result
    assert r is not None
    assert r.ku == pytest.approx(ku, rel=0.01)
    assert r.pu == pytest.approx(pu, rel=0.01)


@pytest.mark.parametrize("direction", [1.0, -1.0], ids=["reverse", "direct"])
def test_recorded_as_decided_every_switch_is_a_sample_early_and_the_point_is_off(direction):
    """What the relay measured on this clock before (K_u 5 % low on hx1): the check above
    is not one any record would pass."""
    ku, pu = ultimate_point(*HX[:3])
    r = _relay_on_realtime(False, direction).result
    assert r is not None
    assert r.ku < 0.97 * ku and r.pu > 1.02 * pu


def test_lockstep_set_ups_record_the_decisions_as_before():
    """No ``outputs_from_samples`` in the set-up (lockstep, and every run recorded before it
    existed): the relay records its decisions, so a replay of an older file is the same."""
    setup = Setup(sample_time=0.25, op_lo=0, op_hi=100, pv_lo=0, pv_hi=1, op_start=50, direction=1)
    assert build(Settings(), setup).outputs_from_samples is False
    assert "outputs_from_samples" not in setup.to_dict()
