"""Refusals in a client's name told from its own: the plant counts refusals per sender and
names only the last; the client knows what it sent since its last sync. A setpoint forged
outside the PV range in a run's name was refused, and the run, which sent no setpoint,
aborted blaming itself (helper trial)."""

from __future__ import annotations

from collections import Counter

import pytest

from services.autotuner.loop_client import LoopClient, refused_kind, split_refusals
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import LoopStatus, ReleaseCommand, TuneRequest

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


def _client() -> LoopClient:
    """A client's refusal bookkeeping as its constructor leaves it (no bus)."""
    c = LoopClient.__new__(LoopClient)
    c.loop, c.source = "hx1", "autotune-set"
    c._refused, c._own_refused, c._own_reject = None, 0, None
    c.forged_refused, c.forged_reject = 0, None
    c._unanswered, c._sent_unnamed = Counter(), Counter()
    return c


def _answer(rejected: int, last: str | None) -> LoopStatus:
    """A sync's answer as far as the refusals go."""
    return LoopStatus.model_construct(sync_rejected=rejected, sync_last_reject=last)


def test_refusals_before_the_client_began_are_neither_its_own_nor_forged():
    """The plant counts by source; `autotune set` and the console use one fixed source, so a
    new client's first sync carries the refusals of every earlier one (an earlier `set`
    refused once: the next `set` logged "1 refusal(s) in this client's name of commands it
    did not send"). The first answer is the baseline; refusals after it are split."""
    c = _client()
    assert c._count_refusals(_answer(3, SP)) == 0
    assert (c.forged_refused, c._own_refused) == (0, 0)
    assert c._count_refusals(_answer(4, SP)) == 1  # one more, no setpoint sent: not its own
    assert (c.forged_refused, c._own_refused) == (1, 0)
