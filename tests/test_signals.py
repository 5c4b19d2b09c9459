"""The signal helpers against figures worked by hand (ramps, a sine, residuals orthogonal to a
line), never against the code under test."""

import math

import numpy as np
import pytest

from shared.control.signals import (
    at_rest,
    decay_ratio,
    difference_noise,
    extrema,
    first_crossing,
    noise_level,
    overshoot_decay,
    slowest_decay,
    smooth,
    trapezoid,
)


def test_first_crossing_interpolates_between_the_samples_either_side():
    t = np.arange(0.0, 11.0)  # s
    z = t / 10.0
    assert first_crossing(t, z, 0.25) == pytest.approx(2.5, abs=1e-12)
    assert first_crossing(t + 3.0, z, 0.0) == 3.0  # the first sample is already there
    assert first_crossing(t, z, 1.5) is None  # never reached


def test_trapezoid_is_exact_for_a_piecewise_linear_record():
    t = np.array([0.0, 0.5, 2.0, 3.0])
    y = 2.0 * t + 1.0  # ∫₀³ (2t + 1) dt = 9 + 3
    assert trapezoid(y, t) == pytest.approx(12.0, abs=1e-12)
    assert trapezoid(np.array([5.0]), np.array([1.0])) == 0.0


def test_extrema_are_the_turning_points_of_a_sine():
    t = np.linspace(0.0, 4.0 * math.pi, 4001)
    turns = extrema(t, np.sin(t), 0.5)
    want = [(math.pi * (k + 0.5), (-1.0) ** k) for k in range(4)]
    assert len(turns) == 4
    for (tt, v), (tw, vw) in zip(turns, want, strict=True):
        assert tt == pytest.approx(tw, abs=t[1]) and v == pytest.approx(vw, abs=1e-5)
    assert extrema(t, 0.1 * np.sin(t), 0.5) == []  # swings below min_swing are not turns


def test_smooth_is_a_centred_average_with_the_ends_repeated():
    y = np.array([0.0, 3.0, 6.0, 9.0])
    assert np.allclose(smooth(y, 3), [1.0, 3.0, 6.0, 8.0])  # (0+0+3)/3, …, (6+9+9)/3
    assert np.allclose(smooth(y, 2), y)  # below 3: unchanged
    assert np.allclose(smooth(y, 4), smooth(y, 5))  # an even width is made odd


def test_noise_about_the_trend_and_from_the_differences():
    x = np.arange(4.0)
    e = np.array([1.0, -1.0, -1.0, 1.0])  # orthogonal to 1 and x: the line fit leaves it
    assert noise_level(3.0 + 2.0 * x + e) == pytest.approx(math.sqrt(4.0 / 2.0), rel=1e-12)
    assert noise_level(np.array([1.0, 2.0])) == 0.0
    # differences ±1: their σ is 1, white noise of σ 1/√2 would give it
    zigzag = np.array([0.0, 1.0, 0.0, 1.0, 0.0])
    assert difference_noise(zigzag) == pytest.approx(1.0 / math.sqrt(2.0), rel=1e-12)
    assert difference_noise(np.arange(50.0)) == 0.0  # a trend is not noise here


def test_at_rest_means_no_trend_beyond_the_noise():
    rng = np.random.default_rng(1)
    quiet = 20.0 + 0.1 * rng.standard_normal(200)
    assert at_rest(quiet)
    assert not at_rest(quiet + 0.01 * np.arange(200))  # drifts 2 units, 20σ
    assert not at_rest(np.array([1.0, 1.0]))  # too short to tell


def _through(turns: list[tuple[float, float]], end: float, after: float = 0.0):
    """A record through the turning points (straight between them), from 0 at t = 0, then to
    ``after`` at ``end``: (t, dev) every 0.01."""
    tv = np.array([0.0, *(tt for tt, _ in turns), end])
    yv = np.array([0.0, *(v for _, v in turns), after])
    t = np.arange(0.0, end + 1e-9, 0.01)
    return t, np.interp(t, tv, yv)


def test_decay_ratio_is_the_crest_after_the_largest_over_the_largest():
    """Turning points of deviations from the final value worked by hand: a small crest of the
    approach (0.7) ahead of the overshoot (4.65, then 1.6) is not the oscillation's (second
    over first read 6.6, a growing loop's figure); a trough that stays above the final value
    (0.37) is not a crest (it read 0.37/14.38 = 0.026 for a response whose next crest is
    3.15)."""
    approach = [(1.0, 0.7), (2.0, -0.3), (3.0, 4.65), (4.0, -2.0), (5.0, 1.6), (6.0, -0.5)]
    assert decay_ratio(approach, *_through(approach, 7.0)) == pytest.approx(1.6 / 4.65)
    shallow = [(42.0, 14.38), (66.0, 0.37), (86.0, 3.15), (100.0, -0.4)]
    assert decay_ratio(shallow, *_through(shallow, 200.0)) == pytest.approx(3.15 / 14.38)
    quarter = [(1.0, 8.0), (2.0, -4.0), (3.0, 2.0), (4.0, -1.0), (5.0, 0.5)]
    assert decay_ratio(quarter, *_through(quarter, 6.0)) == pytest.approx(0.25)


def test_decay_ratio_where_the_largest_crest_is_the_last():
    """Growing crests (1, 2, 4): cut by the record's end within 1.5 crest spacings of the
    last, 4/2 (it may grow on); watched for 1.5 spacings beyond it and never again as far
    from zero, it died (None); running on past it without a crest (drifting away to −9),
    4/2 again, not hidden (review); one crest or none: None."""
    growing = [(10.0, 1.0), (15.0, -1.5), (20.0, 2.0), (25.0, -3.0), (30.0, 4.0), (35.0, -1.0)]
    assert decay_ratio(growing, *_through(growing, 38.0)) == pytest.approx(2.0)
    assert decay_ratio(growing, *_through(growing, 45.0)) is None
    assert decay_ratio(growing, *_through(growing, 45.0, after=-9.0)) == pytest.approx(2.0)
    one = [(1.0, 3.0), (2.0, -0.5)]
    assert decay_ratio(one, *_through(one, 10.0)) is None
    below = [(1.0, -3.0), (2.0, -0.5)]
    assert decay_ratio(below, *_through(below, 10.0)) is None
    assert decay_ratio([], np.arange(3.0), np.zeros(3)) is None


def test_the_slowest_decay_after_a_kick_is_the_loops():
    """Crests 1.49 (the setpoint kick's), then 0.98, 1.01, 1.03, 1.00, 0.94 (lvl2 under ZN
    PID, Ms 201): the crest after the largest over the largest reads 0.66; the slowest decay
    among crests of at least a quarter of the largest, from it on, is 1.01/0.98. A geometric
    decay (8, 2, 0.5) is its own ratio, 0.25; crests below a quarter of the largest (1.9, 2.1
    after 10) do not count."""
    crests = [1.49, 0.98, 1.01, 1.03, 1.00, 0.94]
    turns = [x for j, c in enumerate(crests) for x in ((2.0 * j, c), (2.0 * j + 1, -0.5))]
    assert slowest_decay(turns) == pytest.approx(1.01 / 0.98)
    geometric = [(1.0, 8.0), (2.0, -4.0), (3.0, 2.0), (4.0, -1.0), (5.0, 0.5), (6.0, -0.2)]
    assert slowest_decay(geometric) == pytest.approx(0.25)
    small = [(1.0, 10.0), (2.0, -2.0), (3.0, 1.9), (4.0, -1.0), (5.0, 2.1), (6.0, -0.5)]
    assert slowest_decay(small) is None  # only one crest of a quarter of 10 or more
    assert slowest_decay([(1.0, 3.0), (2.0, -1.0)]) is None


def _second_order_error(zeta: float, wn: float, t: np.ndarray) -> np.ndarray:
    """y − 1 of the standard second-order step, ω_n²/(s² + 2ζω_n s + ω_n²), in closed form."""
    sigma, wd = zeta * wn, wn * math.sqrt(1.0 - zeta**2)
    return -np.exp(-sigma * t) * (np.cos(wd * t) + sigma / wd * np.sin(wd * t))


@pytest.mark.parametrize("zeta", [0.1, 0.215, 0.4, 0.6])
def test_overshoot_decay_of_a_second_order_step_is_its_pole_pairs(zeta):
    """Poles −σ ± jω: successive overshoots are a period 2π/ω apart, each e^{−2πσ/ω} of the
    one before (ζ = 0.6: 0.0090, its second overshoot 8.5e-4 of the step); sampled at 2000
    a period, the peaks are read within 1e-5 of their value."""
    wn = 2.0
    sigma, wd = zeta * wn, wn * math.sqrt(1.0 - zeta**2)
    t = np.arange(0.0, 40.0 * 2.0 * math.pi / wd, 2.0 * math.pi / wd / 2000.0)
    expected = math.exp(-2.0 * math.pi * sigma / wd)
    assert overshoot_decay(_second_order_error(zeta, wn, t), 1e-6) == pytest.approx(
        expected, rel=1e-4
    )


def test_a_ripple_on_a_slow_tail_is_no_second_overshoot():
    """−e^{−3t} + 0.06·e^{−t/8}·(1 − e^{−3t}) + 0.02·e^{−0.3t}·sin(2.3t): a rise, a slow tail
    from above and a ripple on it. The ripple's crests above the final value (0.0469, then
    0.0316 a period later) read 0.67 as crests (``decay_ratio``), the ripple's own decay being
    e^{−0.3·2π/2.3} = 0.44 a period; but the response never comes back through its final
    value: one overshoot, no decay ratio to state."""
    t = np.arange(0.0, 120.0, 0.01)
    rise = -np.exp(-3.0 * t)
    dev = rise + 0.06 * np.exp(-t / 8.0) * (1.0 - np.exp(-3.0 * t))
    dev = dev + 0.02 * np.exp(-0.3 * t) * np.sin(2.3 * t)
    crests = extrema(t, dev, 1e-3)
    assert decay_ratio(crests, t, dev) > 0.5  # the crests' figure: the ripple on the tail
    assert overshoot_decay(dev, 1e-3) is None


def test_overshoot_decay_of_a_kick_then_a_ringing_is_the_ringings():
    """Overshoots 1.49 (the setpoint kick's), then 0.98, 1.01, 1.03, 1.00, 0.94 (lvl2 under ZN
    PID, Ms 201): the mean decay a period from the largest, (0.94/1.49)^(1/5) = 0.912, not
    the 0.66 of the second over the first, and not above 1 (1.03/1.00 read as growth) on a
    loop whose overshoots shrink. A first overshoot a zero made small (0.2, then 0.5, 0.1):
    0.1/0.5 = 0.2, not 2.5. No overshoot after the largest, or only one: None."""
    lobes = [-1.0, 1.49, -0.5, 0.98, -0.5, 1.01, -0.5, 1.03, -0.5, 1.00, -0.5, 0.94, -0.5]
    dev = np.array([v for x in lobes for v in (0.0, x)] + [0.0])
    assert overshoot_decay(dev, 1e-3) == pytest.approx((0.94 / 1.49) ** (1 / 5))
    zero = np.array([-1.0, 0.0, 0.2, 0.0, -0.3, 0.0, 0.5, 0.0, -0.3, 0.0, 0.1, 0.0, 0.0])
    assert overshoot_decay(zero, 1e-3) == pytest.approx(0.2)
    assert overshoot_decay(np.array([-1.0, 0.0, 0.3, 0.0, -0.1, 0.0]), 1e-3) is None
    assert overshoot_decay(np.array([-1.0, 0.0, 0.1, 0.0, -0.1, 0.3, 0.0]), 1e-3) is None
    assert overshoot_decay(np.array([-1.0, -0.5, 0.0]), 1e-3) is None
    # a crossing within the band is no crossing: 0.4, a dip to −0.0005, then 0.3 is one lobe
    assert overshoot_decay(np.array([-1.0, 0.4, -0.0005, 0.3, 0.0]), 1e-3) is None
