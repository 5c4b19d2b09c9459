"""Gains in % of span (issue 13, item 4; seed 001: industrial controllers work on normalised
0–100 % signals).

The output is in % already; the PV is in engineering units over its transmitter's range
(lo, hi), span = hi − lo. Every expected figure here is converted by hand from the span:

* a controller gain or K_u (% of output per PV unit): × span/100 → % of output per % of span;
* the proportional band PB = 100/Kc(%/%), in % of span;
* a process gain K (PV units per %), a reaction rate or K' (PV units per s per %), a = R·L:
  × 100/span → % of span per % (per s per %);
* Ti and Td: unchanged, s.
"""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import zenoh

from services.autotuner.commands.tune import format_result
from services.autotuner.identify.experiments import Identification
from services.autotuner.identify.reaction_curve import IntegratingCurve, ReactionCurve
from services.autotuner.tuning import TuningRun
from services.cli import build_parser, main
from services.logger.analysis import Analysis
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.control.forms import (
    IsaGains,
    all_forms,
    kc_percent,
    process_gain_percent,
    proportional_band,
    pv_span,
    step_percent,
    to_percent,
)
from shared.messages import PidGains, TuneRequest, TuneResult, Verification

# (pv_range, Kc in % per PV unit, Kc in % per % by hand, PB in % by hand)
CONTROLLER = [
    ((0.0, 150.0), 2.0, 3.0, 100.0 / 3.0),  # hx1: 2 %/degC on 150 degC is 3 %/%, PB 33.3 %
    ((0.0, 3.0), 20.0, 0.6, 100.0 / 0.6),  # a 3 m tank: 20 %/m is 0.6 %/%, PB 167 %
    ((0.0, 40.0), 0.3, 0.12, 100.0 / 0.12),  # a 40 m3/h flow: 0.3 %/(m3/h) is 0.12 %/%
    ((-50.0, 250.0), 1.0, 3.0, 100.0 / 3.0),  # span 300, not hi: 1 %/unit is 3 %/%
    ((20.0, 70.0), 4.0, 2.0, 50.0),  # span 50: 4 %/unit is 2 %/%, PB 50 %
]


@pytest.mark.parametrize(("pv_range", "kc", "kc_pct", "pb"), CONTROLLER)
def test_controller_gain_and_proportional_band_by_hand(pv_range, kc, kc_pct, pb):
    span = pv_span(pv_range)
    assert span == pv_range[1] - pv_range[0]
    assert kc_percent(kc, span) == pytest.approx(kc_pct, rel=1e-12)
    assert proportional_band(kc_pct) == pytest.approx(pb, rel=1e-12)
    g = to_percent(IsaGains(kc, 120.0, 30.0), span)
    assert (g.kc, g.pb) == (pytest.approx(kc_pct, rel=1e-12), pytest.approx(pb, rel=1e-12))
    assert (g.ti, g.td) == (120.0, 30.0)  # times do not scale


def test_isa_percent_in_the_gains_json_beside_isa():
    """``all_forms(g, span).to_dict()`` keeps every key it had and adds ``isa_percent``; with
    no span the object is as before (no key)."""
    g = IsaGains(2.0, 120.0, 30.0)
    before = all_forms(g).to_dict()
    assert "isa_percent" not in before
    with_pct = all_forms(g, 150.0).to_dict()
    assert {k: v for k, v in with_pct.items() if k != "isa_percent"} == before
    assert with_pct["isa_percent"] == {
        "kc": pytest.approx(3.0, rel=1e-12),
        "ti": 120.0,
        "td": 30.0,
        "pb": pytest.approx(100.0 / 3.0, rel=1e-12),
    }
    p_only = all_forms(IsaGains(3.0), 50.0).to_dict()["isa_percent"]
    assert p_only == {"kc": pytest.approx(1.5), "ti": None, "td": 0.0, "pb": pytest.approx(200 / 3)}
    assert to_percent(IsaGains(0.0), 150.0).pb is None  # no proportional action: no band


# (pv_range, process figure in PV units per % or per s per %, by hand in % of span)
PROCESS = [
    ((0.0, 150.0), 0.85, 0.85 * 100 / 150),  # hx1: 0.85 degC/% is 0.567 % of span per %
    ((0.0, 3.0), 0.01, 1.0 / 3.0),  # a tank's K' 0.01 m/s per % is 0.333 %/s per %
    ((-50.0, 250.0), 0.9, 0.3),
    ((20.0, 70.0), -0.5, -1.0),  # a direct-acting process keeps its sign
]


@pytest.mark.parametrize(("pv_range", "k", "k_pct"), PROCESS)
def test_process_gain_by_hand(pv_range, k, k_pct):
    assert process_gain_percent(k, pv_span(pv_range)) == pytest.approx(k_pct, rel=1e-12)


def test_step_figures_by_hand_for_both_curves():
    """The step's K, R and a (the fields of ReactionCurve and IntegratingCurve by those names)
    × 100/span; the other figures (times, sizes in %, levels) are left out."""
    for cls in (ReactionCurve, IntegratingCurve):
        names = {f.name for f in dataclasses.fields(cls)}
        assert {"reaction_rate", "a"} <= names
    assert "gain" in {f.name for f in dataclasses.fields(ReactionCurve)}
    self_regulating = {"gain": 0.9, "reaction_rate": 0.03, "a": 0.15, "dead_time": 5.0}
    assert step_percent(self_regulating, 150.0) == {
        "gain": pytest.approx(0.6),
        "reaction_rate": pytest.approx(0.02),
        "a": pytest.approx(0.1),
    }
    integrating = {"method": "integrating", "reaction_rate": 0.01, "a": 0.03, "slope": 0.05}
    assert step_percent(integrating, 3.0) == {
        "reaction_rate": pytest.approx(1 / 3),
        "a": pytest.approx(1.0),
    }
    assert step_percent(None, 150.0) is None


@pytest.mark.parametrize(
    "bad", [(5.0, 1.0), (1.0, 1.0), (0.0, math.inf), (math.nan, 1.0), (-1e308, 1e308)]
)
def test_a_range_that_has_no_span_is_refused(bad):
    with pytest.raises(ValueError, match="pv_range"):
        pv_span(bad)
    assert pv_span(None) is None


# --- the tuner's result -----------------------------------------------------------------------

RANGE = (-50.0, 250.0)  # span 300: × 3 for a controller gain, ÷ 3 for a process gain
THIRD = {
    "model": "transfer_function",
    "num": [6.0],
    "den": [1.0, 6.0, 11.0, 6.0],
    "sample_time": 0.02,
    "noise_std": 0.0,
    "mode": "manual",
    "pid": {"kc": 2.0, "ti": 2.0},
    "pv_range": list(RANGE),
    "pv_units": "degC",
}


def tune(spec: dict, method: str) -> TuneResult:
    loop = build_plant({"seed": 1, "loops": {"x": spec}})["x"]
    req = TuneRequest(loop="x", method=method, apply=False)
    r = TuningRun(LocalLoopClient(loop), req, "unit").run()
    assert r.status == "proposed" and not r.applied and "--no-apply" in r.reason, r.reason
    # what the bus carries: the same result back from its JSON
    assert TuneResult.model_validate_json(r.model_dump_json()) == r
    return r


def assert_rules_by_hand(r: TuneResult, up: float) -> None:
    """Every rule's isa_percent (and the chosen one's): Kc × ``up`` (span/100), PB = 100/that,
    Ti and Td as in isa."""
    for name, g in [*r.gains.items(), ("chosen", r.chosen)]:
        isa, pct = g["isa"], g["isa_percent"]
        assert pct["kc"] == pytest.approx(isa["kc"] * up, rel=1e-12), name
        assert pct["pb"] == pytest.approx(100.0 / (isa["kc"] * up), rel=1e-12), name
        assert (pct["ti"], pct["td"]) == (isa["ti"], isa["td"]), name


def test_a_relay_result_carries_both():
    r = tune(THIRD, "relay")
    assert r.pv_range == RANGE
    assert r.ku_percent == pytest.approx(r.ku * 3.0, rel=1e-12)
    assert r.model_gain_percent == pytest.approx(r.experiment["model_gain"] / 3.0, rel=1e-12)
    assert r.step is None and r.step_percent is None
    assert_rules_by_hand(r, 3.0)


def test_a_step_result_carries_both():
    """K, R and a ÷ 3; and ZN's open-loop P rule Kc = 1/a gives PB = 100·a(% of span)."""
    r = tune(THIRD, "step")
    assert r.ku is None and r.ku_percent is None
    for k in ("gain", "reaction_rate", "a"):
        assert r.step_percent[k] == pytest.approx(r.step[k] / 3.0, rel=1e-12), k
    assert_rules_by_hand(r, 3.0)
    a_pct = r.step["a"] * 100.0 / 300.0
    assert r.gains["zn-ol-p"]["isa_percent"]["pb"] == pytest.approx(100.0 * a_pct, rel=1e-9)


def test_an_integrating_step_result_in_percent_of_span():
    """K'·e^{−Ls}/s with K' = 0.01 m/s per %, L = 3 s, on a 20–70 m range (span 50): R = K'
    is 0.01 × 100/50 = 0.02 % of span per s per %, a = R·L = 0.06 % of span per %."""
    spec = {
        "model": "ipdt",
        "gain": 0.01,
        "delay": 3.0,
        "sample_time": 0.5,
        "noise_std": 0.0,
        "pv0": 50.0,
        "op0": 50.0,
        "pv_range": [20.0, 70.0],
        "pv_units": "m",
        "mode": "manual",
    }
    r = tune(spec, "step")
    assert r.step["method"] == "integrating"
    assert r.step_percent == {
        "reaction_rate": pytest.approx(0.02, rel=1e-6),
        "a": pytest.approx(0.06, rel=1e-6),
    }
    assert r.model_gain_percent == pytest.approx(0.02, rel=1e-6)
    assert_rules_by_hand(r, 0.5)


def test_an_old_result_without_the_new_fields_still_reads():
    old = '{"run_id": "a", "loop": "hx1", "t": 1.0, "method": "relay", "rule": "zn-pi", '
    old += '"status": "ok", "ku": 15.0, "gains": {"zn-pi": {"isa": {"kc": 1, "ti": 2, "td": 0}}}}'
    r = TuneResult.model_validate_json(old)
    assert (r.pv_range, r.ku_percent, r.step_percent, r.model_gain_percent) == (None,) * 4


# --- the printed tables ------------------------------------------------------------------------

HX1 = (0.0, 150.0)  # span 150: Kc × 1.5, process gains ÷ 1.5


def verification(iae_sp: float, iae_load: float) -> Verification:
    return Verification(
        gains={"kc": 1.0},
        sp_step=3.0,
        overshoot=5.0,
        decay_ratio=None,
        rise_time=10.0,
        settling_time=100.0,
        iae_sp=iae_sp,
        load_step=5.0,
        iae_load=iae_load,
        max_deviation_load=1.0,
        recovery_time=50.0,
        stable=True,
        saturated=False,
        score=1.0,
    )


def hx1_result(**extra) -> TuneResult:
    gains = {
        "zn-pi": all_forms(IsaGains(6.9, 36.4, 0.0)).to_dict(),
        "tl-pid": all_forms(IsaGains(6.972, 96.09, 6.933)).to_dict(),
    }
    fields = {
        "run_id": "r1",
        "loop": "hx1",
        "t": 1344.0,
        "method": "relay",
        "rule": "tl-pid",
        "pv_units": "degC",
        "status": "ok",
        "ku": 15.34,
        "pu": 43.68,
        "experiment": {"model": "sopdt", "model_gain": 0.8494, "model_delay": 5.0},
        "gains": gains,
        "after": verification(54.41, 69.27),
        "applied": True,
    }
    return TuneResult(**{**fields, **extra})


def test_the_percent_table_by_hand():
    r = hx1_result(pv_range=HX1)
    text = format_result(r, "percent")
    assert "PV range 0 to 150 degC (span 150)" in text
    assert f"K_u = {15.34 * 1.5:.4g} %/% (15.34 %/degC)" in text
    assert f"K = {0.8494 / 1.5:.4g} %/% (0.8494 degC/%)" in text
    rows = {w[0]: w for w in map(str.split, text.splitlines()) if w[0] in ("zn-pi", "tl-pid")}
    # rule, Kc %/%, PB %, Ti, Td, Kc %/degC (engineering, beside)
    assert rows["zn-pi"][1:6] == [
        f"{6.9 * 1.5:.4g}",
        f"{100 / (6.9 * 1.5):.4g}",
        "36.4",
        "0",
        "6.9",
    ]
    assert rows["tl-pid"][1:6] == [
        f"{6.972 * 1.5:.4g}",
        f"{100 / (6.972 * 1.5):.4g}",
        "96.09",
        "6.933",
        "6.972",
    ]
    assert rows["tl-pid"][-1] == "←"
    # the verification's IAE (PV units·s) in % of span·s: before (none), after
    iae = {w[1]: w[3:] for w in map(str.split, text.splitlines()) if w[0] == "IAE"}
    assert iae == {"setpoint": ["—", f"{54.41 / 1.5:.4g}"], "load": ["—", f"{69.27 / 1.5:.4g}"]}


def test_engineering_is_the_default_and_prints_no_percent():
    r = hx1_result(pv_range=HX1)
    text = format_result(r)
    assert text == format_result(r, "engineering")
    assert "%/%" not in text and "PB" not in text
    assert "K_u = 15.34 %/degC" in text and "model SOPDT: K = 0.8494  " in text


def test_percent_without_a_range_says_so_and_prints_engineering():
    r = hx1_result()
    text = format_result(r, "percent")
    assert "no PV range in the result: the figures are in engineering units" in text
    assert text.replace(text.splitlines()[1] + "\n", "") == format_result(r)


def test_the_integrating_step_line_in_percent():
    """R = K' and a on the tank's 0–3 m: × 100/3."""
    step = {
        "method": "integrating",
        "reaction_rate": 0.001,
        "reaction_rate_precision": 0.02,
        "dead_time": 2.0,
        "a": 0.002,
        "pv_after": 1.5,
    }
    r = hx1_result(method="step", pv_range=(0.0, 3.0), pv_units="m", step=step, ku=None)
    line = next(x for x in format_result(r, "percent").splitlines() if "integrating" in x)
    assert f"R = K' = {0.001 * 100 / 3:.4g} %/s per % (0.001 m/s per %)" in line
    assert f"a = R·L = {0.002 * 100 / 3:.4g} %/% (0.002 m/%)" in line


# --- the flag ----------------------------------------------------------------------------------


def test_the_units_flag(monkeypatch, capsys):
    parse = build_parser().parse_args
    assert parse(["tune", "hx1"]).units == "engineering"
    assert parse(["tune", "hx1", "--units", "percent"]).units == "percent"

    def refuse(*_a, **_k):
        raise AssertionError("a session was opened before the flags were judged")

    monkeypatch.setattr(zenoh, "open", refuse)
    try:
        code = main(["tune", "hx1", "--units", "kelvin"])
    except SystemExit as stop:
        code = stop.code
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "--units" in err and "invalid choice" in err


# --- the offline analysis ----------------------------------------------------------------------


def test_the_analysis_json_carries_the_percent_figures():
    ident = Identification(ku=10.0, pu=2.0)
    gains = {"zn-pi": all_forms(IsaGains(4.5, 1.6), 300.0)}
    a = Analysis("f.mcap", "x", "relay", ident, gains, None, None, RANGE)
    d = a.to_dict(None)
    assert d["pv_range"] == list(RANGE)
    assert d["ku_percent"] == pytest.approx(30.0)
    assert d["gains"]["zn-pi"]["isa_percent"]["kc"] == pytest.approx(13.5)
    assert d["gains"]["zn-pi"]["isa_percent"]["pb"] == pytest.approx(100 / 13.5)
    bare = Analysis("f.mcap", "x", "relay", ident, {}, None, None).to_dict(None)
    assert "ku_percent" not in bare


def test_the_left_line_prints_the_mean_at_rest_it_judged_by():
    """A noisy loop's last sample can sit 4σ off the target while its mean at rest is on it:
    the line gives the mean (what "back where it was" is judged by) and the sample beside."""
    left = {
        "mode": "auto",
        "sp": 50.0,
        "op": 41.0,
        "gains": {},
        "pv": 49.21,
        "pv_rest": 50.02,
        "pv_target": 50.0,
        "band": 0.8,
        "returned": True,
        "waited": 30.0,
    }
    line = next(x for x in format_result(hx1_result(left=left)).splitlines() if "left:" in x)
    assert "PV 50.02 degC at rest (last sample 49.21)" in line
    assert "(the PV is back where it was: target 50 ± 0.8)" in line
    # not waited for (or never at rest): the last sample alone, as before
    left = {**left, "pv_rest": None, "returned": False}
    line = next(x for x in format_result(hx1_result(left=left)).splitlines() if "left:" in x)
    assert "PV 49.21 degC (the PV is still on its way back: target 50 ± 0.8)" in line
    # at rest, but off its target: not "at rest" and "on its way back" at once (helper finding)
    left = {**left, "pv_rest": 48.6, "returned": False}
    line = next(x for x in format_result(hx1_result(left=left)).splitlines() if "left:" in x)
    assert "PV 48.6 degC at rest (last sample 49.21)" in line
    assert "(the PV is not back where it was, at rest off it: target 50 ± 0.8)" in line
    # not waited for at all (cancelled, --no-wait): not "on its way back" (a level in manual
    # never comes back by itself: 1.96 m for 1.79 was so called, helper trial E)
    left = {**left, "pv_rest": None, "returned": False, "waited": 0.0}
    line = next(x for x in format_result(hx1_result(left=left)).splitlines() if "left:" in x)
    assert "(the PV is not back where it was, not waited for: target 50 ± 0.8)" in line
    # not waited for, its last sample within the band: not known (one sample says nothing
    # of where it heads: a relay cancelled mid-swing was "back" at 50.17, on its way to
    # 50.74, helper trial)
    left = {**left, "pv": 50.17, "returned": None}
    line = next(x for x in format_result(hx1_result(left=left)).splitlines() if "left:" in x)
    assert "(the PV is not known to be back where it was, not waited for: target 50" in line
    # seen by a query after the plant was lost: where it is against where it was
    left = {**left, "pv_target": None, "pv_before": 50.0, "pv": 51.25}
    line = next(x for x in format_result(hx1_result(left=left)).splitlines() if "left:" in x)
    assert "the PV is +1.25 degC from where it was before the test (50), not waited for" in line
    assert "a level in manual" not in line  # a loop in auto (it was said of a pressure loop)
    manual = {**left, "mode": "manual"}
    line = next(x for x in format_result(hx1_result(left=manual)).splitlines() if "left:" in x)
    assert "a level in manual" not in line  # a self-regulating loop comes back (helper 52)
    ipdt = {"model": "ipdt", "model_gain": 1e-4, "model_delay": 2.0}
    level = hx1_result(left=manual, experiment=ipdt)  # an integrating one does not
    line = next(x for x in format_result(level).splitlines() if "left:" in x)
    assert "not waited for: a level in manual stays where it is" in line
    # the wait cut short by the plant falling silent: said, the figures the last seen (the
    # stale PV was printed as "still on its way back": helper trial E)
    left = {**left, "pv_target": 50.0, "waited": 2.0, "cut": "loop 'hx1': no message for 5 s"}
    line = next(x for x in format_result(hx1_result(left=left)).splitlines() if "left:" in x)
    assert "the wait for it was cut short, the figures the last seen: loop 'hx1': no" in line


def test_the_rules_table_marks_a_rule_unstable_and_keeps_its_columns_apart():
    """zn-pid unstable on the model (its margins and overshoot mean nothing) printed
    "1.34   88.216491.6": a positive gain margin with no mark, two figures run together."""
    rob = {
        "zn-pi": {"ms": 1.9, "gain_margin": 2.1, "phase_margin_deg": 88.2, "stable": True}
        | {"overshoot_pct": 16491.6, "decay_ratio": 0.43},
        "tl-pid": {"ms": 25.7, "gain_margin": 1.36, "phase_margin_deg": 111.0, "stable": False}
        | {"overshoot_pct": 8600.6, "decay_ratio": 2.02},
    }
    text = format_result(hx1_result(robustness=rob))
    rows = {w[0]: w for w in map(str.split, text.splitlines()) if w[0] in ("zn-pi", "tl-pid")}
    assert rows["zn-pi"][-5:] == ["1.9", "2.1", "88.2", "16491.6", "0.43"]
    assert "UNSTABLE on the model" in " ".join(rows["tl-pid"])
    assert "1.36" not in rows["tl-pid"] and "8600.6" not in rows["tl-pid"]


def test_a_predicted_overshoot_of_next_to_nothing_prints_as_none():
    """The acceptance line printed "within 20 points of the 5.32e-05 % predicted" (helper
    trial E): an overshoot of a few 1e-5 % is none."""
    acceptance = {
        "max_overshoot": 35.0,
        "max_decay_ratio": 0.35,
        "overshoot_miss": 20.0,
        "predicted_overshoot": 5.32e-05,
        "passed": True,
        "problems": "",
    }
    text = format_result(hx1_result(acceptance=acceptance))
    assert "within 20 points of the 0 % predicted: passed" in text
    text = format_result(hx1_result(acceptance={**acceptance, "predicted_overshoot": 5.43}))
    assert "within 20 points of the 5.43 % predicted: passed" in text


def test_analyze_says_when_the_live_run_measured_no_ultimate_point() -> None:
    """A relay run whose cycle never reached −180° has no K_u or P_u: `analyze` printed
    "live run: K_u = None, P_u = None" (helper trial)."""
    from services.autotuner.identify.experiments import Identification
    from services.logger.analysis import Analysis, format_analysis
    from shared.messages import TuneResult

    live = TuneResult(run_id="r", loop="x", t=1.0, method="relay", rule="simc-pi", status="ok")
    a = Analysis("f.mcap", "x", "relay", Identification(), {}, live)
    text = format_analysis(a, None)
    assert "live run: no K_u and P_u measured → identical" in text, text
    assert "None" not in text


def test_the_model_line_gives_the_models_own_l_over_t_not_the_step_tangents():
    """A step run's ``l_over_t`` is the tangent's (10.62/85.69 = 0.124 on hx1); the model line
    beside its SOPDT (T 60, 9.983 s, L 4.982 s) gives the model's own by the half rule,
    (4.982 + 9.983/2)/(60 + 9.983/2) = 0.1535 (helper trial: it gave 0.124); an FOPDT's is
    L/T; an IPDT has none."""
    sopdt = {
        "model": "sopdt",
        "model_gain": 0.99,
        "model_lag_1": 60.0,
        "model_lag_2": 9.983,
        "model_delay": 4.982,
    }
    r = hx1_result(experiment=sopdt, l_over_t=10.62 / 85.69)
    (line,) = [x for x in format_result(r).splitlines() if "model SOPDT" in x]
    assert line.endswith(
        f"L/T = {(4.982 + 9.983 / 2) / (60 + 9.983 / 2):.3f} (its FOPDT's, half rule)"
    ), line
    fo = {"model": "fopdt", "model_gain": 1.0166, "model_lag_1": 1.782, "model_delay": 1.557}
    (line,) = [x for x in format_result(hx1_result(experiment=fo)).splitlines() if "FOPDT" in x]
    assert line.endswith(f"L/T = {1.557 / 1.782:.3f}"), line
    ip = {"model": "ipdt", "model_gain": 1e-4, "model_delay": 2.0}
    (line,) = [x for x in format_result(hx1_result(experiment=ip)).splitlines() if "IPDT" in x]
    assert "L/T" not in line


def test_a_quotient_unit_is_bracketed_where_it_is_a_factor():
    """flow1's m3/h: '%/m3/h' reads as % per m3 per hour; it is %/(m3/h), and its process
    gain (m3/h)/% (helper trial)."""
    from shared.control.forms import unit

    assert (unit("m3/h"), unit("degC"), unit(""), unit(None), unit("kg·m-3")) == (
        "(m3/h)",
        "degC",
        "PV unit",
        "PV unit",
        "(kg·m-3)",
    )
    r = hx1_result(pv_units="m3/h", experiment={"model": "fopdt", "model_gain": 1.0,
                   "model_lag_1": 1.8, "model_delay": 1.6})  # fmt: skip
    text = format_result(r)
    assert "K_u = 15.34 %/(m3/h)" in text and "%/m3/h" not in text


def test_analyze_says_a_live_run_ended_before_its_figures_and_compares_nothing() -> None:
    """An hx1 relay cancelled at the sample that closed its last cycle: the record completes
    the test offline, and `analyze` printed "live run: no K_u and P_u measured → DIFFERENT",
    nowhere that the run had been cancelled (helper review). It says how the run ended."""
    from services.autotuner.identify.experiments import Identification
    from services.logger.analysis import Analysis, dumps, format_analysis
    from shared.messages import TuneResult

    live = TuneResult(
        run_id="r", loop="x", t=1.0, method="relay", rule="auto", status="aborted",
        reason="cancelled",
    )  # fmt: skip
    a = Analysis("f.mcap", "x", "relay", Identification(ku=15.2, pu=43.7), {}, live)
    text = format_analysis(a, None)
    assert "live run: aborted (cancelled) before it reported its figures" in text, text
    assert "DIFFERENT" not in text and "None" not in text, text
    assert json.loads(dumps(a, None))["live"]["status"] == "aborted"
    # nothing identified offline either: said as before, with how the run ended
    a = Analysis("f.mcap", "x", "relay", Identification(), {}, live)
    assert "live run: aborted (cancelled); no K_u and P_u measured" in format_analysis(a, None)
    # a run that ended with figures and was rejected: its status, then the comparison
    rejected = live.model_copy(update={"status": "rejected", "reason": "worse", "ku": 15.2})
    rejected = rejected.model_copy(update={"pu": 43.7})
    a = Analysis("f.mcap", "x", "relay", Identification(ku=15.2, pu=43.7), {}, rejected)
    text = format_analysis(a, None)
    assert "live run: rejected (worse)\n  live run: K_u = 15.2, P_u = 43.7 → identical" in text


def test_analyze_gives_its_figures_in_the_pv_units_the_run_recorded() -> None:
    """`analyze` printed K_u without a unit and an integrating loop's R = K' "per s per %"
    where the tune prints "m/s per %" (helper review): the run's PV units, as the tune's."""
    from services.autotuner.identify.experiments import Identification
    from services.logger.analysis import Analysis, format_analysis

    a = Analysis("f.mcap", "x", "relay", Identification(ku=15.2, pu=43.7), {}, None)
    assert "K_u = 15.2 %/PV unit   P_u = 43.7 s" in format_analysis(a, None)
    a.pv_units = "m3/h"
    assert "K_u = 15.2 %/(m3/h)   P_u = 43.7 s" in format_analysis(a, None)


def test_a_measured_step_without_a_second_crest_says_none_not_a_dash():
    """The verification table's decay ratio and ring of a measured setpoint step that had
    none (no crest after its largest, no oscillatory mode) read "none"; a column with no step
    measured (the loop was in manual before: no "before" verification) keeps "—", as does
    any figure of it (walkthrough: "decay ratio —" beside a 5.5 % overshoot read as not
    measured)."""
    text = format_result(hx1_result())
    rows = {
        line.split()[0] + " " + line.split()[1]: line.split()
        for line in text.splitlines()
        if line.startswith("  decay ratio")
        or line.startswith("  ringing /period")
        or line.startswith("  overshoot %")
    }
    assert rows["decay ratio"][2:] == ["—", "none"], rows
    assert rows["ringing /period"][2:] == ["—", "none"], rows
    assert rows["overshoot %"][2:] == ["—", "5"], rows
    # a measured decay ratio is its figure
    after = verification(54.41, 69.27).model_copy(update={"decay_ratio": 0.12})
    text = format_result(hx1_result(after=after))
    line = next(x for x in text.splitlines() if x.startswith("  decay ratio"))
    assert line.split()[2:] == ["—", "0.12"], line


def test_an_apply_of_gains_the_loop_held_says_nothing_changed():
    """`autotune apply` of the same run twice: "new gains applied" where `history` said
    "gains unchanged" (walkthrough). The same Kc, Ti, Td and β before and after: said so;
    any term changed: new gains, as before."""
    after = verification(54.41, 69.27).model_copy(
        update={"gains": PidGains(kc=6.972, ti=96.09, td=6.933)}
    )
    held = hx1_result(after=after, previous_gains=PidGains(kc=6.972, ti=96.09, td=6.933))
    assert "gains applied (the loop held them already: nothing changed)" in format_result(held)
    changed = hx1_result(after=after, previous_gains=PidGains(kc=2.0, ti=60.0))
    assert "new gains applied, loop in auto" in format_result(changed)


def test_the_model_line_says_the_rules_design_dead_time():
    """The model rules are designed with the hold's half sample added to the model's L
    (``selection``): SIMC PI from a printed K 2, T 20 s, L 4 s read Kc 1.126 where 1.139
    follows from L alone (helper audit). hx1 at 0.25 s: L + T/2 = 5 + 0.125 s."""
    on = {"sample_time": 0.25, "node": "n", "model": "heat_exchanger"}
    lines = format_result(hx1_result(identified_on=on)).splitlines()
    i = next(i for i, x in enumerate(lines) if "model SOPDT" in x)
    assert lines[i + 1].strip() == (
        "the model's rules are designed with L + T/2 = 5.125 s (the hold's half sample at "
        "T = 0.25 s)"
    )
    # not known at what sample time (a result without it): nothing said
    assert "L + T/2" not in format_result(hx1_result())


def test_a_run_that_sent_nothing_does_not_judge_where_the_pv_is():
    """Refused at its start (nothing sent to the loop): where the PV is, the last run's test
    still moving it, is none of its doing; it said "not back where it was: target 51.02"
    (helper review)."""
    left = {
        "mode": "manual",
        "sp": 50.0,
        "op": 50.0,
        "gains": {},
        "pv": 50.6,
        "pv_rest": None,
        "pv_target": 51.02,
        "band": 0.2,
        "returned": False,
        "waited": 0.0,
    }
    r = hx1_result(left=left, status="aborted", applied=False, untouched=True, restored=True)
    line = next(x for x in format_result(r).splitlines() if "left:" in x)
    assert line.endswith("PV 50.6 degC (as the run found it: nothing was sent to it)"), line
    assert "not back" not in format_result(r)


def test_a_lag_far_slower_than_the_rest_of_its_model_is_called_an_integrator():
    """A ramp of 0.05·e^{−2s}/(s(10s + 1)) printed "model SOPDT: K = 1.364e+07 T = 2.72e+08,
    10.02 s" and never said integrating (helper review): K/T = 1.364e7/2.72e8 = 0.0501 per s
    per %, the plant's 0.05."""
    int1 = {
        "model": "sopdt",
        "model_gain": 1.364e7,
        "model_lag_1": 2.72e8,
        "model_lag_2": 10.02,
        "model_delay": 2.0,
    }
    lines = format_result(hx1_result(experiment=int1)).splitlines()
    i = next(i for i, x in enumerate(lines) if "model SOPDT" in x)
    said = lines[i + 1].strip()
    assert said.startswith("(its T = 2.72e+08 s is an integrator over any time that matters"), said
    assert f"K/T = {1.364e7 / 2.72e8:.4g} per s per %, behind 10.02 s, dead time 2 s)" in said
    # hx1's own SOPDT (lags 48.73 and 10.68 s, L 5 s): no such line
    assert "integrator" not in format_result(hx1_result())
