"""``autotune report RUN.mcap -o report.png``: the figures a control engineer expects of a run.

From the recorded samples and messages (sim time ``t`` of each message, never the file's log
time): PV and setpoint (top) and output against sim time, with a legend for every mark —
relay switches, cycles, stage 2, ramp trials with their Kc, the verifications and their load
steps — and K_u, P_u and the chosen gains (Kc with its units, as %/% and PB) in a box; the
fitted model simulated over the recorded data; a Bode and a Nyquist plot of the measured
frequency points with their stated uncertainty, the model's curve and the −180° crossings;
the verifications before and after side by side with their figures; the loop's change
history and the watch after the change. The numbers come from the pure modules beside this
one (``run_marks``, ``bode``, ``overlay``, ``before_after``, ``gain_text``); this module
reads the file and draws, with matplotlib's object API on the Agg canvas (no display, no
global pyplot state). ``build_figure`` is the trend page alone; ``render`` the whole report
as PNG or SVG bytes (the console serves those).
"""

from __future__ import annotations

import argparse
import io
import json
import math
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pydantic

from services.logger.before_after import VerifyTrace, figures_rows, verify_traces
from services.logger.bode import FrequencyFigure, frequency_figure
from services.logger.gain_text import gains_text, kc_text, span_of
from services.logger.mcap_io import (
    bus_of,
    decode,
    one_result,
    read_run,
    seq_gaps,
    unique_samples,
)
from services.logger.overlay import Overlay, model_overlay
from services.logger.result_model import result_model
from services.logger.run_marks import (
    Mark,
    VerifyWindow,
    experiment_marks,
    gains_marks,
    verify_windows,
)
from shared import keys
from shared.control.forms import unit
from shared.errors import AutotuneError, one_line
from shared.history_file import HISTORY_FILE, loop_changes, read_history
from shared.messages import (
    DisturbanceCommand,
    GainsCommand,
    LoopMonitor,
    SetpointCommand,
    TuneProgress,
    TuneResult,
    TunerEvent,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

HELP = (
    "the run's report: trends with every mark, model against data, Bode and Nyquist, before/after"
)
FORMATS = ("png", "svg")


@dataclass
class RunSeries:
    t: np.ndarray
    pv: np.ndarray
    sp: np.ndarray
    op: np.ndarray
    marks: list[tuple[float, str]]  # (t, label) of cycles or trials
    verify_spans: list[tuple[float, float]]
    result: TuneResult | None
    meta: dict[str, str]
    # the loop's gains changes from the change history beside the file (history.jsonl), and
    # the watch's assessments after this run's change where the tuner kept them
    history: list[str] = field(default_factory=list)
    events: list[Mark] = field(default_factory=list)  # every mark of the experiment
    windows: list[VerifyWindow] = field(default_factory=list)  # the verifications
    setup: dict[str, Any] = field(default_factory=dict)  # the experiment event's data
    seq: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))  # the samples'

    @property
    def units(self) -> str:
        return self.result.pv_units if self.result else str(self.setup.get("pv_units") or "")

    @property
    def span(self) -> float | None:
        """The PV's span (PV units): the result's range, else the experiment's set-up's."""
        span = span_of(self.result.pv_range) if self.result else None
        if span is None:
            span = span_of((self.setup.get("pv_range_lo"), self.setup.get("pv_range_hi")))
        return span


def _by_schema(path: str | Path, records: list, model: type) -> list:
    return [decode(path, r, model) for r in records if r.schema == model.__name__]


def load_series(path: str | Path) -> RunSeries:
    """The run's series and marks; AutotuneError (one line naming the record and field) for
    a file or a message that cannot be read."""
    meta, records = read_run(path)
    samples = unique_samples(path, records)
    if not samples:
        raise AutotuneError(f"{path}: no process samples recorded")
    run_id = meta.get("run_id")
    events = [decode(path, r, TunerEvent) for r in records if keys.leaf(r.topic) == "event"]
    progress = [decode(path, r, TuneProgress) for r in records if keys.leaf(r.topic) == "progress"]
    results = [(r, decode(path, r, TuneResult)) for r in records if keys.leaf(r.topic) == "result"]
    if run_id:  # another run's messages (a stale tail) are not this run's
        events = [e for e in events if e.run_id == run_id]
        progress = [p for p in progress if p.run_id == run_id]
        results = [(r, x) for r, x in results if x.run_id == run_id]
    result = one_result(path, results)
    setpoints = _by_schema(path, records, SetpointCommand)
    loads = _by_schema(path, records, DisturbanceCommand)
    gains = _by_schema(path, records, GainsCommand)
    marks = [(e.t, f"cycle {e.data.get('n')}") for e in events if e.kind == "cycle"]
    marks += [(e.t, f"trial {e.data.get('n')}") for e in events if e.kind == "trial"]
    ended_within = result is not None and result.before is None and result.after is None
    windows = verify_windows(
        progress,
        setpoints,
        loads,
        samples[-1].t,
        result is not None and result.before is not None,
        gains,
        result.previous_gains if ended_within and result is not None else None,
    )
    setup = next((dict(e.data) for e in events if e.kind == "experiment"), {})
    units = result.pv_units if result else str(setup.get("pv_units") or "")
    previous = result.previous_gains if result else None
    # the gain-margin check's factor (2, less under a --ms-bound past 2: margin_check)
    factor = (result.after.margin_factor if result and result.after else None) or 2.0
    return RunSeries(
        np.array([s.t for s in samples]),
        np.array([s.pv for s in samples]),
        np.array([s.sp for s in samples]),
        np.array([s.op for s in samples]),
        marks,
        [(w.start, w.end) for w in windows],
        result,
        meta,
        history_lines(Path(path).parent, meta.get("loop", ""), run_id or "", bus_of(meta))
        + watch_lines(Path(path).parent, meta.get("loop", ""), run_id or "", bus_of(meta)),
        sorted(
            experiment_marks(events, units) + gains_marks(gains, windows, previous, units, factor),
            key=lambda m: m.t,
        ),
        windows,
        setup,
        np.array([s.seq for s in samples]),
    )


HISTORY_SHOWN = 8  # the last changes the report lists
MONITOR_FILE = "monitor.jsonl"  # the tuner's watch of the loops it tuned, kept by the logger


def _monitor_records(path: Path) -> Iterator[LoopMonitor]:
    """The file's assessments that are ``LoopMonitor``s (a line edited or cut short is passed
    over: a window's ``flags`` edited to a list stopped the report with an internal error)."""
    for rec in read_history(path):
        try:
            yield LoopMonitor.model_validate(rec)
        except pydantic.ValidationError:
            continue


def watch_lines(runs: Path, loop: str, run_id: str, prefix: str | None = None) -> list[str]:
    """The performance after this run's change, where the tuner watched the loop (its
    assessments compared with this run, from ``monitor.jsonl`` beside the file): the windows,
    their flags, the latest window's figures. Empty where there is none. Windows that end
    after the loop's next change of gains (the history's) are another's gains: left out, said
    so (an operator's Kc 14 made the loop oscillate, and the run's report showed it
    "oscillating, degraded" after the run's change: helper trial)."""
    if not run_id:
        return []
    windows = [
        m.model_dump()
        for m in _monitor_records(runs / MONITOR_FILE)
        if m.loop == loop and m.run_id == run_id
    ]
    later = _next_change_t(runs, loop, run_id, prefix)
    after = [m for m in windows if later is not None and m["t"] > later]
    windows = [m for m in windows if later is None or m["t"] <= later]
    if not windows:
        if not after or later is None:
            return []
        return [f"watched after the change: no window before the next change (t = {later:.6g} s)"]
    flagged = sorted({f for m in windows for f in (m.get("flags") or {})})
    last = windows[-1]
    osc = (
        f"oscillating, period {_g(last.get('oscillation_period'), '.3g', ' s')}"
        if last.get("oscillating")
        else "no oscillation"
    )
    lines = [
        f"watched after the change: {len(windows)} window(s), t = "
        f"{_g(windows[0].get('t_start'), '.6g')} … {_g(last.get('t'), '.6g')} s; "
        f"flags: {', '.join(flagged) if flagged else 'none'}",
        f"  last window: IAE/time {_g(last.get('iae_rate'), '.3g')} {last.get('pv_units', '')}, "
        f"error s.d. {_g(last.get('error_std'), '.3g')}, saturation "
        f"{_g(last.get('saturation'), '.0f', ' %')}, output reversals "
        f"{_g(last.get('reversals'), 'd')}, idle index {_g(last.get('idle_index'), '.2f')}, "
        f"{osc} (T_u {_g(last.get('period'), '.3g', ' s')}, {last.get('period_source', '')})",
    ]
    for flag, why in (last.get("flags") or {}).items():
        lines.append(f"  {flag}: {str(why)[:110]}")
    if after and later is not None:
        lines.append(
            f"  {len(after)} later window(s) left out: the gains changed again at t = {later:.6g} s"
        )
    return lines


def _next_change_t(runs: Path, loop: str, run_id: str, prefix: str | None) -> float | None:
    """The sim time of the loop's first change of gains after run ``run_id``'s (None: none
    on record, or the run's change not on record)."""
    changes = loop_changes(runs / HISTORY_FILE, loop, prefix) if loop else []
    mine = [i for i, c in enumerate(changes) if c.get("run_id") == run_id]
    if not mine or mine[-1] + 1 >= len(changes):
        return None
    t = changes[mine[-1] + 1].get("t")
    return float(t) if isinstance(t, int | float) else None


def _gains_text(g: dict | None) -> str:
    if not isinstance(g, dict):
        return "—"
    ti = g.get("ti")
    beta = g.get("beta")
    return (
        f"Kc {_g(g.get('kc'), '.4g')}  Ti {'off' if ti is None else _g(ti, '.4g', ' s')}  "
        f"Td {_g(g.get('td'), '.3g', ' s')}"
        + (f"  β {_g(beta, 'g')}" if isinstance(beta, int | float) and beta != 1 else "")
    )


def _weight_text(r: TuneResult) -> str:
    """The setpoint weight the run's verification settled on (``design.setpoint_weight``),
    after its gains; "" where it kept full weight."""
    beta = (r.acceptance or {}).get("setpoint_weight")
    return f"  β {beta:g} (setpoint weight)" if isinstance(beta, int | float) else ""


def history_lines(runs: Path, loop: str, run_id: str, prefix: str | None = None) -> list[str]:
    """The loop's last gains changes (this run's marked ▶), oldest first: UTC, who, before →
    after; empty without a history beside the file."""
    changes = loop_changes(runs / HISTORY_FILE, loop, prefix) if loop else []
    if not changes:
        return []
    mine = [i for i, c in enumerate(changes) if run_id and c.get("run_id") == run_id]
    end = mine[-1] + HISTORY_SHOWN // 2 if mine else len(changes)
    shown = changes[max(0, end - HISTORY_SHOWN) : end]
    lines = [f"changes of {loop}'s gains ({HISTORY_FILE}, {len(changes)} on record):"]
    for c in shown:
        mark = "▶" if run_id and c.get("run_id") == run_id else " "
        who = c.get("by_source") or c.get("cause") or "?"
        lines.append(
            f"{mark} {str(c.get('utc', ''))[:19]}  {who:<22.22}  {_gains_text(c.get('before'))}"
            f"  →  {_gains_text(c.get('after'))}"
        )
    return lines


def _g(value: object, spec: str, unit: str = "") -> str:
    """A recorded number formatted, or "—" where the file has none (or not a number)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return "—"
    return f"{value:{spec}}{unit}"


REASON_WIDTH, REASON_LINES = 70, 3  # the summary box's reason: characters a line, lines


def _summary(s: RunSeries) -> str:
    r = s.result
    if r is None:
        return f"status: {s.meta.get('status', 'incomplete')}"
    span = s.span
    lines = [f"{_what(s)} · rule {r.rule} · {r.status}"]
    missing, first = seq_gaps(s.seq.tolist())
    if missing:
        lines.append(
            f"WARNING: {missing} samples missing from the record (first after seq {first})"
        )
    if r.ku is not None:
        lines.append(
            f"K_u = {_g(r.ku, '.4g')} %/{unit(r.pv_units)}"
            + (
                f" = {_g(r.ku * span / 100, '.4g')} %/%"
                if span and span != 100 and isinstance(r.ku, float)
                else ""
            )
            + f"   P_u = {_g(r.pu, '.4g', ' s')}"
        )
    step = r.step if isinstance(r.step, dict) else {}
    pv = unit(r.pv_units)
    # the reaction curve's figures, named so: beside the model fitted on the record (its own
    # L, in the fit's title) they read as a second model (lvl1: L 0.5 s here, 1.418 s there)
    if step.get("method") == "integrating":  # no K nor T: its rate and dead time
        lines.append(
            f"reaction curve: R = K' = {_g(step.get('reaction_rate'), '.4g', f' {pv}/s per %')}  "
            f"L = {_g(step.get('dead_time'), '.3g', ' s')}  "
            f"a = R·L = {_g(step.get('a'), '.4g', f' {pv}/%')}"
        )
    elif step:
        lines.append(
            f"reaction curve: K = {_g(step.get('gain'), '.3g', f' {pv}/%')}  "
            f"L = {_g(step.get('dead_time'), '.3g', ' s')}  "
            f"T = {_g(step.get('time_constant_tangent'), '.3g', ' s')}"
        )
    shown = _shown_gains(r)
    if shown is not None:
        label, isa = shown
        lines.append(
            ("" if label == "chosen" else f"{label}: ")
            + gains_text(isa, r.pv_units, span)
            + _weight_text(r)
        )
    if r.after is not None:
        a = r.after
        lines.append(
            f"after: overshoot {_g(a.overshoot, '.0f', ' %')}, decay ratio "
            f"{_g(a.decay_ratio, '.2f')}, IAE {_g(a.iae_sp, '.3g', f' {unit(s.units)}·s')}"
        )
    if r.reason:  # wrapped, not cut mid-word ("…the gains were computed, not")
        lines += textwrap.wrap(r.reason, REASON_WIDTH, max_lines=REASON_LINES, placeholder=" …")
    return "\n".join(lines)


# the marks' styles: (colour, line style); a cycle's is dotted and only a cycle's
MARK_STYLE = {
    "cycle": ("0.55", ":"),
    "stage 2": ("tab:purple", "-"),
    "stage 2 again": ("tab:pink", "-"),
    "relay amplitude": ("tab:orange", "-"),
    "trial": ("tab:purple", "--"),
    "load": ("tab:brown", "-."),
    "output step": ("tab:cyan", "-"),
    "gains": ("black", (0, (1, 1))),
}


def _proxy(label: str, color: str, ls: str = "-", marker: str = "", lw: float = 1.0) -> Any:
    """A legend entry that is not drawn on the axes (the marks' own lines carry no label)."""
    from matplotlib.lines import Line2D

    return Line2D([], [], color=color, ls=ls, marker=marker, lw=lw, label=label)


def _pv_limits(setup: dict[str, Any]) -> list[float]:
    """The PV limits the test was to abort outside, where they were narrower than the
    transmitter's range (a run's ``--pv-limits``): an abort at one is seen against it."""
    out = []
    for limit, end in (("pv_lo", "pv_range_lo"), ("pv_hi", "pv_range_hi")):
        v = setup.get(limit)
        if isinstance(v, int | float) and math.isfinite(v) and v != setup.get(end):
            out.append(float(v))
    return out


def _broken_at_holes(seq: np.ndarray, *series: np.ndarray) -> list[np.ndarray]:
    """The series with a NaN where samples are missing (a gap in ``seq``), so that no line
    is drawn across the hole: a straight line across 344 samples a paused logger missed, in
    the middle of a relay, looked like a record (helper trial)."""
    if seq.size < 2 or any(x.size != seq.size for x in series):
        return list(series)
    at = np.flatnonzero(np.diff(seq) > 1) + 1
    return [np.insert(np.asarray(x, dtype=float), at, np.nan) for x in series]


def draw_trends(ax_pv: Axes, ax_op: Axes, s: RunSeries) -> None:
    """PV and setpoint over output against sim time, every mark in the legend."""
    ax_op.sharex(ax_pv)
    units = s.units
    t, pv, sp, op = _broken_at_holes(s.seq, s.t, s.pv, s.sp, s.op)
    ax_pv.plot(t, pv, lw=1.0, color="tab:blue", label="PV")
    ax_pv.plot(t, sp, lw=1.0, color="tab:red", ls="--", drawstyle="steps-post", label="setpoint")
    ax_op.plot(t, op, lw=1.0, color="tab:green", drawstyle="steps-post", label="output")
    handles_pv: list[Any] = []
    handles_op: list[Any] = []
    limits = _pv_limits(s.setup)
    if limits:
        for v in limits:
            ax_pv.axhline(v, color="tab:gray", lw=0.8, ls=":")
        handles_pv.append(_proxy("the test's PV limits (--pv-limits)", "tab:gray", ":"))
    kinds = {m.kind for m in s.events}
    for m in s.events:
        if m.kind in MARK_STYLE:
            color, ls = MARK_STYLE[m.kind]
            both = m.kind in ("output step", "relay amplitude", "gains")
            for ax in (ax_pv, ax_op) if both else (ax_pv,):
                ax.axvline(m.t, color=color, lw=0.7, ls=ls)
        if m.kind in ("cycle", "trial"):
            ax_pv.text(
                m.t,
                1.0,
                m.label.split(":")[1].strip() if m.kind == "trial" else m.label.split()[-1],
                transform=ax_pv.get_xaxis_transform(),
                rotation=90,
                va="top",
                ha="right",
                fontsize=6,
                color=MARK_STYLE[m.kind][0],
                gid=MARK_LABEL,
            )
    if not s.events and s.marks:  # a file whose events only the old marks list holds
        for t, _ in s.marks:
            ax_pv.axvline(t, color="0.6", lw=0.6, ls=":")
    switches = [m for m in s.events if m.kind == "switch"]
    if switches:
        ts = np.array([m.t for m in switches])
        ax_op.plot(ts, np.interp(ts, s.t, s.op), ls="", marker="v", ms=3, color="tab:olive")
        handles_op.append(_proxy(f"relay switch ({len(switches)})", "tab:olive", "", "v"))
    if "cycle" in kinds:
        n = sum(1 for m in s.events if m.kind == "cycle")
        handles_pv.append(_proxy(f"relay cycle closed (n = 1…{n})", *MARK_STYLE["cycle"]))
    if "relay amplitude" in kinds:
        grew = ", ".join(
            m.label.removeprefix("relay amplitude ")
            for m in s.events
            if m.kind == "relay amplitude"
        )
        handles_op.append(_proxy(f"relay amplitude grew: {grew}", *MARK_STYLE["relay amplitude"]))
    if "stage 2" in kinds:
        handles_pv.append(_proxy("relay stage 2 starts", *MARK_STYLE["stage 2"]))
    if "stage 2 again" in kinds:
        handles_pv.append(_proxy("relay stage 2 set again (stuck)", *MARK_STYLE["stage 2 again"]))
    if "output step" in kinds:
        text = _steps_text([m for m in s.events if m.kind == "output step"])
        handles_pv.append(_proxy(text, *MARK_STYLE["output step"]))
        handles_op.append(_proxy(text, *MARK_STYLE["output step"]))
    for m in (m for m in s.events if m.kind == "gains"):  # each its own: its gains differ
        handles_pv.append(_proxy(f"{m.label} (t = {m.t:g} s)", *MARK_STYLE["gains"]))
        handles_op.append(_proxy(m.label.split(":")[0], *MARK_STYLE["gains"]))
    if "trial" in kinds:
        handles_pv.append(_proxy(f"ramp trial (its Kc, %/{unit(units)})", *MARK_STYLE["trial"]))
    for w in s.windows:
        for ax in (ax_pv, ax_op):
            ax.axvspan(w.start, w.end, color="tab:orange", alpha=0.08, lw=0)
            if w.load_t is not None:
                ax.axvline(w.load_t, color=MARK_STYLE["load"][0], lw=0.9, ls=MARK_STYLE["load"][1])
        ax_pv.text(
            w.start,
            0.02,
            f" verification {w.label}",
            transform=ax_pv.get_xaxis_transform(),
            va="bottom",
            fontsize=7,
            color="tab:orange",
            gid=WINDOW_LABEL,
        )
    if s.windows:
        loads = [w for w in s.windows if w.load_t is not None]
        steps = "setpoint step, load step" if loads else "setpoint step"
        handles_pv.append(_proxy(f"verification ({steps})", "tab:orange", lw=6))
        if loads:
            size = loads[-1].load
            text = f"load step {size:+.3g} %" if size is not None else "load step"
            handles_pv.append(_proxy(text, *MARK_STYLE["load"]))
            handles_op.append(_proxy(text, *MARK_STYLE["load"]))
    ax_pv.set_ylabel(f"PV, setpoint ({units})" if units else "PV, setpoint")
    ax_op.set_ylabel("output (%)")
    ax_op.set_xlabel("sim time (s)")
    for ax, extra in ((ax_pv, handles_pv), (ax_op, handles_op)):
        ax.grid(True, lw=0.4, alpha=0.5)
        base, _ = ax.get_legend_handles_labels()
        ax.legend(handles=[*base, *extra], loc="upper right", fontsize=7)
    ax_pv.text(
        0.01,
        0.98,
        _summary(s),
        transform=ax_pv.transAxes,
        va="top",
        fontsize=8,
        family="monospace",
        bbox={"boxstyle": "round", "fc": "white", "alpha": 0.85},
    )


def _steps_text(steps: list[Mark]) -> str:
    """The legend's entry for a step test's output steps: one step's own label; of repeated
    steps, how many and each output they went to (the first step's "to 54.05 %" stood for
    all six, three of which went down to 44.05 %: helper review)."""
    if len(steps) == 1:
        return f"step test: {steps[0].label}"
    prefix = "output step to "
    targets = dict.fromkeys(
        m.label.removeprefix(prefix).removesuffix(" %") for m in steps if m.label.startswith(prefix)
    )
    to = f", to {' / '.join(targets)} %" if targets else ""
    return f"step test: {len(steps)} output steps{to}"


def _text_panel(ax: Axes, lines: list[str], fontsize: float = 8) -> None:
    ax.axis("off")
    ax.text(
        0.0,
        1.0,
        "\n".join(lines),
        transform=ax.transAxes,
        va="top",
        fontsize=fontsize,
        family="monospace",
    )


def _what(s: RunSeries) -> str:
    """What the run did: its test, or (``autotune apply``) another run's gains, no test."""
    source = s.result.applied_from if s.result is not None else None
    if source:
        return f"apply of run {source}'s gains (no test)"
    return f"{s.meta.get('method', '')} test"


def _title(s: RunSeries) -> str:
    loop, run_id, started = (
        s.meta.get("loop", ""),
        s.meta.get("run_id", ""),
        s.meta.get("started", ""),
    )
    if s.result is not None and s.result.applied_from:
        what = f"run {run_id}, apply of run {s.result.applied_from}'s gains"
    else:
        what = f"{s.meta.get('method', '')} tuning run {run_id}"
    return f"{loop}: {what} ({started[:19]} UTC)"


MARK_LABEL, WINDOW_LABEL = "mark label", "window label"  # the trends' labels (``place_labels``)


def place_labels(fig: Figure) -> None:
    """Keep the trends' labels readable (the layout final: they are measured as drawn). A
    mark's label (a relay cycle's number, a trial's Kc) hangs from the top of the plot; one
    that falls under the summary box or the legend hangs from its foot instead, on a white ground
    (the first six trials' Kc of an hx1 ramp were hidden under it). A verification's label
    that would overprint the one before it (flow1's two windows 25 s apart read "verification
    bevfecification after") goes up a line."""
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        boxes = [t.get_window_extent(renderer) for t in ax.texts if t.get_bbox_patch()]
        if ax.get_legend() is not None:  # lvl2's cycle numbers 9–16 hid under the legend
            boxes.append(ax.get_legend().get_window_extent(renderer))
        to_axes = ax.transAxes.inverted()
        for t in (t for t in ax.texts if t.get_gid() == MARK_LABEL):
            e = t.get_window_extent(renderer)
            under = next((b for b in boxes if e.overlaps(b)), None)
            if under is not None:
                t.set_y(to_axes.transform((0.0, under.y0))[1] - 0.01)
                t.set_bbox({"fc": "white", "ec": "none", "alpha": 0.7, "pad": 0.5})
        placed: list[Any] = []
        right = ax.get_window_extent(renderer).x1
        for t in sorted(
            (t for t in ax.texts if t.get_gid() == WINDOW_LABEL), key=lambda t: t.get_position()[0]
        ):
            if t.get_window_extent(renderer).x1 > right:  # a window near the end: cut at the
                # plot's edge ("verification aft" of a run cancelled there), so set inside it
                t.set_x(ax.get_xlim()[1])
                t.set_horizontalalignment("right")
            for _ in range(len(placed)):
                e = t.get_window_extent(renderer)
                if not any(e.overlaps(p) for p in placed):
                    break
                t.set_y(to_axes.transform((0.0, e.y1))[1] + 0.005)
            placed.append(t.get_window_extent(renderer))


def keep_clear(fig: Figure) -> None:
    """Widen each plot's PV (or output) range until no legend and no boxed note of it stands
    over its data: a legend in the upper part gets headroom, one in the lower part room
    below. Linear axes only (a log or equal-aspect plot keeps its range); the layout must be
    final (boxes are measured as drawn)."""
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        if ax.get_yscale() != "linear" or ax.get_aspect() != "auto":
            continue
        boxes = [t.get_window_extent(renderer) for t in ax.texts if t.get_bbox_patch()]
        if ax.get_legend() is not None:
            boxes.append(ax.get_legend().get_window_extent(renderer))
        data = [ln.get_xydata() for ln in ax.lines if ln.get_transform() is ax.transData]
        if not boxes or not data:
            continue
        xy = np.vstack(data)
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        ax.get_xlim(), ax.get_ylim()  # the autoscaled limits made now, before the transform
        px = ax.transData.transform(xy)[:, 0] if xy.size else np.array([])
        for _ in range(2):  # room made below moves the data up: the boxes above are seen again
            for box in boxes:
                _clear_of(ax, box, xy[(px >= box.x0) & (px <= box.x1), 1])


def _clear_of(ax: Axes, box: Any, ys: np.ndarray, margin: float = 0.02) -> None:
    """Extend ``ax``'s y range so that the values ``ys`` (those under the box's width) lie
    below the box (a box in the upper half) or above it (lower half), ``margin`` of the
    axes' height clear of it."""
    if ys.size == 0:
        return
    lo, hi = ax.get_ylim()
    (_, f0), (_, f1) = ax.transAxes.inverted().transform([[box.x0, box.y0], [box.x1, box.y1]])
    if hi <= lo:
        return
    if f0 + f1 > 1.0:  # upper: the highest value at most f0 − margin of the height up
        room, top = f0 - margin, float(np.max(ys))
        if room > 0.3 and (top - lo) / (hi - lo) > room:
            ax.set_ylim(lo, lo + (top - lo) / room)
    else:  # lower: the lowest value at least f1 + margin up
        room, bottom = f1 + margin, float(np.min(ys))
        if room < 0.7 and (bottom - lo) / (hi - lo) < room:
            ax.set_ylim((bottom - room * hi) / (1.0 - room), hi)


def _canvas(fig: Figure) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)


def build_figure(s: RunSeries) -> Figure:
    """The trend page alone: PV and setpoint, output, the change history."""
    # imported here: every service process imports this module through the CLI, and only
    # the report needs matplotlib (0.2 s of start-up)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 7 + 0.22 * len(s.history)), layout="constrained")
    _canvas(fig)
    heights = [2, 1, 0.12 * len(s.history)] if s.history else [2, 1]
    axes = fig.subplots(len(heights), 1, height_ratios=heights)
    draw_trends(axes[0], axes[1], s)
    if s.history:
        _text_panel(axes[2], s.history)
    fig.suptitle(_title(s))
    fig.draw_without_rendering()  # the constrained layout made, the boxes where they will be
    place_labels(fig)
    keep_clear(fig)
    return fig


# --- the whole report -------------------------------------------------------------------


@dataclass
class Report:
    """Everything the report draws: the series and the figures' data (None: not available,
    with the reason in ``notes``)."""

    path: str
    series: RunSeries
    frequency: FrequencyFigure | None
    overlay: Overlay | None
    traces: list[VerifyTrace]
    notes: dict[str, str] = field(default_factory=dict)


def load_report(path: str | Path) -> Report:
    """The run's series and every figure's data; AutotuneError as ``load_series``."""
    s = load_series(path)
    notes: dict[str, str] = {}
    freq = overlay = None
    try:
        freq = frequency_figure(s.result)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as err:
        notes["frequency"] = f"cannot be computed: {one_line(err)}"
    if freq is None and "frequency" not in notes:
        notes["frequency"] = "no frequency point nor model recorded"
    try:
        overlay = _overlay(s)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as err:
        notes["overlay"] = f"cannot be simulated: {one_line(err)}"
    if overlay is None and "overlay" not in notes:
        notes["overlay"] = "no model, or no experiment set-up recorded"
    traces = verify_traces(s.t, s.pv, s.sp, s.op, s.windows)
    return Report(str(path), s, freq, overlay, traces, notes)


def _overlay(s: RunSeries) -> Overlay | None:
    """The model against the data, from the experiment's first sample to the first load step."""
    r = s.result
    model = result_model(r.experiment, r.step) if r is not None else None
    ts = s.setup.get("sample_time")
    if model is None or not isinstance(ts, int | float) or isinstance(ts, bool):
        return None
    first = s.setup.get("first_seq")  # the experiment's first sample
    start = int(np.searchsorted(s.seq, first)) if isinstance(first, int) and s.seq.size else 0
    loads = [w.load_t for w in s.windows if w.load_t is not None]
    end = int(np.searchsorted(s.t, loads[0])) if loads else s.t.size
    # a direct-acting loop's model is of the process as its controller acts on it (−G): it
    # is driven by the output turned over, as the controller turns it
    op = -s.op if s.setup.get("direction") == -1 else s.op
    # the model is simulated sample after sample: across a hole in the record it ran on as
    # if the samples after it came straight after those before (its time, and every sample
    # after, shifted by the hole) and its fit took that for a misfit; it stops at the hole
    holes = np.flatnonzero(np.diff(s.seq[start:end]) != 1) if end > start else []
    hole = None
    if len(holes):
        end, hole = start + int(holes[0]) + 1, float(s.t[start + int(holes[0])] + ts)
    o = model_overlay(s.t, s.pv, op, model, float(ts), start, end)
    return o if o is None or hole is None else replace(o, hole=hole)


def _unavailable(ax: Axes, title: str, why: str) -> None:
    ax.set_title(title, fontsize=9)
    # the ticks hidden on this axes alone: emptying its tick locations would empty those of
    # the axes it shares a scale with too (the "after" panel lost its PV scale so)
    ax.tick_params(left=False, labelleft=False, bottom=False, labelbottom=False)
    # wrapped here: matplotlib wraps at the figure's edge, not the panel's (the reason ran
    # across the next panel)
    text = "\n".join(textwrap.fill(part, 40) for part in f"not available: {why}".split("\n"))
    ax.text(0.5, 0.5, text, ha="center", va="center", fontsize=8, transform=ax.transAxes)


def draw_overlay(ax: Axes, rep: Report) -> None:
    """The recorded PV and the model's, driven by the recorded output, over the window."""
    o, s = rep.overlay, rep.series
    title = "model against data"
    if o is None:
        _unavailable(ax, title, rep.notes.get("overlay", ""))
        return
    units = s.units
    ax.plot(o.t, o.pv, lw=0.9, color="tab:blue", label="PV recorded")
    ax.plot(
        o.t,
        o.model_pv,
        lw=1.2,
        color="black",
        ls="--",
        label="model, driven by the recorded output",
    )
    m = s.result and result_model(s.result.experiment, s.result.step)
    desc = _model_text(m, units) if m else "model"
    cut = "" if o.hole is None else f", up to the hole in the record at {o.hole:.6g} s"
    ax.set_title(
        f"{title}: {desc}; fit {o.fit_percent:.1f} % (100·(1 − ‖y − ŷ‖/‖y − ȳ‖)), "
        f"rms {o.rms:.3g} {units}{cut}",
        fontsize=9,
    )
    for w in s.windows:
        if w.start <= o.end:
            ax.axvspan(w.start, min(w.end, o.end), color="tab:orange", alpha=0.08, lw=0)
    ax.set_xlabel("sim time (s)")
    ax.set_ylabel(f"PV ({units})" if units else "PV")
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.legend(loc="upper right", fontsize=7)


def _model_text(m: Any, units: str) -> str:
    """The model in its units: K in PV units per % of output (an IPDT's per s: the PV's
    rate; its "K 0.0001003" was given without any: helper review), T and L in s."""
    lags = ", ".join(f"{x:.4g}" for x in m.lags)
    per = f"{unit(units)}/s per %" if m.kind == "ipdt" else f"{unit(units)}/%"
    body = f"K {m.gain:.4g} {per}" + (f", T {lags} s" if lags else "") + f", L {m.delay:.4g} s"
    return f"{m.kind.upper()} ({body})"


STAGE_STYLE = {
    "stage 1": ("tab:blue", "o"),
    "stage 2": ("tab:red", "s"),
    "ultimate point": ("tab:red", "D"),
}


def draw_bode(ax_mag: Axes, ax_ph: Axes, ax_ny: Axes, rep: Report) -> None:
    """Bode (magnitude and phase) and Nyquist of the measured points and the model."""
    f = rep.frequency
    if f is None:
        why = rep.notes.get("frequency", "")
        for ax, title in ((ax_mag, "Bode"), (ax_ph, ""), (ax_ny, "Nyquist")):
            _unavailable(ax, title, why) if title else ax.axis("off")
        return
    units = rep.series.units or "PV unit"
    if f.model is not None:
        c = f.model
        ax_mag.loglog(c.omega, c.magnitude, color="black", lw=1.1, label=c.label)
        ax_ph.semilogx(c.omega, c.phase_deg, color="black", lw=1.1, label=c.label)
        ax_ny.plot(c.g.real, c.g.imag, color="black", lw=1.1, label=c.label)
    open_below = False  # a harmonic's bar that reaches 0 (drawn to the axis' foot)
    for stage in dict.fromkeys(p.stage for p in f.points):
        color, marker = STAGE_STYLE.get(stage, ("tab:green", "o"))
        pts = [p for p in f.points if p.stage == stage]
        fund = [p for p in pts if p.harmonic == 1]
        harm = [p for p in pts if p.harmonic != 1]
        if fund:
            w = np.array([p.omega for p in fund])
            mag = np.array([p.magnitude for p in fund])
            ph = np.array([p.phase_deg for p in fund])
            if all(p.uncertainty is not None for p in fund):
                lo_hi = np.array([p.magnitude_bounds for p in fund]).T
                err_mag = np.vstack((mag - lo_hi[0], lo_hi[1] - mag))
                err_ph = np.array([p.phase_bound_deg for p in fund])
                d = fund[0].uncertainty or 0.0
                label = f"{stage}: G(jω) ± {100 * d:.2g} %"
            else:
                err_mag = err_ph = None
                label = f"{stage}: G(jω)"
            style = dict(ls="", marker=marker, color=color, ms=5, label=label)
            gid = f"{stage} fundamental"
            for ax, values, err in ((ax_mag, mag, err_mag), (ax_ph, ph, err_ph)):
                ax.errorbar(w, values, yerr=err, capsize=3, gid=gid, **style)
            g = np.array([p.g for p in fund])
            ax_ny.plot(g.real, g.imag, gid=gid, **style)
            for p in fund:
                if p.uncertainty is not None:
                    from matplotlib.patches import Circle

                    ax_ny.add_patch(
                        Circle(
                            (p.g.real, p.g.imag),
                            p.uncertainty * p.magnitude,
                            fill=False,
                            color=color,
                            lw=0.8,
                        )
                    )
        if harm:
            w = np.array([p.omega for p in harm])
            label = f"{stage}: harmonics k = {', '.join(str(p.harmonic) for p in harm)}"
            stated = all(p.uncertainty is not None for p in harm)
            if stated:
                label += " ± " + ", ".join(f"{100 * (p.uncertainty or 0):.2g} %" for p in harm)
            style = dict(ls="", marker=marker, mfc="none", color=color, ms=5, label=label)
            mag = np.array([p.magnitude for p in harm])
            ph = np.array([p.phase_deg for p in harm])
            err_mag = err_ph = None
            if stated:  # the noise's share: a lower bound at 0 where it is over 100 %
                lo_hi = np.array([p.magnitude_bounds for p in harm]).T
                err_mag = np.vstack((mag - np.maximum(lo_hi[0], 1e-3 * mag), lo_hi[1] - mag))
                err_ph = np.array([p.phase_bound_deg for p in harm])
                open_below |= bool(np.any(lo_hi[0] <= 0))
            ax_mag.errorbar(w, mag, yerr=err_mag, capsize=3, **style)
            ax_ph.errorbar(w, ph, yerr=err_ph, capsize=3, **style)
            ax_mag.set_xscale("log")
            ax_mag.set_yscale("log")
            ax_ph.set_xscale("log")
            g = np.array([p.g for p in harm])
            ax_ny.plot(g.real, g.imag, **style)
    for c in f.crossings:
        marker, color = ("x", "tab:purple") if c.source == "result" else ("+", "black")
        label = (
            f"−180°: result K_u {1 / c.magnitude:.4g}, P_u {2 * math.pi / c.omega:.4g} s"
            if c.source == "result"
            else f"−180°: model K_u {1 / c.magnitude:.4g}, P_u {2 * math.pi / c.omega:.4g} s"
        )
        ax_mag.plot(
            [c.omega], [c.magnitude], ls="", marker=marker, ms=9, mew=1.5, color=color, label=label
        )
        ax_ph.plot(
            [c.omega], [-180.0], ls="", marker=marker, ms=9, mew=1.5, color=color, label=label
        )
        ax_ny.plot(
            [-c.magnitude], [0.0], ls="", marker=marker, ms=9, mew=1.5, color=color, label=label
        )
    if open_below:
        _magnitude_range(ax_mag, f)
    ax_ph.axhline(-180.0, color="0.4", lw=0.7, ls="--")
    ax_ny.axhline(0.0, color="0.6", lw=0.5)
    ax_ny.axvline(0.0, color="0.6", lw=0.5)
    ax_mag.set_title(
        f"Bode: measured points and fitted model ({f.uncertainty_note})"
        if f.uncertainty_note
        else "Bode",
        fontsize=9,
    )
    ax_mag.set_ylabel(f"|G| ({unit(units)}/%)")
    ax_ph.set_ylabel("phase (deg)")
    ax_ph.set_xlabel("ω (rad/s)")
    ax_ph.sharex(ax_mag)
    ax_mag.tick_params(labelbottom=False)
    from matplotlib.ticker import LogLocator, MaxNLocator, NullFormatter, NullLocator

    # few minor ticks: each is an artist, and they are most of the drawing time
    ax_mag.yaxis.set_minor_locator(NullLocator())
    ax_mag.xaxis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
    ax_ph.xaxis.set_minor_formatter(NullFormatter())
    # drawn around the fundamentals alone (a harmonic's uncertainty is a bar): a title that
    # promised discs over a relay whose fundamentals stated none (lvl2) showed none
    discs = any(p.uncertainty is not None for p in f.fundamentals)
    ax_ny.set_title(f"Nyquist: G(jω){', discs of radius δ·|G|' if discs else ''}", fontsize=9)
    ax_ny.set_xlabel(f"Re G ({unit(units)}/%)")
    ax_ny.set_ylabel(f"Im G ({unit(units)}/%)")
    _nyquist_limits(ax_ny, f)
    # a small |G| (a level loop's 1e-4 m/%) wrote each tick in full, and they ran together
    # along Re G: a few ticks, the power of ten said once by the axis
    ax_ny.xaxis.set_major_locator(MaxNLocator(5))
    ax_ny.ticklabel_format(style="sci", scilimits=(-2, 3), useMathText=True)
    for ax in (ax_mag, ax_ph, ax_ny):
        ax.grid(True, which="both", lw=0.3, alpha=0.5)
    ax_mag.legend(fontsize=6, loc="lower left")
    ax_ny.legend(fontsize=6, loc="lower right")


def _magnitude_range(ax: Axes, f: FrequencyFigure) -> None:
    """|G|'s range from the model over the plotted band, the points and their bars' finite
    bounds, a factor 2 beyond: a harmonic's bar whose lower bound is 0 (its noise's share
    over 100 %) runs off the foot, open below, instead of stretching the axis down to a
    thousandth of the point (lvl2's k = 5 at ± 130 %: the axis went to 1e-7 and the model
    and the points filled its top third)."""
    values = [p.magnitude for p in f.points]
    values += [p.magnitude_bounds[0] for p in f.points if p.uncertainty is not None]
    values += [p.magnitude_bounds[1] for p in f.points if p.uncertainty is not None]
    values += [c.magnitude for c in f.crossings]
    if f.model is not None:
        lo_w, hi_w = ax.get_xlim()
        inside = (f.model.omega >= lo_w) & (f.model.omega <= hi_w)
        values += [float(v) for v in np.asarray(f.model.magnitude)[inside]]
    finite = [v for v in values if math.isfinite(v) and v > 0]
    if finite:
        ax.set_ylim(min(finite) / 2, max(finite) * 2)


def _nyquist_limits(ax: Axes, f: FrequencyFigure) -> None:
    """Frame the measured points and the crossings (the model's low-frequency arc is long)."""
    g = [p.g for p in f.points] + [complex(-c.magnitude, 0) for c in f.crossings]
    if not g:
        return
    re = np.array([z.real for z in g] + [0.0])
    im = np.array([z.imag for z in g] + [0.0])
    r = max(np.ptp(re), np.ptp(im), 1e-12)
    ax.set_xlim(re.min() - 0.5 * r, re.max() + 0.5 * r)
    ax.set_ylim(im.min() - 0.5 * r, im.max() + 0.5 * r)
    ax.set_aspect("equal", adjustable="box")


def _no_verification(r: TuneResult | None, label: str) -> str:
    """Why the report has no ``label`` ("before"/"after") verification to draw. The old gains
    are verified only on the way to applying new ones, and only in auto: an aborted or
    refused run ended first (its report said the loop had not been in auto)."""
    if r is None:  # a file cut off before the run's end (a recovered one)
        return "the run's result is not in the file (it was cut off before the run ended)"
    if r.status == "unverified":
        return "applied without verification (--no-verify)"
    if not r.applied and r.after is None:
        what = "any verification" if label == "before" else "the new gains' verification"
        return f"the run ended ({r.status}) before {what} was complete"
    if label == "before":
        return "the loop was not in auto before the run:\nno verification of its old gains"
    return "no verification recorded"


def draw_before_after(axes: list[Axes], ax_table: Axes, rep: Report) -> None:
    """The verifications side by side on one scale, and their figures as a table."""
    s, r = rep.series, rep.series.result
    units = s.units
    by_label = {tr.label: tr for tr in rep.traces}
    labels = ["before", "after"]
    # the scale of the steps' responses, from a quarter of each response's length before its
    # step: a window opens as the gains go on, where the PV may still be coming back from the
    # test, and its tail set the scale (lvl1's 0.016 m step drawn in a twentieth of it)
    shown = {tr.label: tr.t >= -0.25 * max(float(tr.t[-1]), 0.0) for tr in rep.traces}
    ys = [y[shown[tr.label]] for tr in rep.traces for y in (tr.pv, tr.sp)]
    ys = [y for y in ys if y.size]
    lim = (min(float(np.min(y)) for y in ys), max(float(np.max(y)) for y in ys)) if ys else None
    for ax, label in zip(axes, labels, strict=True):
        tr = by_label.get(label)
        if tr is not None and tr.t.size < 3:  # a run cancelled as the verification began
            why = f"the run ended ({r.status if r else 'not known'}) as this verification began"
            _unavailable(ax, f"{label}: {tr.gains}", why)
            continue
        if tr is None:
            _unavailable(ax, f"{label}", _no_verification(r, label))
            continue
        ax.plot(tr.t, tr.pv, color="tab:blue", lw=0.9, label="PV − SP₀")
        ax.plot(
            tr.t,
            tr.sp,
            color="tab:red",
            lw=0.9,
            ls="--",
            drawstyle="steps-post",
            label="setpoint − SP₀",
        )
        if tr.load_t is not None:
            text = f"load step {tr.load:+.3g} %" if tr.load is not None else "load step"
            ax.axvline(
                tr.load_t, color=MARK_STYLE["load"][0], ls=MARK_STYLE["load"][1], lw=0.9, label=text
            )
        # the run ended within it: the result has no such verification
        cut = r is not None and (r.before if label == "before" else r.after) is None
        ax.set_title(
            f"{label}: {tr.gains}" + (f" (cut short: {r.status})" if cut else ""), fontsize=8
        )
        ax.set_xlabel("s since the setpoint step")
        if np.any(shown[label]) and not np.all(shown[label]):  # from where the scale is read
            ax.set_xlim(float(tr.t[shown[label]][0]), float(tr.t[-1]))
        ax.set_ylabel(f"deviation ({units})" if units else "deviation")
        if lim is not None and lim[1] > lim[0]:
            pad = 0.05 * (lim[1] - lim[0])
            ax.set_ylim(lim[0] - pad, lim[1] + pad)
        ax.grid(True, lw=0.4, alpha=0.5)
        ax.legend(fontsize=6, loc="upper right")
    rows = figures_rows(r.before if r else None, r.after if r else None, units)
    if rows:
        lines = [f"{'':<28}{'before':>10}{'after':>10}"]
        lines += [f"{a:<28.28}{b:>10}{c:>10}" for a, b, c in rows]
    else:  # a header over nothing read as figures lost (an aborted or refused run)
        why = "none: " + _no_verification(r, "after").replace("\n", " ")
        lines = textwrap.wrap(why, 44)  # the panel's width (it ran off the page's edge)
    if r is not None and isinstance(r.acceptance, dict):
        lines.append("")
        lines.append(f"acceptance: {'passed' if r.acceptance.get('passed') else 'not passed'}")
        pred = r.acceptance.get("predicted_overshoot")
        if isinstance(pred, int | float):
            lines.append(f"predicted overshoot {pred:.3g} %")
    _text_panel(ax_table, lines, 7.5)
    ax_table.set_title("verification figures", fontsize=9, loc="left")


def _shown_gains(r: TuneResult) -> tuple[str, dict] | None:
    """("chosen", the chosen gains' ISA dict), or for a run refused before any was chosen (the
    safety envelope: `chosen` empty) ("refused", its rule's own), as `autotune runs` lists
    them; None without either (the refused zn-pid's report showed no gains at all, while
    `runs` listed them)."""
    isa = (r.chosen or {}).get("isa") if isinstance(r.chosen, dict) else None
    if isinstance(isa, dict):
        return "chosen", isa
    ruled = r.gains.get(r.rule) if isinstance(r.gains, dict) else None
    isa = ruled.get("isa") if isinstance(ruled, dict) else None
    if isinstance(isa, dict) and r.status == "rejected":
        return "refused", isa
    return None


def _gains_lines(s: RunSeries) -> list[str]:
    """The chosen gains in every unit, and the loop's gains before (what revert gives back)."""
    r = s.result
    if r is None:
        return []
    span = s.span
    lines = []
    shown = _shown_gains(r)
    if shown is not None:
        label, isa = shown
        lines.append(f"{label} ({r.rule}): {gains_text(isa, r.pv_units, span)}{_weight_text(r)}")
    if r.previous_gains is not None:
        g = r.previous_gains
        lines.append(
            f"before the run:  {kc_text(g.kc, r.pv_units, span)}  Ti "
            f"{'off' if g.ti is None else _g(g.ti, '.4g', ' s')}  Td {_g(g.td, '.4g', ' s')}"
        )
    if span is None:
        lines.append("(no PV range recorded: no %/% nor PB)")
    return lines


# the report's rows (inches): trends, output, overlay, Bode magnitude and phase (Nyquist
# beside), verifications; gaps between; a fixed grid is several times faster to lay out than
# matplotlib's constrained layout
ROWS_IN = (4.2, 2.0, 0.8, 3.0, 0.9, 2.8, 2.8, 0.8, 3.2, 0.6)
TEXT_LINE_IN = 0.16


def build_report(rep: Report) -> Figure:
    """The whole report on one page."""
    from matplotlib.figure import Figure

    s = rep.series
    text = _gains_lines(s) + ([""] if s.history else []) + s.history
    heights = [*ROWS_IN, 0.3 + TEXT_LINE_IN * len(text)]
    total = sum(heights) + 1.0
    fig = Figure(figsize=(13, total))
    _canvas(fig)
    grid = fig.add_gridspec(
        len(heights),
        3,
        height_ratios=heights,
        width_ratios=[1, 0.5, 1],
        left=0.07,
        right=0.98,
        top=1 - 0.55 / total,
        bottom=0.15 / total,
        hspace=0.0,
        wspace=0.3,
    )
    ax_pv, ax_op = fig.add_subplot(grid[0, :]), fig.add_subplot(grid[1, :])
    draw_trends(ax_pv, ax_op, s)
    ax_pv.tick_params(labelbottom=False)
    draw_overlay(fig.add_subplot(grid[3, :]), rep)
    draw_bode(
        fig.add_subplot(grid[5, :2]),
        fig.add_subplot(grid[6, :2]),
        fig.add_subplot(grid[5:7, 2]),
        rep,
    )
    ver = grid[8, :].subgridspec(1, 3, width_ratios=[1, 1, 0.85], wspace=0.25)
    ax_b, ax_a, ax_t = (fig.add_subplot(ver[0, i]) for i in range(3))
    ax_a.sharey(ax_b)
    ax_a.sharex(ax_b)  # one time scale too: a faster answer after is seen to be faster
    draw_before_after([ax_b, ax_a], ax_t, rep)
    _text_panel(fig.add_subplot(grid[10, :]), text)
    fig.suptitle(_title(s), y=1 - 0.15 / total)
    place_labels(fig)
    keep_clear(fig)
    return fig


def render(path: str | Path, fmt: str = "png", dpi: int = 110) -> bytes:
    """The run's whole report as PNG or SVG bytes; AutotuneError (one line) for a file that
    cannot be read or plotted."""
    if fmt not in FORMATS:
        raise AutotuneError(f"format {fmt!r}: the report is one of {', '.join(FORMATS)}")
    return draw_report(load_report(path), fmt, dpi)


def draw_report(rep: Report, fmt: str = "png", dpi: int = 110) -> bytes:
    """``rep`` drawn as PNG or SVG bytes."""
    out = io.BytesIO()
    try:
        build_report(rep).savefig(out, format=fmt, dpi=dpi)
    except (ValueError, OverflowError) as err:  # e.g. values beyond what an axis can scale
        raise AutotuneError(
            f"{rep.path}: cannot plot the recorded series: {one_line(err)}"
        ) from None
    return out.getvalue()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="RUN.mcap")
    parser.add_argument(
        "-o",
        "--output",
        default="report.png",
        metavar="PNG|SVG",
        help="where to write the report, .png or .svg (default: %(default)s)",
    )
    parser.add_argument("--dpi", type=int, default=110)
    parser.add_argument(
        "--json", action="store_true", help="print one JSON object: the report's path, samples"
    )


def run(args: argparse.Namespace) -> int:
    out = Path(args.output)
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise AutotuneError(f"-o {out}: the report is a PNG or SVG file (name it .png or .svg)")
    rep = load_report(args.file)
    data = draw_report(rep, fmt, args.dpi)
    try:
        out.write_bytes(data)
    except OSError as err:
        raise AutotuneError(f"-o {out}: cannot write it: {err.strerror}") from None
    samples = int(rep.series.t.size)
    if args.json:
        print(json.dumps({"report": str(out), "samples": samples}))
    else:
        print(f"{out}: the report of {args.file} ({samples} samples)")
    return 0
