"""The loop's oscillatory mode in a verification's response (``design.ringing``), and the
verification's refusal of gains whose loop rings though the setpoint step's first peaks do
not show it (helper trial: ZN PI from a ramp test on e^{−0.5s}/(s² + 0.6s + 1) ended ``ok``
at Ms 3.1, its loop's poles at ζ 0.086). Expected figures from closed forms: the second-order
step response, and the dominant pole of the exact loop with the gains the run applied."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import fsolve

from services.autotuner.design.ringing import ringing
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

DT = 0.05


def second_order_step(zeta: float, wn: float, t: np.ndarray) -> np.ndarray:
    """The unit step response of wn²/(s² + 2ζwn·s + wn²)."""
    wd = wn * math.sqrt(1 - zeta**2)
    return 1 - np.exp(-zeta * wn * t) * (
        np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t)
    )


@pytest.mark.parametrize("zeta", [0.05, 0.1, 0.2])
def test_a_lightly_damped_modes_decay_and_period_are_read(zeta: float) -> None:
    t = np.arange(0.0, 60.0, DT)
    # the mode beside a slow approach, as a PI loop's setpoint step shows it, with noise
    y = 0.6 * (1 - np.exp(-t / 15.0)) + 0.4 * second_order_step(zeta, 1.2, t)
    y += np.random.default_rng(1).normal(0.0, 0.001, t.size)
    mode = ringing(t, y, 0.001)
    assert mode is not None
    wd = 1.2 * math.sqrt(1 - zeta**2)
    assert mode.period == pytest.approx(2 * math.pi / wd, rel=0.01)
    assert mode.decay == pytest.approx(
        math.exp(-2 * math.pi * zeta / math.sqrt(1 - zeta**2)), abs=0.02
    )


def test_a_well_damped_response_or_noise_alone_shows_no_ringing() -> None:
    t = np.arange(0.0, 60.0, DT)
    noise = np.random.default_rng(2).normal(0.0, 0.01, t.size)
    mode = ringing(t, second_order_step(0.8, 1.2, t) + noise, 0.01)
    assert mode is None or mode.decay < 0.01
    assert ringing(t, 5.0 + noise, 0.01) is None


UNDERDAMPED = {
    "model": "transfer_function",
    "num": [1.0],
    "den": [1.0, 0.6, 1.0],  # ζ 0.3, ω 1 rad/s
    "delay": 0.5,
    "sample_time": DT,
    "noise_std": 0.005,
    "pv_range": [0.0, 100.0],
}


def test_gains_whose_loop_rings_are_rejected_with_the_modes_true_decay() -> None:
    """ZN PI forced on the ramp's SOPDT model (no resonance in its class): the setpoint step
    overshoots nothing, and the run used to end ok. The loop's dominant pole, solved on the
    exact plant with the gains applied (a zero-order hold's half-sample delay added), gives
    the decay per period the verification must read."""
    sim = build_plant({"seed": 0, "loops": {"u3": UNDERDAMPED}}, "ringing")["u3"]
    req = TuneRequest(loop="u3", method="ramp", rule="zn-pi")
    r = TuningRun(LocalLoopClient(sim), req, "ring", RunHooks()).run()
    assert r.status == "rejected", (r.status, r.reason)
    assert "ring: an oscillation of" in r.reason
    kc, ti = r.chosen["isa"]["kc"], r.chosen["isa"]["ti"]

    def char(x: np.ndarray) -> list[float]:
        s = complex(x[0], x[1])
        g = np.exp(-s * (0.5 + DT / 2)) / (s * s + 0.6 * s + 1)
        v = 1 + kc * (1 + 1 / (ti * s)) * g
        return [v.real, v.imag]

    sigma, wd = fsolve(char, [-0.1, 2 * math.pi / r.after.ringing_period])
    assert r.after.ringing_period == pytest.approx(2 * math.pi / wd, rel=0.03)
    assert r.after.ringing == pytest.approx(math.exp(2 * math.pi * sigma / wd), abs=0.04)
    assert r.after.ringing > 0.35 and r.restored
