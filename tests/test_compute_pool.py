"""The tuner's worker processes compute a run's heavy steps exactly as its own thread would
(the relay's closing fits, the design), and a lost worker costs the run nothing."""

from __future__ import annotations

import functools
import math
import multiprocessing
import os
import subprocess
import sys
import threading

import numpy as np
import pytest

from services.autotuner.compute_pool import ComputePool, compute_all, inline
from services.autotuner.design.ringing import ringing
from services.autotuner.design.selection import select
from services.autotuner.identify.driver import drive
from services.autotuner.identify.oscillation import SLOW_STARTS
from services.autotuner.identify.relay import RelayConfig, RelayTest
from services.offline.local_loop import SimLoopPort
from services.plant_sim.plant_file import build_plant

PLANT = {"seed": 5, "loops": {"x": {"model": "heat_exchanger", "noise_std": 0.05}}}


@pytest.fixture(scope="module")
def pool():
    p = ComputePool(1)
    yield p
    p.close()


def relay_run(compute=None) -> RelayTest:
    loop = build_plant(PLANT)["x"]
    st = loop.settings
    test = RelayTest(RelayConfig(), loop.op, st.op_limits, st.pv_range, st.sample_time)
    test.compute = compute
    drive(test, SimLoopPort(loop), max_chunk=64)
    return test


def test_the_relay_and_the_design_computed_by_a_worker_are_computed_here(pool):
    here, there = relay_run(), relay_run(pool.call)
    assert here.result is not None, here.reason
    assert repr(there.result) == repr(here.result) and there.events == here.events
    assert there.compute == pool.call  # the worker's copy came back as data only
    ident = here.identification()
    args = (ident, "auto", 2.0, False, 0.5, None, "balanced")
    assert repr(pool.call(select, *args)) == repr(select(*args))


def test_the_design_judged_in_parts_at_once_is_the_design_judged_in_turn(pool):
    """The tuner hands the judging's two parts (robustness, simulated steps) to its workers
    at once: the selection is the same to the bit as one computed in turn here."""
    ident = relay_run().identification()
    args = (ident, "auto", 2.0, False, 0.5, None, "balanced")
    at_once = select(*args, functools.partial(compute_all, pool.call))
    assert repr(at_once) == repr(select(*args))
    assert at_once.assessments and all(a.step is not None for a in at_once.assessments.values())


def ramp_run(parts=None):
    """A ramp on a small lag loop, its closing refines computed by ``parts`` (None: in turn)."""
    from tests.test_ramp_limits import lags_ultimate, make_loop, ramp_for

    _, pu = lags_ultimate(3)
    loop = make_loop([1.0], [1.0, 3.0, 3.0, 1.0], 0.0, pu / 100, noise=0.01, seed=4)
    test = ramp_for(loop)
    if parts is not None:
        test.parts = parts
    drive(test, SimLoopPort(loop, present_first=True), max_chunk=256)
    return test, test.identification()


def test_the_ramp_refined_in_parts_at_once_is_the_ramp_refined_in_turn(pool):
    """The tuner hands the ramp's closing refines (one per starting model), and each trial's
    slow-mode fits (one per start), to its workers at once: the identification is the same
    to the bit."""
    asked: list[int] = []

    def at_once(calls):
        asked.append(len(calls))
        return compute_all(pool.call, calls)

    _, here = ramp_run()
    _, there = ramp_run(at_once)
    assert here.model is not None and asked[-1] == 5
    assert asked[:-1] and set(asked[:-1]) == {len(SLOW_STARTS)}  # a slow-mode fit a trial
    assert repr(there) == repr(here)


def test_a_ringing_fitted_in_parts_at_once_is_the_ringing_fitted_in_turn(pool):
    """The verification hands the ringing fit's slow-mode starts (its steps' modes, the
    unmodelled mode's) to the workers at once: the same mode to the bit. The response: a
    slow approach with a ringing on it, 0.4 e^{−0.08t} sin(2πt/5), whose decay over one
    period is e^{−0.4}."""
    asked: list[int] = []

    def at_once(calls):
        asked.append(len(calls))
        return compute_all(pool.call, calls)

    t = np.arange(0.0, 60.0, 0.05)
    noise = 0.01 * np.random.default_rng(3).standard_normal(t.size)
    y = 1 - 0.6 * np.exp(-t / 20) + 0.4 * np.exp(-0.08 * t) * np.sin(2 * np.pi * t / 5) + noise
    here, there = ringing(t, y, 0.01, 5.0), ringing(t, y, 0.01, 5.0, parts=at_once)
    assert here is not None and here.decay == pytest.approx(math.exp(-0.4), rel=0.02)
    assert asked == [len(SLOW_STARTS)] and repr(there) == repr(here)


def _direct(fn, *args):
    """A compute that is not ``inline``: each call in the thread that asks."""
    return fn(*args)


def test_compute_all_runs_the_calls_at_once():
    """Each call waits for the others at a barrier: in turn, the first would wait alone."""
    barrier = threading.Barrier(3, timeout=10.0)

    def meet(x: int) -> tuple[int, int]:
        barrier.wait()
        return x, threading.get_ident()

    out = compute_all(_direct, [(meet, (1,)), (meet, (2,)), (meet, (3,))])
    assert [x for x, _ in out] == [1, 2, 3]  # in the calls' order
    assert out[0][1] == threading.get_ident() and len({t for _, t in out}) == 3


def test_compute_all_waits_for_every_call_then_raises_the_first_error():
    done = threading.Event()

    def fails() -> None:
        raise ArithmeticError("first")

    def slow() -> int:
        done.wait(0.2)  # still running when the first has failed
        done.set()
        return 1

    with pytest.raises(ArithmeticError, match="first"):
        compute_all(_direct, [(fails, ()), (slow, ()), (fails, ())])
    assert done.is_set()


def test_compute_all_inline_is_in_turn_in_this_thread():
    seen: list[tuple[int, int]] = []

    def note(x: int) -> int:
        seen.append((x, threading.get_ident()))
        return -x

    assert compute_all(inline, [(note, (1,)), (note, (2,))]) == [-1, -2]
    assert seen == [(1, threading.get_ident()), (2, threading.get_ident())]


def _dies_in_a_worker(x: int) -> int:
    if multiprocessing.parent_process() is not None:
        os._exit(3)  # a worker killed mid-step
    return 2 * x


def test_a_lost_worker_costs_the_run_nothing(pool):
    assert pool.call(_dies_in_a_worker, 21) == 42  # computed here instead
    assert pool.call(abs, -3) == 3  # and the pool replaced


def test_a_pool_needs_a_worker():
    with pytest.raises(ValueError, match="workers 0"):
        ComputePool(0)


# in a fresh interpreter (pytest's own process runs threads): a pool's workers, and whose
# children they are, with and without a thread running when ``fork_now`` is asked
FORKED = """
import os, signal, sys, threading, time
from services.autotuner.compute_pool import ComputePool
from services.autotuner.design.selection import select
from services.autotuner.identify.oscillation import SLOW_STARTS
if sys.argv[1] == "thread":
    threading.Thread(target=time.sleep, args=(30,), daemon=True).start()
pool = ComputePool(2)
real_fork, forks = os.fork, []


def fork_once():  # the system refuses every fork after the first (a process limit)
    if forks:
        raise OSError(11, "Resource temporarily unavailable")
    pid = real_fork()
    if pid:
        forks.append(pid)
    return pid


if sys.argv[1] in ("no fork", "one fork"):
    from unittest import mock
    refused = OSError(11, "Resource temporarily unavailable")
    how = {"side_effect": refused} if sys.argv[1] == "no fork" else {"new": fork_once}
    with mock.patch("os.fork", **how):
        forked = pool.fork_now()
    if forks:  # the worker forked before the refusal is gone, not left waiting for work
        assert not os.path.exists(f"/proc/{forks[0]}"), "a worker forked before the refusal"
else:
    forked = pool.fork_now()
parent = pool.call(os.getppid)
workers = {pool.call(os.getpid) for _ in range(20)}
for pid in workers:  # Ctrl-C at a terminal reaches them all, pkill -f the forked ones
    os.kill(pid, signal.SIGINT)
time.sleep(0.5)
print(forked, parent == os.getpid(), pool.call(select.__module__.upper))
pool.close()
"""


def _forked(mode: str) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", FORKED, mode], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr, out.stderr  # a worker interrupted says nothing
    return out.stdout.split()


def test_workers_forked_at_start_up_are_the_process_own_children():
    """Alone (the tuner before its session opens): the workers are forked from it at once,
    its children, and compute as the fork server's would."""
    assert _forked("alone") == ["True", "True", "SERVICES.AUTOTUNER.DESIGN.SELECTION"]


def test_with_a_thread_running_the_workers_come_from_the_fork_server():
    """A fork would copy the other thread's locks in an unknown state: not forked, the
    workers are the fork server's children (started with the first call)."""
    assert _forked("thread") == ["False", "False", "SERVICES.AUTOTUNER.DESIGN.SELECTION"]


def test_a_refused_fork_leaves_the_workers_to_the_fork_server():
    """No fork to be had at start-up: said in a line, and the workers start with the first
    call, from the server, as they would with threads running."""
    assert _forked("no fork") == ["False", "False", "SERVICES.AUTOTUNER.DESIGN.SELECTION"]


def test_a_fork_refused_after_the_first_leaves_no_worker_behind():
    """The first worker forked, the second refused: the first is stopped (found in review:
    it waited for work as long as the tuner lived), the rest left to the server."""
    assert _forked("one fork") == ["False", "False", "SERVICES.AUTOTUNER.DESIGN.SELECTION"]
