"""Repeated step tests (issue 13, item 3; seed 001: "do two or three more step tests … and
use the average").

On K·e^{−Ls}/(Ts + 1) the up and down steps read the same figures; their mean and spread are
checked against the tests' own figures by hand (statistics over the list). With noise σ the
gain's spread must match what the noise alone gives: K = (ȳ∞ − ȳ₀)/Δu with ȳ₀ the mean of the
40-sample baseline and ȳ∞ that of the rest window (the trailing quarter of the samples since
the step), so s.d.(K) = σ·√(1/40 + 1/m)/|Δu|.
"""

from __future__ import annotations

import math
import statistics
from types import SimpleNamespace

import pytest

from services.autotuner.design.request_check import validate_request
from services.autotuner.identify.driver import drive
from services.autotuner.identify.reaction_curve import IntegratingCurve
from services.autotuner.identify.repeated_steps import AUTO_FIRST, AUTO_LIMIT, RepeatedSteps
from services.autotuner.identify.step_test import StepTestConfig
from services.autotuner.step_run import run_step_test
from services.offline.local_loop import LocalLoopClient, SimLoopPort
from services.plant_sim.plant_file import build_plant

K, T, L, TS = 2.0, 20.0, 3.0, 0.1


def fopdt(noise: float = 0.0, seed: int = 1):
    spec = {
        "model": "fopdt",
        "gain": K,
        "time_constant": T,
        "delay": L,
        "sample_time": TS,
        "noise_std": noise,
        "pv0": 50.0,
        "pv_range": [0.0, 100.0],
    }
    return build_plant({"seed": seed, "loops": {"x": spec}})["x"]


def repeated(loop, repeat: int = 3, auto: bool = False, size: float = 5.0) -> RepeatedSteps:
    st = loop.settings
    e = RepeatedSteps(
        StepTestConfig(size=size),
        loop.op,
        st.op_limits,
        st.pv_range,
        st.sample_time,
        pv_range=st.pv_range,
        repeat=repeat,
        auto=auto,
    )
    drive(e, SimLoopPort(loop, limit=2_000_000 * st.sample_time))
    assert e.phase == "done", e.reason
    return e


def test_up_and_down_in_turn_each_reads_the_plant_and_the_mean_is_theirs():
    e = repeated(fopdt(), 3)
    curves = e.curves()
    assert [c.step_size for c in curves] == [5.0, -5.0, 5.0]
    for c in curves:
        assert c.gain == pytest.approx(K, rel=0.005)  # the exponential's tail, as for one test
        assert c.dead_time == pytest.approx(L, abs=1e-3)
        assert c.time_constant_63 == pytest.approx(T, rel=0.01)
    ident = e.identification()
    mean = ident.step
    for name in ("gain", "dead_time", "time_constant_tangent", "time_constant_63"):
        values = [getattr(c, name) for c in curves]
        s = ident.experiment.spreads[name]
        assert getattr(mean, name) == pytest.approx(sum(values) / 3, rel=1e-12)
        assert s.mean == pytest.approx(sum(values) / 3, rel=1e-12)
        sd = math.sqrt(sum((v - s.mean) ** 2 for v in values) / 2)
        assert s.spread == pytest.approx(sd / abs(s.mean), rel=1e-9, abs=1e-15)
        assert s.precision == pytest.approx(2 * sd / math.sqrt(3) / abs(s.mean), abs=1e-15)
    assert mean.reaction_rate == pytest.approx(mean.gain / mean.time_constant_tangent)
    assert mean.a == pytest.approx(mean.reaction_rate * mean.dead_time)
    assert ident.repeats == curves and ident.notes == []
    assert ident.experiment.to_dict()["tests"] == 3 and ident.experiment.settled


@pytest.mark.parametrize("noise", [0.05, 0.2])
def test_the_gains_spread_is_what_the_noise_gives(noise):
    e = repeated(fopdt(noise, seed=7), 8)
    expected = []
    for test in e.done:
        n = sum(1 for t in test.t if t >= test.t_step)
        m = max(20, n // 4)
        expected.append(noise * math.sqrt(1 / 40 + 1 / m) / 5.0)
    sd = statistics.stdev(c.gain for c in e.curves())
    ratio = sd / statistics.fmean(expected)
    assert 0.5 <= ratio <= 2.0, ratio  # 8 tests: s/σ within about ±50 % (χ², 7 dof)
    spread = e.identification().experiment.spreads["gain"]
    assert spread.std == pytest.approx(sd, rel=1e-12)


def test_auto_stops_at_two_when_they_agree_and_goes_on_when_they_do_not():
    agree = repeated(fopdt(), AUTO_LIMIT, auto=True)
    assert len(agree.done) == AUTO_FIRST
    # lvl1: the tank's square-root outflow reads up and down steps differently (≈ 10 %)
    lvl1 = build_plant({"seed": 1, "loops": {"x": {"model": "tank_level"}}})["x"]
    e = repeated(lvl1, AUTO_LIMIT, auto=True)
    ident = e.identification()
    assert len(e.done) == AUTO_LIMIT and not ident.experiment.settled
    ups = [c.gain for c in e.curves()[0::2]]
    downs = [c.gain for c in e.curves()[1::2]]
    assert min(ups) > max(downs)  # the nonlinearity, not noise: every up above every down
    assert ident.notes and "disagree beyond the tolerance" in ident.notes[0]


def test_an_integrating_loop_repeats_with_its_level_given_back_each_time():
    spec = {"model": "ipdt", "gain": 0.01, "delay": 3.0, "sample_time": 0.5, "noise_std": 0.03}
    loop = build_plant({"seed": 1, "loops": {"x": {**spec, "pv0": 50.0}}})["x"]
    e = repeated(loop, 2)
    for c in e.curves():
        assert isinstance(c, IntegratingCurve) and c.returned
        assert c.reaction_rate == pytest.approx(0.01, rel=0.02)
        assert abs(c.pv_after - 50.0) < 0.2
    ident = e.identification()
    assert ident.integrating and ident.model.kind == "ipdt"
    assert set(ident.experiment.spreads) == {"reaction_rate", "dead_time"}


def test_a_down_step_outside_the_outputs_limits_is_refused_before_anything_moves():
    loop = fopdt()
    st = loop.settings
    with pytest.raises(ValueError, match="size -40 %"):
        RepeatedSteps(StepTestConfig(size=40.0), 30.0, st.op_limits, st.pv_range, TS, repeat=2)


def test_run_step_test_repeats_and_reports_every_test_restored():
    loop = fopdt(0.05)
    report = run_step_test(LocalLoopClient(loop), StepTestConfig(size=5.0), repeat=3)
    d = report.to_dict()
    assert len(d["tests"]) == 3 and set(d["spreads"]) >= {"gain", "dead_time"}
    assert d["gain"] == pytest.approx(statistics.fmean(t["gain"] for t in d["tests"]))
    assert d["restored"] and d["returned_to_rest"]
    assert loop.op == 50.0 and abs(loop.pv - 50.0) < 0.2


def _request(**kw):
    base = {"rule": "auto", "method": "step", "pv_limits": None, "step_size": None, "repeat": 3}
    return SimpleNamespace(**{**base, **kw})


def test_the_request_check_names_repeat():
    validate_request(_request())
    validate_request(_request(repeat="auto"))
    with pytest.raises(ValueError, match="repeat: repeated tests are step tests"):
        validate_request(_request(method="relay"))
    with pytest.raises(ValueError, match="repeat: 21 tests"):
        validate_request(_request(repeat=21))
