"""Experiments on a finely sampled noisy loop: the heat exchanger e^{−5s}/((10s+1)(60s+1))
sampled every 0.025 s (1,742 samples an ultimate period) under its transmitter's noise, 0.02 °C.

Sampled so finely, the PV moves a small fraction of σ a sample and the noise's own turning
points are many: the ramp closed its trials on fits of the noise a few seconds into a 44 s
period, judged them "did not oscillate" and raised the gain to 3.8·K_u (aborted at 5.7·K_u,
its output saturated). Expected figures: the exact ultimate point.
"""

from __future__ import annotations

import math

import pytest

from services.autotuner.identify.oscillation import Oscillation, stands_out
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest
from tests.exact import ultimate_point

HX = ([1.0], [600.0, 70.0, 1.0], 5.0)
TS = 0.025  # s
NOISE = 0.02  # °C, the preset's
KU, PU = ultimate_point(*HX)


def test_ramp_trials_are_not_closed_on_fits_of_the_noise():
    sim = build_plant(
        {"seed": 1, "loops": {"hx": {"model": "heat_exchanger", "sample_time": TS}}}, "fine"
    )["hx"]
    assert sim.settings.noise_std == NOISE
    run = TuningRun(LocalLoopClient(sim), TuneRequest(loop="hx", method="ramp"), "r", RunHooks())
    result = run.run()
    assert result.status == "ok", result.reason
    assert result.ku == pytest.approx(KU, rel=0.01)
    assert result.pu == pytest.approx(PU, rel=0.01)


def _osc(amplitude: float, growth: float, period: float) -> Oscillation:
    return Oscillation(growth, period, amplitude, 0.0, 0.0, 9)


def test_an_oscillation_stands_out_where_its_envelope_is_largest_for_one_and_a_half_periods():
    # the noise fit the ramp acted on: 7σ at the start, gone within a sixth of its period
    spike = _osc(0.1416, -3.787, 2.11)
    assert not stands_out(spike, 10.2, 2 * 0.0191)
    # decaying, 1.5 periods on: A·e^{g·1.5P} against the level, either side of it
    g = -0.05
    at = 0.2 * math.exp(g * 1.5 * 10.0)
    assert stands_out(_osc(0.2, g, 10.0), 40.0, 0.999 * at)
    assert not stands_out(_osc(0.2, g, 10.0), 40.0, 1.001 * at)
    # growing: 1.5 periods before the window's end
    g = 0.02
    at = 0.01 * math.exp(g * (40.0 - 1.5 * 10.0))
    assert stands_out(_osc(0.01, g, 10.0), 40.0, 0.999 * at)
    assert not stands_out(_osc(0.01, g, 10.0), 40.0, 1.001 * at)
    # not seen for 1.5 periods at all, however tall; nor a growth that is not a number
    assert not stands_out(_osc(1.0, 0.0, 30.0), 40.0, 0.0)
    assert stands_out(_osc(1.0, 0.0, 20.0), 30.0, 0.5)
    assert not stands_out(_osc(1.0, float("nan"), 10.0), 40.0, 0.0)
