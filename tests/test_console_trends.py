"""The console's trends: a window of sim time, batches since the last push, thinned so that
a spike stays visible."""

from __future__ import annotations

import numpy as np

from services.console.trends import Trend, thin


def test_thinning_keeps_everything_that_fits_and_else_the_limit_with_the_last():
    assert thin(5, 10).tolist() == [0, 1, 2, 3, 4]
    kept = thin(10_000, 100)
    assert len(kept) == 100 and kept[-1] == 9999 and np.all(np.diff(kept) > 0)


def test_a_spike_survives_the_thinning():
    pv = np.zeros(10_000)
    pv[4321] = 7.0  # one sample out of line: the bucket keeps it, not its first
    assert 4321 in thin(pv.size, 50, pv).tolist()


def test_the_window_is_sim_time_and_each_batch_is_what_came_since_the_last():
    tr = Trend(history=10.0)
    for k in range(30):  # 1 s samples: 30 s of sim time
        tr.add(float(k), pv=float(k), sp=1.0, op=50.0)
    snap = tr.snapshot()
    assert snap["t"] == [float(k) for k in range(19, 30)]  # t ≥ 29 − 10
    assert tr.take_new()["t"] == [float(k) for k in range(30)]
    assert tr.take_new() is None
    tr.add(30.0, 30.0, 1.0, 50.0)
    assert tr.take_new() == {"t": [30.0], "pv": [30.0], "sp": [1.0], "op": [50.0]}


def test_a_plant_restart_starts_the_trend_again():
    tr = Trend(history=100.0)
    for t in (50.0, 51.0, 52.0):
        tr.add(t, 1.0, 1.0, 1.0)
    tr.add(0.0, 2.0, 2.0, 2.0)  # sim time from zero: another plant instance
    assert tr.snapshot()["t"] == [0.0] and tr.take_new()["pv"] == [2.0]
