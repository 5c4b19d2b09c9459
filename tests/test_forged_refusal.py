"""Refusals in a client's name told from its own: the plant counts refusals per sender and
names only the last; the client knows what it sent since its last sync. A setpoint forged
outside the PV range in a run's name was refused, and the run, which sent no setpoint,
aborted blaming itself (helper trial)."""

from __future__ import annotations

from collections import Counter

import pytest

from services.autotuner.loop_client import refused_kind, split_refusals

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
