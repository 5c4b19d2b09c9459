"""A run watches while a heavy step computes (the relay's closing fits, the design): in
lockstep it keeps its lease (the plant does not move meanwhile, and a step that outlasts the
lease on a busy machine must not have the plant's watchdog take back a loop the run is still
working on); a cancel or the plant's token vanishing ends the run at once, not when the step
is done.

The slow steps are made slow on purpose (they sleep before computing): they stand for a
worker starting on a machine whose cores are all taken.
"""

from __future__ import annotations

import threading
import time

import pytest

from services.autotuner.loop_client import LoopClient
from services.autotuner.tuning import RunHooks, TuningRun
from shared.messages import TuneRequest
from shared.session import open_session
from tests.integration.tuning_cli import plant_toml

pytestmark = pytest.mark.integration

LEASE = 0.5  # s of wall time: the lease this test's client asks for
# 6/((s+1)(s+2)(s+3)), ~95 samples a period: a relay run of a few thousand samples
CUBIC = {"num": [6.0], "den": [1.0, 6.0, 11.0, 6.0], "delay": 0.0, "sample_time": 0.02}


def test_a_step_slower_than_the_lease_leaves_the_loop_leased(start_plant):
    p = start_plant(plant_toml("x1", CUBIC), loops=("x1",))
    steps: list[str] = []

    def slow(fn, *args):
        time.sleep(3 * LEASE)
        steps.append(fn.__name__)
        return fn(*args)

    with (
        open_session(p.client_settings()) as s,
        LoopClient(s, p.prefix, "x1", lease_timeout=LEASE) as c,
    ):
        req = TuneRequest(loop="x1", method="relay")
        r = TuningRun(c, req, "lease-test", RunHooks(compute=slow)).run()
        assert r.status == "ok", r.reason
        assert steps == ["_finished", "select"]  # the relay's closing fits, then the design
        after = c.sync()
    assert after.leased_by is None  # released at the end, not taken back by the watchdog
    assert after.reason != "watchdog"


def _run_with(p, compute, cancelled=None):
    with (
        open_session(p.client_settings()) as s,
        LoopClient(s, p.prefix, "x1", lease_timeout=LEASE) as c,
    ):
        hooks = RunHooks(compute=compute, cancelled=cancelled)
        return TuningRun(c, TuneRequest(loop="x1", method="relay"), "watch-test", hooks).run()


def test_the_plant_gone_during_a_step_ends_the_run_without_waiting_for_it(start_plant):
    p = start_plant(plant_toml("x1", CUBIC), loops=("x1",))
    finished = threading.Event()

    def kill_then_compute(fn, *args):
        p.proc.kill()
        time.sleep(60.0)  # a step far longer than the run may wait once the plant is gone
        finished.set()
        return fn(*args)

    r = _run_with(p, kill_then_compute)
    assert r.status == "aborted" and "lost the plant" in r.reason, r.reason
    assert not finished.is_set()


def test_a_cancel_during_a_step_ends_the_run_without_waiting_for_it(start_plant):
    p = start_plant(plant_toml("x1", CUBIC), loops=("x1",))
    cancel, finished = threading.Event(), threading.Event()

    def cancel_then_compute(fn, *args):
        cancel.set()
        time.sleep(60.0)
        finished.set()
        return fn(*args)

    r = _run_with(p, cancel_then_compute, cancel)
    assert (r.status, r.reason, r.restored) == ("aborted", "cancelled", True)
    assert not finished.is_set()
