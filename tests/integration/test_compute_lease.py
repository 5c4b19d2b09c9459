"""A run watches while a heavy step computes (the relay's closing fits, the design): it
keeps its lease (a step that outlasts the lease on a busy machine must not have the plant's
watchdog take back a loop the run is still working on); in realtime, where the loop goes on
meanwhile, only while the PV stays within the experiment's limits; a cancel or the plant's
token vanishing ends the run at once, not when the step is done.

The slow steps are made slow on purpose (they sleep before computing): they stand for a
worker starting on a machine whose cores are all taken.
"""

from __future__ import annotations

import re
import threading
import time

import pytest

from services.autotuner.loop_client import LoopClient
from services.autotuner.tuning import RunHooks, TuningRun
from shared.messages import DisturbanceCommand, TuneRequest
from shared.session import open_session
from tests.integration.tuning_cli import plant_toml

pytestmark = pytest.mark.integration

LEASE = 0.5  # s of wall time: the lease this test's client asks for
# realtime (both realtime cases): twice that. The slow-step case failed once in CI with 0.5 s
# (its output was not kept): between the slow steps the run renews its lease as samples come,
# and on the suite's two loaded cores 0.5 s of wall time leaves little slack. The slow steps
# still outlast it 3×.
LEASE_RT = 2 * LEASE
# 6/((s+1)(s+2)(s+3)), ~95 samples a period: a relay run of a few thousand samples
CUBIC = {"num": [6.0], "den": [1.0, 6.0, 11.0, 6.0], "delay": 0.0, "sample_time": 0.02}
# the same on the realtime clock at ×5: a sample every 10 ms of wall time (38 a period)
REALTIME = ("--clock", "realtime", "--speed", "5")
CUBIC_RT = {**CUBIC, "sample_time": 0.05}
# the relay's cycles agree within this in the realtime cases (the default 2 %: a switch held
# one sample late moves a period 2.6 %): the steps are under test, not the relay's accuracy
RT_TOLERANCE = 0.05


@pytest.mark.parametrize(
    "clock",
    [
        "lockstep",
        # seen in CI: the relay's closing fits took over the 3 s lease of a realtime run on a
        # loaded machine; the plant's watchdog took the loop back and the healthy run aborted
        "realtime",
    ],
)
def test_a_step_slower_than_the_lease_leaves_the_loop_leased(start_plant, clock):
    if clock == "lockstep":
        p = start_plant(plant_toml("x1", CUBIC), loops=("x1",))
        req, ends = TuneRequest(loop="x1", method="relay"), "ok"
    else:  # proposed, not applied: the steps are what is tested, not the verification
        p = start_plant(plant_toml("x1", CUBIC_RT), *REALTIME, loops=("x1",))
        req = TuneRequest(loop="x1", method="relay", apply=False, tolerance=RT_TOLERANCE)
        ends = "proposed"
    steps: list[str] = []
    lease = LEASE if clock == "lockstep" else LEASE_RT

    def slow(fn, *args):
        time.sleep(3 * lease)
        steps.append(fn.__name__)
        return fn(*args)

    with (
        open_session(p.client_settings()) as s,
        LoopClient(s, p.prefix, "x1", lease_timeout=lease) as c,
    ):
        r = TuningRun(c, req, "lease-test", RunHooks(compute=slow)).run()
        assert r.status == ends, r.reason
        # the relay's closing fits, then the design's two parts (at once, each slow); the
        # setpoint steps only where a model was fitted to simulate them on (seen in CI: a
        # realtime run on a loaded machine fitted none, judged the rules and proposed)
        assert steps[0] == "_finished"
        design = ["judge_all", "predicted_setpoint_steps"] if r.robustness else ["judge_all"]
        # (then the verification's ringing fits, their slow-mode starts side by side)
        assert sorted(steps[1 : 1 + len(design)]) == design, (r.robustness, r.warnings)
        assert set(steps[1 + len(design) :]) <= {"_slow_start"}, steps
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


def test_the_pv_leaving_its_limits_during_a_step_in_realtime_aborts_and_restores(start_plant):
    """The lease is kept through a step only while the loop stays within the experiment's
    limits: a load upset meanwhile ends the run at once, and the loop is restored."""
    p = start_plant(plant_toml("x1", CUBIC_RT), *REALTIME, loops=("x1",))
    finished = threading.Event()
    with (
        open_session(p.client_settings()) as s,
        LoopClient(s, p.prefix, "x1", lease_timeout=LEASE_RT) as c,
    ):
        before = c.sync()

        def upset_then_compute(fn, *args):
            # the process upset while the run computes (sent in the run's name: the loop is
            # leased, and any other client's command would be refused)
            c.send(DisturbanceCommand(loop="x1", name="load", value=30.0, source=c.source))
            time.sleep(30.0)  # far longer than the run may go on once the PV is out
            finished.set()
            return fn(*args)

        req = TuneRequest(loop="x1", method="relay", pv_limits=(40.0, 60.0), tolerance=RT_TOLERANCE)
        r = TuningRun(c, req, "limits-test-rt", RunHooks(compute=upset_then_compute)).run()
        after = c.sync()
    # the run, which watches the samples as it computes, or the plant, which restores a
    # leased loop at the first PV past the lease's limits, whichever reads the sample first
    assert r.status == "aborted" and r.restored is True, r.reason
    by_plant = re.search(r"the PV ([-0-9.e+]+) left the experiment's limits \[40, 60\]", r.reason)
    assert ("left its limits" in r.reason and "while the run computed" in r.reason) or (
        by_plant is not None and float(by_plant[1]) > 60.0
    ), r.reason
    assert not finished.is_set()
    assert (after.mode, after.op, after.leased_by) == (before.mode, before.op, None)
