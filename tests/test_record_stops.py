"""The plant's end test of a verification record (``RecordStops.stop_test``, asked of each
sample as the plant steps) stops at the first judging point where the tuner's own judging of
the record (its rule, written out below from ``TuningRun._record``'s doc: the guard at the
first judge boundary after each window, ``done`` at multiples of 8·judge, the PV limits on
every sample) stops it — or, only where the "long enough" test in sim time is a sample short,
at most a judging point earlier; never later. A record that ends later than the plant stopped
would have run the loop on under gains being judged."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from services.autotuner.identify.experiments import Band
from shared.control.record_stops import Guard, SettleRule, judge_point, settle_point
from shared.messages import AdvanceCommand, CalmStop, GuardStop, RecordStops, SettleStop


def tuner_end(t, y, u, judge, n_max, done: SettleRule, guard: Guard | None, target, lo, hi):
    """Where the tuner's judging ends the record (index + 1), None if it runs to n_max."""
    windows = 0
    for m in range(1, n_max + 1):
        if not lo <= y[m - 1] <= hi:
            return m
        if m % judge and m < n_max:
            continue
        if guard is not None and m // guard.n > windows:
            windows = m // guard.n
            if guard.check(np.asarray(y[:m]) - target, np.asarray(u[:m])):
                return m
        if m % (8 * judge) < judge and done.done(np.asarray(t[:m]), np.asarray(y[:m])):
            return m
    return None


def plant_end(y, u, cmd: AdvanceCommand):
    ends = cmd.stop_test()
    for m in range(1, cmd.steps + 1):
        if ends(y[m - 1], u[m - 1]):
            return m
    return None


def record(rng: random.Random, n: int, kind: str):
    """A PV record about a target of 50: settling, growing, or saturating."""
    t0 = rng.randint(0, 10**6)
    ts = rng.choice([0.1, 0.25, 0.05, 1.0 / 3.0, 0.7])
    t = [(t0 + j) * ts for j in range(n)]
    w = rng.uniform(0.02, 0.3)
    g = {"settle": -rng.uniform(0.002, 0.05), "grow": rng.uniform(0.002, 0.02), "sat": 0.0}[kind]
    noise = rng.uniform(0.0, 0.05)
    y = [50 + 5 * math.exp(g * j) * math.cos(w * j) + rng.gauss(0, noise) for j in range(n)]
    y = [min(max(v, -1e6), 1e6) for v in y]
    u = [100.0 if kind == "sat" and j > n // 3 else 50 + 10 * math.sin(w * j) for j in range(n)]
    return ts, t, y, u


@pytest.mark.parametrize("seed", range(60))
def test_the_plant_stops_where_the_tuner_does(seed: int) -> None:
    rng = random.Random(seed)
    kind = rng.choice(["settle", "grow", "sat"])
    n_max = rng.randint(50, 3000)
    judge = max(1, min(64, n_max // 100))
    ts, t, y, u = record(rng, n_max, kind)
    k = rng.randint(5, 200)
    band = rng.uniform(0.05, 1.0)
    after = rng.choice([None, rng.uniform(0.0, n_max * ts)])
    done = SettleRule(k, 50.0, band, rng.choice([None, 2 * band]), after)
    guard = rng.choice([None, Guard((0.0, 100.0), rng.uniform(4, n_max / 3))])
    lo, hi = rng.choice([(-math.inf, math.inf), (40.0, 60.0), (44.0, 57.0)])
    cmd = AdvanceCommand(
        loop="x",
        steps=n_max,
        source="s",
        t=t[0],
        stop_below=Band(lo, hi).stops()[0],
        stop_above=Band(lo, hi).stops()[1],
        record=RecordStops(
            judge=judge,
            settle=SettleStop(
                k=k, target=50.0, band=band, flat=done.flat, min_samples=done.min_samples(ts)
            ),
            guard=(
                GuardStop(window=guard.n, target=50.0, op_low=0.0, op_high=100.0)
                if guard is not None
                else None
            ),
        ),
    )
    want = tuner_end(t, y, u, judge, n_max, done, guard, 50.0, lo, hi)
    got = plant_end(y, u, cmd)
    if want is None:
        assert got is None or (after is not None and judge_point(got, judge, n_max))
    else:
        assert got is not None and got <= want
        if got < want:  # only a settling a sample short of ``after`` in sim time
            assert after is not None and not done.done(np.asarray(t[:got]), np.asarray(y[:got]))
            assert settle_point(got, judge) and got < done.min_samples(ts) + 8 * judge


def test_min_samples_is_never_more_than_the_sim_time_asks() -> None:
    """``min_samples`` ≤ the first count whose sim-time span t[-1] − t[0] exceeds ``after``,
    with t = seq·ts as the plant stamps it, for any start and sample time."""
    rng = random.Random(5)
    for _ in range(20000):
        ts = rng.choice([0.1, 0.25, 0.05, 1 / 3, 0.7, rng.uniform(1e-3, 10)])
        seq0 = rng.randint(0, 10**8)
        after = rng.choice([rng.randint(1, 500) * ts, rng.uniform(0, 500 * ts)])
        rule = SettleRule(1, 0.0, 1.0, None, after)
        m_min = rule.min_samples(ts)
        # the first m with (seq0 + m − 1)·ts − seq0·ts > after
        m = max(1, math.floor(after / ts) - 2)
        while not (seq0 + m - 1) * ts - seq0 * ts > after:
            m += 1
        assert m_min <= m, (ts, seq0, after, m_min, m)
        assert m_min >= m - 2  # and no more than a sample or so short


def test_a_record_stop_is_validated_as_any_message() -> None:
    with pytest.raises(ValueError):
        RecordStops.model_validate_json('{"judge": 0}')
    with pytest.raises(ValueError):
        SettleStop.model_validate_json('{"k": 3, "target": NaN, "band": 1}')
    with pytest.raises(ValueError):
        GuardStop.model_validate_json('{"window": 4, "target": 1, "op_low": 0, "op_high": 1}')


@pytest.mark.parametrize("after, want", [(14.5, 16), (15.0, 24), (0.5, 8)])
def test_long_enough_counts_from_the_first_sample(after: float, want: int) -> None:
    """A flat record on target, judged every sample (settling every 8th), 1 s a sample: the
    tuner's test ends it at the first multiple of 8 whose span t[-1] − t[0] exceeds ``after``;
    the plant's count stops there too (or, on a whole number of samples, 8 samples earlier,
    where the record reads it as not yet ended and goes on)."""
    n = 40
    t = [100.0 + j for j in range(n)]
    y = [50.0] * n
    u = [50.0] * n
    done = SettleRule(4, 50.0, 0.1, 0.2, after)
    assert tuner_end(t, y, u, 1, n, done, None, 50.0, -math.inf, math.inf) == want
    stops = RecordStops(
        judge=1,
        settle=SettleStop(k=4, target=50.0, band=0.1, flat=0.2, min_samples=done.min_samples(1.0)),
    )
    cmd = AdvanceCommand(loop="x", steps=n, source="s", t=100.0, record=stops)
    got = plant_end(y, u, cmd)
    assert got == (want if after != 15.0 else 16)


def test_a_calm_stop_carries_at_most_its_window() -> None:
    """A ramp's calming check names the PVs it needs from before the advance: at most one
    window of them (a message is bounded by what it is for)."""
    CalmStop(fed=10, start=12, window=10, limit=0.1, history=[1.0] * 10)
    with pytest.raises(ValueError, match="history"):
        CalmStop(fed=10, start=12, window=10, limit=0.1, history=[1.0] * 11)
    with pytest.raises(ValueError):
        CalmStop.model_validate_json(
            '{"fed": 1, "start": 2, "window": 10, "limit": 0.1, "history": [NaN]}'
        )


# the guard's verdict on deviations of closed form, over windows of N samples
N = 50
T = np.arange(4 * N, dtype=float)  # four whole windows, in samples
OP = np.full(T.size, 50.0)  # the output well inside its limits


def test_the_guard_stops_an_oscillation_that_grows():
    dev = 0.1 * np.exp(T / 60.0) * np.sin(2 * np.pi * T / 20.0)  # ×2.3 a window
    assert "the oscillation grows" in Guard((0.0, 100.0), N).check(dev, OP)


def test_the_guard_stops_a_deviation_that_runs_away_without_swinging():
    dev = 0.01 * (np.exp(T / 40.0) - 1.0)  # a real closed-loop pole in the right half-plane
    assert "runs away without swinging" in Guard((0.0, 100.0), N).check(dev, OP)


@pytest.mark.parametrize("tau", [0.8 * N, 1.5 * N, 4.0 * N])
def test_the_guard_lets_a_loop_settle_to_an_offset(tau):
    """P-only control of an integrating process under a load step settles to the offset
    load/Kc along 1 − e^{−t/τ}: its largest deviation grows from window to window (by more
    than 10 % each where τ is over a window), ever more slowly, and never swings. It was
    stopped as "the oscillation grows" (seen: 1.36 → 2.04 → 2.32 on a level loop whose
    previous gains were P-only)."""
    dev = 2.5 * (1.0 - np.exp(-T / tau)) + 0.01 * np.sin(T)  # a little ripple on it
    for m in (3 * N, 4 * N):  # asked as each whole window comes in
        assert Guard((0.0, 100.0), N).check(dev[:m], OP[:m]) is None
        assert Guard((0.0, 100.0), N).check(-dev[:m], OP[:m]) is None


def test_the_guard_lets_a_decaying_oscillation_be():
    dev = 3.0 * np.exp(-T / 60.0) * np.sin(2 * np.pi * T / 20.0)
    for m in (3 * N, 4 * N):
        assert Guard((0.0, 100.0), N).check(dev[:m], OP[:m]) is None
