"""A noise-free relay cycle is smoothed over 3 samples, not a twentieth of itself. A
noise-free rest reads σ ~ 1e-15 (the rounding), and a lag-dominated loop's cycle, nearly a
triangle, finely sampled and smoothed over a twentieth of itself, lost a twentieth of its
peak: the describing-function K_u (the classic relay tuner's, and what a run that falls back
on it takes) read 5 % high (helper audit). Coarse sampling still needs the 3 samples: (s+1)⁻³
at 20 samples a period read raw put K_u 8.6 % off (``test_relay_leakage`` keeps it).
Figures from the plant: under an ideal relay ±d, K·e^{−Ls}/(Ts + 1) swings
a = K·d·(1 − e^{−L/T}) about its rest (control-references.md), and the describing function
reads K_u = 4d/(πa); sampled at T/1000 the relay switches within a sample of the crossing,
which adds under 1 % to a here."""

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


def test_a_noise_free_cycle_is_read_as_it_swings():
    sim = build_plant({"seed": 0, "loops": {"f": SPEC}}, "t")["f"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="f", method="relay"), "t").run()
    e = r.experiment
    d = e["relay_amplitude"]
    a = K * d * (1.0 - math.exp(-L / T))
    assert e["amplitude"] == pytest.approx(a, rel=0.01)
    assert e["ku_describing_function"] == pytest.approx(4 * d / (math.pi * a), rel=0.01)
