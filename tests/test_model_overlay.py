"""The report's model against the data for a model fitted with the output's offset from its
balance (an integrator's, ``refine_on_record`` with ``offset``): driven, as fitted, by the
output less that offset. The record here is an integrator with dead time computed sample by
sample from its definition, not by the code under test."""

from __future__ import annotations

import numpy as np
import pytest

from services.logger.overlay import REST_SAMPLES, model_overlay
from services.logger.result_model import result_model

K, L, TS = 0.05, 1.0, 0.1  # PV units per % per s, s, s
OFFSET = 0.4  # % the held output is off its balance


def _record(n: int = 3000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A PV that integrates K·(u − 50 − OFFSET) held over each sample, L later: the output
    at its balance before the record, then at 50 % from its start (off the balance by
    OFFSET, so the PV creeps), then 2 % higher."""
    t = np.arange(n) * TS
    op = np.full(n, 50.0)
    op[REST_SAMPLES + 200 :] += 2.0
    d = round(L / TS)
    pv = np.full(n, 40.0)
    for k in range(1, n):
        u = op[k - 1 - d] if k - 1 - d >= 0 else 50.0 + OFFSET
        pv[k] = pv[k - 1] + K * TS * (u - 50.0 - OFFSET)
    return t, pv, op


def test_the_model_is_driven_by_the_output_less_its_fitted_offset():
    t, pv, op = _record()
    stated = {"model": "ipdt", "model_gain": K, "model_delay": L, "model_rms": 0.01}
    model = result_model({**stated, "model_offset": OFFSET})
    assert model is not None and model.offset == OFFSET
    over = model_overlay(t, pv, op, model, TS, 0, t.size)
    assert over is not None
    # from the rest window's mean PV (the record creeps over it): a constant gap, no drift
    gap = over.model_pv - pv
    assert np.ptp(gap) == pytest.approx(0.0, abs=1e-9)
    assert over.fit_percent > 99.0
    without = model_overlay(t, pv, op, result_model(stated), TS, 0, t.size)
    assert without is not None and np.ptp(without.model_pv - pv) > 1.0  # it drifted off


@pytest.mark.parametrize("bad", [None, "0.4", True, float("nan"), float("inf")])
def test_an_offset_that_is_not_a_number_is_no_offset(bad):
    stated = {"model": "ipdt", "model_gain": K, "model_delay": L, "model_offset": bad}
    model = result_model(stated)
    assert model is not None and model.offset is None


def test_an_integrating_step_tests_drift_is_its_offset():
    """An integrating step test states no fitted offset, but the PV's drift before its step
    (PV units/s), which its rate is read net of: the model is driven by the output less
    −drift/K', the same record as above. Driven by the output alone it climbed off the data
    by the drift over the record (lvl2: 0.015 m, fit 65.9 %: helper trial)."""
    t, pv, op = _record()
    drift = K * (50.0 - 50.0 - OFFSET)  # the PV's rate at 50 % held, before the step
    stated = {"model": "ipdt", "model_gain": K, "model_delay": L, "model_rms": 0.01}
    step = {"method": "integrating", "drift": drift, "reaction_rate": K}
    model = result_model(stated, step)
    assert model is not None and model.offset == pytest.approx(OFFSET, rel=1e-12)
    over = model_overlay(t, pv, op, model, TS, 0, t.size)
    gap = over.pv - over.model_pv
    assert np.ptp(gap) < 1e-9 * np.ptp(pv)  # a constant gap (the rest's mean), no drift
    # a self-regulating step's drift is no offset of its output; nor a drift not stated
    assert result_model(stated, {**step, "method": "self-regulating"}).offset is None
    assert result_model(stated, {"method": "integrating"}).offset is None
