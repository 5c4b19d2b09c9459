"""The verification's record (``TuningRun._record``) advances the loop straight from one
judging point to the next, the plant stopping at a PV past its limits: the record, its
verdict and where the loop is left equal a record fed one sample at a time and judged at the
same points (the oracle below, written from the rule: ``done`` every 8·judge samples, the
guard at the first judge boundary after each of its windows, the PV limits on every sample),
in far fewer round trips; the loop never runs past the sample that ends the record."""

from __future__ import annotations

import random

import numpy as np
import pytest

from services.autotuner.tuning import MAX_CHUNK, RECORD_ADVANCE, TuningRun, judged_batch_end
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.control.record_stops import Guard, SettleRule
from shared.messages import TuneRequest

TS = 0.1


def loop(kc: float, ti: float | None, noise: float = 0.02, pv_range=(0.0, 100.0)):
    spec = {
        "model": "fopdt",
        "sample_time": TS,
        "gain": 1.5,
        "time_constant": 4.0,
        "delay": 1.0,
        "noise_std": noise,
        "mode": "auto",
        "setpoint": 52.0,
        "pv_range": list(pv_range),
        "pid": {"kc": kc, "ti": ti},
    }
    return build_plant({"seed": 3, "loops": {"x": spec}})["x"]


class Counting(LocalLoopClient):
    """Counts the advances (the round trips a bus client would make)."""

    advances = 0

    def advance(self, steps, band=None, record=None):
        self.advances += 1
        return super().advance(steps, band, record)


def oracle(sim, seconds, done, target, window, pv_limits, op_limits):
    """The record fed one sample at a time, judged as the rule says."""
    client = LocalLoopClient(sim)
    n_max = max(1, round(seconds / TS))
    judge = max(1, min(MAX_CHUNK, n_max // 100))
    guard = Guard(op_limits, window / TS) if window and target is not None else None
    lo, hi = pv_limits
    t, y, u, windows = [], [], [], 0
    while len(t) < n_max:
        (s,) = client.samples(1)
        t.append(s.t)
        y.append(s.pv)
        u.append(s.op)
        if not lo <= s.pv <= hi:
            return t, y, u, "limits"
        if len(t) % judge and len(t) < n_max:
            continue
        if guard is not None and len(t) // guard.n > windows:
            windows = len(t) // guard.n
            if guard.check(np.asarray(y) - target, np.asarray(u)):
                return t, y, u, "guard"
        if len(t) % (8 * judge) < judge and done.done(np.array(t), np.array(y)):
            break
    return t, y, u, None


def settled(target: float, band: float, k: int) -> SettleRule:
    return SettleRule(k, target, band)


CASES = {
    # a loop that settles: stopped by ``done``
    "settles": (dict(kc=1.0, ti=5.0), 120.0, settled(52.0, 0.05, 50), 52.0, 8.0, None),
    # past its ultimate gain (K_u ≈ 4.6 %/% for P alone): the guard sees the oscillation grow
    "grows": (dict(kc=6.0, ti=5.0, noise=0.2), 200.0, settled(52.0, 0.01, 50), 52.0, 4.0, None),
    # tight PV limits: the record ends at the first sample past them
    "limits": (
        dict(kc=6.0, ti=5.0, noise=0.2),
        200.0,
        settled(52.0, 0.01, 50),
        52.0,
        4.0,
        (49.0, 53.5),
    ),
    # no guard, nothing settles: the whole record
    "whole": (dict(kc=0.2, ti=None), 30.0, settled(99.0, 0.01, 50), None, None, None),
    # longer than the plant judges in one advance: the rest a judging point per round trip
    "long": (dict(kc=1.0, ti=5.0), 1700.0, settled(99.0, 0.01, 50), 52.0, 300.0, None),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_record_equals_one_judged_sample_at_a_time(case: str) -> None:
    gains, seconds, done, target, window, limits = CASES[case]
    sim_a, sim_b = loop(**gains), loop(**gains)
    client = Counting(sim_a)
    req = TuneRequest(loop="x", method="relay", pv_limits=limits)
    run = TuningRun(client, req, "v")
    t, y, u, why = run._record(seconds, done, target, window)
    ot, oy, ou, owhy = oracle(
        sim_b, seconds, done, target, window, run.pv_limits, run.info.op_limits
    )
    assert (list(t), list(y), list(u)) == (ot, oy, ou)
    assert (why is None) == (owhy is None)
    if owhy == "limits":
        assert why.startswith("the PV left its limits")
    if owhy == "guard":
        assert "oscillation grows" in why or "saturated" in why
    # the loop is left at the record's last sample, not a batch past it
    assert sim_a.seq == sim_b.seq == round(t[-1] / TS)
    assert run._t == t[-1]
    n_max = round(seconds / TS)
    judge = max(1, min(MAX_CHUNK, n_max // 100))
    assert client.advances <= len(t) // judge + 2  # at most one round trip per judging point
    if case != "limits":
        assert client.advances < len(t) / 4
    if case == "long":  # the plant judged the first RECORD_ADVANCE samples in one advance
        assert len(t) == n_max > RECORD_ADVANCE
        later = [p for p in _decisions(n_max, judge, round(window / TS)) if p > RECORD_ADVANCE]
        assert client.advances == 1 + len(later)


def test_each_case_ends_as_named() -> None:
    """The cases above reach the verdict each is there for (else they test less)."""
    for case, (gains, seconds, done, target, window, limits) in CASES.items():
        sim = loop(**gains)
        pv_limits = limits or (0.0, 100.0)
        *_, why = oracle(sim, seconds, done, target, window, pv_limits, (0.0, 100.0))
        expected = {
            "settles": None,
            "grows": "guard",
            "limits": "limits",
            "whole": None,
            "long": None,
        }
        assert why == expected[case], case


def _decisions(n_max: int, judge: int, window: int | None) -> list[int]:
    """Every sample count at which the rule judges: at judge boundaries (and n_max), the
    guard once a new whole window is in, ``done`` at multiples of 8·judge."""
    out, windows = [], 0
    for m in range(1, n_max + 1):
        if m % judge and m < n_max:
            continue
        hit = m == n_max or m % (8 * judge) < judge
        if window is not None and m // window > windows:
            windows, hit = m // window, True
        if hit:
            out.append(m)
    return out


def test_the_next_judging_point_is_the_rules() -> None:
    rng = random.Random(11)
    for _ in range(400):
        n_max = rng.randint(1, 5000)
        judge = max(1, min(MAX_CHUNK, n_max // 100))
        window = rng.choice([None, rng.randint(8, 700)])
        points = _decisions(n_max, judge, window)
        k, windows = 0, 0
        for p in points:
            assert judged_batch_end(k, n_max, judge, window, windows) == p
            k = p
            if window is not None and k // window > windows:
                windows = k // window
