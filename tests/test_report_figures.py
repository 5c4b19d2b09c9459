"""The report a control engineer expects, on the demo's run: its Bode plot, legends, gains in
every unit, the model against the data, and two runs compared. The run is the demo's (the
default plant's hx1, the default relay request) recorded in-process (``tests.recorded_run``:
the live tuner's code over the plant's loop, every message through the logger's Recorder);
the expected numbers are read from the file's raw JSON or computed here in closed form
(numpy, scipy.signal), never through the modules under test."""

from __future__ import annotations

import itertools
import json
import math
import tomllib
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from scipy import signal

from services.logger.compare import compare, format_compare
from services.logger.report import build_report, load_report, render
from tests.exact import ultimate_point
from tests.recorded_run import raw_messages, record_in_process

PREFIX = "autotune"
LOOP = "hx1"  # the demo's loop: e^{-5s}/((10s+1)(60s+1)), degC per %, range 0–150 degC
HX = ([1.0], [600.0, 70.0, 1.0], 5.0)
SPAN = 150.0


def record_demo(runs: Path) -> Path:
    text = files("services.plant_sim").joinpath("plants/default.toml").read_text()
    path, live = record_in_process(runs, PREFIX, tomllib.loads(text), LOOP, "relay")
    assert live.status == "ok", live.reason
    return path


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    path = record_demo(tmp_path_factory.mktemp("runs"))
    report = load_report(path)
    return path, raw_messages(path), report, build_report(report)


def axes_by_label(fig, ylabel: str):
    return next(ax for ax in fig.axes if ax.get_ylabel().startswith(ylabel))


def plotted_points(ax, stage: str):
    """(ω, value, lower, upper) of a stage's fundamental as drawn, from its error bar."""
    c = next(c for c in ax.containers if c.get_label().startswith(f"{stage}: G(jω)"))
    x, y = (np.asarray(v, float) for v in c.lines[0].get_data())
    seg = np.asarray(c.lines[2][0].get_segments())  # one vertical bar per point
    return x, y, seg[:, :, 1].min(axis=1), seg[:, :, 1].max(axis=1)


def model_line(ax):
    return next(ln for ln in ax.lines if ln.get_label().endswith("model"))


def test_the_measured_fundamentals_lie_on_the_fitted_model_within_their_uncertainty(demo):
    """Acceptance: on the Bode plot as drawn, each stage's fundamental G(jω) sits on the
    fitted model's curve within its error bar (magnitude and phase); the points, the bars
    and the curve are the recorded ones."""
    _, msgs, _, fig = demo
    (result,) = msgs["result"]
    e, delta = result["experiment"], result["ku_spread"]
    ax_mag, ax_ph = axes_by_label(fig, "|G|"), axes_by_label(fig, "phase")
    curve_mag, curve_ph = model_line(ax_mag), model_line(ax_ph)
    w_curve = np.asarray(curve_mag.get_xdata(), float)
    # the curve drawn is the recorded SOPDT model, K·e^{−Ls}/((T₁s + 1)(T₂s + 1))
    s = 1j * w_curve
    g = (
        e["model_gain"]
        * np.exp(-s * e["model_delay"])
        / ((e["model_lag_1"] * s + 1) * (e["model_lag_2"] * s + 1))
    )
    assert np.allclose(curve_mag.get_ydata(), np.abs(g), rtol=1e-9)
    assert np.allclose(np.exp(1j * np.radians(curve_ph.get_ydata())), g / np.abs(g), atol=1e-9)
    checked = 0
    for stage, head in (("stage 1", ""), ("stage 2", "stage2_")):
        w, mag, lo, hi = plotted_points(ax_mag, stage)
        _, ph, ph_lo, ph_hi = plotted_points(ax_ph, stage)
        assert w.tolist() == [e[f"{head}omega_1"]]
        assert mag.tolist() == pytest.approx([e[f"{head}g_1_magnitude"]], rel=1e-12)
        assert ph.tolist() == pytest.approx([e[f"{head}g_1_phase_deg"]], rel=1e-12)
        assert (hi - lo).tolist() == pytest.approx((2 * delta * mag).tolist(), rel=1e-9)
        on_curve_mag = np.interp(np.log(w), np.log(w_curve), curve_mag.get_ydata())
        on_curve_ph = np.interp(np.log(w), np.log(w_curve), curve_ph.get_ydata())
        assert np.all((lo <= on_curve_mag) & (on_curve_mag <= hi)), (stage, lo, on_curve_mag, hi)
        assert np.all((ph_lo <= on_curve_ph) & (on_curve_ph <= ph_hi)), (stage, on_curve_ph)
        checked += 1
    assert checked == 2
    # the stages bracket −180° and the drawn crossings sit near the plant's exact one
    assert e["g_1_phase_deg"] > -180 > e["stage2_g_1_phase_deg"]
    ku, pu = ultimate_point(*HX)
    crossings = [ln for ln in ax_mag.lines if ln.get_label().startswith("−180°")]
    assert {ln.get_label().split(":")[1].split()[0] for ln in crossings} == {"result", "model"}
    for ln in crossings:
        (x,), (y,) = ln.get_data()
        assert 1 / y == pytest.approx(ku, rel=0.02) and 2 * math.pi / x == pytest.approx(
            pu, rel=0.02
        )


def test_the_harmonics_are_drawn_with_the_noises_share_and_hold_the_plant(demo):
    """Stage 1's 3rd and 5th harmonics carry the noise's share of them, kπσ·√(T/W)/(2d·|G|)
    over the stage's window (computed here from the result's figures), drawn as their error
    bars; the plant's exact G(jkω) lies within 3 of them (a 5th harmonic read 42 % off with
    no uncertainty drawn: helper trial)."""
    _, msgs, _, fig = demo
    (result,) = msgs["result"]
    e = result["experiment"]
    ax_mag = axes_by_label(fig, "|G|")
    bars = next(c for c in ax_mag.containers if "harmonics" in c.get_label())
    x, _ = (np.asarray(v, float) for v in bars.lines[0].get_data())
    seg = np.asarray(bars.lines[2][0].get_segments())
    hi = seg[:, :, 1].max(axis=1)
    # read over the agreeing cycles (RelayConfig.cycles of them), not every cycle run
    from services.autotuner.identify.relay import RelayConfig

    assert e["stage_one_periods"] == RelayConfig.cycles < e["stage_one_cycles"]
    window = RelayConfig.cycles * 2 * math.pi / e["omega_1"]
    ts = result["identified_on"]["sample_time"]
    num, den, _ = HX  # |G| needs no delay
    for j, k in enumerate((3, 5)):
        w, mag = e[f"omega_{k}"], e[f"g_{k}_magnitude"]
        share = k * math.pi * e["noise_std"] * math.sqrt(ts / window)
        share /= 2 * e["relay_amplitude"] * mag
        assert e[f"g_{k}_noise"] == pytest.approx(share, rel=1e-9)
        assert x[j] == pytest.approx(w, rel=1e-12)
        assert hi[j] - mag == pytest.approx(share * mag, rel=1e-9)
        exact = abs(np.polyval(num, 1j * w) / np.polyval(den, 1j * w))
        assert abs(exact - mag) <= 3 * share * mag, (k, exact, mag, share)
    assert e["g_1_noise"] < 0.01  # the fundamental's: a few tenths of a per cent


def test_every_mark_has_a_legend_entry_at_the_recorded_times(demo):
    _, msgs, _, fig = demo
    ax_pv, ax_op = axes_by_label(fig, "PV, setpoint"), axes_by_label(fig, "output")
    legend = [t.get_text() for t in ax_pv.get_legend().get_texts()]
    legend_op = [t.get_text() for t in ax_op.get_legend().get_texts()]
    events = msgs["event"]
    switches = [e["t"] for e in events if e["kind"] == "switch"]
    cycles = [e["t"] for e in events if e["kind"] == "cycle"]
    (load_on, _) = [c for c in msgs["disturbance"] if c["name"] == "load"]
    assert f"relay switch ({len(switches)})" in legend_op
    assert f"relay cycle closed (n = 1…{len(cycles)})" in legend
    assert "relay stage 2 starts" in legend
    assert "load step +5 %" in legend and "load step +5 %" in legend_op
    assert any(t.startswith("verification") for t in legend)
    (marker,) = [ln for ln in ax_op.lines if ln.get_marker() == "v"]
    assert marker.get_xdata().tolist() == switches
    dotted = [ln.get_xdata()[0] for ln in ax_pv.lines if ln.get_linestyle() == ":"]
    assert dotted == cycles
    loads = {ln.get_xdata()[0] for ln in ax_pv.lines if ln.get_linestyle() == "-."}
    assert loads == {load_on["t"]}


def test_kc_is_shown_with_its_units_as_percent_per_percent_and_as_proportional_band(demo):
    _, msgs, _, fig = demo
    (result,) = msgs["result"]
    kc = result["chosen"]["isa"]["kc"]
    ax_pv = axes_by_label(fig, "PV, setpoint")
    box = next(t.get_text() for t in ax_pv.texts if t.get_text().startswith("relay test"))
    pct = kc * SPAN / 100
    assert f"Kc {kc:.4g} %/degC = {pct:.4g} %/% (PB {100 / pct:.3g} %)" in box


def test_the_verification_after_keeps_its_scale_when_before_is_not_available(demo):
    """The demo's loop was in manual before the run: no "before" panel, and the "after" one,
    which shares its PV scale, still shows that scale's numbers."""
    _, _, _, fig = demo
    fig.canvas.draw()
    ax = axes_by_label(fig, "deviation")
    before = next(a for a in fig.axes if a.get_title() == "before")
    assert any(t.get_text().startswith("not available") for t in before.texts)
    shown = [t.get_text() for t in ax.get_yticklabels() if t.get_visible() and t.get_text()]
    lo, hi = ax.get_ylim()
    within = [v for v in (float(t.replace("−", "-")) for t in shown) if lo <= v <= hi]
    assert len(within) >= 3, (shown, lo, hi)


def _points_under_boxes(fig, ax) -> int:
    """How many vertices of the axes' data lines its legend's box and its boxed notes cover,
    as drawn."""
    fig.canvas.draw()
    boxes = [t.get_window_extent() for t in ax.texts if t.get_bbox_patch() is not None]
    if ax.get_legend() is not None:
        boxes.append(ax.get_legend().get_window_extent())
    under = 0
    for ln in ax.lines:
        if ln.get_transform() is not ax.transData:
            continue  # a mark's vertical line across the plot, not data
        px = ax.transData.transform(ln.get_xydata())
        for box in boxes:
            inside = (px[:, 0] >= box.x0) & (px[:, 0] <= box.x1)
            under += int(np.sum(inside & (px[:, 1] >= box.y0) & (px[:, 1] <= box.y1)))
    return under


def test_no_legend_or_note_hides_the_recorded_data_or_the_model(demo):
    """The demo's PV rises to its highest just after the setpoint step, at the right-hand end
    of the model's window: where the model panel's upper-right legend stood over 471 samples.
    Every time plot is checked: the trends (legend and the summary box), the model against
    the data, the verification after."""
    _, _, _, fig = demo
    overlay = axes_by_label(fig, "PV (")
    assert overlay.get_title().startswith("model against data")
    for ax in (
        axes_by_label(fig, "PV, setpoint"),
        axes_by_label(fig, "output"),
        overlay,
        axes_by_label(fig, "deviation"),
    ):
        assert _points_under_boxes(fig, ax) == 0, ax.get_ylabel()


def test_the_model_is_simulated_over_the_recorded_data(demo):
    """The overlay's model line is the recorded model driven by the recorded output from
    the rest of the experiment's quiet period, up to the load step: checked against
    scipy.signal's exact ZOH discretisation of the delay-free model, the dead time L taken
    as y(t) = y₀(t − L) (whole samples, then the state advanced over the fraction with the
    output held)."""
    _, msgs, _, fig = demo
    (result,) = msgs["result"]
    e = result["experiment"]
    ax = next(a for a in fig.axes if a.get_title().startswith("model against data"))
    model = next(ln for ln in ax.lines if ln.get_label().startswith("model"))
    t = np.asarray(model.get_xdata(), float)
    setup = next(x["data"] for x in msgs["event"] if x["kind"] == "experiment")
    ts_ = setup["sample_time"]
    samples = [s for s in sorted(msgs["pv"], key=lambda s: s["seq"]) if s["t"] >= t[0]]
    (load_on, _) = [c for c in msgs["disturbance"] if c["name"] == "load"]
    first = next(s["t"] for s in samples if s["seq"] == setup["first_seq"])
    assert t[0] == first and t[-1] < load_on["t"] <= t[-1] + ts_
    u = np.array([s["op"] for s in samples[: t.size]])
    pv = np.array([s["pv"] for s in samples[: t.size]])
    rest, u0 = pv[:40].mean(), u[:40].mean()  # the quiet period's 40 samples, at rest
    u -= u0
    assert np.allclose(np.diff(t), ts_)
    a, b, c, d = signal.tf2ss(
        [e["model_gain"]], np.polymul([e["model_lag_1"], 1], [e["model_lag_2"], 1])
    )
    whole, frac = divmod(e["model_delay"], ts_)
    ad, bd, *_ = signal.cont2discrete((a, b, c, d), ts_, "zoh")
    # y₀ at t_j + (T − frac): the state at t_j advanced over T − frac with u_j held
    af, bf, *_ = signal.cont2discrete((a, b, c, d), ts_ - frac, "zoh")
    x = np.zeros((a.shape[0], 1))
    y0_mid = []
    for uj in u:
        y0_mid.append((c @ (af @ x + bf * uj)).item())
        x = ad @ x + bd * uj
    n = int(whole) + 1  # y(t_k) = y₀(t_k − L) = y₀(t_{k−n} + T − frac)
    expected = np.full(t.size, rest)
    expected[n:] += np.array(y0_mid)[: t.size - n]
    assert np.allclose(model.get_ydata(), expected, atol=1e-6 * SPAN)


def test_render_gives_png_and_svg_and_the_cli_writes_either(demo, tmp_path, capsys):
    from services.logger import report

    path = demo[0]
    assert render(path, "svg")[:5] == b"<?xml"
    argv = [str(path), "-o", str(tmp_path / "r.png"), "--dpi", "30", "--json"]
    import argparse

    parser = argparse.ArgumentParser()
    report.add_arguments(parser)
    assert report.run(parser.parse_args(argv)) == 0
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    out = json.loads(capsys.readouterr().out)
    assert out["samples"] == len({s["seq"] for s in demo[1]["pv"]})


def test_two_runs_compared_side_by_side(demo):
    path, msgs, _, _ = demo
    (result,) = msgs["result"]
    c = compare(path, path)
    rows = {r["key"]: r for r in c["rows"]}
    assert rows["ku"]["a"] == rows["ku"]["b"] == result["ku"] and rows["ku"]["change"] == 0
    kc = result["chosen"]["isa"]["kc"]
    assert rows["kc"]["a"] == kc and rows["kc"]["unit"] == "%/degC"
    assert rows["kc_percent"]["a"] == pytest.approx(kc * SPAN / 100, rel=1e-12)
    assert rows["pb"]["a"] == pytest.approx(100 / (kc * SPAN / 100), rel=1e-12)
    assert rows["overshoot"]["b"] == result["after"]["overshoot"]
    text = format_compare(c)
    assert f"{result['ku']:.5g}" in text and "B vs A" in text


def test_runs_compare_takes_files_names_and_run_ids_and_refuses_others_in_one_line(demo, capsys):
    from services.cli import main

    path, msgs, _, _ = demo
    run_id = msgs["result"][0]["run_id"]
    argv = ["runs", str(path.parent), "--compare", run_id, path.name, "--json"]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["file"] for r in out["runs"]] == [str(path), str(path)]
    assert main(["runs", str(path.parent), "--compare", run_id, "nosuchrun"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--compare nosuchrun" in err
    (path.parent / "dir.mcap").mkdir()  # a directory is said to be one (not "no such file")
    assert main(["runs", str(path.parent), "--compare", run_id, "dir.mcap"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "dir.mcap is a directory, not a run file" in err


def test_a_damaged_command_record_is_refused_in_one_line(demo, tmp_path, capsys):
    """The report reads the setpoint and load commands it marks: one that is not its model's
    JSON is named (topic, index, field) in one line, exit 2."""
    from mcap.writer import Writer

    from services.cli import main

    path = demo[0]
    bad = tmp_path / "bad.mcap"
    hit = None
    with path.open("rb") as f, bad.open("wb") as out:
        reader = make_reader(f)
        w = Writer(out)
        w.start(profile="", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for i, (sc, ch, m) in enumerate(reader.iter_messages(log_time_order=False)):
            if sc.id not in schemas:
                schemas[sc.id] = w.register_schema(sc.name, sc.encoding, sc.data)
            if ch.id not in channels:
                channels[ch.id] = w.register_channel(
                    ch.topic, ch.message_encoding, schemas[sc.id], ch.metadata
                )
            data = m.data
            if hit is None and sc.name == "SetpointCommand":
                hit, data = i, json.dumps({**json.loads(data), "sp": "hot"}).encode()
            w.add_message(channels[ch.id], m.log_time, data, m.publish_time, m.sequence)
        f.seek(0)
        for meta in make_reader(f).iter_metadata():
            w.add_metadata(meta.name, dict(meta.metadata))
        w.finish()
    assert main(["report", str(bad), "-o", str(tmp_path / "r.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert f"message {hit}" in err and "sp:" in err and "/cmd/setpoint" in err


def test_the_nyquist_ticks_of_a_small_gain_do_not_run_together(tmp_path):
    """A level loop's |G| is about 1e-4 m per %: its Nyquist ticks were each written in full
    (−0.0005 … 0.0002) and ran together along Re G. Each visible tick label stands clear of
    the next, on both axes."""
    text = files("services.plant_sim").joinpath("plants/default.toml").read_text()
    path, live = record_in_process(tmp_path, PREFIX, tomllib.loads(text), "lvl2", "relay")
    assert live.status == "ok", live.reason
    fig = build_report(load_report(path))
    fig.canvas.draw()
    ax = axes_by_label(fig, "Im G")
    for labels, along in ((ax.get_xticklabels(), 0), (ax.get_yticklabels(), 1)):
        boxes = sorted(
            (b.x0, b.x1) if along == 0 else (b.y0, b.y1)
            for b in (t.get_window_extent() for t in labels if t.get_visible() and t.get_text())
        )
        assert len(boxes) >= 3
        assert all(a[1] < b[0] for a, b in itertools.pairwise(boxes)), boxes


def test_a_harmonic_open_below_leaves_the_magnitude_axis_to_the_data_and_no_disc_is_promised():
    """lvl2's relay: the fundamentals stated no uncertainty, a harmonic ± 130 %. Its lower
    bar was drawn to a thousandth of the point and took the |G| axis down to 1e-7, and the
    Nyquist title promised discs that were not drawn (helper review)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from services.logger.bode import Crossing, FrequencyFigure, MeasuredPoint
    from services.logger.report import Report, RunSeries, draw_bode

    points = (
        MeasuredPoint("stage 1", 1, 0.4, 2.5e-4, -135.0, None),
        MeasuredPoint("stage 1", 3, 1.2, 1.2e-4, -210.0, 0.26),
        MeasuredPoint("stage 1", 5, 2.0, 4.0e-5, -390.0, 1.3),
    )
    f = FrequencyFigure(points, None, (Crossing("model", 0.78, 1.28e-4),), "no uncertainty")
    s = RunSeries(*(np.zeros(2),) * 4, [], [], None, {})
    fig = Figure()
    FigureCanvasAgg(fig)
    mag, ph, ny = fig.add_subplot(311), fig.add_subplot(312), fig.add_subplot(313)
    draw_bode(mag, ph, ny, Report("f.mcap", s, f, None, []))
    assert "disc" not in ny.get_title(), ny.get_title()
    lo, hi = mag.get_ylim()
    # the lowest point (k = 5's; its bar's lower bound is below 0) and the highest (the
    # fundamental, over every bar's upper bound), a factor 2 beyond each
    assert (lo, hi) == pytest.approx((4.0e-5 / 2, 2.5e-4 * 2)), (lo, hi)
