"""A run whose lease is refused (another supervisor holds the loop) says nothing was sent and
nothing of the loop: it printed the holder's relay output as its own "left: manual, OP 45.02
%, the PV is back where it was" (helper 60, two tuners on one loop)."""

from __future__ import annotations

from services.autotuner.loop_client import CommandRefused
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import LeaseCommand, TuneRequest


class HeldElsewhere(LocalLoopClient):
    def command(self, cmd):
        if isinstance(cmd, LeaseCommand):
            why = "lease refused: the loop is leased by 'tuner:b'"
            raise CommandRefused(f"loop {self.loop}: {why}")
        return super().command(cmd)


def test_a_refused_lease_reports_no_loop_state():
    sim = build_plant({"seed": 1, "loops": {"hx1": {"model": "heat_exchanger"}}})["hx1"]
    client = HeldElsewhere(sim)
    r = TuningRun(client, TuneRequest(loop="hx1", method="relay"), "x", RunHooks()).run()
    assert r.status == "aborted" and r.untouched and r.restored
    assert r.reason == "not started: loop hx1: lease refused: the loop is leased by 'tuner:b'"
    assert r.left is None and client.commands == []
