"""Tuning rules against the formulas of two sources each; form conversions both ways."""

import math

import pytest

from services.autotuner.design.rules import RULES, UltimatePoint, apply_rules
from services.autotuner.identify.model_fit import ProcessFit, StepModel, model_of
from shared.control.forms import (
    IsaGains,
    ParallelGains,
    SeriesGains,
    all_forms,
    from_parallel,
    from_series,
    integral_time_from_reset_rate,
    reset_rate,
    to_parallel,
    to_series,
)

KU, PU = 10.0, 2 * math.pi / math.sqrt(11)  # 6/((s+1)(s+2)(s+3)), seed 000

# (rule, Kc, Ti, Td) from seed 003 Tables 6-1/6-2 and control-references.md (Åström–Hägglund)
CLOSED = [
    ("zn-p", 0.5 * KU, None, 0.0),
    ("zn-pi", 0.45 * KU, PU / 1.2, 0.0),
    ("zn-pid", 0.6 * KU, PU / 2, PU / 8),
    ("tl-pi", KU / 3.2, 2.2 * PU, 0.0),
    ("tl-pid", KU / 2.2, 2.2 * PU, PU / 6.3),
    ("zn-pid-half", 0.3 * KU, PU / 2, PU / 8),
]


@pytest.mark.parametrize(("name", "kc", "ti", "td"), CLOSED)
def test_closed_loop_rules(name, kc, ti, td):
    g = RULES[name].compute(UltimatePoint(KU, PU))
    assert g.kc == pytest.approx(kc, rel=1e-12)
    assert (g.ti is None and ti is None) or g.ti == pytest.approx(ti, rel=1e-12)
    assert g.td == pytest.approx(td, rel=1e-12, abs=0)


def test_seed_000_worked_example_of_the_step_response_method():
    """Seed 000: R = 0.4437, L = 0.42 → PID Kc = 1.2/a, Ti = 2L, Td = 0.5L, i.e. the
    compensator (1.136 s² + 5.41 s + 6.44)/(0.84 s) it prints."""
    r, lag = 0.4437, 0.42
    g = RULES["zn-ol-pid"].compute(StepModel(gain=1.0, dead_time=lag, time_constant=1.0 / r))
    # Kc(1 + 1/(Ti s) + Td s) = (Kc·Ti·Td s² + Kc·Ti s + Kc)/(Ti s)
    assert g.ti == pytest.approx(0.84, rel=1e-12)
    assert g.kc == pytest.approx(6.44, rel=1e-3)
    assert g.kc * g.ti == pytest.approx(5.41, rel=1e-3)
    assert g.kc * g.ti * g.td == pytest.approx(1.136, rel=1e-3)


def test_seed_000_worked_example_of_the_ultimate_sensitivity_method():
    """Seed 000: Ku = 10, Tu = 2π/√11 → PID2 = (1.346 s² + 5.683 s + 6)/(0.9472 s)."""
    g = RULES["zn-pid"].compute(UltimatePoint(KU, PU))
    assert g.kc == pytest.approx(6.0)
    assert g.ti == pytest.approx(0.9472, rel=1e-4)
    assert g.kc * g.ti == pytest.approx(5.683, rel=1e-3)
    assert g.kc * g.ti * g.td == pytest.approx(1.346, rel=1e-3)


def test_open_loop_rules_match_both_their_forms():
    """Seed 003 Table 6-3: Kc = {1, 0.9, 1.2}/(kθ) with k the slope, or τ/(k_p θ)·{…}."""
    k, tau, theta = 2.0, 30.0, 6.0
    m = StepModel(k, theta, tau)
    slope = k / tau
    for name, factor, ti, td in (
        ("zn-ol-p", 1.0, None, 0.0),
        ("zn-ol-pi", 0.9, theta / 0.3, 0.0),
        ("zn-ol-pid", 1.2, 2 * theta, 0.5 * theta),
    ):
        g = RULES[name].compute(m)
        assert g.kc == pytest.approx(factor / (slope * theta), rel=1e-12)
        assert g.kc == pytest.approx(factor * tau / (k * theta), rel=1e-12)
        assert (g.ti is None and ti is None) or g.ti == pytest.approx(ti, rel=1e-12)
        assert g.td == pytest.approx(td)


def test_cohen_coon_table():
    """Seed 003 Table 6-4, checked against the same formulas written with r = θ/τ."""
    k, tau, th = 1.5, 20.0, 4.0
    r = th / tau
    m = StepModel(k, th, tau)
    p, pi, pid = (RULES[n].compute(m) for n in ("cc-p", "cc-pi", "cc-pid"))
    assert p.kc == pytest.approx((1 / k) * (1 / r) * (1 + r / 3))
    assert pi.kc == pytest.approx((1 / k) * (1 / r) * (0.9 + r / 12))
    assert pi.ti == pytest.approx(th * (30 + 3 * r) / (9 + 20 * r))
    assert pid.kc == pytest.approx((1 / k) * (1 / r) * (4 / 3 + r / 4))
    assert pid.ti == pytest.approx(th * (32 + 6 * r) / (13 + 8 * r))
    assert pid.td == pytest.approx(4 * th / (11 + 2 * r))


def test_apply_rules_uses_what_is_available():
    closed = apply_rules(UltimatePoint(KU, PU), None)
    assert set(closed) == {n for n, r in RULES.items() if r.kind == "closed"}
    both = apply_rules(UltimatePoint(KU, PU), StepModel(1.0, 2.0, 10.0))
    # every rule but the integrating one (T = 10 s is not above 8θ = 16 s)
    assert set(both) == set(RULES) - {"simc-pi-int"}


@pytest.mark.parametrize(
    "g", [IsaGains(2.0, 30.0, 5.0), IsaGains(1.0, 8.0, 2.0), IsaGains(3.0), IsaGains(0.5, 4.0)]
)
def test_forms_round_trip(g):
    back = from_parallel(to_parallel(g))
    assert back.kc == pytest.approx(g.kc) and back.td == pytest.approx(g.td)
    assert (back.ti is None and g.ti is None) or back.ti == pytest.approx(g.ti)
    s = to_series(g)
    assert s is not None
    back = from_series(s)
    assert back.kc == pytest.approx(g.kc) and back.td == pytest.approx(g.td)
    assert (back.ti is None and g.ti is None) or back.ti == pytest.approx(g.ti)


def test_series_of_zn_pid_is_the_interactive_form():
    """ZN PID has Ti = 4·Td exactly: its series form is 0.3·Ku, Pu/4, Pu/4."""
    s = to_series(RULES["zn-pid"].compute(UltimatePoint(KU, PU)))
    assert s.kc == pytest.approx(0.3 * KU) and s.ti == pytest.approx(PU / 4)
    assert s.td == pytest.approx(PU / 4)
    assert to_series(IsaGains(1.0, 4.0, 1.5)) is None  # Ti < 4 Td: no series form


def test_series_to_isa_by_multiplying_out():
    s = SeriesGains(2.0, 10.0, 2.5)  # 2(1 + 1/(10s))(1 + 2.5s) = 2(1.25 + 1/(10s) + 2.5s)
    g = from_series(s)
    assert g.kc == pytest.approx(2.5)
    assert g.kc / g.ti == pytest.approx(2.0 / 10.0)
    assert g.kc * g.td == pytest.approx(2.0 * 2.5)


def test_reset_rate_and_minutes():
    assert reset_rate(30.0) == 2.0 and integral_time_from_reset_rate(2.0) == 30.0
    assert reset_rate(None) == 0.0 and integral_time_from_reset_rate(0.0) is None
    f = all_forms(IsaGains(2.0, 120.0, 30.0))
    assert f.ti_min == 2.0 and f.td_min == 0.5 and f.reset_rate_rpm == 0.5
    assert f.parallel == ParallelGains(2.0, 2.0 / 120.0, 60.0)
    assert f.series == SeriesGains(1.0, 60.0, 60.0)  # Ti = 4·Td: the double root


def test_gain_forms_as_json():
    """The result's ``gains`` object: these keys, ISA as given, None where a form lacks."""
    f = all_forms(IsaGains(2.0, 120.0, 30.0)).to_dict()
    assert f == {
        "isa": {"kc": 2.0, "ti": 120.0, "td": 30.0},
        "parallel": {"kp": 2.0, "ki": 2.0 / 120.0, "kd": 60.0},
        "series": {"kc": 1.0, "ti": 60.0, "td": 60.0},
        "ti_min": 2.0,
        "td_min": 0.5,
        "reset_rate_rpm": 0.5,
    }
    assert all_forms(IsaGains(2.0, 100.0, 30.0)).to_dict()["series"] is None  # Ti < 4·Td
    p = all_forms(IsaGains(3.0)).to_dict()
    assert p["isa"] == {"kc": 3.0, "ti": None, "td": 0.0} and p["ti_min"] is None
    assert p["parallel"] == {"kp": 3.0, "ki": 0.0, "kd": 0.0} and p["reset_rate_rpm"] == 0.0


@pytest.mark.parametrize(("k", "t", "lag"), [(1.0, 60.0, 10.6), (2.0, 5.0, 5.0), (0.5, 1.0, 4.0)])
def test_amigo_and_simc(k, t, lag):
    """The formulas as control-references.md gives them (Åström & Hägglund 2006; Skogestad
    2003), written out here independently of the rules module."""
    m = model_of(StepModel(k, lag, t))
    pi, pid, simc = (RULES[n].compute(m) for n in ("amigo-pi", "amigo-pid", "simc-pi"))
    assert pi.kc == pytest.approx(0.15 / k + (0.35 - lag * t / (lag + t) ** 2) * t / (k * lag))
    assert pi.ti == pytest.approx(
        0.35 * lag + 13 * lag * t * t / (t * t + 12 * lag * t + 7 * lag * lag)
    )
    assert pid.kc == pytest.approx((0.2 + 0.45 * t / lag) / k)
    assert pid.ti == pytest.approx((0.4 * lag + 0.8 * t) * lag / (lag + 0.1 * t))
    assert pid.td == pytest.approx(0.5 * lag * t / (0.3 * lag + t))
    assert simc.kc == pytest.approx(t / (2 * k * lag)) and simc.ti == pytest.approx(min(t, 8 * lag))


def test_amigo_pi_on_a_pure_delay_is_the_textbook_limit():
    """For T → 0 (pure delay) AMIGO PI tends to K = 0.15/K_p and Ti = 0.35 L."""
    g = RULES["amigo-pi"].compute(model_of(StepModel(2.0, 1.0, 1e-9)))
    assert g.kc == pytest.approx(0.075, rel=1e-6) and g.ti == pytest.approx(0.35, rel=1e-6)


@pytest.mark.parametrize(("k", "t1", "t2", "th"), [(1.0, 60.0, 10.0, 5.0), (2.0, 3.0, 1.0, 1.0)])
def test_simc_pid_is_the_series_form_of_skogestad_2003(k, t1, t2, th):
    """Series PID Kc' = τ₁/(k·2θ), τI' = min(τ₁, 8θ), τD' = τ₂ (Skogestad 2003, Table 3;
    Grimholt & Skogestad 2018): the ISA gains give the same controller at every frequency."""
    g = RULES["simc-pid"].compute(ProcessFit("sopdt", k, (t1, t2), th, 0.0))
    kc_s, ti_s, td_s = t1 / (k * 2 * th), min(t1, 8 * th), t2
    for w in (0.01, 0.1, 1.0, 10.0):
        s = 1j * w
        series = kc_s * (1 + 1 / (ti_s * s)) * (1 + td_s * s)
        isa = g.kc * (1 + 1 / (g.ti * s) + g.td * s)
        assert isa == pytest.approx(series, rel=1e-12)


def test_simc_for_integrating_processes():
    """Kc = 1/(k'·2θ), Ti = 8θ for k'·e^{−θs}/s (Skogestad 2003, Table 3), also for a
    first-order model lag-dominated enough (τ₁ > 8θ) to count as integrating, k' = k/τ₁."""
    g = RULES["simc-pi-int"].compute(ProcessFit("ipdt", 0.5, (), 2.0, 0.0))
    assert g.kc == pytest.approx(1 / (0.5 * 4.0)) and g.ti == pytest.approx(16.0)
    g = RULES["simc-pi-int"].compute(ProcessFit("fopdt", 10.0, (100.0,), 2.0, 0.0))
    assert g.kc == pytest.approx(1 / (0.1 * 4.0)) and g.ti == pytest.approx(16.0)
    with pytest.raises(ValueError, match="not an integrating"):
        RULES["simc-pi-int"].compute(ProcessFit("fopdt", 1.0, (10.0,), 2.0, 0.0))
    # a second-order model is first made first-order by the half rule, as for SIMC PI: its
    # τ₂ was ignored (θ = 3 s for a τ₂ of 5 s: Kc 1.8 × SIMC PI's, Ms 4.3)
    k, t1, t2, th = 33695.0, 1.68e6, 5.0, 3.0
    g = RULES["simc-pi-int"].compute(ProcessFit("sopdt", k, (t1, t2), th, 0.0))
    theta, k_int = th + t2 / 2, k / (t1 + t2 / 2)
    assert g.kc == pytest.approx(1 / (k_int * 2 * theta)) and g.ti == pytest.approx(8 * theta)
