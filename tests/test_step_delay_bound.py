"""A step test whose record does not resolve the dead time designs with the most dead time the
record cannot tell from none, not with the floor of half a sample or a fitted figure lost in
the noise.

A lag's response in noise fits any dead time within a few standard errors of the fitted one
about as well, and a rule that rests on L scales its gain by 1/L: the gravity-drain tank
sampled at 0.1 s (its fit found no dead time: the floor, 0.05 s) was given AMIGO PI at Kc
1.8e4 %/m, which saturated its output in the verification (rejected). Where the fitted L is
within three of its standard errors of none, the design takes three standard errors, and no
more than the time the PV took to clear its noise after the step (before which the response
began). The standard error is checked against its closed form: σ·√((JᵀJ)⁻¹)_LL, with J the
derivatives of K·Δu·(1 − e^{−(t−L)/T}) in (ln K, ln T, L) at the record's samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from services.autotuner.identify.step_test import StepTest, StepTestConfig
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

K, T, TS, SIGMA, SIZE, PV0, OP0 = 1.0, 20.0, 0.1, 0.05, 5.0, 30.0, 50.0


@dataclass(frozen=True)
class Sample:
    t: float  # s
    pv: float  # PV units
    op: float  # %


def lag_step(
    seed: int, bound: bool, sigma: float = SIGMA, delay: float = 0.0, size: float = SIZE
) -> StepTest:
    """K·e^{−delay·s}/(T·s + 1), stepped by ``size`` %, its PV with white noise of σ
    ``sigma``."""
    rng = np.random.default_rng(seed)
    test = StepTest(
        StepTestConfig(size=size, bound_delay=bound), OP0, (0.0, 100.0), (0.0, 100.0), TS
    )
    op, t_hold = OP0, None
    for k in range(1, 100_000):
        t = k * TS
        moved = t_hold is not None and t > t_hold + delay
        rise = K * (op - OP0) * (1 - math.exp(-(t - t_hold - delay) / T)) if moved else 0.0
        demand = test.feed(Sample(t, PV0 + rise + sigma * float(rng.standard_normal()), op))
        if demand.op != op and t_hold is None:
            t_hold = t
            test.held(t)
        op = demand.op
        if test.finished:
            return test
    raise AssertionError("the step test never finished")


def closed_form_spread(test: StepTest, delay: float, size: float = SIZE) -> float:
    """σ·√((JᵀJ)⁻¹)_LL at the true parameters, over the samples the test recorded (all of
    them: under 4,000, so the fit worked on every one)."""
    tau = np.asarray(test.t) - test.t_step
    on = tau > delay
    e = np.where(on, np.exp(-(tau - delay) / T), 1.0)
    a = K * size
    jac = np.column_stack(
        [
            np.where(on, a * (1 - e), 0.0),  # ∂/∂ln K
            np.where(on, -a * e * (tau - delay) / T, 0.0),  # ∂/∂ln T
            np.where(on, -a * e / T, 0.0),  # ∂/∂L
        ]
    )
    return SIGMA * math.sqrt(np.linalg.inv(jac.T @ jac)[2, 2])


@pytest.mark.parametrize("seed", [0, 1])
def test_the_dead_times_standard_error_is_its_closed_form(seed):
    test = lag_step(seed, bound=True, delay=1.0)
    assert len(test.t) < 4000
    model, spread = test._record_fit()
    assert spread == pytest.approx(closed_form_spread(test, 1.0), rel=0.05)
    assert model.delay == pytest.approx(1.0, abs=4 * spread)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_unresolved_dead_time_is_designed_on_three_standard_errors(seed):
    """No dead time: the fit finds none (the floor, 0.05 s), within three standard errors
    (0.09 s) of none; the design takes those (recorded before: the floor)."""
    before = lag_step(seed, bound=False).identification()
    assert before.model.kind == "fopdt" and before.model.delay == pytest.approx(TS / 2)
    test = lag_step(seed, bound=True)
    assert test.phase == "done", test.reason
    ident = test.identification()
    taken = ident.model.delay
    assert taken == pytest.approx(3 * closed_form_spread(test, 0.0), rel=0.05)
    assert taken < test._t_moved  # not capped here: the PV cleared its noise later
    assert ident.step_model.dead_time == taken  # the open-loop rules' L too
    assert ident.experiment.model.delay == taken  # the model reported is the one designed on
    assert ident.step == before.step  # the reaction curve as measured
    (note,) = [n for n in ident.notes if "dead time not resolved" in n]
    assert f"take {taken:.4g} s, three standard errors" in note


@pytest.mark.parametrize("seed", [0, 1])
def test_a_dead_time_the_record_resolves_is_kept(seed):
    """A 1 s dead time under a 20 s lag, the same noise: the fit reads it (its standard error
    0.03 s), and the model is the same with the bound asked for or not."""
    kept = lag_step(seed, bound=False, delay=1.0).identification().model
    assert kept.delay == pytest.approx(1.0, abs=0.15)
    assert lag_step(seed, bound=True, delay=1.0).identification().model == kept


def test_a_clean_record_keeps_the_floor():
    """Without noise the fit's error is nil: the floor of half a sample stands, said as
    before."""
    ident = lag_step(0, bound=True, sigma=0.0).identification()
    assert ident.model.delay == pytest.approx(TS / 2)
    (note,) = [n for n in ident.notes if "dead time not resolved" in n]
    assert "floored at half a sample" in note and "standard errors" not in note


def test_the_gravity_drain_tank_at_a_tenth_of_a_second_is_tuned():
    """The square-root tank (1 s dead time under a 320 s lag) sampled at 0.1 s: its fit puts
    the dead time at 0, the floor was 0.05 s, and AMIGO PI at Kc 1.8e4 %/m saturated the
    output in the verification (rejected). On three standard errors of the fit the gains are
    verified and the dead time designed on is over ten times the floor."""
    sim = build_plant(
        {"seed": 1, "loops": {"x": {"model": "tank_level", "area": 1.0, "sample_time": 0.1}}},
        "x",
    )["x"]
    result = TuningRun(
        LocalLoopClient(sim), TuneRequest(loop="x", method="step"), "x", RunHooks()
    ).run()
    assert result.status == "ok", result.reason
    assert result.experiment["model_delay"] >= 10 * 0.05
    assert result.chosen["isa"]["kc"] < 1.8e4 / 5
    # the L/T said is the design's, not the floor's over the tangent's T
    taken, lag = result.experiment["model_delay"], result.step["time_constant_tangent"]
    assert result.l_over_t == pytest.approx(taken / lag, rel=1e-12)


def test_an_integrating_loop_is_designed_on_three_standard_errors_too():
    """A pure integrator (0.01 %/s per %, no dead time, σ 0.05 %) sampled at 0.1 s: the ramp's
    line meets the rest at the step, L floored at 0.05 s, and SIMC's integrating PI there was
    Kc 500 (30 % of output noise from the PV's). The kink's own standard error (the curve's
    ``dead_time_se``, about 0.045 s) puts three of them at 0.13 s: the design's L, and the gain
    under 0.6 of the floor's. Without noise the error is nil and the floor stands."""
    spec = {
        "model": "ipdt",
        "gain": 0.01,
        "delay": 0.0,
        "sample_time": 0.1,
        "noise_std": 0.05,
        "pv0": 50.0,
        "op0": 50.0,
        "pv_range": [0.0, 100.0],
    }
    for noise in (0.05, 0.0):
        sim = build_plant({"seed": 1, "loops": {"x": {**spec, "noise_std": noise}}}, "x")["x"]
        result = TuningRun(
            LocalLoopClient(sim), TuneRequest(loop="x", method="step"), "x", RunHooks()
        ).run()
        assert result.status == "ok", result.reason
        (note,) = [w for w in result.warnings if "dead time not resolved" in w]
        taken = result.experiment.get("model_delay", result.step["dead_time"])
        if noise:
            assert "three standard errors" in note
            assert taken == pytest.approx(3 * result.step["dead_time_se"], rel=1e-9)
            assert result.chosen["isa"]["kc"] < 0.6 * 500
        else:
            assert "floored at half a sample" in note and "standard errors" not in note
            assert result.step["dead_time"] == pytest.approx(0.05)


def test_repeated_steps_design_on_their_mean_model_and_say_so():
    """``--repeat 2`` on the lag without dead time: each step's model takes three standard
    errors; the mean model is designed on, the open-loop rules' L is that too (the L/T said),
    and the warning says in how many steps (it was dropped, the step model left at the
    floor)."""
    spec = {
        "model": "fopdt",
        "gain": K,
        "time_constant": T,
        "delay": 0.0,
        "sample_time": TS,
        "noise_std": SIGMA,
        "pv0": PV0,
        "op0": OP0,
    }
    sim = build_plant({"seed": 1, "loops": {"x": spec}}, "x")["x"]
    request = TuneRequest(loop="x", method="step", repeat=2)
    result = TuningRun(LocalLoopClient(sim), request, "x", RunHooks()).run()
    assert result.status == "ok", result.reason
    (note,) = [w for w in result.warnings if "dead time not resolved" in w]
    assert note.startswith("dead time not resolved by the record in 2 of 2 steps; ")
    taken = result.experiment["model_delay"]
    assert taken > TS / 2 * 1.5  # over the floor: three standard errors (0.09 s)
    assert result.l_over_t == pytest.approx(taken / result.step["time_constant_tangent"])
