"""A tune never applies a gain above what any write of gains may ask (1000 % of output per %
of span, a proportional band of 0.1 %): `autotune set` and `apply` refuse such a gain, and a
noise-free loop with a dead time 1/10,000 of its lag was tuned `ok` at TL PI 4,700 %/%."""

import math
import re

import pytest

from services.autotuner.design.selection import select
from services.autotuner.identify import experiments
from services.autotuner.identify.model_fit import ProcessFit
from services.autotuner.tuning import TuningRun
from services.logger.analysis import analyze_file, format_analysis
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.control.forms import MAX_KC_PERCENT
from shared.messages import TuneRequest
from tests.exact import lag_ultimate
from tests.recorded_run import record_in_process

K, T, L, TS = 1.0, 200.0, 0.02, 0.01  # e^{−0.02s}/(200s + 1) sampled at 10 ms
SPAN = 100.0  # PV units: Kc in % per PV unit is then Kc in % per % of span
FOPDT = ProcessFit("fopdt", K, (T,), L, 1e-6, noise_rms=0.0)


def least_lambda_rounded_up() -> float:
    """The λ the refusals name: a lag this far past its dead time is designed as the
    integrator K/T·e^{−L's}/s (L' = L + Ts/2, the hold's), lambda PI Kc = (2λ + L')/(K/T·
    (λ + L')²), which falls to Kc_max at λ + L' = (1 + √(1 − Kc_max·K/T·L'))/(Kc_max·K/T);
    named to 3 figures rounded up (it lies between 0.1 and 1 s here)."""
    ki, lh, cap = K / T, L + TS / 2, MAX_KC_PERCENT * 100.0 / SPAN
    least = (1 + math.sqrt(1 - cap * ki * lh)) / (cap * ki) - lh
    assert 0.1 < least < 1.0
    return math.ceil(least * 1000) / 1000


@pytest.fixture(scope="module")
def ident():
    ku, pu = lag_ultimate(K, (T,), L)
    return experiments.Identification(ku=ku, pu=pu, ku_spread=0.01, pu_spread=0.01, model=FOPDT)


def test_the_rules_ask_more_than_the_limit_and_without_a_span_one_is_chosen(ident):
    """The case itself: K_u ≈ πT/(2L) ≈ 15,700, so every rule is far above 1000 %/%; with
    no span (no % to judge by) the selection is what it was."""
    assert ident.ku > 10 * MAX_KC_PERCENT
    sel = select(ident, "auto", sample_time=TS)
    assert sel.chosen is not None and sel.chosen.kc > MAX_KC_PERCENT


def test_no_rule_above_the_limit_is_recommended_and_the_refusal_names_the_way_out(ident):
    sel = select(ident, "auto", sample_time=TS, span=SPAN)
    assert sel.chosen is None and sel.refusal.startswith("no rule could be recommended")
    assert f"above the {MAX_KC_PERCENT:g} % of output per % of span" in sel.refusal
    assert set(sel.unsafe) == set(sel.table)
    lam = float(re.search(r"--lambda ([0-9.e+-]+)", sel.refusal).group(1))
    assert lam == least_lambda_rounded_up()
    took = select(ident, "lambda-pi", sample_time=TS, span=SPAN, lambda_s=lam)
    assert took.refusal is None and took.chosen.kc <= MAX_KC_PERCENT
    ki, lh = K / T, L + TS / 2
    assert took.chosen.kc == pytest.approx((2 * lam + lh) / (ki * (lam + lh) ** 2))


def test_rules_above_the_limit_are_passed_over_and_said_to_be(ident):
    """On a 15-unit span (Kc in %/% = 0.15 Kc): ZN PID at 0.6 K_u is above the limit,
    TL PI at K_u/3.2 within it."""
    sel = select(ident, "auto", sample_time=TS, span=15.0)
    assert 0.6 * ident.ku * 0.15 > MAX_KC_PERCENT > ident.ku / 3.2 * 0.15
    assert sel.chosen is not None and sel.chosen.kc * 0.15 <= MAX_KC_PERCENT
    assert "zn-pid" in sel.unsafe and "tl-pi" not in sel.unsafe
    (said,) = [w for w in sel.warnings if "not offered for applying" in w]
    assert "zn-pid (" in said and "tl-pi (" not in said and sel.rule not in said


def test_force_does_not_take_a_gain_above_the_limit(ident):
    sel = select(ident, "tl-pi", sample_time=TS, span=SPAN, force=True)
    assert sel.refusal and "not even with --force" in sel.refusal
    assert f"--rule lambda-pi --lambda {least_lambda_rounded_up():.3g} " in sel.refusal
    # the same gains on a 10 × narrower span are 10 × fewer % per %: within, and taken
    narrow = select(ident, "tl-pi", sample_time=TS, span=SPAN / 10, force=True)
    kc = 0.3125 * ident.ku  # Tyreus–Luyben PI: Kc = K_u/3.2
    assert kc * (SPAN / 10) / 100 < MAX_KC_PERCENT
    assert narrow.refusal is None and narrow.chosen.kc == pytest.approx(kc)


# the loop as a plant file has it (noise-free)
PLANT = {
    "seed": 0,
    "loops": {
        "a": {
            "model": "transfer_function",
            "num": [K],
            "den": [T, 1.0],
            "delay": L,
            "sample_time": TS,
            "noise_std": 0.0,
            "pv_range": [0.0, SPAN],
        }
    },
}


def _loop():
    return build_plant(PLANT, "t")["a"]


def test_a_tune_of_such_a_loop_is_rejected_and_leaves_the_loop_as_it_was():
    sim = _loop()
    before = (sim.pid.gains, sim.mode)
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="a", method="relay"), "t").run()
    assert r.status == "rejected" and not r.applied and r.restored
    assert f"{MAX_KC_PERCENT:g} % of output per % of span" in r.reason
    assert "--rule lambda-pi --lambda" in r.reason  # the relay's pool is Tyreus–Luyben's
    assert (sim.pid.gains, sim.mode) == before
    # every rule it computed is above the limit (else one would have been taken)
    pct = [g["isa_percent"]["kc"] for g in r.gains.values()]
    assert min(pct) > MAX_KC_PERCENT and all(math.isfinite(p) for p in pct)


def test_a_rule_above_the_limit_proposed_with_no_apply_is_not_sent_to_apply():
    """--no-apply proposes a named rule's gains; one above the limit was proposed with
    "`autotune apply …` applies and verifies them", and apply refuses it."""
    sim = _loop()
    req = TuneRequest(loop="a", method="relay", rule="tl-pi", apply=False)
    r = TuningRun(LocalLoopClient(sim), req, "t").run()
    assert r.status == "proposed" and not r.applied
    assert r.reason.startswith("not applied (apply = false, --no-apply), and not to be: refused")
    assert "not even with --force" in r.reason and "applies and verifies them" not in r.reason


def test_the_offline_analysis_of_such_a_run_says_its_own_refusal(tmp_path):
    """`autotune analyze` printed every rule's gains (4,700 %/% for TL PI) and only the live
    run's reason: its own selection's refusal is said above the table, and the live reason,
    the same words, is not printed twice."""
    path, live = record_in_process(tmp_path, "gl", PLANT, "a", "relay")
    assert live.status == "rejected"
    a = analyze_file(str(path))
    assert a.selection is not None and a.selection.recommended is None
    own = a.selection.refusal
    assert own is not None and f"{MAX_KC_PERCENT:g} % of output per % of span" in own
    text = format_analysis(a, None)
    assert f"  refused: {own}" in text.splitlines()
    assert "  live run: rejected (refused as above)" in text.splitlines()
    assert text.count(own) == 1
    assert a.to_dict(None)["refusal"] == own
