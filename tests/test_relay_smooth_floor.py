"""A noise-free relay cycle is read as it is: its PV is not smoothed before its amplitude is
read. A noise-free rest reads σ ~ 1e-15 (the rounding), and a lag-dominated loop's cycle,
nearly a triangle, smoothed over a twentieth of itself lost a twentieth of its peak, so the
describing-function K_u (the classic relay tuner's, and what a run that falls back on it
takes) read 5 % high (helper audit). Figures from the plant: under an ideal relay ±d,
K·e^{−Ls}/(Ts + 1) swings a = K·d·(1 − e^{−L/T}) about its rest (control-references.md), and
the describing function reads K_u = 4d/(πa); sampled at T/1000 the relay switches within a
sample of the crossing, which adds at most 2 % to a here."""

from __future__ import annotations

import math

import pytest

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

K, T, L, TS = 1.0, 10.0, 0.5, 0.01
SPEC = {
    "model": "transfer_function",
    "num": [K],
    "den": [T, 1.0],
    "delay": L,
    "sample_time": TS,
    "noise_std": 0.0,
    "pv_range": [0.0, 100.0],
}


def test_a_noise_free_cycle_is_read_unsmoothed():
    sim = build_plant({"seed": 0, "loops": {"f": SPEC}}, "t")["f"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="f", method="relay"), "t").run()
    e = r.experiment
    d = e["relay_amplitude"]
    a = K * d * (1.0 - math.exp(-L / T))
    assert e["amplitude"] == pytest.approx(a, rel=0.02)
    assert e["ku_describing_function"] == pytest.approx(4 * d / (math.pi * a), rel=0.02)
