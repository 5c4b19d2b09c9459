"""Two plant processes found serving one loop after both started: the later started stops.

Two processes started within milliseconds of each other can both miss the other's claim at
start (3 tries in 10 over a router, helper trial: both served the loop). A plant process
watches the other plant processes' instance tokens for as long as it serves. The other
process here is this test's session: it claims the plant's loop, with a start time before
or after the plant's, once the plant's own start check is over (its loop's token is up)."""

from __future__ import annotations

import threading
import time

import pytest

from shared import keys, wire
from shared.messages import ServiceStatus
from shared.session import open_session

pytestmark = pytest.mark.integration

PLANT = """
[loops.x]
model = "fopdt"
gain = 1.0
time_constant = 3.0
delay = 0.5
sample_time = 0.1
"""
INSTANCE = "0123456789ab"


def _claim(
    session,
    prefix: str,
    started: float | None,
    asked: threading.Event | None = None,
    answer: threading.Event | None = None,
):
    """A plant process of node 'other' that serves loop x and started at ``started``;
    ``asked`` set at each query, answered only once ``answer`` is set (None: at once)."""
    status = ServiceStatus(
        node="other",
        clock="lockstep",
        speed=1.0,
        loops={"x": 0.0},
        accepted=0,
        rejected=0,
        rejected_by_reason={},
        overruns=0,
        instance=INSTANCE,
        started=started,
    )
    key = keys.service_status(prefix, "plant_sim", "other")

    def on_query(q):
        if asked is not None:
            asked.set()
        if answer is None or answer.is_set():  # else paused: asked, silent
            wire.reply(q, key, status)

    queryable = session.declare_queryable(key, on_query)
    token = session.liveliness().declare_token(
        keys.service_instance(prefix, "plant_sim", "other", INSTANCE)
    )
    return queryable, token


@pytest.mark.parametrize("started", [0.0, None])  # None: a plant that does not say
def test_a_plant_that_started_later_stops_naming_the_other(start_plant, started):
    plant = start_plant(PLANT, loops=("x",))
    with open_session(plant.client_settings()) as s:
        held = _claim(s, plant.prefix, started=started)  # long before the plant, or unsaid
        assert plant.proc.wait(timeout=30) == 2, plant.stderr()
        del held
    err = plant.stderr()
    assert "plant_sim: error: loop(s) x also served by plant process 'other'" in err, err
    assert f"(instance {INSTANCE})" in err and "this process stops" in err, err


def test_a_plant_that_started_first_goes_on_and_says_the_other_stops(start_plant):
    plant = start_plant(PLANT, loops=("x",))
    with open_session(plant.client_settings()) as s:
        held = _claim(s, plant.prefix, started=time.time() + 3600.0)  # after the plant
        deadline = time.monotonic() + 30.0
        while "it stops" not in plant.stderr() and time.monotonic() < deadline:
            time.sleep(0.05)  # a log line is the only sign: read until it comes (bounded)
        del held
    err = plant.stderr()
    assert "plant process 'other' (instance 0123456789ab), started after this one, also " in err
    assert plant.proc.poll() is None, err  # still serving


def test_a_plant_that_did_not_answer_is_asked_again_once_it_runs(start_plant):
    """A process paused through this one's start (its token alive, its queryable silent) is
    asked again while its token lives, and judged once it answers: both had served the loop
    when it resumed (review)."""
    plant = start_plant(PLANT, loops=("x",))
    asked, answer = threading.Event(), threading.Event()
    with open_session(plant.client_settings()) as s:
        held = _claim(s, plant.prefix, 0.0, asked, answer)
        assert asked.wait(30), plant.stderr()  # asked once, no answer
        answer.set()  # resumed
        assert plant.proc.wait(timeout=30) == 2, plant.stderr()
        del held
    assert "also served by plant process 'other'" in plant.stderr()
