"""``autotune report RUN.mcap -o report.png``: the figure for a commissioning report.

PV and setpoint (top) and output (bottom) against sim time, from the recorded samples; the
relay's cycle boundaries or the ramp's trials marked; the verification steps shaded; K_u,
P_u, the chosen gains and the verification figures in a box. matplotlib's object API with
the Agg canvas: no display and no global pyplot state.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from services.logger.mcap_io import read_run
from shared.errors import AutotuneError
from shared.messages import ProcessSample, TuneProgress, TuneResult, TunerEvent

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


def load_series(path: str | Path) -> RunSeries:
    meta, records = read_run(path)
    samples = sorted(
        (ProcessSample.model_validate_json(r.data) for r in records if r.topic.endswith("/pv")),
        key=lambda s: s.seq,
    )
    if not samples:
        raise AutotuneError(f"{path}: no process samples recorded")
    events = [TunerEvent.model_validate_json(r.data) for r in records if r.topic.endswith("/event")]
    progress = [
        TuneProgress.model_validate_json(r.data) for r in records if r.topic.endswith("/progress")
    ]
    result = next(
        (TuneResult.model_validate_json(r.data) for r in records if r.topic.endswith("/result")),
        None,
    )
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
    )


def _summary(s: RunSeries) -> str:
    r = s.result
    if r is None:
        return f"status: {s.meta.get('status', 'incomplete')}"
    lines = [f"{r.method} test · rule {r.rule} · {r.status}"]
    if r.ku is not None:
        lines.append(f"K_u = {r.ku:.4g} %/{r.pv_units}   P_u = {r.pu:.4g} s")
    if r.step:
        lines.append(
            f"K = {r.step['gain']:.3g}  L = {r.step['dead_time']:.3g} s  "
            f"T = {r.step['time_constant_tangent']:.3g} s"
        )
    if r.chosen:
        isa = r.chosen["isa"]
        ti = "—" if isa["ti"] is None else f"{isa['ti']:.4g} s"
        lines.append(f"Kc = {isa['kc']:.4g}  Ti = {ti}  Td = {isa['td']:.4g} s")
    if r.after is not None:
        a = r.after
        over = "—" if a.overshoot is None else f"{a.overshoot:.0f} %"
        decay = "—" if a.decay_ratio is None else f"{a.decay_ratio:.2f}"
        lines.append(f"after: overshoot {over}, decay ratio {decay}, IAE {a.iae_sp:.3g}")
    if r.reason:
        lines.append(r.reason[:70])
    return "\n".join(lines)


def build_figure(s: RunSeries) -> Figure:
    # imported here: every service process imports this module through the CLI, and only
    # the report needs matplotlib (0.2 s of start-up)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 7), layout="constrained")
    FigureCanvasAgg(fig)
    ax_pv, ax_op = fig.subplots(2, 1, sharex=True, height_ratios=[2, 1])
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
    build_figure(series).savefig(out, dpi=args.dpi)
    print(json.dumps({"report": str(out), "samples": int(series.t.size)}))
    return 0
