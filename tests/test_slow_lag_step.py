"""A lag far slower than its step test, read as integrating: the dead time with the ramps'
slowing (``reaction_curve.fit_integrator``'s leak).

K·e^{−Ls}/(τs + 1) with τ ≫ L ramps after a step like an integrator K/τ, and the step test
rightly takes it as one (SIMC does, past τ = 8θ); but each ramp slows, K·(1 − e^{−t/τ}), so a
straight line fitted over the record meets the baseline early. On e^{−10s}/(1000s + 1) the
step test's record (16 dead times) read L = 7.8 s, and SIMC's PI for a level designed on it
had Ms 2.05 on the plant, above the default bound 2, where 1.70 was predicted; its run ended
``ok``. The expected figures here are the plants' own coefficients, records computed from
their closed-form step responses, and Ms computed with numpy on the exact plant.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.autotuner.identify import experiments, reaction_curve
from services.autotuner.identify.reaction_curve import fit_integrator
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from shared.messages import TuneRequest
from tests.exact import isa_ms
from tests.plants import transfer_function_loop

TS = 1.0  # s
# the step test's own output changes on the plant below: a step of 5 %, then the pulse of
# −10 % that gives an integrator its level back, then the return
CHANGES = [(80.0, 5.0), (224.0, -10.0), (368.0, 5.0)]


def _record(tau: float | None, delay: float, gain: float, sigma: float, seed: int = 0):
    """The PV at the samples for CHANGES, from the closed forms: a lag's K·Δu·(1 − e^{−r/τ}),
    an integrator's K'·Δu·r (τ None), r the time since the change's effect began."""
    t = np.arange(0.0, 360.0, TS)
    y = np.full(t.size, 50.0)
    for tk, du in CHANGES:
        run = np.maximum(t - tk - delay, 0.0)
        y += gain * du * (run if tau is None else 1.0 - np.exp(-run / tau))
    return t, y + np.random.default_rng(seed).normal(0.0, sigma, t.size)


def test_a_slow_lag_is_read_with_its_own_dead_time():
    t, y = _record(1000.0, 10.0, 1.0, 0.002)
    fit = fit_integrator(t, y, CHANGES, 144.0)
    assert fit is not None
    assert fit.dead_time == pytest.approx(10.0, rel=0.02)
    assert fit.rate == pytest.approx(1.0 / 1000.0, rel=0.02)  # K/τ: the first slope
    assert fit.leak == pytest.approx(1.0 / 1000.0, rel=0.15)
    assert abs(fit.drift) < 3e-5  # at rest before the step: no drift to mimic the slowing


def test_without_the_slowing_the_dead_time_comes_out_short(monkeypatch):
    """The defect itself: the integrator's line alone puts L 20 % early."""
    monkeypatch.setattr(reaction_curve, "LEAK_F", math.inf)
    t, y = _record(1000.0, 10.0, 1.0, 0.002)
    fit = fit_integrator(t, y, CHANGES, 144.0)
    assert fit is not None and fit.leak == 0.0
    assert fit.dead_time < 8.5


@pytest.mark.parametrize("seed", range(8))
def test_an_integrators_noise_is_not_read_as_a_slowing(seed):
    """An exact integrator in white noise: no leak kept, L and K' as they were."""
    t, y = _record(None, 10.0, 1e-3, 0.002, seed)
    fit = fit_integrator(t, y, CHANGES, 144.0)
    assert fit is not None and fit.leak == 0.0
    assert fit.dead_time == pytest.approx(10.0, abs=0.3)
    assert fit.rate == pytest.approx(1e-3, rel=0.01)


def test_a_step_recorded_before_is_read_with_straight_ramps(monkeypatch):
    """A run recorded before ``step_leak`` replays as it ran: straight ramps, L short."""
    live = experiments.live_flags
    monkeypatch.setattr(
        experiments,
        "live_flags",
        lambda method: {k: v for k, v in live(method).items() if k != "step_leak"},
    )
    res = _slow_step()
    assert res.experiment["model_delay"] < 8.5
    assert res.step["slowing_lag"] is None
    assert not [w for w in res.warnings if "ramps slowed" in w]


def _slow_step():
    sim = transfer_function_loop([1.0], [1000.0, 1.0], 10.0, TS, 0.002, name="slow")
    req = TuneRequest(loop="slow", method="step")
    return TuningRun(LocalLoopClient(sim), req, "t", RunHooks()).run()


def test_a_noise_free_integrator_keeps_no_slowing():
    """Without noise the straight fit's residual is rounding alone: no slowing is read from
    rounding over rounding, and L and K' come out exact."""
    t, y = _record(None, 10.0, 1e-3, 0.0)
    fit = fit_integrator(t, y, CHANGES, 144.0)
    assert fit is not None and fit.leak == 0.0
    assert fit.dead_time == pytest.approx(10.0, abs=1e-6)
    assert fit.rate == pytest.approx(1e-3, rel=1e-9)


def test_the_step_tests_level_rule_on_a_slow_lag_is_as_safe_as_predicted():
    res = _slow_step()
    assert res.status == "ok", res.reason
    assert res.experiment["model_delay"] == pytest.approx(10.0, rel=0.03)
    assert res.step["slowing_lag"] == pytest.approx(1000.0, rel=0.1)
    (said,) = [w for w in res.warnings if w.startswith("the ramps slowed as a lag of about")]
    assert "read as integrating" in said
    isa = res.chosen["isa"]
    assert isa["td"] == 0.0
    ms = isa_ms([1.0], [1000.0, 1.0], 10.0, TS, isa)
    assert ms < 2.0
    assert ms == pytest.approx(res.robustness[res.rule]["ms"], rel=0.05)


def test_a_lag_too_slow_for_the_time_allowed_is_named_with_the_time_it_needs():
    """A clean e^{−10s}/(1000s + 1) does not come to rest within the step test's 7,200 s, nor
    does it ramp steadily enough to be read as integrating (its slowing is plain without
    noise): the abort names the lag the record shows and a --max-time, and that time ends
    the test with the plant's own FOPDT."""

    def run(max_time: float | None):
        sim = transfer_function_loop([1.0], [1000.0, 1.0], 10.0, TS, name="s")
        req = TuneRequest(loop="s", method="step", max_time=max_time)
        return TuningRun(LocalLoopClient(sim), req, "t", RunHooks()).run()

    first = run(None)
    assert first.status == "aborted"
    assert "no steady state within 7200 s of the step: the PV is still settling" in first.reason
    tau = float(first.reason.split("a lag of about ")[1].split(" s")[0])
    assert tau == pytest.approx(1000.0, rel=0.05)
    asked = float(first.reason.split("--max-time (about ")[1].split(")")[0])
    assert 5 * tau < asked < 10 * tau
    second = run(asked)
    assert second.status == "ok", second.reason
    e = second.experiment
    assert e["model"] == "fopdt"
    assert e["model_lag_1"] == pytest.approx(1000.0, rel=0.01)
    assert e["model_delay"] == pytest.approx(10.0, rel=0.01)


def test_autotune_step_names_its_own_flag_for_the_time_it_needs():
    """`autotune step` has --timeout where a tune has --max-time: its abort advised "a longer
    --max-time (about 8100)", a flag it refuses (helper trial). The same lag, stepped by the
    command's own test: the advice names --timeout, and that time ends the test with the
    plant's own lag."""
    from services.autotuner.commands.step import config_from_args
    from services.autotuner.identify.step_test import StepTestAborted
    from services.autotuner.step_run import run_step_test
    from services.cli import build_parser

    def run(*flags: str):
        sim = transfer_function_loop([1.0], [1000.0, 1.0], 10.0, TS, name="s")
        args = build_parser().parse_args(["step", "s", *flags])
        return run_step_test(LocalLoopClient(sim), config_from_args(args), wait_return=False)

    with pytest.raises(StepTestAborted) as stop:
        run()
    said = str(stop.value)
    assert "--max-time" not in said and "a longer --timeout (about " in said
    asked = float(said.split("--timeout (about ")[1].split(")")[0])
    assert 5 * 1000.0 < asked < 10 * 1000.0
    report = run("--timeout", f"{asked:g}")
    assert report.curve.gain == pytest.approx(1.0, rel=0.01)
    assert report.curve.time_constant_63 == pytest.approx(1000.0, rel=0.01)  # τ, past L
