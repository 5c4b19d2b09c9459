"""The sampled loop's Ms, margins and stability against closed forms.

Expected figures come from the z-domain algebra of a zero-order-hold plant under P or PI
control (Jury's conditions, closed-loop roots by numpy), from the PID block run sample by
sample, and from the continuous ultimate point as T → 0 — never from the code under test.
"""

import math

import numpy as np
import pytest

from services.autotuner.design.robustness import robustness
from services.autotuner.design.sampled_loop import (
    pid_response,
    sampled_loop_robustness,
    sampled_plant,
)
from shared.control.forms import IsaGains
from shared.control.pid import PidBlock, PidSettings
from shared.control.transfer import DelayedTF
from tests.exact import ultimate_point

K, TAU, T = 2.0, 5.0, 0.5
A = math.exp(-T / TAU)  # the ZOH pole of K/(τs+1): G(z) = K(1 − a)/(z − a)
KC_U = (1 + A) / (K * (1 - A))  # z = −1 is a closed-loop pole at this P gain


@pytest.mark.parametrize("fraction", [0.2, 0.5, 0.9])
def test_first_order_p_control_gain_margin_and_ms_closed_form(fraction):
    """G(z) = K(1−a)/(z−a), P control g = Kc·K(1−a): the phase reaches −180° only at ω = π/T,
    GM = Kc_u/Kc; |S| = |z−a|/|z−a+g| is largest at z = −1: Ms = (1+a)/(1+a−g)."""
    kc = fraction * KC_U
    r = sampled_loop_robustness(IsaGains(kc), DelayedTF.of([K], [TAU, 1.0], 0.0), T)
    assert r.gain_margin == pytest.approx(1 / fraction, rel=1e-9)
    assert r.omega_180 == pytest.approx(math.pi / T, rel=1e-12)
    g = kc * K * (1 - A)
    assert r.ms == pytest.approx((1 + A) / (1 + A - g), rel=1e-9)
    assert r.stable and r.unstable_poles == 0 and r.sample_time == T


def test_first_order_p_control_above_the_discrete_ultimate_gain_is_unstable():
    """One real closed-loop pole a − g leaves the unit circle through −1; the loop has no
    Ms (1/Ms is a stable loop's distance to −1: |S| at z = −1 is finite, (1 + a)/|1 + a − g|,
    and was stated beside "unstable")."""
    r = sampled_loop_robustness(IsaGains(1.05 * KC_U), DelayedTF.of([K], [TAU, 1.0], 0.0), T)
    assert not r.stable and r.unstable_poles == 1
    assert r.gain_margin == pytest.approx(1 / 1.05, rel=1e-9)
    assert r.ms == math.inf


@pytest.mark.parametrize("n", [0, 1, 2, 5])
def test_integrator_with_whole_sample_delay(n):
    """K/s held: G(z) = KT/(z^n(z−1)). On the unit circle z^n(z−1) + g = 0 at z = e^{jθ}
    needs θ = π/(2n+1): Kc_u = 2·sin(π/(2(2n+1)))/(K·T), ω_u = π/((2n+1)T)."""
    kc_u = 2 * math.sin(math.pi / (2 * (2 * n + 1))) / (K * T)
    r = sampled_loop_robustness(IsaGains(0.4 * kc_u), DelayedTF.of([K], [1.0, 0.0], n * T), T)
    assert r.gain_margin == pytest.approx(2.5, rel=1e-9)
    assert r.omega_180 == pytest.approx(math.pi / ((2 * n + 1) * T), rel=1e-9)
    assert r.stable
    assert not sampled_loop_robustness(
        IsaGains(1.1 * kc_u), DelayedTF.of([K], [1.0, 0.0], n * T), T
    ).stable


@pytest.mark.parametrize("phi", [0.1, 0.4, 0.7])
def test_integrator_with_fractional_delay_jury(phi):
    """Delay f = φT: G(z) = K((T−f)z + f)/(z(z−1)). Under P control the characteristic
    polynomial is z² − (1 − g(1−φ))z + gφ with g = Kc·K·T; Jury: stable iff gφ < 1 and
    g(1−2φ) < 2, so Kc_u = min(1/φ, 2/(1−2φ) for φ < ½)/(K·T)."""
    bounds = [1 / phi] + ([2 / (1 - 2 * phi)] if phi < 0.5 else [])
    kc_u = min(bounds) / (K * T)
    r = sampled_loop_robustness(IsaGains(0.5 * kc_u), DelayedTF.of([K], [1.0, 0.0], phi * T), T)
    assert r.gain_margin == pytest.approx(2.0, rel=1e-7)
    assert r.stable
    assert not sampled_loop_robustness(
        IsaGains(1.02 * kc_u), DelayedTF.of([K], [1.0, 0.0], phi * T), T
    ).stable


def _roots_stable(kc: float, ti: float, n: int) -> bool:
    """PI on K/(τs+1) held, n whole samples of delay: G = K(1−a)/(z^n(z−a)),
    C = Kc((z−1) + T/Ti)/(z−1); the closed loop's poles are the roots of
    z^n(z−a)(z−1) + K(1−a)·Kc·((z−1) + T/Ti)."""
    lhs = np.polymul(np.polymul([1.0] + [0.0] * n, [1.0, -A]), [1.0, -1.0])
    rhs = K * (1 - A) * kc * np.array([1.0, -1.0 + T / ti])
    char = np.polyadd(lhs, rhs)
    return bool(np.max(np.abs(np.roots(char))) < 1.0)


@pytest.mark.parametrize("n", [0, 3])
def test_pi_stability_matches_the_closed_loop_roots(n):
    ti = 2.0
    for kc in np.linspace(0.1, 12.0, 40):
        r = sampled_loop_robustness(IsaGains(kc, ti), DelayedTF.of([K], [TAU, 1.0], n * T), T)
        assert r.stable == _roots_stable(kc, ti, n), kc


def test_first_order_fractional_delay_response_closed_form():
    """K/(τs+1)·e^{−(nT+f)s} held (modified z-transform): G(z) = K·z^{−n−1}·((1 − b) +
    (b − a)z^{−1})/(1 − a·z^{−1}) with b = e^{−(T−f)/τ}."""
    n, f = 3, 0.3 * T
    plant = sampled_plant(DelayedTF.of([K], [TAU, 1.0], n * T + f), T)
    w = np.array([0.01, 0.3, 1.7, math.pi / T])
    z = np.exp(1j * w * T)
    b = math.exp(-(T - f) / TAU)
    want = K * z ** (-n - 1) * ((1 - b) + (b - A) / z) / (1 - A / z)
    assert np.allclose(plant.at(w), want, rtol=1e-10, atol=0)


@pytest.mark.parametrize(
    "gains", [IsaGains(2.0), IsaGains(2.0, 3.0), IsaGains(1.5, 4.0, 0.8)], ids=["p", "pi", "pid"]
)
def test_pid_transfer_function_is_the_blocks_own(gains):
    """Σ h_k z^{−k} of the PID block's response to a unit PV pulse (converging for |z| > 1
    despite the integrator) is −C(z)."""
    ts, n = 0.25, 10.0
    block = PidBlock(
        PidSettings(kc=gains.kc, ti=gains.ti, td=gains.td, n=n),
        ts,
        (0.0, 100.0),
        mode="auto",
        op=50.0,
    )
    block.update(0.0, 0.0)  # at rest: the derivative's first sample has no previous PV
    h = np.array([block.update(0.0, 1.0 if k == 0 else 0.0) - 50.0 for k in range(3000)])
    for z in (1.1, 1.05j + 0.3, -1.2):
        series = np.sum(h * np.asarray(z, complex) ** -np.arange(h.size))
        assert series == pytest.approx(-pid_response(gains, ts, np.array([z]), n)[0], rel=1e-9)


@pytest.mark.parametrize("fraction", [0.3, 0.6])
def test_tends_to_the_continuous_margin_as_t_goes_to_zero(fraction):
    """P control on e^{−s}/(3s+1): the continuous GM is K_u/Kc; the hold's lag ωT/2 lowers
    the sampled one by O(T), so the error falls tenfold with T."""
    plant = ([1.0], [3.0, 1.0], 1.0)
    ku, pu = ultimate_point(*plant)
    errors = []
    for spp in (100, 1000):
        r = sampled_loop_robustness(IsaGains(fraction * ku), DelayedTF.of(*plant), pu / spp)
        errors.append(r.gain_margin * fraction - 1.0)
        assert 2 * math.pi / r.omega_180 == pytest.approx(pu, rel=2.0 / spp)
    assert -0.03 < errors[0] < 0 and -0.003 < errors[1] < 0
    assert errors[1] / errors[0] == pytest.approx(0.1, rel=0.05)


def test_heat_exchanger_sampled_gain_margin_below_the_continuous_one():
    """e^{−5s}/((10s+1)(60s+1)) at T = 0.25 s (174 samples per period): the hold costs the
    gain margin a few %; at 17 samples per period far more."""
    plant = ([1.0], [600.0, 70.0, 1.0], 5.0)
    ku, pu = ultimate_point(*plant)
    gains = IsaGains(ku / 2.2, 2.2 * pu, pu / 6.3)  # Tyreus–Luyben PID
    g = DelayedTF.of(*plant)
    cont = robustness(gains, g)
    fine = sampled_loop_robustness(gains, g, 0.25)
    coarse = sampled_loop_robustness(gains, g, 2.5)
    assert 0.93 < fine.gain_margin / cont.gain_margin < 0.995
    assert coarse.gain_margin / cont.gain_margin < 0.85
    assert cont.ms < fine.ms < coarse.ms
    assert fine.stable and coarse.stable


def test_no_gain_crossover_means_no_phase_margin_to_lose():
    """Kc·K = 0.5: |L| = g/|z − a| ≤ g/(1 − a) = 0.5 < 1 everywhere, the phase margin is
    infinite while the gain margin stays Kc_u/Kc."""
    kc = 0.5 / K
    r = sampled_loop_robustness(IsaGains(kc), DelayedTF.of([K], [TAU, 1.0], 0.0), T)
    assert r.phase_margin_deg == math.inf and r.omega_c is None
    assert r.gain_margin == pytest.approx(KC_U / kc, rel=1e-9) and r.stable


@pytest.mark.parametrize(
    ("name", "kc", "ti", "td"),
    [
        ("zn-pid", 0.6, 0.5, 0.125),
        ("zn-pid-half", 0.3, 0.5, 0.125),
        ("tl-pid", 1 / 2.2, 2.2, 1 / 6.3),
    ],
)
def test_the_gain_margin_is_the_least_over_every_phase_crossover(name, kc, ti, td):
    """e^{−10s}/(2s + 1) with ZN and TL PIDs from its exact K_u, P_u: the filtered derivative
    keeps the loop gain up while the delay turns the phase past −540°, and that crossing is
    nearer to −1 than the first (ZN PID: 1.37 was printed at the first, 1.03 at the next;
    ×1.05 on Kc goes unstable). Expected: the least 1/|L| where L is real and negative, on a
    fine linear grid (sampled: L(e^{jωT}) from the PID's and the held plant's own responses,
    up to π/T); and the gain factor at which the Nyquist count first calls the sampled loop
    unstable (bisection), to the grid's resolution."""
    plant = DelayedTF.of([1.0], [2.0, 1.0], 10.0)
    ku, pu = ultimate_point([1.0], [2.0, 1.0], 10.0)
    gains = IsaGains(kc * ku, ti * pu, td * pu)

    def least(lw: np.ndarray) -> float:
        real_negative = np.nonzero((np.diff(np.sign(lw.imag)) != 0) & (lw.real[1:] < 0))[0]
        return float(np.min(1.0 / np.abs(lw[real_negative])))

    ts = 0.25
    r = sampled_loop_robustness(gains, plant, ts)
    w = np.linspace(1e-3, math.pi / ts, 2_000_000)
    lw = pid_response(gains, ts, np.exp(1j * w * ts)) * sampled_plant(plant, ts).at(w)
    assert r.gain_margin == pytest.approx(least(lw), rel=1e-4)
    lo, hi = 0.5, 10.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        stable = sampled_loop_robustness(IsaGains(mid * gains.kc, gains.ti, gains.td), plant, ts)
        lo, hi = (mid, hi) if stable.stable else (lo, mid)
    assert r.gain_margin == pytest.approx(lo, rel=1e-3)
    w = np.linspace(1e-3, 200.0, 4_000_000)
    s = 1j * w
    lw = gains.kc * (1 + 1 / (gains.ti * s) + gains.td * s / (1 + gains.td * s / 10.0))
    lw = lw * np.exp(-10.0 * s) / (2.0 * s + 1.0)
    assert robustness(gains, plant).gain_margin == pytest.approx(least(lw), rel=1e-3)
