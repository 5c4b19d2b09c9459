"""``autotune report RUN.mcap -o report.png``: the figure for a commissioning report.

PV and setpoint (top) and output (bottom) against sim time, from the recorded samples; the
relay's cycle boundaries or the ramp's trials marked; the verification steps shaded; K_u,
P_u, the chosen gains and the verification figures in a box. matplotlib's object API with
the Agg canvas: no display and no global pyplot state.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from services.logger.mcap_io import decode, one_result, read_run, unique_samples
from shared import keys
from shared.errors import AutotuneError, one_line
from shared.history_file import HISTORY_FILE, loop_changes, read_history
from shared.messages import TuneProgress, TuneResult, TunerEvent

if TYPE_CHECKING:
    from matplotlib.figure import Figure

HELP = "plot a recorded run (PV, setpoint, output, cycles, verification) to a PNG"


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
    marks = [(e.t, f"cycle {e.data.get('n')}") for e in events if e.kind == "cycle"]
    marks += [(e.t, f"trial {e.data.get('n')}") for e in events if e.kind == "trial"]
    spans: list[tuple[float, float]] = []
    start = None
    for p in progress:
        if p.phase == "verify" and start is None:
            start = p.t
        elif p.phase != "verify" and start is not None:
            spans.append((start, p.t))
            start = None
    if start is not None:
        spans.append((start, samples[-1].t))
    return RunSeries(
        np.array([s.t for s in samples]),
        np.array([s.pv for s in samples]),
        np.array([s.sp for s in samples]),
        np.array([s.op for s in samples]),
        marks,
        spans,
        result,
        meta,
        history_lines(Path(path).parent, meta.get("loop", ""), run_id or "", meta.get("prefix"))
        + watch_lines(Path(path).parent, meta.get("loop", ""), run_id or ""),
    )


HISTORY_SHOWN = 8  # the last changes the report lists
MONITOR_FILE = "monitor.jsonl"  # the tuner's watch of the loops it tuned, kept by the logger


def watch_lines(runs: Path, loop: str, run_id: str) -> list[str]:
    """The performance after this run's change, where the tuner watched the loop (its
    assessments compared with this run, from ``monitor.jsonl`` beside the file): the windows,
    their flags, the latest window's figures. Empty where there is none."""
    if not run_id:
        return []
    windows = [
        m
        for m in read_history(runs / MONITOR_FILE)
        if m.get("loop") == loop and m.get("run_id") == run_id
    ]
    if not windows:
        return []
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
    return lines


def _gains_text(g: dict | None) -> str:
    if not isinstance(g, dict):
        return "—"
    ti = g.get("ti")
    return (
        f"Kc {_g(g.get('kc'), '.4g')}  Ti {'off' if ti is None else _g(ti, '.4g', ' s')}  "
        f"Td {_g(g.get('td'), '.3g', ' s')}"
    )


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


def _summary(s: RunSeries) -> str:
    r = s.result
    if r is None:
        return f"status: {s.meta.get('status', 'incomplete')}"
    lines = [f"{r.method} test · rule {r.rule} · {r.status}"]
    if r.ku is not None:
        lines.append(f"K_u = {_g(r.ku, '.4g')} %/{r.pv_units}   P_u = {_g(r.pu, '.4g', ' s')}")
    step = r.step if isinstance(r.step, dict) else {}
    if step:
        lines.append(
            f"K = {_g(step.get('gain'), '.3g')}  L = {_g(step.get('dead_time'), '.3g', ' s')}  "
            f"T = {_g(step.get('time_constant_tangent'), '.3g', ' s')}"
        )
    isa = (r.chosen or {}).get("isa") if isinstance(r.chosen, dict) else None
    if isinstance(isa, dict):
        lines.append(
            f"Kc = {_g(isa.get('kc'), '.4g')}  Ti = {_g(isa.get('ti'), '.4g', ' s')}  "
            f"Td = {_g(isa.get('td'), '.4g', ' s')}"
        )
    if r.after is not None:
        a = r.after
        lines.append(
            f"after: overshoot {_g(a.overshoot, '.0f', ' %')}, decay ratio "
            f"{_g(a.decay_ratio, '.2f')}, IAE {_g(a.iae_sp, '.3g')}"
        )
    if r.reason:
        lines.append(r.reason[:70])
    return "\n".join(lines)


def build_figure(s: RunSeries) -> Figure:
    # imported here: every service process imports this module through the CLI, and only
    # the report needs matplotlib (0.2 s of start-up)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = 3 if s.history else 2
    fig = Figure(figsize=(12, 7 + 0.22 * len(s.history)), layout="constrained")
    FigureCanvasAgg(fig)
    heights = [2, 1, 0.12 * len(s.history)] if s.history else [2, 1]
    axes = fig.subplots(rows, 1, height_ratios=heights)
    ax_pv, ax_op = axes[0], axes[1]
    ax_op.sharex(ax_pv)
    if s.history:
        ax_h = axes[2]
        ax_h.axis("off")
        ax_h.text(
            0.0,
            1.0,
            "\n".join(s.history),
            transform=ax_h.transAxes,
            va="top",
            fontsize=8,
            family="monospace",
        )
    units = s.result.pv_units if s.result else ""
    ax_pv.plot(s.t, s.pv, lw=1.0, color="tab:blue", label="PV")
    ax_pv.plot(
        s.t, s.sp, lw=1.0, color="tab:red", ls="--", drawstyle="steps-post", label="setpoint"
    )
    ax_op.plot(s.t, s.op, lw=1.0, color="tab:green", drawstyle="steps-post", label="output")
    for t, _ in s.marks:
        ax_pv.axvline(t, color="0.6", lw=0.6, ls=":")
    for a, b in s.verify_spans:
        for ax in (ax_pv, ax_op):
            ax.axvspan(a, b, color="tab:orange", alpha=0.08, lw=0)
    if s.verify_spans:
        ax_pv.text(
            s.verify_spans[0][0],
            1.0,
            " verification",
            transform=ax_pv.get_xaxis_transform(),
            va="top",
            fontsize=8,
            color="tab:orange",
        )
    ax_pv.set_ylabel(f"PV, setpoint ({units})" if units else "PV, setpoint")
    ax_op.set_ylabel("output (%)")
    ax_op.set_xlabel("sim time (s)")
    for ax in (ax_pv, ax_op):
        ax.grid(True, lw=0.4, alpha=0.5)
        ax.legend(loc="upper right", fontsize=8)
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
    fig.suptitle(
        f"{s.meta.get('loop', '')}: {s.meta.get('method', '')} tuning run "
        f"{s.meta.get('run_id', '')} ({s.meta.get('started', '')[:19]} UTC)"
    )
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="RUN.mcap")
    parser.add_argument(
        "-o",
        "--output",
        default="report.png",
        metavar="PNG",
        help="where to write the figure (default: %(default)s)",
    )
    parser.add_argument("--dpi", type=int, default=110)


def run(args: argparse.Namespace) -> int:
    out = Path(args.output)
    if out.suffix.lower() != ".png":
        raise AutotuneError(f"-o {out}: the report is a PNG file (name it .png)")
    series = load_series(args.file)
    try:
        build_figure(series).savefig(out, dpi=args.dpi)
    except (ValueError, OverflowError) as err:  # e.g. values beyond what an axis can scale
        raise AutotuneError(
            f"{args.file}: cannot plot the recorded series: {one_line(err)}"
        ) from None
    except OSError as err:
        raise AutotuneError(f"-o {out}: cannot write it: {err.strerror}") from None
    print(json.dumps({"report": str(out), "samples": int(series.t.size)}))
    return 0
