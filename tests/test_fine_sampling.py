"""Experiments on a finely sampled noisy loop: the heat exchanger e^{−5s}/((10s+1)(60s+1))
sampled every 0.025 s (1,742 samples an ultimate period; the ramp, at 0.05 s, is tried at half
the cost) under its transmitter's noise, 0.02 °C.

Sampled so finely, the PV moves a small fraction of σ a sample: the noise's own turning points
are many, and the PV lingers near any level it crosses. The relay counted the noise's
crossings of the rest value as cycles (0.16 s long, and others half a period early: 30 cycles
and none agreed), and the ramp closed its trials on fits of the noise a few seconds into a
44 s period, judged them "did not oscillate" and raised the gain to 3.8·K_u (aborted at
5.7·K_u, its output saturated). Expected figures: the exact ultimate point.
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
from tests.plants import run_relay

HX = ([1.0], [600.0, 70.0, 1.0], 5.0)
TS = 0.025  # s
NOISE = 0.02  # °C, the preset's
KU, PU = ultimate_point(*HX)


@pytest.mark.parametrize("seed", [1, 2])
def test_relay_cycles_are_not_split_by_the_noise_near_the_rest_value(seed):
    test = run_relay(*HX, TS, noise=NOISE, seed=seed)
    assert test.result is not None, test.reason
    # one cycle per switch up, and none closed early: none is a fraction of the period
    assert min(c.period for c in test.cycles[1:]) > 0.5 * PU
    assert test.result.ku == pytest.approx(KU, rel=0.01)
    assert test.result.pu == pytest.approx(PU, rel=0.01)


def test_ramp_trials_are_not_closed_on_fits_of_the_noise():
    # at 0.05 s (871 samples a period; half the cost of 0.025 s, where every seed failed)
    # this seed ran to its output's limit on the noise's "oscillations" and aborted
    sim = build_plant(
        {"seed": 2, "loops": {"hx": {"model": "heat_exchanger", "sample_time": 2 * TS}}},
        "fine",
    )["hx"]
    assert sim.settings.noise_std == NOISE
    run = TuningRun(LocalLoopClient(sim), TuneRequest(loop="hx", method="ramp"), "r", RunHooks())
    result = run.run()
    assert result.status == "ok", result.reason
    assert result.ku == pytest.approx(KU, rel=0.01)
    assert result.pu == pytest.approx(PU, rel=0.01)


def _osc(amplitude: float, growth: float, period: float) -> Oscillation:
    return Oscillation(growth, period, amplitude, 0.0, 0.0, 9)


def test_an_oscillation_stands_out_if_it_swings_out_of_the_noise_for_half_a_period():
    # the noise fit the ramp acted on: 7σ at the start, under 2σ a sixth of a period on
    spike = _osc(0.1416, -3.787, 2.11)
    assert not stands_out(spike, 10.2, 2 * 0.0191)
    # decaying: half a period on, A·e^{g·P/2} against the level, either side of it
    g = -0.05
    at = 0.2 * math.exp(g * 0.5 * 10.0)
    assert stands_out(_osc(0.2, g, 10.0), 40.0, 0.999 * at)
    assert not stands_out(_osc(0.2, g, 10.0), 40.0, 1.001 * at)
    # a dead-time loop's own at a low gain: 0.34 a period from 10σ, 1.9σ 1.5 periods on
    assert stands_out(_osc(10.0, math.log(0.34) / 58.0, 58.0), 400.0, 2.0)
    # growing: half a period before the window's end
    g = 0.02
    at = 0.01 * math.exp(g * (40.0 - 0.5 * 10.0))
    assert stands_out(_osc(0.01, g, 10.0), 40.0, 0.999 * at)
    assert not stands_out(_osc(0.01, g, 10.0), 40.0, 1.001 * at)
    # a window shorter than 1.5 periods, however tall; a growth that is not a number
    assert not stands_out(_osc(1.0, 0.0, 30.0), 40.0, 0.0)
    assert stands_out(_osc(1.0, 0.0, 20.0), 30.0, 0.5)
    assert not stands_out(_osc(1.0, float("nan"), 10.0), 40.0, 0.0)
