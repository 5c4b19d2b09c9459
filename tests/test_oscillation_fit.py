"""The growing/decaying sinusoid fit (``oscillation.fit_oscillation``): a fit that turns into a
spike at its record's end is given up at once; a fast-growing oscillation is not one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.autotuner.identify import oscillation
from services.autotuner.identify.oscillation import DecayingSine, fit_oscillation


def _counted(monkeypatch) -> list[int]:
    """How many Jacobians the fits ask for (one per step the fit takes)."""
    count = [0]
    jac = DecayingSine.jac

    def counting(self, p):
        count[0] += 1
        return jac(self, p)

    monkeypatch.setattr(DecayingSine, "jac", counting)
    return count


def test_a_fit_that_becomes_a_spike_at_the_records_end_is_given_up_at_once(monkeypatch):
    """A ramp's first trial at a low gain: a lag's slow rise under noise, no oscillation. The
    fit starts from the noise's turning points and crawls to a sinusoid under a period long,
    grown e^26 over the record (its start 10⁻¹¹ tall): 1,955 steps to fail, before."""
    count = _counted(monkeypatch)
    sigma = 0.0187
    t = np.arange(408) * 0.25
    y = (
        60.0
        + 0.75 * (1 - np.exp(-t / 30.0))
        + sigma * np.random.default_rng(6).standard_normal(t.size)
    )
    assert fit_oscillation(t, y, sigma) is None
    assert count[0] < 200


@pytest.mark.parametrize("growth_over_record", [25.0, 40.0])
def test_a_fast_growing_oscillation_is_fitted_however_much_it_grew(growth_over_record):
    """20 periods, grown e^25 or e^40 over the record (from 10⁻¹⁰ to the PV's scale): the
    growth and period are read, not taken for a spike."""
    span, period = 100.0, 5.0
    g = growth_over_record / span
    t = np.arange(0.0, span + 1e-9, 0.05)
    a0 = 10.0 * math.exp(-growth_over_record)
    y = 50.0 + a0 * np.exp(g * t) * np.sin(2 * math.pi / period * t + 0.3)
    osc = fit_oscillation(t, y, 0.0)
    assert osc is not None
    assert osc.growth == pytest.approx(g, rel=1e-3)
    assert osc.period == pytest.approx(period, rel=1e-4)


def test_a_spike_is_under_a_period_and_grown_past_the_limit():
    span = 100.0
    grown = (oscillation.SPIKE_GROWTH + 1) / span
    assert oscillation._spike(np.array([0.0, 1.0, grown, 0.9 * 2 * math.pi / span, 0.0]), span)
    assert not oscillation._spike(np.array([0.0, 1.0, grown, 1.1 * 2 * math.pi / span, 0.0]), span)
    assert not oscillation._spike(np.array([0.0, 1.0, -grown, 0.5 / span, 0.0]), span)
    assert not oscillation._spike(np.array([0.0, 1.0, 0.9 * grown, 0.5 / span, 0.0]), span)
