"""The open-loop step test in few lockstep round trips: ``StepTest.horizon`` counts the
samples up to the next one at which the test may decide anything (the baseline's rest, the
rest and trend checks every ``SETTLE_CHECK_EVERY`` samples, the timeout, an integrating
loop's pulse and rest window), and ``StepTest.band`` ends a batch at the first sample past
the PV limits or at an end of the transmitter's range — so a run in batches is the run fed
sample by sample: the same samples, events and result, to the bit. Checked on the test's
ways to end (at rest, an integrator's return pulse, the range's end, the allowance, the PV
limits, the timeout), on repeated tests (``RepeatedSteps``: the running test's horizon, then
each return to rest up to its next check), and on whole live-path runs of the preset loops."""

from __future__ import annotations

import tomllib
from importlib.resources import files

import pytest

from services.autotuner.identify.repeated_steps import RepeatedSteps
from services.autotuner.identify.step_test import StepTest, StepTestConfig
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from services.plant_sim.simulation.loop import SimLoop
from shared.messages import ModeCommand, OutputCommand
from tests.plants import drive_in_batches, live_tune, transfer_function_loop

PLANT = tomllib.loads(files("services.plant_sim").joinpath("plants/default.toml").read_text())


def open_loop(
    num, den, delay, ts, noise=0.0, seed=0, pv_range=(0.0, 100.0), start: int = 0
) -> SimLoop:
    """A transfer-function loop in manual at 50 % output, its clock at sample ``start``."""
    loop = transfer_function_loop(num, den, delay, ts, noise, seed, pv_range)
    loop.apply(ModeCommand(loop="x", mode="manual"))
    loop.apply(OutputCommand(loop="x", op=50.0))
    loop.seq = start
    return loop


def step_for(loop: SimLoop, size: float, **config) -> StepTest:
    st = loop.settings
    limits = config.pop("pv_limits", st.pv_range)
    return StepTest(
        StepTestConfig(size=size, **config),
        loop.op,
        st.op_limits,
        limits,
        loop.sample_time,
        pv_range=st.pv_range,
    )


def lag(size: float = 5.0, noise: float = 0.02, pv_range=(0.0, 100.0), start=0, **config):
    """A first-order lag with dead time: the PV comes to rest."""
    loop = open_loop(
        [2.0], [20.0, 1.0], 3.0, 0.1, noise=noise, seed=1, pv_range=pv_range, start=start
    )
    return loop, step_for(loop, size, **config)


def fast():
    """A lag of a second, no dead time, stepped far past the range's top."""
    loop = open_loop([2.0], [1.0, 1.0], 0.0, 0.1, noise=0.02, seed=3, pv_range=(0.0, 80.0))
    # PV limits wider than the range: only the range's end stops the batch
    return loop, step_for(loop, 30.0, max_move=1.0, pv_limits=(-1000.0, 1000.0))


def integrator(start: int = 0, **config):
    """A level: the PV ramps; the return pulse gives it back its level."""
    loop = open_loop([0.05], [1.0, 0.0], 2.0, 0.1, noise=0.01, seed=2, start=start)
    return loop, step_for(loop, 5.0, **config)


LATE = 123_456_789_012  # a clock at 1.2e10 s: the times' rounding is 1e-6 s and more


def repeated(integrating: bool = False, noise: float = 0.02, pv_limits=None, **kw):
    """Up and down steps from rest, each one's return to rest watched (``ReturnWatch``)."""
    limits = {} if pv_limits is None else {"pv_limits": pv_limits}
    loop, single = integrator(**limits) if integrating else lag(noise=noise, **limits)
    return loop, RepeatedSteps.like(single, **kw)


CASES = {
    "at-rest": lambda: lag(),
    "at-rest-step-down": lambda: lag(-4.0),
    "quiet": lambda: lag(noise=0.0),
    "integrating": lambda: integrator(),
    # the PV's gain takes it past the range's top: stopped before it clips
    "range-end": lambda: lag(20.0, pv_range=(0.0, 80.0), max_move=1.0),
    # a fast lag past the range's top between two checks: the band ends the batch there
    "clipped": lambda: fast(),
    # a small allowance: stopped before the PV leaves it
    "allowance": lambda: lag(10.0, max_move=0.05),
    # PV limits inside the range: stopped before the PV would leave them
    "pv-limits": lambda: lag(10.0, pv_limits=(0.0, 55.0)),
    "timeout": lambda: lag(timeout=31.3),  # between two checks
    "integrating-late": lambda: integrator(LATE),
    "timeout-late": lambda: lag(start=LATE, timeout=0.7),
    "repeated": lambda: repeated(repeat=3),
    "repeated-auto": lambda: repeated(repeat=4, auto=True),
    "repeated-integrating": lambda: repeated(True, repeat=2),
    # the first (up) step leaves the PV limits; then the second (down) one
    "repeated-limits-first": lambda: repeated(pv_limits=(0.0, 55.0), repeat=3),
    "repeated-limits-second": lambda: repeated(pv_limits=(45.0, 100.0), repeat=3),
}

REACHES = {
    "at-rest": lambda t: t.phase == "done",
    "at-rest-step-down": lambda t: t.phase == "done",
    "quiet": lambda t: t.phase == "done",
    "integrating": lambda t: t.phase == "done" and t.ramp is not None,
    "range-end": lambda t: "would reach the top of its range" in t.reason,
    "clipped": lambda t: "reached the top of its range" in t.reason,
    "allowance": lambda t: "allowance" in t.reason,
    "pv-limits": lambda t: "would leave its limits" in t.reason,
    "timeout": lambda t: "no steady state" in t.reason,
    "integrating-late": lambda t: t.phase == "done" and t.ramp is not None,
    "timeout-late": lambda t: "no steady state" in t.reason,
    "repeated": lambda t: t.phase == "done" and len(t.done) == 3,
    "repeated-auto": lambda t: t.phase == "done" and len(t.done) >= 2,
    "repeated-integrating": lambda t: t.phase == "done" and len(t.done) == 2,
    "repeated-limits-first": lambda t: t.reason.startswith("test 1 of 3") and not t.done,
    "repeated-limits-second": lambda t: t.reason.startswith("test 2 of 3") and len(t.done) == 1,
}


def run(case: str, cap: int):
    loop, test = CASES[case]()
    calls = drive_in_batches(test, loop, cap, 20_000.0)
    if isinstance(test, RepeatedSteps):
        record = ([(s.t, s.pv, s.events) for s in test.done], test.events, test.phase, test.reason)
    else:
        record = (test.t, test.pv, test.events, test.phase, test.reason, test.t_step)
    return record, test.identification(), (loop.seq, loop.pv, loop.op), calls, test


@pytest.mark.parametrize("case", sorted(CASES))
def test_batched_step_test_is_the_test_fed_sample_by_sample(case: str) -> None:
    one, found_one, left_one, by_one, _ = run(case, 1)
    batched, found, left, by_batch, test = run(case, 1024)
    assert REACHES[case](test), (case, test.phase, test.reason)
    assert batched == one
    assert repr(found) == repr(found_one)  # NaN-safe, to the bit
    assert left == left_one
    assert by_batch["batches"] < 0.3 * by_one["batches"]


def tune(loop: str, per_sample: bool, monkeypatch, repeat: int | None) -> tuple[dict, tuple]:
    """A whole live-path step tune on a fresh preset loop: its result and the loop as left."""
    one = (StepTest, RepeatedSteps) if per_sample else ()
    return live_tune(PLANT, loop, monkeypatch, one, method="step", repeat=repeat)


@pytest.mark.parametrize(("loop", "repeat"), [("flow1", None), ("hx1", None), ("lvl1", 2)])
def test_live_step_tunes_are_the_tunes_fed_sample_by_sample(loop, repeat, monkeypatch) -> None:
    one, left_one = tune(loop, True, monkeypatch, repeat)
    batched, left = tune(loop, False, monkeypatch, repeat)
    assert one["status"] in ("ok", "rejected"), one["reason"]
    assert batched == one and left == left_one


def step_command(model: str, per_sample: bool, monkeypatch, **kw):
    """``autotune step``'s run (``run_step_test``) on a fresh loop, lockstep in process: its
    report and the loop as left (with the wait for the return to rest)."""
    from services.autotuner.identify.step_test import ReturnWatch
    from services.autotuner.step_run import run_step_test

    sim = build_plant({"seed": 1, "loops": {"x": {"model": model}}})["x"]
    with monkeypatch.context() as m:
        if per_sample:
            m.setattr(StepTest, "horizon", lambda self, cap: 1)
            m.setattr(RepeatedSteps, "horizon", lambda self, cap: 1)
            m.setattr(ReturnWatch, "horizon", lambda self, cap, ts: 1)
        seen: list[float] = []
        report = run_step_test(
            LocalLoopClient(sim),
            StepTestConfig(size=5.0),
            progress=lambda test, s: seen.append(s.t),
            **kw,
        )
    return report, seen, (sim.seq, sim.pv, sim.op, sim.mode)


@pytest.mark.parametrize(
    ("model", "kw"),
    [
        ("heat_exchanger", {}),
        ("heat_exchanger", {"repeat": 2}),
        ("tank_level_integrating", {}),
    ],
)
def test_the_step_command_in_batches_is_the_command_fed_sample_by_sample(model, kw, monkeypatch):
    """``autotune step`` drives its test (and the wait for the return to rest) in the same
    batches: the same report, every sample shown to its progress once, the loop left alike."""
    one = step_command(model, True, monkeypatch, **kw)
    batched = step_command(model, False, monkeypatch, **kw)
    assert repr(batched[0]) == repr(one[0]) and batched[1:] == one[1:]
    assert one[0].restored and len(one[1]) == len(set(one[1])) > 100
    assert batched[2][0] == len(batched[1])  # the loop stepped the samples shown, no more


def test_samples_until_counts_to_the_first_sample_that_may_reach_a_time_limit():
    """A time limit's batch ends with the first sample whose time may reach it (it may
    decide there), never later, the rounding of the sample times (k·T) and the step test's
    tolerance (1e-9 of the time) allowed for; a limit past, or not a number, is the next
    sample; none, no bound."""
    import math
    import random

    from services.autotuner.identify.experiments import samples_until

    assert samples_until(1.0, 0.1, 0.0) == 10  # the 10th sample is at the limit: it decides
    assert samples_until(1.05, 0.1, 0.0) == 11
    assert samples_until(0.0, 0.1, 5.0) == 1 and samples_until(-3.0, 0.1, 5.0) == 1
    assert samples_until(math.nan, 0.1, 5.0) == 1 and samples_until(-math.inf, 0.1, 5.0) == 1
    assert samples_until(math.inf, 0.1, 5.0) == 1 << 30
    rng = random.Random(3)
    for _ in range(20_000):
        ts = rng.choice([0.01, 0.05, 0.1, 0.25, 0.37, 1.0, 10.0])
        seq = rng.choice([0, 1, 17, 10**4, 10**6, 10**8, 123_456_789, 10**11])
        m = rng.randint(1, 2_000)
        seconds = rng.choice([m * ts, (m + 0.5) * ts, m * ts * (1 + 1e-12), (m - 1e-9) * ts])
        t0 = seq * ts
        k = samples_until(seconds, ts, t0)
        # the first sample whose time, as the plant computes it, reaches the limit, with
        # either comparison the experiments make (>= with the tolerance, or > exactly)
        first = next(
            j
            for j in range(1, m + 3)
            if (seq + j) * ts - t0 >= seconds - 1e-9 * max(1.0, abs((seq + j) * ts))
        )
        assert 1 <= k <= first, (ts, seq, seconds, k, first)
        if seq * ts < 1e3:  # early on, no more than a sample short
            assert k >= first - 1, (ts, seq, seconds, k, first)
