"""Refusals in a client's name told from its own: the plant counts refusals per sender and
names only the last; the client knows what it sent since its last sync. A setpoint forged
outside the PV range in a run's name was refused, and the run, which sent no setpoint,
aborted blaming itself (helper trial)."""

from __future__ import annotations

from collections import Counter

import pytest

from services.autotuner.loop_client import refused_kind, split_refusals
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import ReleaseCommand, TuneRequest

SP = "setpoint: sp 1000000.0 is outside the PV range [0.0, 100.0] %"


@pytest.mark.parametrize(
    ("reason", "kind"),
    [
        (SP, "setpoint"),
        ("advance refused: the plant runs in realtime", "advance"),
        ("lease refused: the loop is leased by 'tuner:b'", "lease"),
        ("gains: kc must be finite", "gains"),
        ("unexpected key 'x'", None),
        (None, None),
    ],
)
def test_the_kind_a_refusal_names(reason, kind):
    assert refused_kind(reason) == kind


@pytest.mark.parametrize(
    ("new", "possible", "last", "split"),
    [
        (0, {}, None, (0, 0)),
        (1, {}, SP, (0, 1)),  # nothing sent that could be refused
        (1, {"setpoint": 1}, SP, (1, 0)),  # its own setpoint
        (1, {"advance": 1}, SP, (0, 1)),  # an advance sent, a setpoint refused
        (2, {"gains": 1}, "gains: kc must be finite", (1, 1)),  # one more than it sent
        # at least max(3 − 2 over, 1 of a kind not sent): the other two may be its own
        (3, {"gains": 1, "advance": 1}, SP, (2, 1)),
        (3, {"gains": 1}, SP, (1, 2)),  # 3 − 1 over
        (1, {"advance": 1}, "unexpected key 'x'", (1, 0)),  # no kind named: may be its own
    ],
)
def test_refusals_split_into_own_and_not_sent(new, possible, last, split):
    assert split_refusals(new, Counter(possible), last) == split


class RefusedInItsName(LocalLoopClient):
    """A client that, at its release, heard of a refusal in its name it did not send."""

    def command(self, cmd):
        status = super().command(cmd)
        if isinstance(cmd, ReleaseCommand):
            self.forged_refused, self.forged_reject = 1, SP
        return status


def test_a_refusal_not_sent_seen_after_the_run_is_a_warning_of_its_result():
    """Seen at its release (no run left to abort: it came after the run's last command),
    it was only logged by the tuner, the result silent on it: now a warning of the result."""
    sim = build_plant({"seed": 1, "loops": {"hx1": {"model": "heat_exchanger"}}})["hx1"]
    req = TuneRequest(loop="hx1", method="relay", apply=False)
    r = TuningRun(RefusedInItsName(sim), req, "x", RunHooks()).run()
    assert r.status == "proposed", r.reason
    said = [w for w in r.warnings if "in this run's name that it did not send" in w]
    assert said == [
        "the plant refused command(s) in this run's name that it did not send (1; the last: "
        f"{SP}): another client on the bus writes as this run (a bus without credentials "
        "cannot tell them apart: see Security)"
    ]
