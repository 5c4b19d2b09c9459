"""The signal helpers against figures worked by hand (ramps, a sine, residuals orthogonal to a
line), never against the code under test."""

import math

import numpy as np
import pytest

from shared.control.signals import (
    at_rest,
    difference_noise,
    extrema,
    first_crossing,
    noise_level,
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
