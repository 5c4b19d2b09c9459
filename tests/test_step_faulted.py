"""A step test of a faulted loop is refused before it takes the loop's lease, as a tune is:
it took the lease, then failed "output refused … loop restored" (helper review)."""

from __future__ import annotations

import pytest

from services.autotuner.identify.step_test import StepTestConfig
from services.autotuner.step_run import StepTestAborted, run_step_test
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import LeaseCommand

SPEC = {"model": "fopdt", "gain": 1.0, "time_constant": 3.0, "delay": 0.5, "sample_time": 0.1}


class Recording(LocalLoopClient):
    def __init__(self, sim):
        super().__init__(sim)
        self.sent = []

    def command(self, cmd):
        self.sent.append(cmd)
        return super().command(cmd)


def test_a_faulted_loop_is_not_stepped_nor_leased():
    sim = build_plant({"loops": {"x": SPEC}}, "t")["x"]
    sim._set_fault("model: step() raised ValueError: test", sim.op, sim.t)
    client = Recording(sim)
    with pytest.raises(StepTestAborted, match=r"not started: the loop is faulted \(model: "):
        run_step_test(client, StepTestConfig(size=5.0))
    assert not any(isinstance(c, LeaseCommand) for c in client.sent)


def test_limits_the_pv_is_already_outside_are_refused_before_the_lease():
    """`autotune step lvl1 --pv-limits 45 55` of a level at 1.5 m took the loop and aborted
    "left its limits" a second in (user trial): refused before the lease, as a tune is."""
    sim = build_plant({"loops": {"x": SPEC}}, "t")["x"]
    client = Recording(sim)
    with pytest.raises(StepTestAborted, match=r"the PV 50 % is already outside them"):
        run_step_test(client, StepTestConfig(size=5.0, pv_limits=(45.0 + 10, 55.0 + 10)))
    assert not any(isinstance(c, LeaseCommand) for c in client.sent)
