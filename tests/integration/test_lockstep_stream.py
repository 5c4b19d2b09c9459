"""Batched lockstep (``LoopClient.stream``) against plant_sim as a process: the next batch is
asked for while one is watched, a consumer that stops early leaves the loop at most one batch
past the batch it stopped in, and the in-process client (``LocalLoopClient``) steps exactly
the same samples and leaves the loop at the same time."""

from __future__ import annotations

import tomllib

import pytest

from services.autotuner.loop_client import LoopClient
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.session import open_session

pytestmark = pytest.mark.integration

PLANT = """
seed = 5
[loops.s1]
model = "heat_exchanger"
sample_time = 0.5
noise_std = 0.1
"""
BATCH = 8
STOP_AFTER = 13  # samples taken before the consumer stops (in the second batch)
# asked for when it stops: a batch ahead of the one being watched, i.e. the first two at once
# and the third once the first is taken: 3 batches; the loop is left at sample 24, 11 past
# the last one taken and fewer than 2 batches
ASKED = 3 * BATCH


def _take(stream, n: int) -> list:
    out = []
    for s in stream:
        out.append(s)
        if len(out) == n:
            break
    stream.close()
    return out


def test_a_stream_stopped_early_leaves_the_loop_one_batch_ahead_as_in_process(start_plant):
    plant = start_plant(PLANT, loops=("s1",))
    local = LocalLoopClient(build_plant(tomllib.loads(PLANT))["s1"])
    with (
        open_session(plant.client_settings()) as session,
        LoopClient(session, plant.prefix, "s1", timeout=10.0) as client,
    ):
        start = client.sync().seq
        taken = _take(client.stream(100, BATCH), STOP_AFTER)
        after = client.sync()  # the drained batch is applied; nothing more is on its way
        following = client.advance(1)[0]
    assert [s.seq for s in taken] == list(range(start + 1, start + 1 + STOP_AFTER))
    assert after.seq == start + ASKED
    assert following.seq == start + ASKED + 1  # no sample of the drained batch read as new

    local_start = local.sync().seq
    local_taken = _take(local.stream(100, BATCH), STOP_AFTER)
    assert local.sync().seq == local_start + ASKED
    assert local_start == start
    # the same plant file and seed: the same samples, to the bit
    assert [s.pv for s in local_taken] == [s.pv for s in taken]
    assert local.next_sample().pv == following.pv
