"""A rejection says the previous gains were restored only where the run's own restore did
so: hx2's forced ZN PID, rejected for its overshoot, with the restore's output command
refused, was reported "previous gains restored; the loop is NOT as it was before the test"
(review). The release then asks the plant to restore its state before the test, and the
result says which of the two put the loop back."""

from __future__ import annotations

import tomllib

import pytest

from services.autotuner.loop_client import CommandRefused
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant, default_plant_path
from shared.messages import OutputCommand, TuneRequest


class Refusing(LocalLoopClient):
    """A local client whose plant refuses output commands once ``refuse`` is set."""

    refuse = False

    def command(self, cmd):
        if self.refuse and isinstance(cmd, OutputCommand):
            raise CommandRefused("loop hx2: output: refused (test)")
        return super().command(cmd)


def test_a_failed_restore_is_not_said_done(monkeypatch: pytest.MonkeyPatch) -> None:
    with open(default_plant_path(), "rb") as f:
        doc = tomllib.load(f)
    doc["seed"] = 11
    sim = build_plant(doc, "unit")["hx2"]
    before = sim.snapshot()
    client = Refusing(sim)
    restore = TuningRun._restore

    def failing(self: TuningRun) -> bool:
        client.refuse = True  # the restore's output is refused
        return restore(self)

    monkeypatch.setattr(TuningRun, "_restore", failing)
    req = TuneRequest(loop="hx2", method="relay", rule="zn-pid", force=True)
    r = TuningRun(client, req, "unit").run()
    assert r.status == "rejected" and "overshoot" in r.reason, r.reason
    assert "previous gains restored" not in r.reason, r.reason
    assert "could not restore the state before the test itself" in r.reason, r.reason
    # the release asked the plant to: it did, and the result says so
    assert r.restored is True and "the plant restored the loop" in r.reason, r.reason
    after = sim.snapshot()
    assert (after.mode, after.gains, after.op) == (before.mode, before.gains, before.op)
