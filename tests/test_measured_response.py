"""Step figures read off a measured record, on synthetic records whose figures are known in
closed form: the underdamped second-order step (overshoot e^{−πζ/√(1−ζ²)}, decay ratio its
square), a first-order step short of its setpoint (P control's offset), and a load dip
D·(t/τ)·e^{1−t/τ} (peak D at τ, IAE D·e·τ).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

from services.autotuner.design.measured_response import load_step, measured_setpoint_step
from shared.control.record_stops import settled

ZETA, WN = 0.3, 1.0  # rad/s
SIGMA, WD = ZETA * WN, WN * math.sqrt(1 - ZETA**2)
T0, Y0, TARGET = 5.0, 20.0, 30.0


def z_of(t):
    """(y − y₀)/(r − y₀) of 1/(s²/ω_n² + 2ζs/ω_n + 1) after a unit step at 0."""
    return 1 - np.exp(-SIGMA * t) * (np.cos(WD * t) + SIGMA / WD * np.sin(WD * t))


def second_order_record(dt: float = 0.001, span: float = 40.0):
    t = np.linspace(0.0, span, round(span / dt) + 1)
    return T0 + t, Y0 + (TARGET - Y0) * z_of(t)


def test_second_order_step_figures_are_the_closed_forms():
    t, y = second_order_record()
    f = measured_setpoint_step(t, y, T0, Y0, TARGET, band=0.02)
    overshoot = math.exp(-math.pi * ZETA / math.sqrt(1 - ZETA**2))
    assert f["overshoot"] == pytest.approx(100 * overshoot, rel=1e-5)
    # the peaks above r come every 2π/ω_d, each e^{−σ·2π/ω_d} of the one before
    assert f["decay_ratio"] == pytest.approx(overshoot**2, rel=1e-4)
    t10 = brentq(lambda s: z_of(s) - 0.1, 0.0, math.pi / WD)
    t90 = brentq(lambda s: z_of(s) - 0.9, 0.0, math.pi / WD)
    assert f["rise_time"] == pytest.approx(t90 - t10, abs=1e-5)
    # |z − 1| peaks at kπ/ω_d with height e^{−σkπ/ω_d}: the last peak outside the band,
    # then the fall to the band before the zero of z − 1 at ω_d t = φ + π/2 + kπ
    k = max(k for k in range(100) if math.exp(-SIGMA * k * math.pi / WD) > 0.02)
    phi = math.atan(SIGMA / WD)
    t_settle = brentq(
        lambda s: abs(z_of(s) - 1) - 0.02, k * math.pi / WD, (phi + math.pi / 2 + k * math.pi) / WD
    )
    assert f["settling_time"] == pytest.approx(t_settle, abs=2e-3) and f["settled"] is True
    zeros = [(phi + math.pi / 2 + j * math.pi) / WD for j in range(13)]
    iae, _ = quad(lambda s: abs(1 - z_of(s)), 0.0, 40.0, points=zeros, limit=200)
    assert f["iae"] == pytest.approx((TARGET - Y0) * iae, rel=1e-5)


def test_a_step_down_reads_the_same_as_a_step_up():
    t, y = second_order_record()
    up = measured_setpoint_step(t, y, T0, Y0, TARGET)
    down = measured_setpoint_step(t, 2 * Y0 - y, T0, Y0, 2 * Y0 - TARGET)
    assert down == pytest.approx(up, rel=1e-9)


def test_an_offset_short_of_the_setpoint_is_no_overshoot_and_never_settles():
    """0.8(1 − e^{−t/2}): P control's offset of 20 % never reaches the setpoint: no
    overshoot, no decay ratio, no 90 % rise, not settled within 2 %."""
    t = np.linspace(0.0, 30.0, 3001)
    z = 0.8 * (1 - np.exp(-t / 2.0))
    f = measured_setpoint_step(T0 + t, Y0 + 10.0 * z, T0, Y0, Y0 + 10.0)
    assert f["overshoot"] == 0.0 and f["decay_ratio"] is None and f["rise_time"] is None
    assert f["settled"] is False and f["settling_time"] is None


def test_noise_is_averaged_before_the_peaks_are_read():
    """σ = 0.2 % of the step on 630 samples per period: the smoothed peaks keep the closed
    forms within a few tenths of a percent of the step."""
    t, y = second_order_record(dt=0.01)
    rng = np.random.default_rng(3)
    noisy = y + 0.02 * rng.standard_normal(y.size)
    f = measured_setpoint_step(t, noisy, T0, Y0, TARGET, noise=0.02)
    overshoot = math.exp(-math.pi * ZETA / math.sqrt(1 - ZETA**2))
    assert f["overshoot"] == pytest.approx(100 * overshoot, abs=0.3)
    assert f["decay_ratio"] == pytest.approx(overshoot**2, abs=0.02)


def _noisy_reads(zeta: float, per_radian: int, sigmas: float, n: int = 60) -> np.ndarray:
    """The overshoot read off ``n`` records of the unit second-order step (ω_n = 1 rad per
    ``per_radian`` samples, 40 radians long) under white noise of 1/``sigmas`` of the step,
    averaged over 5 samples as the verification does."""
    rng = np.random.default_rng(11)
    wn, wd = 1.0 / per_radian, math.sqrt(1 - zeta**2) / per_radian
    t = np.arange(40 * per_radian, dtype=float)
    z = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta * wn / wd * np.sin(wd * t))
    sd = 1.0 / sigmas
    return np.array(
        [
            measured_setpoint_step(t, z + sd * rng.standard_normal(t.size), 0, 0, 1, noise=sd)[
                "overshoot"
            ]
            for _ in range(n)
        ]
    )


def test_noise_does_not_raise_the_overshoot_read():
    """A step 9σ tall, as the verification makes it on a noisy loop with a high gain (the
    preset lvl2's steps are 9–16σ): the highest averaged sample stood 5 points above a 28 %
    crest on average, 7 points short of the acceptance's 35 %. The crest's parabola reads it
    within 2 points on average."""
    zeta = 0.376
    exact = 100 * math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2))
    assert np.mean(_noisy_reads(zeta, 12, 9.0)) == pytest.approx(exact, abs=2.0)


def test_a_narrow_crest_is_not_read_low():
    """A crest only a few samples wide (ζ = 0.2, 3 samples a radian) is not flattened by the
    reading: reading an overshoot low is the unsafe side of the acceptance."""
    zeta = 0.2
    exact = 100 * math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2))
    assert np.mean(_noisy_reads(zeta, 3, 20.0)) >= exact - 2.5


@pytest.mark.parametrize("rel_noise", [1e-6, 1e-3])
def test_a_sharp_crest_is_not_read_low_where_the_noise_is_small(rel_noise):
    """A crest that is no parabola (a rise at 1 a second to 1.2, then down at 0.02: its
    overshoot 20 % at the corner) read through the crest's parabola came out 18.9 % at any
    noise up to 1 % of the step, and AMIGO PID's 19.76 % on a first order with dead time read
    19.16 % at noise 1e-6 of its step (helper audit): the highest sample less 4σ is a floor."""
    t = np.arange(0.0, 40.0, 0.05)
    z = np.where(t >= 1.2, np.maximum(1.2 - 0.02 * (t - 1.2), 1.0), t)
    noise = rel_noise * (TARGET - Y0)
    y = Y0 + (TARGET - Y0) * z + noise * np.random.default_rng(3).standard_normal(t.size)
    read = measured_setpoint_step(t, y, 0.0, Y0, TARGET, noise=noise)["overshoot"]
    assert read >= 20.0 - 100 * 5 * rel_noise


D, TAU, SP = 3.0, 4.0, 50.0


def load_record(span: float):
    t = np.linspace(0.0, span, round(span / 0.001) + 1)
    return T0 + t, SP - D * (t / TAU) * np.exp(1 - t / TAU)


def test_load_dip_figures_are_the_closed_forms():
    t, y = load_record(80.0)
    f = load_step(t, y, T0, SP)
    assert f["max_deviation"] == pytest.approx(D, rel=1e-9)
    # ∫₀^T D(t/τ)e^{1−t/τ} dt = D·e·τ·(1 − (1 + T/τ)e^{−T/τ})
    assert f["iae"] == pytest.approx(D * math.e * TAU * (1 - 21 * math.exp(-20)), rel=1e-6)
    # back within a tenth of the peak where x·e^{1−x} = 0.1, x = t/τ > 1
    x = brentq(lambda v: v * math.exp(1 - v) - 0.1, 1.0, 20.0)
    assert f["recovery_time"] == pytest.approx(x * TAU, abs=2e-3) and f["recovered"] is True


def test_a_load_dip_cut_short_has_not_recovered():
    t, y = load_record(2 * TAU)  # still at 2e^{−1} ≈ 74 % of its peak
    f = load_step(t, y, T0, SP)
    assert f["recovered"] is False and f["recovery_time"] is None


def _loop_noise(k: int, seed: int) -> np.ndarray:
    """A PV at rest under control: measurement noise (σ 1) on the loop's own correlated
    wander (AR(1), 0.5 a sample, σ 1.5)."""
    rng = np.random.default_rng(seed)
    w = rng.normal(0.0, 1.5 * math.sqrt(1 - 0.25), k)
    e = np.empty(k)
    e[0] = w[0]
    for n in range(1, k):
        e[n] = 0.5 * e[n - 1] + w[n]
    return e + rng.normal(0.0, 1.0, k)


def test_a_noisy_loop_at_rest_is_settled_though_its_samples_spread_past_flat():
    """Judged by the spread of its samples, a level loop at rest on its setpoint (the last
    600 samples past 8σ) was "unsettled, resting +5.4e-06 m off it" and its gains rejected."""
    y = _loop_noise(600, 3)
    assert np.ptp(y) > 8.0  # what the samples' own spread said
    assert settled(y, 600, 0.0, 4.0, 8.0)


@pytest.mark.parametrize(
    "move",
    [
        lambda n: 12.0 * n / n[-1],  # still drifting: 12 over the window
        lambda n: 6.0 * np.sin(2 * np.pi * n / 200),  # still swinging, ±6 at 200 samples
    ],
)
def test_a_loop_still_moving_is_not_settled(move):
    n = np.arange(600.0)
    assert not settled(_loop_noise(600, 3) + move(n), 600, 0.0, 4.0, 8.0)


def test_settled_asks_for_a_number_last_and_a_short_record_its_own_spread():
    y = _loop_noise(600, 3)
    y[-1] = math.nan
    assert not settled(y, 600, 0.0, 4.0, 8.0)
    assert settled(np.array([1.0, 1.5, 0.75]), 3, 1.0, 0.5, 0.75)  # binary-exact spread
    assert not settled(np.array([1.0, 1.5, 0.75]), 3, 1.0, 0.5, 0.7499)


def test_a_small_crest_ahead_of_the_overshoot_is_not_the_oscillations():
    """A record through vertices worked by hand, z = 1 + (0.03, −0.01, 0.20, −0.08, 0.06) at
    crests and troughs: its decay ratio is 0.06/0.20 (the crest after the largest), not
    0.20/0.03 = 6.7, which called a decaying response growing."""
    tv = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 12.0])
    zv = np.array([0.0, 1.03, 0.99, 1.20, 0.92, 1.06, 1.0, 1.0])
    t = np.linspace(0.0, 12.0, 1201)
    f = measured_setpoint_step(T0 + t, Y0 + 10.0 * np.interp(t, tv, zv), T0, Y0, Y0 + 10.0)
    assert f["decay_ratio"] == pytest.approx(0.06 / 0.20, rel=1e-9)
    assert f["overshoot"] == pytest.approx(20.0, rel=1e-9)


def test_settling_and_recovery_times_are_the_responses_not_the_last_noise_spike():
    """A sample's noise crosses 3σ once in 370 samples: read on the raw samples, settling
    and recovery times were those of the record's last spike (hx1: 117.75 s of a 120 s
    record, 65.75 s with the noise averaged: helper trial). They are read with the noise
    averaged as the peaks are: a first-order response (τ 10 s) enters the 3σ band of σ 0.02
    (6 % of the step) at τ·ln(1/0.06) = 28.1 s, whatever the noise does in the 270 s after."""
    from services.autotuner.design.measured_response import load_step, measured_setpoint_step

    rng = np.random.default_rng(5)
    t = np.arange(0.25, 300.0, 0.25)
    sigma = 0.02
    y = 1.0 - np.exp(-t / 10.0) + sigma * rng.standard_normal(t.size)
    exact = 10.0 * math.log(1.0 / 0.06)
    m = measured_setpoint_step(t, y, 0.0, 0.0, 1.0, noise=sigma, width=5)
    assert m["settled"] and abs(m["settling_time"] - exact) < 5.0, m
    raw = np.abs(y - 1.0) > 0.06  # the raw samples: spikes long after it settled
    assert t[np.nonzero(raw)[0][-1]] > 100.0
    dev = 1.0 * np.exp(-t / 10.0) + sigma * rng.standard_normal(t.size)  # a load's dip
    r = load_step(t, dev, 0.0, 0.0, noise=sigma, width=5)  # back within 0.1 of its peak
    assert r["recovered"] and abs(r["recovery_time"] - 10.0 * math.log(10.0)) < 5.0, r


def test_the_settling_band_is_said_where_the_noise_widens_it():
    """A level's verification step of 8σ: its settling time is read within 3σ = 37.5 % of
    the step, not 2 %, and the figures say so (helper trial: "settling 6 s" meant 62.5 %)."""
    t, y = second_order_record(dt=0.05)  # a step of TARGET − Y0 = 10
    clean = measured_setpoint_step(t, y, T0, Y0, TARGET)
    assert clean["settling_band"] == pytest.approx(2.0)
    sigma = (TARGET - Y0) / 8.0
    f = measured_setpoint_step(t, y, T0, Y0, TARGET, noise=sigma)
    assert f["settling_band"] == pytest.approx(37.5)  # 3σ of a step 8σ tall
