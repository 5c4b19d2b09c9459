"""The verification's gain-margin check: a PID that passes its steps is run at twice its gain,
and a loop that swings on, or more and more, is refused (``design.margin_check``).

Random field case: 2.74·e^{−1.53s}/((9.24s + 1)(s²/52.2 + 0.0136s + 1)) (a resonance at
7.2 rad/s, ζ 0.05, five times ω_u), sampled every 0.078 s, noise σ 0.036. A ramp test read
K_u within 1 %, and AMIGO PID, predicted Ms 1.46 on the model, passed its setpoint and load
steps: its ringing at the resonance stayed in the noise. Its exact gain margin on the plant
is about 1.0 (computed here from G(jω) and the PID block's own transfer function), and the
run ended `ok`.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.autotuner.design import margin_check
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant, default_plant_path
from shared.messages import TuneRequest

NUM = [2.7393054372333046]
DEN = [0.17626282921942302, 0.14386461056502364, 9.241494558529572, 1.0]
DELAY = 1.5286884383422488
SPEC = {
    "model": "transfer_function",
    "num": NUM,
    "den": DEN,
    "delay": DELAY,
    "sample_time": 0.0781261006375372,
    "noise_std": 0.035518025632768846,
}


def loop_gain(w: np.ndarray, kc: float, ti: float, td: float, n: float = 10.0) -> np.ndarray:
    """C(jω)·G(jω): the ISA PID with its derivative filtered at Td/N, and the plant behind
    the output's hold (half a sample's delay: 16° at the resonance)."""
    s = 1j * w
    c = kc * (1 + 1 / (ti * s) + td * s / (1 + td * s / n))
    hold = np.exp(-s * SPEC["sample_time"] / 2)
    return c * np.polyval(NUM, s) / np.polyval(DEN, s) * np.exp(-s * DELAY) * hold


def gain_margin(kc: float, ti: float, td: float) -> float:
    """The least 1/|L| where the phase crosses −180° (mod 360°), up to 40 rad/s: on a grid
    of 1e-4 rad/s, the margins read at the sample past each crossing."""
    w = np.linspace(0.01, 40.0, 400_000)
    lw = loop_gain(w, kc, ti, td)
    turns = np.floor((np.unwrap(np.angle(lw)) + math.pi) / (2 * math.pi))
    crossings = np.nonzero(np.diff(turns))[0] + 1
    return float(np.min(1 / np.abs(lw[crossings])))


def test_a_pid_with_a_gain_margin_near_one_is_refused_and_the_loop_restored():
    sim = build_plant({"seed": 204, "loops": {"x": dict(SPEC)}}, "unit")["x"]
    before = sim.snapshot()
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method="ramp"), "unit").run()
    assert r.status == "rejected", r.reason
    assert "gain margin under 2: with Kc × 2" in r.reason
    assert r.after.margin_factor == 2.0
    g = r.chosen["isa"]
    assert g["td"] > 0
    # the gains refused are the plant's trouble indeed: margin about 1 (unsafe), not 2
    assert gain_margin(g["kc"], g["ti"], g["td"]) < 1.2
    after = sim.snapshot()
    assert (after.mode, after.gains) == (before.mode, before.gains)


def test_healthy_pids_pass_it_and_pis_are_not_run_at_twice_their_gain():
    plant = build_plant_file()
    sim = plant["hx1"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="hx1", method="relay"), "unit").run()
    assert r.status == "ok", r.reason
    assert r.chosen["isa"]["td"] > 0
    assert r.after.margin_factor == 2.0
    assert r.after.margin_swing < margin_check.GROWING
    assert r.after.margin_stopped is None
    sim = build_plant_file()["hx1"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="hx1", method="step"), "unit").run()
    assert r.status == "ok", r.reason
    assert not r.chosen["isa"]["td"]
    assert r.after.margin_factor is None


def build_plant_file():
    import tomllib

    with open(default_plant_path(), "rb") as f:
        doc = tomllib.load(f)
    doc["seed"] = 1
    return build_plant(doc, "unit")


def damped(growth: float, n: int = 400, scale: int = 100, noise: float = 0.0, seed: int = 1):
    """A sinusoid about 0 of amplitude 1 whose amplitude changes by ``growth`` per time scale
    (``scale`` samples, 8 periods each), and white noise of σ ``noise``."""
    k = np.arange(n)
    y = growth ** (k / scale) * np.sin(2 * math.pi * 8 * k / scale)
    return y + noise * np.random.default_rng(seed).standard_normal(n)


@pytest.mark.parametrize(
    ("growth", "failed"),
    [(0.3, False), (0.7, False), (1.0, True), (1.5, True)],
)
def test_judge_fails_a_swing_that_lasts_or_grows(growth, failed):
    y = damped(growth)
    check = margin_check.judge(y, 2.0, 0.0, 100)
    assert check.failed is failed
    # the last time scale's RMS about its own straight line, over the step of 2
    k = np.arange(100)
    last = y[300:] - np.polyval(np.polyfit(k, y[300:], 1), k)
    assert check.swing == pytest.approx(math.sqrt(np.mean(last**2)) / 2, rel=1e-6)


def test_a_slow_approach_to_the_setpoint_is_no_swing():
    """A lambda PID on a lag 160 time scales long is still on its way to the setpoint four
    time scales on: a deviation of most of the step, but no swing."""
    k = np.arange(400)
    y = -np.exp(-k / 2000.0)  # the setpoint at 0, approached from a step of 1 below
    check = margin_check.judge(y, 1.0, 0.0, 100)
    assert check.swing < 1e-3
    assert not check.failed


def test_judge_takes_the_noise_off_and_reads_no_growth_within_it():
    noise = np.random.default_rng(3).standard_normal(400) * 0.5
    check = margin_check.judge(noise, 4.0, 0.5, 100)
    assert check.swing < 0.05
    assert check.growth is None
    assert not check.failed


def test_a_small_swing_that_grows_clear_of_the_noise_fails():
    y = damped(1.5, noise=0.01) * 0.05  # amplitude 0.05 → 0.25 over the record, σ 5e-4
    check = margin_check.judge(y, 1.0, 5e-4, 100)
    assert margin_check.GROWING < check.swing < margin_check.LASTING
    # the last time scale's over the second's: 1.5² (two scales on)
    assert check.growth == pytest.approx(2.25, rel=0.05)
    assert check.failed
    assert "swung more and more" in margin_check.problem(check)


def test_a_swing_growing_out_of_the_noise_reads_a_finite_growth_that_fails_alike_from_the_result():
    """A mode growing from within the noise: its earlier time scales have no swing left once
    the noise is taken off. Its growth is finite (a message carries no inf), so the check
    rebuilt from the result's figures fails as the live one did."""
    rng = np.random.default_rng(5)
    k = np.arange(400)
    y = 0.01 * rng.standard_normal(400) + 0.15 * (k >= 300) * np.sin(2 * math.pi * k / 12.5)
    check = margin_check.judge(y, 1.0, 0.01, 100)
    assert margin_check.GROWING < check.swing < margin_check.LASTING
    assert math.isfinite(check.growth) and check.growth > 10
    again = margin_check.MarginCheck(check.swing, check.growth, check.stopped)
    assert check.failed and again.failed
