"""The P-gain ramp in few lockstep round trips: ``RampTest.horizon`` counts the samples up to
the next one at which the test may decide anything, and ``RampTest.band`` ends a batch at the
first sample past the PV limits, the trial's swing limit, or with the output at a limit — so
a run in batches is the run fed sample by sample: the same samples, events, trials and
result, to the bit. Checked on the ramp's hard cases (output saturating at rest and in a
trial, start gains far too high, budgets running out) and on whole live-path runs of the
preset loops and a direct-acting loop."""

from __future__ import annotations

import math
import tomllib
from collections import Counter
from importlib.resources import files

import numpy as np
import pytest

from services.autotuner.identify.driver import drive
from services.autotuner.identify.ramp import RampConfig, RampTest
from services.offline.local_loop import SimLoopPort
from shared.messages import GainsCommand, PidGains
from tests.plants import drive_in_batches, live_tune
from tests.test_ramp_limits import (
    RELAY_SWING,
    fopdt_ultimate,
    hx_ultimate,
    lags_ultimate,
    make_loop,
    ramp_for,
)
from tests.test_relay_band import CLIPPED, DIRECT

PLANT = tomllib.loads(files("services.plant_sim").joinpath("plants/default.toml").read_text())


def lag_dominated():
    ku, pu = fopdt_ultimate(1.0, 50.0, 1.0)
    loop = make_loop([1.0], [50.0, 1.0], 1.0, pu / 100, noise=0.01 * RELAY_SWING / ku, seed=3)
    return loop, ramp_for(loop), 400 * pu


def huge_start(noise: float):
    def build():
        ku, pu = fopdt_ultimate(1.0, 1.0, 1.0)
        loop = make_loop([1.0], [1.0, 1.0], 1.0, pu / 400, noise=noise * RELAY_SWING / ku, seed=1)
        return loop, ramp_for(loop, kc_start=1e6), 200 * pu

    return build


def saturating_trial():
    _, pu = hx_ultimate()
    loop = make_loop([1.0], [600.0, 70.0, 1.0], 5.0, 0.05, kc=4.0)
    return loop, ramp_for(loop), 200 * pu


def eight_lags():
    ku, pu = lags_ultimate(8)
    den = [float(c) for c in np.poly([-1.0] * 8)]
    loop = make_loop([1.0], den, 0.0, pu / 400, noise=0.01 * RELAY_SWING / ku, seed=2)
    return loop, ramp_for(loop), 200 * pu


def budget(**limits):
    """A 4-lag loop whose budget (``total_periods``; ``max_time`` in exact periods) runs out."""

    def build():
        ku, pu = lags_ultimate(4)
        ts = pu / 400
        loop = make_loop([1.0], [float(c) for c in np.poly([-1.0] * 4)], 0.0, ts)
        scaled = {k: v * pu if k == "max_time" else v for k, v in limits.items()}
        cfg = RampConfig(kc_start=0.3 * ku, bump=1.0, **scaled)
        test = RampTest(cfg, (0.0, 100.0), ts, sp_start=loop.pv, op_limits=(0.0, 100.0))
        loop.apply(GainsCommand(loop="x", gains=PidGains(kc=cfg.kc_start)))
        return loop, test, 200 * pu

    return build


def swinging():
    """A tight swing limit on a noisy loop: trials cut by the swing band."""
    ku, pu = lags_ultimate(3)
    ts = pu / 200
    loop = make_loop([1.0], [1.0, 3.0, 3.0, 1.0], 0.0, ts, noise=0.05, seed=4)
    cfg = RampConfig(kc_start=0.5 * ku, bump=1.0, swing_limit=1.5)
    test = RampTest(cfg, (0.0, 100.0), ts, sp_start=loop.pv, op_limits=(0.0, 100.0))
    loop.apply(GainsCommand(loop="x", gains=PidGains(kc=cfg.kc_start)))
    return loop, test, 300 * pu


def late(build):
    """The same case on a clock at 1.2e10 s (sample 123,456,789,012 × its sample time):
    the times' rounding grows with them (``samples_until``)."""

    def built():
        loop, test, limit = build()
        loop.seq = 123_456_789_012 if loop.sample_time < 1.0 else 12_345_678_901
        return loop, test, limit

    return built


CASES = {
    "lag-dominated": lag_dominated,
    "huge-start-noise": huge_start(0.01),
    "huge-start-quiet": huge_start(0.0),
    "saturating-trial": saturating_trial,
    "eight-lags": eight_lags,
    "period-budget": budget(total_periods=6.0),
    "max-time": budget(max_time=5.0),
    "swing-limit": swinging,
    "max-time-late": late(budget(max_time=5.0)),
    "lag-dominated-late": late(lag_dominated),
}


def run(case: str, cap: int):
    loop, test, limit = CASES[case]()
    calls = drive_in_batches(test, loop, cap, limit)
    record = (test._t, test._y, test._u, test.events, test.trials, test.phase, test.reason)
    return record, test.result, (loop.seq, loop.pv, loop.op, loop.sp), calls, test


def _kinds(test: RampTest) -> list[str]:
    return [e[1] for e in test.events]


# what each case is there for (else it tests less than it says)
REACHES = {
    "lag-dominated": lambda t: t.result is not None and "bump" in _kinds(t),
    "huge-start-noise": lambda t: "back_off" in _kinds(t),
    "huge-start-quiet": lambda t: "back_off" in _kinds(t),
    "saturating-trial": lambda t: "saturated" in _kinds(t),
    "eight-lags": lambda t: t.finished,
    "period-budget": lambda t: "periods" in t.reason,
    "max-time": lambda t: "max_time" in t.reason,
    "swing-limit": lambda t: any(tr.cut_short for tr in t.trials),
    "max-time-late": lambda t: "max_time" in t.reason,
    "lag-dominated-late": lambda t: t.result is not None,
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_batched_ramp_is_the_ramp_fed_sample_by_sample(case: str) -> None:
    one, result_one, left_one, by_one, _ = run(case, 1)
    batched, result, left, by_batch, test = run(case, 1024)
    assert REACHES[case](test), case
    assert batched == one
    assert repr(result) == repr(result_one)  # NaN-safe, to the bit
    assert left == left_one
    assert by_batch["batches"] < 0.5 * by_one["batches"]


def tune(loop: str, per_sample: bool, monkeypatch, plant: dict = PLANT, **request):
    """A whole live-path ramp run on a fresh loop: its result and the loop as left."""
    one = (RampTest,) if per_sample else ()
    return live_tune(plant, loop, monkeypatch, one, method="ramp", **request)


@pytest.mark.parametrize(("loop", "plant"), [("hx1", PLANT), ("flow1", PLANT), ("d1", DIRECT)])
def test_live_ramp_runs_are_the_runs_fed_sample_by_sample(loop, plant, monkeypatch) -> None:
    one, left_one = tune(loop, True, monkeypatch, plant)
    batched, left = tune(loop, False, monkeypatch, plant)
    assert one["ku"] is not None and math.isfinite(one["ku"]), one["reason"]
    assert batched == one and left == left_one


def test_a_calming_is_a_batch_or_two_not_one_per_check() -> None:
    """The loop makes the calming's checks as it steps (``Band.calm``), so a calming between
    trials ends in a batch or two (its window's start, then the check that passes), where a
    round trip per check (every 8th sample) took dozens."""
    loop, test, limit = lag_dominated()
    port = SimLoopPort(loop, present_first=True, limit=limit)
    take = port.samples
    in_settle: Counter[str] = Counter()

    def counted(n, band=None):
        in_settle[test.phase] += 1
        return take(n, band)

    port.samples = counted
    drive(test, port, held=port.held_now(), max_chunk=1024)
    calmings = sum(1 for e in test.events if e[1] == "trial") - 1
    assert calmings >= 5 and test.result is not None
    assert in_settle["settle"] <= 3 * calmings


def test_a_calming_with_its_output_at_a_limit_is_batched_not_a_sample_a_round_trip() -> None:
    """A calming whose output sits at a limit is stuck once it has sat there for half its
    window: each sample adds one at most to that count, so the batch runs to the first sample
    at which it could be (``_until_stuck``), where a round trip a sample took hundreds (the
    run is still the one fed sample by sample: above)."""
    loop, test, limit = huge_start(0.0)()
    port = SimLoopPort(loop, present_first=True, limit=limit)
    take = port.samples
    at_limit: Counter[str] = Counter()

    def counted(n, band=None):
        out = take(n, band)
        if test.phase == "settle" and test._sat_run:
            at_limit["batches"] += 1
            at_limit["samples"] += len(out)
        return out

    port.samples = counted
    drive(test, port, held=port.held_now(), max_chunk=1024)
    assert "calm" in _kinds(test) and at_limit["samples"] >= 200
    assert at_limit["batches"] <= 0.1 * at_limit["samples"]


def test_a_pv_clipped_inside_wider_limits_ends_the_batch_where_it_aborts(monkeypatch):
    """The ramp's band ends a batch at an end of the transmitter's range inside wider PV
    limits, where the test aborts (``clipped``), as the relay's does."""
    # the range's top 0.5 above the rest: a bump of 0.2 fits under it, a growing swing not
    plant = {**CLIPPED, "loops": {"c1": {**CLIPPED["loops"]["c1"], "pv_range": [0.0, 60.5]}}}
    wide = {"plant": plant, "pv_limits": (-100.0, 200.0), "bump": 0.2}
    one, left_one = tune("c1", True, monkeypatch, **wide)
    batched, left = tune("c1", False, monkeypatch, **wide)
    assert one["status"] == "aborted" and "transmitter's range" in one["reason"]
    assert batched == one and left == left_one
