"""What the relay's result says when its cycle ran far short of −180°: the cause it names is
the one the figures show (the hysteresis's lag asin(ε/a), or the sampling's 360° over the
samples a period), with what would help."""

from __future__ import annotations

import math

from services.autotuner.identify.relay_result import RelayResult


def _short_cycle(hysteresis: float, phase: float, samples_per_period: float) -> str:
    r = RelayResult(
        ku=math.nan,
        pu=math.nan,
        amplitude=1.0,
        relay_amplitude=5.0,
        hysteresis=hysteresis,
        bias=50.0,
        noise_std=hysteresis / 3,
        cycles=6,
        ku_spread=0.0,
        pu_spread=0.0,
        rest_pv=0.0,
        crossing="not reached",
        phase_reached_deg=phase,
        cycle_period=10.0,
        sample_time=10.0 / samples_per_period,
    )
    (note,) = r.identification().notes
    return note


def test_a_cycle_lagged_by_its_hysteresis_is_said_to_be():
    """ε/a = 0.9: asin gives 64° of the 80° short; 100 samples a period add 3.6°."""
    note = _short_cycle(0.9, -100.0, 100)
    assert "is 90% of the cycle's amplitude, 64° of lag" in note and "--amplitude" in note
    assert "samples a period" not in note


def test_a_cycle_lagged_by_its_sampling_is_said_to_be():
    """12 samples a period: a sample is 30° of the 45° short; ε/a = 0.01 gives 0.6°."""
    note = _short_cycle(0.01, -135.0, 12)
    assert "12 samples a period" in note and "(30°) late" in note
    assert "--amplitude" not in note
