"""The report of runs other than the demo's, on a fast plant (6/((s+1)(s+2)(s+3)), 0.05 s
samples) that starts in auto: a relay run verified before and after, side by side, and a
ramp run whose trials are labelled with their Kc and whose ultimate point is drawn with its
bracket. Recorded in-process (``tests.recorded_run``); the expected values are read from the
file's raw JSON."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.logger.compare import compare, format_compare
from services.logger.report import build_report, load_report
from tests.recorded_run import raw_messages, record_in_process

LOOP = "x1"
PLANT = {
    "seed": 3,
    "loops": {
        LOOP: {
            "model": "transfer_function",
            "num": [6.0],
            "den": [1.0, 6.0, 11.0, 6.0],
            "sample_time": 0.05,
            "noise_std": 0.002,
            "mode": "auto",
            "pid": {"kc": 0.5, "ti": 2.0},
        }
    },
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = {}
    for method in ("relay", "ramp"):
        path, live = record_in_process(tmp_path_factory.mktemp(method), "r", PLANT, LOOP, method)
        assert live.status == "ok" and live.before is not None, live.reason
        out[method] = (raw_messages(path), build_report(load_report(path)))
        out[f"{method} file"] = path
    return out


def axes_titled(fig, start: str):
    return next(ax for ax in fig.axes if ax.get_title().startswith(start))


def test_before_and_after_side_by_side_from_their_setpoint_steps(runs):
    msgs, fig = runs["relay"]
    (result,) = msgs["result"]
    before, after = axes_titled(fig, "before: Kc 0.5"), axes_titled(fig, "after: Kc")
    assert f"Kc {result['chosen']['isa']['kc']:.4g}" in after.get_title()
    assert before.get_ylim() == after.get_ylim()  # one scale
    steps = sorted(c["t"] for c in msgs["setpoint"])
    loads = [c for c in msgs["disturbance"] if c["name"] == "load"]
    for ax, load, v in ((before, loads[0], "before"), (after, loads[2], "after")):
        pv, sp = ax.lines[0], ax.lines[1]
        t, y = np.asarray(sp.get_xdata()), np.asarray(sp.get_ydata())
        # the setpoint steps by the verification's step after 0 s (the command's time is
        # the last sample the tuner saw), and the load step sits where its command was sent
        assert y[t <= 0].tolist() == [0.0] * int(np.sum(t <= 0))
        assert y[(t > 0) & (t < 1)] == pytest.approx(result[v]["sp_step"], rel=1e-12)
        step_t = max(s for s in steps if s < load["t"])  # the step, then the load
        (load_line,) = [ln for ln in ax.lines if ln.get_linestyle() == "-."]
        assert load_line.get_xdata()[0] == pytest.approx(load["t"] - step_t)
        assert pv.get_xdata()[0] < 0 < pv.get_xdata()[-1]
    ax_table = next(ax for ax in fig.axes if ax.get_title(loc="left") == "verification figures")
    rows = ax_table.texts[0].get_text().splitlines()
    assert rows[0].split() == ["before", "after"]
    over = f"{result['before']['overshoot']:.4g}", f"{result['after']['overshoot']:.4g}"
    assert next(r for r in rows if r.startswith("overshoot (%)")).split()[-2:] == list(over)


def test_ramp_trials_carry_their_kc_and_the_ultimate_point_its_bracket(runs):
    msgs, fig = runs["ramp"]
    (result,) = msgs["result"]
    trials = [e for e in msgs["event"] if e["kind"] == "trial"]
    ax_pv = next(ax for ax in fig.axes if ax.get_ylabel().startswith("PV, setpoint"))
    # the trials' marks: dashed, in their colour (the setpoint is dashed too, in red)
    dashed = [
        ln.get_xdata()[0]
        for ln in ax_pv.lines
        if ln.get_linestyle() == "--" and ln.get_color() == "tab:purple"
    ]
    assert dashed == [e["t"] for e in trials]
    labels = [t.get_text() for t in ax_pv.texts]
    for e in trials:
        assert f"Kc {e['data']['kc']:.4g} %/{result['pv_units']}" in labels
    legend = [t.get_text() for t in ax_pv.get_legend().get_texts()]
    assert f"ramp trial (its Kc, %/{result['pv_units']})" in legend
    ax_mag = next(ax for ax in fig.axes if ax.get_ylabel().startswith("|G|"))
    (c,) = [c for c in ax_mag.containers if c.get_label().startswith("ultimate point")]
    (w,), (mag,) = c.lines[0].get_data()
    assert w == pytest.approx(2 * math.pi / result["pu"], rel=1e-12)
    assert mag == pytest.approx(1 / result["ku"], rel=1e-12)
    (seg,) = c.lines[2][0].get_segments()
    e = result["experiment"]
    # the stated spread: the final bracket, or what the hold's correction leaves, if more
    assert result["ku_spread"] >= (e["kc_high"] - e["kc_low"]) / result["ku"]
    assert result["ku_spread"] >= (e["hold_spread_ku"] or 0.0)
    half = result["ku_spread"] * mag
    assert (seg[1][1] - seg[0][1]) / 2 == pytest.approx(half, rel=1e-9)


def test_runs_compare_shows_a_gain_once_where_its_pv_is_in_percent_over_0_to_100(runs):
    """PV units % over 0–100 %: Kc in %/PV unit is Kc in %/%, one row, not two equal rows."""
    (result,) = runs["relay"][0]["result"]
    assert result["pv_units"] == "%" and result["pv_range"] == [0.0, 100.0]
    c = compare(runs["relay file"], runs["ramp file"])
    keys = [r["key"] for r in c["rows"]]
    assert "ku" in keys and "kc" in keys and "pb" in keys
    assert "ku_percent" not in keys and "kc_percent" not in keys
    assert sum(line.startswith("Kc (") for line in format_compare(c).splitlines()) == 1


def test_runs_compare_does_not_take_other_pv_units_for_a_change(runs, tmp_path):
    """A in %, B in degC: K_u 2 %/% against 3 %/degC is no change of +50 % (it was printed
    as one, under the unit "%/%|degC"); such rows show both units and no change, and a line
    says why. Rows in s or % still compare."""
    plant = {"seed": 3, "loops": {LOOP: {**PLANT["loops"][LOOP], "pv_units": "degC"}}}
    other, live = record_in_process(tmp_path, "r", plant, LOOP, "relay")
    assert live.status == "ok" and live.pv_units == "degC", live.reason
    c = compare(runs["relay file"], other)
    assert c["pv_units_differ"] is True
    rows = {r["key"]: r for r in c["rows"]}
    assert rows["ku"]["unit"] == "%/% | %/degC" and rows["ku"]["change"] is None
    assert rows["kc"]["change"] is None and rows["model_gain"]["change"] is None
    assert rows["pu"]["change"] is not None and rows["ti"]["change"] is not None
    text = format_compare(c)
    assert "PV units differ (A %, B degC): figures in PV units are shown, not compared" in text
    same = compare(runs["relay file"], runs["ramp file"])
    assert same["pv_units_differ"] is False
    assert {r["key"]: r for r in same["rows"]}["ku"]["change"] is not None


def test_runs_compare_gives_spreads_in_the_percent_its_unit_says(runs):
    """The spreads' unit is "%": their values in --json were the result's fractions."""
    (result,) = runs["relay"][0]["result"]
    c = compare(runs["relay file"], runs["ramp file"])
    row = next(r for r in c["rows"] if r["key"] == "ku_spread")
    assert row["unit"] == "%" and row["a"] == pytest.approx(100.0 * result["ku_spread"])
    line = next(x for x in format_compare(c).splitlines() if x.startswith("K_u spread (%)"))
    assert f"{100.0 * result['ku_spread']:.3g}" in line


def test_runs_compare_keeps_its_columns_apart():
    """A change of +65,184 % filled its column and ran into B's figure ("9.5405+65183.9 %")."""
    run = {"file": "f", "loop": "x", "method": "relay", "run_id": "r", "started": ""}
    row = {"key": "ku", "label": "K_u", "unit": "%/%", "a": 0.014634, "b": 9.5405}
    c = {"runs": [run, run], "rows": [{**row, "change": 9.5405 / 0.014634 - 1}]}
    line = format_compare(c).splitlines()[-1]
    assert line.split() == ["K_u", "(%/%)", "0.014634", "9.5405", "+65094.1", "%"]


def test_an_apply_runs_report_says_it_applied_another_runs_gains(runs, tmp_path):
    """``autotune apply``'s run makes no test: its report was titled "ramp tuning run" and
    boxed "ramp test" (the method is the identifying run's); it now names the run whose
    gains it applied."""
    (result,) = runs["ramp"][0]["result"]
    isa = result["chosen"]["isa"]
    path, live = record_in_process(
        tmp_path,
        "r",
        {**PLANT, "seed": 4},
        LOOP,
        "ramp",
        rule=result["rule"],
        apply_from="ab12cd34ef56",
        apply_gains={"kc": isa["kc"], "ti": isa["ti"], "td": isa["td"] or 0.0},
        apply_timescale=result["timescale"],
        apply_noise=result["noise"],
    )
    assert live.applied_from == "ab12cd34ef56", live.reason
    fig = build_report(load_report(path))
    title = fig._suptitle.get_text()
    assert title.startswith(f"{LOOP}: run {live.run_id}, apply of run ab12cd34ef56's gains ("), (
        title
    )
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert any(
        t.startswith(f"apply of run ab12cd34ef56's gains (no test) · rule {result['rule']}")
        for t in texts
    ), texts
    labels = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().texts]
    assert "verification (setpoint step, load step)" in labels, labels
    assert not any("ramp t" in t for t in [title, *labels, *texts])  # ramp test, trial, tuning


def test_an_aborted_runs_report_says_why_it_has_no_verification(runs, tmp_path):
    """A relay aborted at its PV limits, the loop in auto before it: the "before" panel said
    the loop had not been in auto (the old gains are verified only on the way to applying
    new ones, which an aborted run never reaches)."""
    (result,) = runs["relay"][0]["result"]
    sp = result["left"]["sp"]
    path, live = record_in_process(
        tmp_path, "r", PLANT, LOOP, "relay", pv_limits=(sp - 0.05, sp + 0.05)
    )
    assert live.status == "aborted" and "left its limits" in live.reason, live.reason
    fig = build_report(load_report(path))
    texts = [" ".join(t.get_text().split()) for ax in fig.axes for t in ax.texts]
    said = "the run ended (aborted) before any verification was complete"
    assert any(said in t for t in texts), texts
    assert not any("not in auto" in t for t in texts)
    # its figures' table says why it is empty, not a header over nothing (helper review),
    # within the panel's width (it ran off the page)
    why = "none: the run ended (aborted) before the new gains' verification was complete"
    assert why in texts, texts
    # the limits it aborted at are drawn, and named in the legend
    ax_pv = next(ax for ax in fig.axes if ax.get_ylabel().startswith("PV, setpoint"))
    flat = {float(ln.get_ydata()[0]) for ln in ax_pv.lines if len(set(ln.get_ydata())) == 1}
    assert {sp - 0.05, sp + 0.05} <= flat
    labels = [t.get_text() for t in ax_pv.get_legend().texts]
    assert "the test's PV limits (--pv-limits)" in labels, labels


def test_a_refused_runs_report_shows_the_refused_gains_and_an_integrating_curve_its_rate():
    """The refused zn-pid run's report showed no gains, while `autotune runs` listed them;
    an integrating step test's summary read "K = −  T = −" (helper review). The summary and
    the gains lines give the refused rule's gains, and R = K', L and a in the PV's units."""
    from services.logger.report import RunSeries, _gains_lines, _summary
    from shared.messages import TuneResult

    isa = {"kc": 9.182, "ti": 21.78, "td": 5.445}
    refused = TuneResult(
        run_id="r", loop="hx1", t=1.0, method="relay", rule="zn-pid", status="rejected",
        reason="refused: zn-pid: predicted Ms 2.28 above the bound 2", pv_units="degC",
        gains={"zn-pid": {"isa": isa}}, ku=15.3, pu=43.56,
    )  # fmt: skip
    s = RunSeries(*(np.zeros(2),) * 4, [], [], refused, {})
    assert "refused: Kc 9.182 %/degC" in _summary(s), _summary(s)
    assert any(line.startswith("refused (zn-pid): Kc 9.182") for line in _gains_lines(s))
    step = {"method": "integrating", "reaction_rate": 1.001e-4, "dead_time": 2.281, "a": 2.283e-4}
    level = refused.model_copy(update={"status": "ok", "pv_units": "m", "step": step})
    text = _summary(RunSeries(*(np.zeros(2),) * 4, [], [], level, {}))
    assert "R = K' = 0.0001001 m/s per %  L = 2.28 s  a = R·L = 0.0002283 m/%" in text, text
    assert "K = " not in text and "refused:" not in text.split("\n")[2]  # ok: chosen, bare
    # named as the reaction curve's, not read as a second model beside the fit's (lvl1's
    # report: "K = 0.063 m/%  L = 0.5 s  T = 641 s" in its box, L 1.418 s in the fit's title)
    assert "reaction curve: R = K' = " in text, text
    regulating = {"gain": 0.063, "dead_time": 0.5, "time_constant_tangent": 641.0}
    lvl1 = level.model_copy(update={"step": regulating})
    text = _summary(RunSeries(*(np.zeros(2),) * 4, [], [], lvl1, {}))
    assert "reaction curve: K = 0.063 m/%  L = 0.5 s  T = 641 s" in text, text


def test_report_says_what_it_wrote_in_words_and_as_json_with_json(runs, tmp_path, capsys):
    """``autotune report`` printed a JSON object where every other command without --json
    prints words (helper review); the JSON object is now ``--json``'s."""
    import json

    from services.cli import main

    path = runs["relay file"]
    png = tmp_path / "r.png"
    assert main(["report", str(path), "-o", str(png), "--dpi", "20"]) == 0
    out = capsys.readouterr().out.strip()
    samples = load_report(path).series.t.size
    assert out == f"{png}: the report of {path} ({samples} samples)"
    assert main(["report", str(path), "-o", str(png), "--dpi", "20", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"report": str(png), "samples": samples}
