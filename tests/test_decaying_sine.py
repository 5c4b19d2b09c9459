"""The sinusoid fits' own residuals and Jacobians (``oscillation.DecayingSine``, and
``DriftingSine`` with its bounds) against scipy's forward differences: the same numbers to the
bit, so every fit (and every figure built on it) is what scipy's ``'2-point'`` scheme gives,
only cheaper."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from services.autotuner.identify.oscillation import DecayingSine, DriftingSine


def _record(growth: float, noise: float, n: int = 400, seed: int = 3) -> tuple[np.ndarray, ...]:
    tt = 0.25 * np.arange(n)
    rng = np.random.default_rng(seed)
    y = 40.0 + 3.0 * np.exp(growth * tt) * np.sin(2 * math.pi / 17.0 * tt + 0.7)
    return tt, y + noise * rng.standard_normal(n)


def _model(tt: np.ndarray, y: np.ndarray):
    """The residual written out as the fit states it (scipy differentiates this one)."""

    def resid(p: np.ndarray) -> np.ndarray:
        c, a, g, w, phi = p
        return c + a * np.exp(g * tt) * np.sin(w * tt + phi) - y

    return resid


RECORDS = [(-0.02, 0.0), (0.0, 0.05), (0.015, 0.3), (-0.2, 1.0)]


@pytest.mark.parametrize(("growth", "noise"), RECORDS)
def test_residuals_and_jacobian_equal_scipy_forward_differences(growth, noise):
    tt, y = _record(growth, noise)
    resid = _model(tt, y)
    rng = np.random.default_rng(11)
    starts = [np.array([40.0, 3.0, growth, 2 * math.pi / 17.0, 0.7])]
    starts += [np.array([-1.5, 0.0, 0.0, 1e-3, -4.0]), np.array([1e6, -2e-9, -0.5, 30.0, 1e3])]
    starts += [starts[0] * (1 + 0.5 * rng.standard_normal(5)) for _ in range(12)]
    for p in starts:
        sine = DecayingSine(tt, y)
        assert np.array_equal(sine.resid(p), resid(p))
        # least_squares' `jac` of its result is the Jacobian at its x: with max_nfev=1 that
        # x is the start, differentiated by scipy's own 2-point scheme in one case
        ref = least_squares(resid, p, method="lm", max_nfev=1)
        ours = least_squares(sine.resid, p, jac=sine.jac, method="lm", max_nfev=1)
        assert np.array_equal(ref.x, ours.x)
        assert np.array_equal(ref.jac, ours.jac)
        assert np.array_equal(ref.jac, sine.jac(ref.x))


@pytest.mark.parametrize(("growth", "noise"), RECORDS)
@pytest.mark.parametrize("max_nfev", [2000, 15])
def test_a_fit_is_scipys_to_the_bit(growth, noise, max_nfev):
    """Converged or cut off by its evaluation budget, the fit ends where scipy's own finite
    differences end it: the same parameters, residuals, verdict and count."""
    tt, y = _record(growth, noise)
    resid = _model(tt, y)
    for p0 in ([40.5, 2.0, 0.0, 0.33, 0.0], [39.0, 5.0, -0.05, 0.4, 1.5]):
        ref = least_squares(resid, p0, method="lm", max_nfev=max_nfev)
        sine = DecayingSine(tt, y)
        ours = least_squares(sine.resid, p0, jac=sine.jac, method="lm", max_nfev=max_nfev)
        assert np.array_equal(ref.x, ours.x)
        assert np.array_equal(ref.fun, ours.fun)
        assert (ref.success, ref.status, ref.nfev) == (ours.success, ours.status, ours.nfev)


def test_the_residual_is_not_aliased():
    """A caller that changes the residual it got does not change the next one."""
    tt, y = _record(-0.02, 0.0)
    sine = DecayingSine(tt, y)
    p = np.array([40.0, 3.0, -0.02, 0.37, 0.7])
    first = sine.resid(p)
    first[:] = 0.0
    assert np.array_equal(sine.resid(p), _model(tt, y)(p))


def _drifting(tt: np.ndarray, y: np.ndarray):
    def resid(p: np.ndarray) -> np.ndarray:
        c, a, g, w, phi, b, lam = p
        return c + b * np.exp(-lam * tt) + a * np.exp(g * tt) * np.sin(w * tt + phi) - y

    return resid


INF = np.inf
W = 2 * math.pi / 17.0


@pytest.mark.parametrize(
    ("x", "lb", "ub"),
    [
        # inside its bounds: scipy's plain steps
        (
            [40.0, 3.0, -0.02, W, 0.7, 1.5, 0.01],
            [-INF] * 3 + [0.5 * W] + [-INF] * 2 + [1e-3],
            [INF] * 3 + [2 * W] + [INF] * 2 + [0.2],
        ),
        # ω a hair below its upper bound: the step turned back
        (
            [40.0, 3.0, -0.02, 2 * W - 1e-12, 0.7, 1.5, 0.01],
            [-INF] * 3 + [0.5 * W] + [-INF] * 2 + [1e-3],
            [INF] * 3 + [2 * W] + [INF] * 2 + [0.2],
        ),
        # λ between bounds closer than a step: the step cut to the farther bound
        (
            [40.0, -3.0, 0.0, W, -0.7, 0.0, 0.0100000001],
            [-INF] * 3 + [0.5 * W] + [-INF] * 2 + [0.01],
            [INF] * 3 + [2 * W] + [INF] * 2 + [0.0100000003],
        ),
    ],
    ids=["inside", "at-upper-bound", "tighter-than-a-step"],
)
def test_drifting_jacobian_equals_scipys_at_bounds(x, lb, ub):
    tt, y = _record(-0.02, 0.05)
    resid = _drifting(tt, y)
    model = DriftingSine(tt, y, np.array(lb), np.array(ub))
    x = np.array(x)
    assert np.array_equal(model.resid(x), resid(x))
    ref = least_squares(resid, x, bounds=(lb, ub), max_nfev=1)
    ours = least_squares(model.resid, x, jac=model.jac, bounds=(lb, ub), max_nfev=1)
    assert np.array_equal(ref.x, ours.x)
    assert np.array_equal(ref.jac, ours.jac)
    assert np.array_equal(ref.jac, model.jac(ref.x))


@pytest.mark.parametrize(("growth", "noise"), RECORDS)
def test_a_drifting_fit_within_bounds_is_scipys_to_the_bit(growth, noise):
    tt, y = _record(growth, noise)
    y = y + 4.0 * np.exp(-0.01 * tt)  # a slow mode beside the oscillation
    resid = _drifting(tt, y)
    span = float(tt[-1])
    lb = [-INF, -INF, -INF, 0.5 * W, -INF, -INF, 0.1 / span]
    ub = [INF, INF, INF, 2.0 * W, INF, INF, 0.5 * W]
    for lam0 in (1.0 / span, 4.0 / span):
        x0 = [40.0, 3.0, 0.0, 1.1 * W, 0.5, 3.0, lam0]
        ref = least_squares(resid, x0, bounds=(lb, ub), max_nfev=400)
        model = DriftingSine(tt, y, np.array(lb), np.array(ub))
        ours = least_squares(model.resid, x0, jac=model.jac, bounds=(lb, ub), max_nfev=400)
        assert np.array_equal(ref.x, ours.x)
        assert np.array_equal(ref.fun, ours.fun)
        assert (ref.success, ref.status, ref.nfev) == (ours.success, ours.status, ours.nfev)
