"""Lockstep batches on the bus against plant_sim as a process: an advance of several periods
goes out as ``ProcessSamples`` on ``pv_batch``, one message per part stepped (each sent
before the next is stepped: ``FIRST_CHUNK`` samples, then twice as many each time up to
``STREAM_CHUNK``), one period as a ``ProcessSample`` on ``pv``; the tuner's ``LoopClient``
and the console's bridge see every sample, in order, the same as the in-process loop steps
them; a batch that is not valid is rejected, counted and named, and the advance goes on."""

from __future__ import annotations

import json
import math
import queue
import re
import time
import tomllib

import pytest

from services.autotuner.identify.experiments import Band
from services.autotuner.loop_client import LoopClient
from services.console.bridge import Bridge
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from services.plant_sim.service import FIRST_CHUNK, STREAM_CHUNK
from shared import keys, wire
from shared.messages import (
    GainsCommand,
    ModeCommand,
    PidGains,
    ProcessSample,
    ProcessSamples,
)
from shared.session import open_session

pytestmark = pytest.mark.integration

PLANT = """
seed = 3
[loops.b1]
model = "heat_exchanger"
sample_time = 0.5
noise_std = 0.1
"""
STEPS = 4 * STREAM_CHUNK + 6  # 64, 128, 256, 256, 256 and the rest: six messages
PARTS = [FIRST_CHUNK, 2 * FIRST_CHUNK, *[STREAM_CHUNK] * 3]


def test_an_advance_is_one_message_per_batch_and_the_client_reads_every_sample(
    start_plant, tmp_path
):
    plant = start_plant(PLANT, loops=("b1",))
    local = LocalLoopClient(build_plant(tomllib.loads(PLANT))["b1"])
    seen: queue.Queue[tuple[str, bytes]] = queue.Queue()
    with open_session(plant.client_settings()) as session:
        sub = session.declare_subscriber(
            keys.loop_feed(plant.prefix, "b1"),
            lambda x: seen.put((keys.leaf(str(x.key_expr)), x.payload.to_bytes())),
        )
        bridge = Bridge(session, plant.prefix, tmp_path, lambda msg: None)
        try:
            with LoopClient(session, plant.prefix, "b1", timeout=10.0) as client:
                start = client.sync().seq
                many = client.advance(STEPS)
                one = client.advance(1)
                few = client.advance(3)
            got = [*many, *one, *few]
            # the console's trend: every sample, in order (its reader thread may trail)
            deadline, trend = time.monotonic() + 10.0, {"t": []}
            while len(trend["t"]) < len(got) and time.monotonic() < deadline:
                time.sleep(0.01)
                shown = [m for m in bridge.snapshot() if m["type"] == "trend"]
                trend = shown[0] if shown else trend
        finally:
            bridge.close()
            sub.undeclare()
    assert [s.seq for s in got] == list(range(start + 1, start + STEPS + 5))
    rows = list(zip(trend["t"], trend["pv"], trend["sp"], trend["op"], strict=True))
    assert rows == [(s.t, s.pv, s.sp, s.op) for s in got]

    messages, carried = [], []  # what went over the bus, samples only, in order
    while len(carried) < len(got):
        leaf, payload = seen.get(timeout=10.0)
        if leaf == "pv":
            messages.append((leaf, 1))
            carried.append(wire.decode(ProcessSample, payload))
        elif leaf == "pv_batch":
            batch = wire.decode(ProcessSamples, payload).samples
            messages.append((leaf, len(batch)))
            carried += batch
    assert FIRST_CHUNK * 4 == STREAM_CHUNK
    assert messages == [
        *[("pv_batch", n) for n in PARTS],
        ("pv_batch", STEPS - sum(PARTS)),
        ("pv", 1),
        ("pv_batch", 3),
    ]
    assert carried == got

    # the same plant file and seed in process: the same samples, to the bit
    assert local.sync().seq == start
    assert local.advance(STEPS) + local.advance(1) + local.advance(3) == got


def test_a_bad_batch_is_rejected_counted_and_named_and_the_advance_goes_on(start_plant):
    """Put on the loop's batch key by the client's own session (delivered before the
    plant's answer to the advance that follows): it is not the plant's, so it is rejected,
    counted and named (the client had stopped on it, and a run aborted with pydantic's
    complaint as its reason: helper trial), and the advance takes the plant's samples."""
    plant = start_plant(PLANT, loops=("b1",))
    empty = json.dumps({"loop": "b1", "samples": []}).encode()
    alien = ProcessSample(loop="b9", seq=1, t=0.5, pv=1.0, sp=1.0, op=1.0, mode="auto")
    other = wire.encode(ProcessSamples(loop="b9", samples=[alien]))  # valid, of another loop
    with open_session(plant.client_settings()) as session:
        for payload, says in (
            (empty, r"/b1/pv_batch: samples: List should have at least 1 item"),
            (other, r"/b1/pv_batch: loop: 'b9' in a batch of loop 'b1'$"),
        ):
            with LoopClient(session, plant.prefix, "b1", timeout=10.0) as client:
                start = client.sync().seq
                session.put(keys.pv_batch(plant.prefix, "b1"), payload)
                got = client.advance(2)
                assert [(s.loop, s.seq) for s in got] == [("b1", start + 1), ("b1", start + 2)]
                assert client.rejected == 1
                assert re.search(says, client.last_rejected or ""), client.last_rejected


def _banded_runs(start_plant, band_about, commands=()) -> None:
    """Three banded advances over the bus (the band from the first sample: ``band_about``),
    after ``commands``: each ends at the first sample past the band (the client knows it has:
    no sample more comes, the next advance carries on from there), and the samples are the
    in-process loop's."""
    plant = start_plant(PLANT, loops=("b1",))
    local = LocalLoopClient(build_plant(tomllib.loads(PLANT))["b1"])
    with (
        open_session(plant.client_settings()) as session,
        LoopClient(session, plant.prefix, "b1", timeout=10.0) as client,
    ):
        start = client.sync().seq
        for cmd in commands:
            client.command(cmd.model_copy(update={"source": client.source}))
        first = client.advance(1)[0]
        band = band_about(first)
        runs = [client.samples(500, band) for _ in range(3)]
        after = client.advance(1)
    got = [first, *(s for run in runs for s in run), *after]
    assert [s.seq for s in got] == list(range(start + 1, start + len(got) + 1))
    for run in runs:
        assert 1 <= len(run) < 500
        assert band.ends(run[-1].pv, run[-1].op)
        assert not any(band.ends(s.pv, s.op) for s in run[:-1])
    assert local.sync().seq == start
    for cmd in commands:
        local.command(cmd.model_copy(update={"source": local.source}))
    same = local.advance(1) + [s for _ in runs for s in local.samples(500, band)]
    assert same + local.advance(1) == got


def test_an_advance_with_stops_ends_at_the_first_sample_past_them(start_plant):
    """A relay's band over the bus: PV stops (σ 0.1 of noise leaves ±0.2 soon)."""
    _banded_runs(start_plant, lambda first: Band(first.pv - 0.2, first.pv + 0.2))


def test_an_advance_with_output_stops_ends_where_the_output_reaches_one(start_plant):
    """A ramp's band over the bus: output stops. In auto at a high gain the output carries
    the PV's noise times Kc (σ 2 % of output: ±1 % is soon left)."""
    auto = [
        GainsCommand(loop="b1", gains=PidGains(kc=20.0), source="t"),
        ModeCommand(loop="b1", mode="auto", source="t"),
    ]
    _banded_runs(
        start_plant, lambda first: Band(-math.inf, math.inf, first.op - 1.0, first.op + 1.0), auto
    )
