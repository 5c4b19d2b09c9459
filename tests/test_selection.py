"""Choosing the gains: every rule judged on the identified model, refusals, L/T guidance."""

import pytest

from services.autotuner import experiments
from services.autotuner.model_fit import ProcessFit
from services.autotuner.selection import guidance, select
from tests.test_experiments import HX, run_relay


@pytest.fixture(scope="module")
def hx_relay():
    return experiments.identification(run_relay(*HX))


def test_auto_applies_the_recommended_rule_within_the_bound(hx_relay):
    sel = select(hx_relay, "auto", sample_time=HX[3])
    assert sel.recommended is not None and sel.rule == sel.recommended.rule
    assert sel.refusal is None
    a = sel.assessments[sel.rule]
    assert a.robustness.ms <= 0.9 * 2.0 and a.stable
    assert a.step is not None and a.step.stable
    # model rules come from the relay's fitted model, beside the ultimate-point rules
    assert {"zn-pid", "tl-pid", "amigo-pid", "simc-pid"} <= set(sel.table)


def test_a_rule_above_the_bound_is_refused_and_forced_only_with_a_warning(hx_relay):
    sel = select(hx_relay, "zn-pi")
    assert sel.refusal and "Ms 4.2" in sel.refusal and "recommended rule" in sel.refusal
    forced = select(hx_relay, "zn-pi", force=True)
    assert forced.refusal is None and any("forced" in w for w in forced.warnings)
    lenient = select(hx_relay, "zn-pi", ms_bound=5.0)
    assert lenient.refusal is None


def test_zn_p_on_the_model_gives_the_quarter_decay_it_promises_near_it(hx_relay):
    a = select(hx_relay, "zn-p").assessments["zn-p"]
    assert 0.15 < a.step.decay_ratio < 0.35


def test_ramp_has_no_model_and_says_so():
    ident = experiments.Identification(ku=2.0, pu=10.0)
    sel = select(ident, "zn-pid")
    assert sel.refusal is None and any("no process model" in w for w in sel.warnings)
    assert select(ident, "amigo-pid").refusal.startswith("rule amigo-pid")


def test_guidance_names_the_ranges():
    assert any("0.15–0.6" in g for g in guidance(2.0, None))
    assert any("delay-dominated" in g for g in guidance(2.0, None))
    assert guidance(0.3, None) == []
    assert any("simc-pi-int" in g for g in guidance(None, ProcessFit("ipdt", 1.0, (), 1.0, 0.0)))
