"""A resonance beyond ω_u is read from the switch to the new gains as well as from the setpoint
step. The plant, 1.55·e^{−0.37s}/(0.0101s³ + 0.022s² + 2.2s + 1) sampled at 0.0134 s with σ
0.067, has a mode at about 0.41 s with ζ near 0.07 that the relay's model lacks; TL PI from
it is Ms 2.4–2.5 on the plant (tests.exact, half a sample of hold), its gain margin under 2.
The verification's gain-margin check runs Kc × 2 and watches that mode where a response rang
with it. Once the step was made from a calm loop (``test_verify_crest``) the step alone rang
it under the noise in 5 of 12 seeds, the check was not told of the mode, and those gains
ended ok; the switch's bump rings it clearly, and the check then finds it growing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.autotuner.design.unmodelled_mode import switch_mode
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest
from tests.exact import isa_ms

RESONANT = {
    "model": "transfer_function",
    "num": [1.5523703711263837],
    "den": [0.010063278299190856, 0.02199975751113506, 2.202107957742752, 1.0],
    "delay": 0.3695768051890075,
    "sample_time": 0.013354274687829413,
    "noise_std": 0.0667102234468854,
}


@pytest.mark.parametrize("seed", [2, 7, 9])  # seeds whose calm step hid the mode
def test_gains_with_a_gain_margin_under_2_at_the_resonance_are_rejected(seed: int):
    sim = build_plant({"seed": seed, "loops": {"x": RESONANT}}, "unit")["x"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method="relay"), "unit").run()
    assert r.after is not None
    g = r.after.gains
    ms = isa_ms(
        RESONANT["num"],
        RESONANT["den"],
        RESONANT["delay"],
        RESONANT["sample_time"],
        {"kc": g.kc, "ti": g.ti, "td": g.td},
    )
    assert ms > 2.2  # past the product's Ms 2, at the resonance
    assert r.status == "rejected" and "gain margin under 2" in (r.reason or ""), r.reason
    assert r.restored


def test_switch_mode_reads_a_fast_ring_out_of_a_slow_return():
    """A mode of 0.4 s decaying 0.8 a period on a slow return to the setpoint (time scale
    5 s) under white noise: its period and decay are read; the slow return alone, or the
    noise alone, is no mode."""
    rng = np.random.default_rng(1)
    ts, scale, noise, step = 0.01, 5.0, 0.01, 1.0
    t = np.arange(0.0, 30.0, ts)
    period, decay = 0.4, 0.8
    ring = 0.3 * decay ** (t / period) * np.sin(2 * math.pi * t / period)
    slow = 0.5 * np.exp(-t / scale)
    y = 50.0 + slow + ring + noise * rng.standard_normal(t.size)
    mode = switch_mode(t, y, noise, scale, ts, step)
    assert mode is not None
    assert mode.period == pytest.approx(period, rel=0.02)
    assert mode.decay == pytest.approx(decay, abs=0.03)
    calm = 50.0 + slow + noise * rng.standard_normal(t.size)
    assert switch_mode(t, calm, noise, scale, ts, step) is None
