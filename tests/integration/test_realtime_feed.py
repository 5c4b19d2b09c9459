"""On the realtime clock the loop runs on while a command is confirmed: the samples that
arrive while the tuner's client waits for the confirming sync are the run's as much as any.
The client hands them out next, in order, none skipped — an experiment that missed them would
decide on a record with holes, and a replay of the run's file (which has them) would decide
otherwise (a realtime ramp's recording could not be re-analysed: its calming checks, every
8th sample, fell elsewhere)."""

from __future__ import annotations

import time

import pytest

from services.autotuner.loop_client import LoopClient
from shared.messages import GainsCommand, ModeCommand, PidGains, SetpointCommand
from shared.session import open_session

pytestmark = pytest.mark.integration

PLANT = """
seed = 2
[loops.r1]
model = "fopdt"
gain = 1.0
time_constant = 2.0
delay = 0.5
sample_time = 0.05
noise_std = 0.01
"""


def test_samples_that_arrive_while_a_command_is_confirmed_come_next_in_order(start_plant):
    plant = start_plant(PLANT, "--clock", "realtime", "--speed", "20", loops=("r1",))
    with (
        open_session(plant.client_settings()) as session,
        LoopClient(session, plant.prefix, "r1", timeout=10.0) as client,
    ):
        got = [client.next_sample()]
        commands = [
            GainsCommand(loop="r1", gains=PidGains(kc=1.0, ti=2.0), source=client.source),
            ModeCommand(loop="r1", mode="auto", source=client.source),
            SetpointCommand(loop="r1", sp=55.0, source=client.source),
        ]
        for cmd in commands * 3:  # each confirmed by a sync while the loop runs on
            # the loop runs on meanwhile (a tuner computing): its samples queue up, and the
            # sync below reads past them to its answer (not a wait for anything: any number
            # queued, none included, must come out the same)
            time.sleep(0.03)
            client.command(cmd)
            got += [client.next_sample() for _ in range(5)]
        last = client.sync()
    seqs = [s.seq for s in got]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # none skipped, in order
    assert last.seq >= seqs[-1]
