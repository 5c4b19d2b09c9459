"""The closed-loop prediction against closed forms: a PI controller on a first-order plant
closes a second-order loop with a zero, whose step response is known exactly.

K/(τs+1) with Kc(1 + 1/(Ti s)): T(s) = ω_n²(1 + s/z)/(s² + 2σs + ω_n²), ω_n² = KcK/(Ti τ),
2σ = (1 + KcK)/τ, z = 1/Ti. Its step response is y_std + y_std'/z (y_std the standard
second-order one), so y − 1 = −A·e^{−σt}·cos(ω_d t − ψ): the maxima come every 2π/ω_d and the
decay ratio is e^{−2πσ/ω_d}; the first peak is where tan(ω_d t) = −ω_d/(z − σ).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.autotuner.commands.tune import _robust_row
from services.autotuner.design.predicted_response import predicted_setpoint_step
from services.autotuner.design.recommend import Assessment
from services.autotuner.design.robustness import Robustness
from services.plant_sim.plant_file import build_plant
from shared.control.forms import IsaGains
from shared.control.transfer import DelayedTF
from shared.messages import GainsCommand, ModeCommand, PidGains, SetpointCommand
from tests.exact import ultimate_point

K, TAU = 2.0, 10.0


def pi_on_first_order(kc: float, ti: float) -> tuple[float, float]:
    """(overshoot %, decay ratio) of the continuous loop, in closed form."""
    wn2 = kc * K / (ti * TAU)
    sigma = (1 + kc * K) / (2 * TAU)
    wd = math.sqrt(wn2 - sigma**2)
    z = 1 / ti
    tp = (math.pi - math.atan(wd / (z - sigma))) / wd
    y_std = 1 - math.exp(-sigma * tp) * (math.cos(wd * tp) + sigma / wd * math.sin(wd * tp))
    dy_std = wn2 / wd * math.exp(-sigma * tp) * math.sin(wd * tp)
    return 100 * (y_std + dy_std / z - 1), math.exp(-2 * math.pi * sigma / wd)


@pytest.mark.parametrize(("kc", "ti"), [(2.0, 0.5), (1.0, 1.0)])
def test_pi_on_a_first_order_plant_is_the_second_order_closed_form(kc, ti):
    """Kc = 2, Ti = 0.5: ζ ≈ 0.28, overshoot ≈ 50 %; Kc = 1, Ti = 1: ζ ≈ 0.34. Simulated at
    1500 samples per period, the sampled loop is the continuous one within 1 %."""
    overshoot, decay = pi_on_first_order(kc, ti)
    wd = math.sqrt(kc * K / (ti * TAU) - ((1 + kc * K) / (2 * TAU)) ** 2)
    period = 2 * math.pi / wd
    f = predicted_setpoint_step(
        IsaGains(kc, ti),
        DelayedTF.of([K], [TAU, 1.0]),
        period,
        sample_time=period / 1500,
        horizon=10.0,
        max_samples=20_000,
    )
    assert f.stable is True
    assert f.overshoot == pytest.approx(overshoot, rel=0.01)
    assert f.decay_ratio == pytest.approx(decay, rel=0.02)
    assert f.overshoot_decay == pytest.approx(decay, rel=0.02)


def test_p_control_offset_is_not_overshoot():
    """Kc·K/(τs + 1 + Kc·K) is first order: it settles at KcK/(1 + KcK) < 1 without passing
    it, so overshoot and decay ratio are 0 although the setpoint is never reached."""
    f = predicted_setpoint_step(IsaGains(2.0), DelayedTF.of([K], [TAU, 1.0]), TAU / 5)
    assert f.overshoot == pytest.approx(0.0, abs=1e-9) and (f.decay_ratio, f.stable) == (0.0, True)
    assert f.overshoot_decay is None  # no oscillation: no decay ratio to print, not 0.00


def test_a_gain_beyond_the_ultimate_one_is_unstable():
    """e^{−s}/(5s+1) under P control at twice its K_u (tests.exact): the oscillation grows
    until the 0–100 % output limits hold it, and is called unstable, its crests then
    sustained (a decay ratio of 1 to within 1 %)."""
    ku, pu = ultimate_point([1.0], [5.0, 1.0], 1.0)
    f = predicted_setpoint_step(IsaGains(2 * ku), DelayedTF.of([1.0], [5.0, 1.0], 1.0), pu)
    assert f.stable is False and f.decay_ratio == pytest.approx(1.0, abs=0.01)


# --- the printed decay ratio against the exact discretised closed loop (scipy.signal) --------


def _closed_loop(num, den, delay, g: IsaGains, ts: float, n: float = 10.0):
    """(numerator, denominator) in z of the sampled loop the prediction simulates, built
    independently of it: the plant ZOH-discretised by scipy.signal (``delay`` a whole number
    of samples), the PID block's difference equations in z — P and I on the error (I from the
    errors before this sample: Kc·Ts/Ti/(z − 1)), D on the measurement through its filter
    (Kc·Td·(z − 1)/((Tf + Ts)(z − a)), Tf = Td/N, a = Tf/(Tf + Ts))."""
    from scipy import signal

    d = round(delay / ts)
    assert abs(d * ts - delay) < 1e-9
    numd, dend, _ = signal.cont2discrete((num, den), ts, method="zoh")
    gn, gd = np.atleast_1d(np.squeeze(numd)), np.polymul(dend, np.r_[1.0, np.zeros(d)])
    ce_n = np.polyadd(g.kc * np.array([1.0, -1.0]), [g.kc * ts / g.ti])
    ce_d = np.array([1.0, -1.0])
    tf = g.td / n
    cd_n = g.kc * g.td / (tf + ts) * np.array([1.0, -1.0])
    cd_d = np.array([1.0, -tf / (tf + ts)])
    num_cl = np.polymul(np.polymul(gn, ce_n), cd_d)
    den_cl = np.polyadd(
        np.polymul(np.polymul(gd, ce_d), cd_d),
        np.polyadd(num_cl, np.polymul(np.polymul(gn, cd_n), ce_d)),
    )
    return num_cl, den_cl


def _printed(f) -> str:
    """The DR cell of the rules table for a stable candidate with these step figures."""
    rb = Robustness(1.5, 3.0, 60.0, None, None, stable=True)
    a = Assessment("x", IsaGains(1.0), rb, f).to_dict()
    return _robust_row(a).split()[-1]


def test_a_ripple_on_the_tail_is_not_read_as_a_decay_ratio():
    """Tyreus–Luyben PID on e^{−s}/(10s + 1) (the benchmark's L/T = 0.1): the loop overshoots
    about 7 % and creeps back to its setpoint from above along its slow real pole, a ripple
    on the way; the crests of that ripple read a decay ratio of 0.94 where the loop's
    oscillatory pole pair decays 0.19 a period. The exact sampled loop's step (scipy.signal)
    never comes back below its final value after its overshoot: there is no second
    overshoot, and the table says so ("—")."""
    from scipy import signal

    num, den, delay = [1.0], [10.0, 1.0], 1.0
    ku, pu = ultimate_point(num, den, delay)
    g = IsaGains(ku / 2.2, 2.2 * pu, pu / 6.3)
    ts = delay / round(delay / (pu / 100))
    num_cl, den_cl = _closed_loop(num, den, delay, g, ts)
    poles = np.roots(den_cl)
    assert np.max(np.abs(poles)) < 1.0  # stable
    samples = int(30 * pu / ts)
    _, (y,) = signal.dstep((num_cl, den_cl, ts), n=samples)
    y = y[:, 0]
    e = y - y[-1]
    peak = int(np.argmax(e))
    assert 0.05 < e[peak] < 0.1  # the overshoot, 5–10 %
    assert np.min(e[peak:]) > -1e-3  # never back through the final value
    f = predicted_setpoint_step(g, DelayedTF.of(num, den, delay), pu, ts, max_samples=10_000)
    assert f.stable and f.overshoot == pytest.approx(100 * e[peak], rel=0.01)
    assert f.overshoot_decay is None
    assert _printed(f) == "—"


def test_a_stable_loop_does_not_read_a_growing_decay_ratio():
    """Ziegler–Nichols PID on e^{−s}/(0.2s + 1) (the benchmark's L/T = 5): the sampled loop is
    stable, its slowest oscillatory pole pair z = r·e^{±jθ} (scipy on the exact discretised
    loop) decaying r^{2π/θ} = 0.98 a period; several pairs of the delay ring together and
    the crest after the largest read 1.57, a growing loop's figure. The printed decay ratio
    is the pair's within 1 %, and below 1."""
    num, den, delay = [1.0], [0.2, 1.0], 1.0
    ku, pu = ultimate_point(num, den, delay)
    g = IsaGains(0.6 * ku, pu / 2, pu / 8)
    ts = delay / round(delay / (pu / 100))
    poles = np.roots(_closed_loop(num, den, delay, g, ts)[1])
    assert np.max(np.abs(poles)) < 1.0
    z = max((p for p in poles if p.imag > 1e-12), key=abs)
    per_period = abs(z) ** (2 * math.pi / np.angle(z))
    f = predicted_setpoint_step(g, DelayedTF.of(num, den, delay), pu, ts, max_samples=10_000)
    assert f.stable
    assert f.overshoot_decay == pytest.approx(per_period, rel=0.01)
    assert f.overshoot_decay < 1.0
    assert float(_printed(f)) == pytest.approx(per_period, abs=0.01)


def test_a_slow_loop_s_overshoot_is_taken_about_its_own_final_value():
    """Lambda PI (λ = T = 100 s) on e^{−s}/(100s + 1): the loop e^{−s}/((λ + 1)s + e^{−s}) is
    λs + 1 to first order in s, no overshoot; its 63 % comes at some 25 P_u, so over the 30
    P_u simulated it still rises, and the mean of its last tenth taken as its final value
    read 2.8 % of overshoot. With integral action the final value is the setpoint's."""
    from tests.exact import lag_ultimate

    tau = 100.0
    _ku, pu = lag_ultimate(1.0, (tau,), 1.0)
    f = predicted_setpoint_step(
        IsaGains(tau / (tau + 1.0), tau, 0.0), DelayedTF.of([1.0], [tau, 1.0], 1.0), pu, 0.1
    )
    assert f.overshoot < 0.01, f
    # P alone settles at Kc·K/(1 + Kc·K): its overshoot about that, settled or not
    kc = 0.3 * _ku
    f = predicted_setpoint_step(IsaGains(kc, None, 0.0), DelayedTF.of([1.0], [tau, 1.0], 1.0), pu)
    assert f.overshoot > 1.0 and f.stable


def test_a_fast_loop_on_a_slow_lag_is_simulated_at_its_own_sample_time():
    """1/(300s + 1) at 0.1 s has no ultimate point: the time scale was the lag, 300 s, and 30
    of them in 2000 samples ran the PI of Kc 2625, Ti 0.35 s at 4.5 s a sample, which grew:
    9743.6 % of overshoot, though its sampled loop has Ms 1.6 (helper trial). Simulated at
    the loop's 0.1 s over its own crossover's time scale, it is the sampled closed loop's
    step, computed here by scipy from C(z) = Kc(1 + T/(Ti(z − 1))) and the exact
    zero-order-hold G(z) = (1 − a)z⁻¹/(1 − a z⁻¹), a = e^{−T/τ}."""
    from scipy import signal

    from services.autotuner.design.recommend import assess
    from services.autotuner.identify.model_fit import ProcessFit

    tau, ts, g = 300.0, 0.1, IsaGains(2625.0, 0.35, 0.0)
    model = ProcessFit("fopdt", 1.0, (tau,), 0.0, 0.0)
    (a,) = assess(None, model, {"lambda-pi": g}, simulate=True, sample_time=ts).values()
    assert a.robustness.stable and a.robustness.ms < 2.0
    # the exact sampled loop: L(z) = C(z)G(z), T = L/(1 + L), as polynomials in z
    q = math.exp(-ts / tau)
    c_num = np.array([g.kc, g.kc * (ts / g.ti - 1.0)])  # Kc(z − 1 + T/Ti)
    c_den = np.array([1.0, -1.0])  # z − 1
    g_num, g_den = np.array([1.0 - q]), np.array([1.0, -q])
    l_num, l_den = np.polymul(c_num, g_num), np.polymul(c_den, g_den)
    t_den = np.polyadd(l_den, l_num)
    _, (y,) = signal.dstep((l_num, t_den, ts), n=400)
    exact = 100.0 * (float(np.max(y)) - 1.0)
    assert abs(float(y[-1, 0]) - 1.0) < 1e-6  # settled within the 40 s
    assert a.step.stable
    assert a.step.overshoot == pytest.approx(exact, rel=1e-3)


def test_the_predicted_step_is_the_loop_as_it_is_sampled():
    """ZN PID from hx1's exact ultimate point, e^{−5s}/((10s + 1)(60s + 1)) at its 0.25 s:
    the prediction's overshoot is the plant simulator's own loop (plant_sim, noise off),
    stepped at that sample time. Simulated at 0.655 s (2,000 samples over 30 P_u) it read
    66.1 % where the loop as sampled overshoots 63.4 % (helper audit)."""
    tf = DelayedTF.of([1.0], [600.0, 70.0, 1.0], 5.0)
    ku, pu = ultimate_point(tf.num, tf.den, tf.delay)
    gains = IsaGains(0.6 * ku, pu / 2, pu / 8)
    f = predicted_setpoint_step(gains, tf, pu, sample_time=0.25)
    spec = {"model": "heat_exchanger", "noise_std": 0.0}
    loop = build_plant({"seed": 0, "loops": {"x": spec}}, "t")["x"]
    assert loop.sample_time == 0.25
    loop.apply(GainsCommand(loop="x", gains=PidGains(kc=gains.kc, ti=gains.ti, td=gains.td)))
    loop.apply(ModeCommand(loop="x", mode="auto"))
    for _ in range(40):  # at rest in auto
        loop.advance()
    sp0 = loop.sp
    step = min(1.0, 10.0 / gains.kc)  # the prediction's: a kick of 10 % at most
    loop.apply(SetpointCommand(loop="x", sp=sp0 + step))
    y = np.array([loop.advance().pv for _ in range(round(30 * pu / 0.25))]) - sp0
    final = float(np.mean(y[-len(y) // 10 :]))
    overshoot = 100 * (y.max() - final) / final
    assert f.overshoot == pytest.approx(overshoot, abs=0.05)
    assert 62.0 < f.overshoot < 65.0
