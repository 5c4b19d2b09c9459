"""Lambda tuning (issue 13, deliverable 1): the rules against their closed forms, the loop
they give on a FOPDT plant, the default λ, the request check, the CLI flags and the aim."""

import cmath
import math

import pytest

from services.autotuner.commands.tune import add_tune_options, request_from_args
from services.autotuner.design.recommend import ROBUST_RULES, assess, recommend
from services.autotuner.design.request_check import validate_request
from services.autotuner.design.rules import RULES, apply_rules, default_lambda
from services.autotuner.design.selection import assessments_dict, select
from services.autotuner.identify.experiments import Identification
from services.autotuner.identify.model_fit import ProcessFit
from shared.cli import OneLineParser, check_flags
from shared.errors import ConfigError
from shared.messages import TuneRequest

K, T, L = 2.5, 40.0, 6.0  # a FOPDT plant: K e^{−Ls}/(Ts + 1)
FOPDT = ProcessFit("fopdt", K, (T,), L, 0.0)
KI, LI = 0.03, 4.0  # an integrating plant: K' e^{−Ls}/s
IPDT = ProcessFit("ipdt", KI, (), LI, 0.0)


def _c(g, s: complex) -> complex:
    """The ISA controller Kc (1 + 1/(Ti s) + Td s)."""
    return g.kc * (1.0 + (1.0 / (g.ti * s) if g.ti else 0.0) + g.td * s)


@pytest.mark.parametrize("lam", [3.0, 18.0, 55.0])
def test_lambda_pi_on_a_fopdt_model(lam):
    g = RULES["lambda-pi"].compute(FOPDT, lam)
    assert g.kc == pytest.approx(T / (K * (lam + L)), rel=1e-12)
    assert g.ti == pytest.approx(T, rel=1e-12)
    assert g.td == 0.0


@pytest.mark.parametrize("lam", [3.0, 18.0, 55.0])
def test_lambda_pid_is_the_imc_design_with_a_pade_delay(lam):
    g = RULES["lambda-pid"].compute(FOPDT, lam)
    assert g.kc == pytest.approx((T + L / 2) / (K * (lam + L / 2)), rel=1e-12)
    assert g.ti == pytest.approx(T + L / 2, rel=1e-12)
    assert g.td == pytest.approx(T * L / (2 * T + L), rel=1e-12)


@pytest.mark.parametrize("lam", [5.0, 12.0, 40.0])
@pytest.mark.parametrize("w", [1e-3, 0.01, 0.07, 0.3, 2.0])
def test_the_lambda_pi_loop_is_a_delayed_integrator(lam, w):
    g = RULES["lambda-pi"].compute(FOPDT, lam)
    s = 1j * w
    loop = _c(g, s) * K * cmath.exp(-L * s) / (T * s + 1.0)
    want = cmath.exp(-L * s) / ((lam + L) * s)
    assert abs(loop - want) <= 1e-9 * abs(want)


@pytest.mark.parametrize("rule", ["lambda-pi", "lambda-pid"])
@pytest.mark.parametrize("lam", [4.0, 12.0, 30.0])
def test_the_integrating_lambda_pi(rule, lam):
    g = RULES[rule].compute(IPDT, lam)
    assert g.kc == pytest.approx((2 * lam + LI) / (KI * (lam + LI) ** 2), rel=1e-12)
    assert g.ti == pytest.approx(2 * lam + LI, rel=1e-12)
    assert g.td == 0.0


def test_a_sopdt_model_is_reduced_by_the_half_rule():
    t1, t2, lag, lam = 30.0, 8.0, 3.0, 20.0
    g = RULES["lambda-pi"].compute(ProcessFit("sopdt", K, (t1, t2), lag, 0.0), lam)
    t, dead = t1 + t2 / 2, lag + t2 / 2
    assert g.kc == pytest.approx(t / (K * (lam + dead)), rel=1e-12)
    assert g.ti == pytest.approx(t, rel=1e-12)


def test_the_default_lambda():
    assert default_lambda(FOPDT) == pytest.approx(max(T, 3 * L))
    short = ProcessFit("fopdt", K, (5.0,), 4.0, 0.0)
    assert default_lambda(short) == pytest.approx(12.0)
    assert default_lambda(IPDT) == pytest.approx(3 * LI)
    g = apply_rules(None, None, FOPDT)["lambda-pi"]
    assert g.kc == pytest.approx(T / (K * (T + L)), rel=1e-12)
    g = apply_rules(None, None, FOPDT, lambda_s=9.0)["lambda-pi"]
    assert g.kc == pytest.approx(T / (K * (9.0 + L)), rel=1e-12)


@pytest.mark.parametrize(("t1", "integrating"), [(4.76e6, True), (1900.0, False)])
@pytest.mark.parametrize("rule", ["lambda-pi", "lambda-pid"])
def test_a_lag_no_test_can_see_is_taken_as_an_integrator(t1, integrating, rule):
    """A ramp's SOPDT of 0.05·e^{−s}/(s(2s + 1)): T₁ = 4.76·10⁶ s, T₂ = 2 s, L = 1 s, gain
    0.05·T₁. Its first-order equivalent (half rule: T₁ + 1 s, L + 1 s = 2 s) lags over 1000
    dead times: the lambda rules take the integrator 0.05·T₁/(T₁ + 1)·e^{−2s}/s, λ = 3·2 s;
    at T₁ = 1900 s (950 dead times) λ = T and the self-regulating form, as before."""
    t2, lag = 2.0, 1.0
    model = ProcessFit("sopdt", 0.05 * t1, (t1, t2), lag, 0.0)
    t, dead = t1 + t2 / 2, lag + t2 / 2
    g = RULES[rule].compute(model, None)
    if integrating:
        ki, lam = 0.05 * t1 / t, 3 * dead
        assert default_lambda(model) == pytest.approx(lam, rel=1e-12)
        assert g.kc == pytest.approx((2 * lam + dead) / (ki * (lam + dead) ** 2), rel=1e-12)
        assert g.ti == pytest.approx(2 * lam + dead, rel=1e-12) and g.td == 0.0
    else:
        assert default_lambda(model) == pytest.approx(t, rel=1e-12)
        assert g.ti == pytest.approx(t + (dead / 2 if rule == "lambda-pid" else 0), rel=1e-12)


@pytest.mark.parametrize("lam", [0.0, -1.0, math.nan, math.inf])
def test_a_lambda_that_is_not_positive_and_finite_is_refused(lam):
    with pytest.raises(ValueError, match="λ > 0"):
        RULES["lambda-pi"].compute(FOPDT, lam)
    assert "lambda-pi" not in apply_rules(None, None, FOPDT, lambda_s=lam)


def test_the_lambda_rules_are_model_rules_with_their_sources():
    for name, controller in (("lambda-pi", "PI"), ("lambda-pid", "PID")):
        r = RULES[name]
        assert (r.kind, r.controller, r.tuned_by_lambda) == ("model", controller, True)
    assert "Dahlin" in RULES["lambda-pi"].source
    assert "Rivera" in RULES["lambda-pid"].source


@pytest.mark.parametrize("rule", ["lambda-pi", "lambda-pid"])
@pytest.mark.parametrize("method", ["relay", "ramp", "step"])
def test_the_request_check_accepts_lambda_rules_from_a_model(rule, method):
    """The ramp's model too: fitted to its whole record, its own recommendation designs
    lambda-pi from it (`autotune apply` of such a run was refused)."""
    assert validate_request(TuneRequest(loop="x", method=method, rule=rule)) is None


def _args(*argv):
    p = OneLineParser(prog="autotune tune")
    p.add_argument("loop")
    add_tune_options(p)
    return p.parse_args(["hx1", *argv])


def test_the_flags_reach_the_request():
    req = request_from_args(_args("--lambda", "25", "--aim", "robust"), "test")
    assert (req.lambda_s, req.aim) == (25.0, "robust")
    req = request_from_args(_args(), "test")
    assert (req.lambda_s, req.aim) == (None, "balanced")
    assert "lambda_s" in req.model_dump()


@pytest.mark.parametrize("value", ["0", "-3", "nan", "inf"])
def test_a_bad_lambda_flag_is_refused(value):
    with pytest.raises(ConfigError, match="--lambda"):
        check_flags("tune", _args(f"--lambda={value}"))


def test_the_aim():
    cands = assess(None, FOPDT, apply_rules(None, None, FOPDT))
    balanced = recommend(None, FOPDT, 2.0, cands)
    assert recommend(None, FOPDT, 2.0, cands, aim="balanced") == balanced
    robust = recommend(None, FOPDT, 2.0, cands, aim="robust")
    assert robust.rule == "lambda-pi" == ROBUST_RULES[0]
    ok = [a for a in cands.values() if RULES[a.rule].controller != "P" and a.within(1.8)]
    fast = recommend(None, FOPDT, 2.0, cands, aim="fast")
    assert fast.rule == max(ok, key=lambda a: a.gains.kc / a.gains.ti).rule
    with pytest.raises(ValueError, match="aim"):
        recommend(None, FOPDT, 2.0, cands, aim="quick")


def test_the_selection_states_lambda_and_follows_the_aim():
    ident = Identification(model=FOPDT)
    sel = select(ident, "auto", sample_time=0.5, lambda_s=20.0, aim="robust")
    assert sel.rule == "lambda-pi" and sel.refusal is None
    design_l = L + 0.25  # the hold's half sample is given to the model rules
    assert sel.chosen.kc == pytest.approx(T / (K * (20.0 + design_l)), rel=1e-12)
    assert assessments_dict(sel)["lambda-pi"]["lambda_s"] == 20.0
    assert "lambda_s" not in assessments_dict(sel)["amigo-pi"]
    default = select(ident, "lambda-pid", sample_time=0.5)
    assert default.lambda_s == pytest.approx(max(T, 3 * design_l))
    assert (
        select(ident, "auto", sample_time=0.5).rule
        == select(ident, "auto", sample_time=0.5, aim="balanced").rule
    )


def _pi_step_overshoot(kc: float, ti: float, dt: float, horizon: float) -> float:
    """The setpoint step's overshoot (% of the change) of PI control of K e^{−Ls}/(Ts + 1),
    integrated here by explicit Euler with the delay as a shift of dt steps (independent of
    the product's discretisation)."""
    n, lag = round(horizon / dt), round(L / dt)
    u_hist = [0.0] * (lag + 1)
    x = integral = peak = 0.0
    for _ in range(n):
        e = 1.0 - x
        integral += e * dt
        u_hist.append(kc * (e + integral / ti))
        x += dt * (K * u_hist[-1 - lag] - x) / T
        peak = max(peak, x)
    return 100.0 * (peak - 1.0)


@pytest.mark.parametrize("factor", [3.0, 5.0])
def test_lambda_pi_setpoint_step_overshoots_less_than_one_percent(factor):
    """With λ ≥ 3L the loop e^{−Ls}/((λ + L)s) has kL = L/(λ + L) ≤ 1/4 < 1/e: its closed
    loop has a real dominant root and does not overshoot. Checked by an independent
    simulation and by the product's prediction."""
    from services.autotuner.design.predicted_response import predicted_setpoint_step
    from shared.control.transfer import DelayedTF

    g = RULES["lambda-pi"].compute(FOPDT, factor * L)
    assert _pi_step_overshoot(g.kc, g.ti, 1e-3, 30.0 * (factor * L + L)) < 1.0
    fig = predicted_setpoint_step(g, DelayedTF.of([K], [T, 1.0], L), timescale=factor * L + L)
    assert fig.stable and fig.overshoot < 1.0
