"""The verification's setpoint step is read to its crest, from a calm loop. On a lag-dominant
plant, e^{−0.1s}/((100s + 1)(s + 1)) at 0.05 s with σ 0.02 (a relay with --relay-bias 0.5), the
step's record was cut 4.35 s after the step while the PV still rose through its target (its
last time scale "flat" within 8σ, 0.31 of the step), before the crest: 17.9 % of overshoot
read for the loop's 30 %. The true figure is the exact sampled loop's (the plant held and
sampled, the PID block's equations), computed here on its own.

Its figures are a calm loop's. After the switch to the new gains the loop was taken to be at
rest once the mean of its last time scale was within 4σ of a sample's noise of the setpoint,
and the step was made while the PV still came back from the switch (+0.06, 3σ and a quarter
of the step, on the step's far side): TL PI read 23.9 % of overshoot for the loop's 35.8 %
and ended ok under the 35 % limit (seed 0), 24.6 % for 33.9 % (seed 1). Such a step is now
made again once the loop is calm, and read there."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg as sla

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

NUM, DEN, DELAY, TS, SIGMA = [1.0], [100.0, 101.0, 1.0], 0.1, 0.05, 0.02


def true_overshoot(kc: float, ti: float, td: float, n: float = 10.0, beta: float = 1.0) -> float:
    """% overshoot of a unit setpoint step of the exact sampled loop: the plant in
    controllable form, zero-order hold, the dead time's fractional part exact; the PID block
    u_k = Kc(β·r − y_k) + I_k − Kc·Td·ẏ_k, I_{k+1} = I_k + Kc·T/Ti·(r − y_k)."""
    a = np.array([[-DEN[1] / DEN[0], -DEN[2] / DEN[0]], [1.0, 0.0]])
    b = np.array([[1.0], [0.0]])
    c = np.array([[0.0, NUM[0] / DEN[0]]])
    m = int(DELAY // TS)
    frac = DELAY - m * TS

    def held(t: float) -> tuple[np.ndarray, np.ndarray]:
        big = np.zeros((3, 3))
        big[:2, :2], big[:2, 2:] = a * t, b * t
        e = sla.expm(big)
        return e[:2, :2], e[:2, 2:]

    phi, _ = held(TS)
    ea, g0 = held(TS - frac)
    _, gf = held(frac)
    g1 = ea @ gf
    x = np.zeros((2, 1))
    us = [0.0] * (m + 2)
    integral, rate, prev, peak = 0.0, 0.0, None, -math.inf
    tf = td / n
    for _ in range(int(200.0 / TS)):
        y = float((c @ x)[0, 0])
        peak = max(peak, y)
        rate = 0.0 if prev is None else tf / (tf + TS) * rate + (y - prev) / (tf + TS)
        prev = y
        u = kc * (beta * 1.0 - y) + integral - kc * td * rate
        integral += kc * TS / ti * (1.0 - y)
        us.append(u)
        x = phi @ x + g0 * us[-1 - m] + g1 * us[-2 - m]
    return 100.0 * (peak - 1.0)


def _run(seed: int, relay_bias: float | None = 0.5):
    spec = {
        "model": "transfer_function",
        "num": NUM,
        "den": DEN,
        "delay": DELAY,
        "sample_time": TS,
        "noise_std": SIGMA,
        "pv_range": [0.0, 100.0],
    }
    sim = build_plant({"seed": seed, "loops": {"a": spec}}, "t")["a"]
    bias = {} if relay_bias is None else {"relay_bias": relay_bias}
    req = TuneRequest(loop="a", method="relay", **bias)
    r = TuningRun(LocalLoopClient(sim), req, "t").run()
    assert r.after is not None and r.after.overshoot is not None, r.reason
    g = r.after.gains
    return r.after.overshoot, true_overshoot(g.kc, g.ti, g.td, g.n, g.beta), r


def test_the_setpoint_steps_record_runs_past_its_crest():
    measured, true, _ = _run(3)  # 17.9 % read before
    assert 29.0 < true < 31.0  # the loop's own overshoot (30.0 %)
    # the step is 18σ tall: its crest is read to a few points
    assert abs(measured - true) <= 6.0, (measured, true)


@pytest.mark.parametrize("seed", [0, 1, 21])
def test_a_step_made_on_the_switchs_tail_is_made_again_from_a_calm_loop(seed: int):
    # read before: 23.9, 24.6 and 29.4 %, all ok; seed 21's loop overshoots 39.2 %
    measured, true, r = _run(seed, relay_bias=None)
    assert 33.0 < true < 40.0
    # the step is 12σ tall: its crest is read to a few points
    assert abs(measured - true) <= 3.0, (measured, true)
    assert r.status == ("ok" if measured <= 35.0 else "rejected"), r.reason
    # and it says so, with what the first step read
    said = [w for w in r.warnings if "made again from a calm loop" in w]
    assert len(said) == 1 and f"{measured:.3g} % from calm" in said[0], r.warnings


@pytest.mark.parametrize("seed", [27, 30])
def test_a_step_failed_on_an_overshoot_read_on_the_switchs_tail_is_read_again_from_calm(seed: int):
    """The tail on the step's own side: 60.5 and 46.3 % read for the loop's 50.1 and 35.9 %.
    The verdict stood, its figure did not (an engineer weighs a 10-point miss differently)."""
    measured, true, r = _run(seed, relay_bias=None)
    assert true > 35.0
    assert abs(measured - true) <= 4.0, (measured, true)
    assert r.status == "rejected" and f"overshoot {measured:.3g} %" in r.reason, r.reason
    assert any("made again from a calm loop" in w for w in r.warnings), r.warnings
