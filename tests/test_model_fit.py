"""Model fits to exact frequency points: in its class each model is recovered exactly."""

import math

import numpy as np
import pytest

from services.autotuner.identify.model_fit import choose, fit_models
from shared.control.transfer import DelayedTF
from tests.exact import ultimate_point


def response(num, den, delay, w):
    s = 1j * np.asarray(w)
    return np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * delay)


PLANTS = {
    "fopdt": ([2.0], [5.0, 1.0], 1.0),
    "sopdt": ([1.0], [600.0, 70.0, 1.0], 5.0),  # the heat exchanger: 60 s and 10 s lags
    "ipdt": ([0.5], [1.0, 0.0], 2.0),
}


@pytest.mark.parametrize("kind", list(PLANTS))
def test_a_plant_in_the_class_is_recovered_with_its_ultimate_point(kind):
    num, den, delay = PLANTS[kind]
    ku, pu = ultimate_point(num, den, delay)
    wu = 2 * math.pi / pu
    # the relay's two stages: fundamentals either side of ω_u, and their odd harmonics
    omega = np.array([0.97, 2.91, 4.85, 1.03, 3.09]) * wu
    fit = choose(fit_models(omega, response(num, den, delay, omega), [10, 1, 0.5, 10, 1]))
    assert fit is not None and fit.rms < 1e-6
    got = fit.ultimate_point()
    assert got[0] == pytest.approx(ku, rel=1e-6) and got[1] == pytest.approx(pu, rel=1e-6)
    if kind != "ipdt":
        assert fit.gain == pytest.approx(num[0] / den[-1], rel=1e-5)
    assert fit.delay == pytest.approx(delay, rel=1e-5)
    w = np.logspace(-3, 1, 50) * wu
    assert np.allclose(fit.response(w), response(num, den, delay, w), rtol=1e-4)


def test_a_third_order_plant_gets_a_second_order_model_that_fits_near_the_crossover():
    num, den = [6.0], [1.0, 6.0, 11.0, 6.0]
    ku, _ = ultimate_point(num, den)
    omega = np.array([0.97, 2.91, 4.85, 1.03, 3.09]) * math.sqrt(11.0)
    fits = fit_models(omega, response(num, den, 0.0, omega), [10, 1, 0.5, 10, 1])
    best = choose(fits)
    assert best.kind == "sopdt"
    assert best.ultimate_point()[0] == pytest.approx(ku, rel=0.03)


def test_too_few_points_are_refused():
    with pytest.raises(ValueError, match="two frequency points"):
        fit_models([1.0], [0.5 + 0j])


def test_the_process_model_never_passes_a_candidate_the_true_plant_would_fail():
    """Every candidate that the relay's process model (refined on the whole record) puts
    within the recommender's margin is within the Ms bound on the true plant."""
    from services.autotuner.design.recommend import MODEL_MARGIN, MS_BOUND, assess
    from services.autotuner.design.robustness import robustness
    from services.autotuner.design.rules import UltimatePoint
    from tests.plants import HX, THIRD, run_relay

    passed = 0
    for num, den, delay, ts in (THIRD, HX):
        r = run_relay(num, den, delay, ts).result
        assert r.model is not None
        for name, a in assess(UltimatePoint(r.ku, r.pu), r.model).items():
            if a.within(MODEL_MARGIN * MS_BOUND):
                passed += 1
                assert robustness(a.gains, DelayedTF.of(num, den, delay)).ms <= MS_BOUND, name
    assert passed >= 3


def test_recommendation_is_stable_with_ms_within_the_bound_on_the_true_plant():
    from services.autotuner.design.recommend import recommend
    from services.autotuner.design.robustness import robustness
    from services.autotuner.design.rules import UltimatePoint
    from tests.plants import HX, THIRD, run_relay

    for num, den, delay, ts in (THIRD, HX):
        r = run_relay(num, den, delay, ts).result
        rec = recommend(UltimatePoint(r.ku, r.pu), r.model)
        true = robustness(rec.gains, DelayedTF.of(num, den, delay))
        assert true.gain_margin > 1 and true.phase_margin_deg > 0
        assert true.ms <= 2.0, (rec.rule, true.ms)
