"""``autotune model check PLANT_FILE [--loop ID] [--json] [--plot PNG]``: check the models of a
plant file open loop before anyone tunes them.

Every loop's model — preset, transfer function, your own class or an FMU — is built as
plant_sim builds it, then stepped from rest at op0 up and down by 2 % and 10 % of output
(within its output limits), without noise or transmitter limits. Printed per loop: behaviour
(self-regulating, integrating or unstable), static gain of each step and the nonlinearity,
dead time, time constants (T63, sum of lags, the reaction curve's apparent dead time and
lag), the ultimate point (exact from the transfer function where the model has one; from the
step response — its linear part at op0 — for every model), and the sample time against it
(samples per ultimate period, with a warning below 20).

A model that returns a PV that is not a finite number, raises, or does not move for any
step is refused: one line on stderr naming the loop, exit 2 (the other loops are still
reported). So is a user's class whose one call outlasts ``--load-timeout``, or whose calls
together would outlast ``--model-time`` (said as soon as its first calls tell, with the cost
per call and the calls needed). No bus, no services: it runs the models in this process.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

from services.plant_sim.load_bound import (
    LOAD_TIMEOUT,
    MODEL_TIME,
    CallBound,
    call_bound,
    check_load_timeout,
    load_bound,
    watch_ctrl_c,
)
from services.plant_sim.model_check import ModelReport, check_loop, refine_step_point
from services.plant_sim.plant_file import load_plant_file
from services.plant_sim.simulation.loop import SimLoop
from shared.errors import ConfigError

HELP = "check a plant file's models open loop before tuning: gain, dead time, K_u, P_u"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "action", choices=("check",), metavar="check", help="what to do with the models: check"
    )
    parser.add_argument("plant_file", metavar="PLANT_FILE", help="the plant file (TOML)")
    parser.add_argument("--loop", metavar="ID", help="check this loop only (default: every loop)")
    parser.add_argument("--json", action="store_true", help="print the reports as one JSON object")
    parser.add_argument(
        "--plot", metavar="PNG", help="draw every loop's step responses into this PNG file"
    )
    parser.add_argument(
        "--load-timeout",
        type=float,
        default=LOAD_TIMEOUT,
        metavar="S",
        help="wall s the plant file's models may take to load, as plant_sim's, and a user "
        "model's reset() or step() may take in any one call of the check (default: "
        "%(default)s)",
    )
    parser.add_argument(
        "--model-time",
        type=float,
        default=MODEL_TIME,
        metavar="S",
        help="wall s a user model's calls may take in all, per loop, in the check (a slow "
        "step() times the tens of thousands of calls a check makes); a check that would take "
        "longer is refused as soon as its first calls tell, naming the cost per call and the "
        "calls needed (default: %(default)s)",
    )


def _rebuilt(
    path: str, timeout: float, guard: Callable[[SimLoop], None], loop_id: str, sample_time: float
) -> SimLoop | str:
    """The plant file's loop ``loop_id`` built alone at ``sample_time``, or why it cannot be
    (a model with a fixed step, one that loads too slowly: the refusal's line)."""
    try:
        with load_bound(timeout, f"plant file {path}"):
            loops = load_plant_file(
                path, select=lambda _: [loop_id], sample_times={loop_id: sample_time}
            )
    except ConfigError as err:
        return str(err)
    loop = loops.get(loop_id)
    if loop is None:
        return f"{loop_id}: not built"
    guard(loop)
    return loop


def _guarded(bound: CallBound) -> Callable[[SimLoop], None]:
    """Bound each reset() and step() call of a loop's model, and all of them together, when
    it is a user's class (a preset's or an FMU's step does not block in Python)."""

    def guard(loop: SimLoop) -> None:
        s = loop.settings
        if ":" in s.model_name:
            bound.guard(loop.process, s.loop_id, s.model_name)

    return guard


def run(args: argparse.Namespace) -> int:
    if args.plot is not None:
        _check_plot_path(args.plot)
    check_load_timeout(args.load_timeout)
    check_load_timeout(args.model_time, "--model-time")
    # what the models print goes to stderr: stdout is the report's (a model that printed in
    # its step() made `--json` unreadable: helper review); a KeyboardInterrupt a model raises
    # is its failure, one line and exit 2: only a Ctrl-C is the user's (exit 130)
    with contextlib.redirect_stdout(sys.stderr), watch_ctrl_c():
        reports = _reports(args)
    if args.json:
        print(
            json.dumps(
                {"plant_file": str(args.plant_file), "loops": [r.to_dict() for r in reports]}
            )
        )
    else:
        print("\n\n".join(format_report(r) for r in reports))
    if args.plot is not None:
        plot_reports(reports, Path(args.plot))
    refused = [r for r in reports if r.refused]
    if refused:
        r = refused[0]
        more = f" (and {len(refused) - 1} more)" if len(refused) > 1 else ""
        raise ConfigError(
            f"plant file {args.plant_file}: loops.{r.loop}.model: refused: {r.refused}{more}"
        )
    return 0


def _reports(args: argparse.Namespace) -> list:
    """Every loop's report (``--loop``: one)."""
    # a model whose __init__ or reset() blocks is refused as plant_sim refuses it (one that
    # slept 1000 s held the check for good)
    with load_bound(args.load_timeout, f"plant file {args.plant_file}"):
        loops = load_plant_file(args.plant_file)
    if args.loop is not None:
        if args.loop not in loops:
            raise ConfigError(
                f"--loop {args.loop}: no such loop in {args.plant_file} "
                f"(it has: {', '.join(loops)})"
            )
        loops = {args.loop: loops[args.loop]}
    # and each call of a model's reset() or step() as it is checked (one whose step() blocked
    # held the check for good, silent), and all its calls (one whose step() slept 50 ms took
    # 143 s for a 5 s lag at 0.1 s samples, 2.3 h for a 300 s lag, silent: helper trial)
    with call_bound(args.load_timeout, total=args.model_time) as bound:
        guard = _guarded(bound)
        for loop in loops.values():
            guard(loop)
        reports = [
            check_loop(loop_id, loop, bound.pace(loop_id)) for loop_id, loop in loops.items()
        ]
        for r in reports:
            refine_step_point(
                r,
                functools.partial(_rebuilt, args.plant_file, args.load_timeout, guard, r.loop),
                bound.pace(r.loop),
            )
    return reports


def _check_plot_path(path: str) -> None:
    p = Path(path)
    if p.suffix.lower() != ".png":
        raise ConfigError(f"--plot {path}: must name a .png file")
    if p.exists() and p.is_dir():
        raise ConfigError(f"--plot {path}: is a directory")
    if not p.parent.is_dir():
        raise ConfigError(f"--plot {path}: the directory {p.parent} does not exist")


def _g(x: float | None, digits: int = 5) -> str:
    if x is None:
        return "—"
    if not math.isfinite(x):
        return str(x)
    return f"{x:.{digits}g}"


def _spread(x: float) -> str:
    return "spread < 0.001 %" if x < 1e-5 else f"spread {100 * x:.3g} %"


def format_report(r: ModelReport) -> str:
    """The report of one loop as lines of text."""
    u = r.pv_units or "PV units"
    head = (
        f"loop {r.loop}: model {r.model}, sample time {_g(r.sample_time)} s, "
        f"op0 {_g(r.op0)} %, PV at rest {_g(r.pv0, 7)} {r.pv_units}".rstrip()
    )
    lines = [head]
    if r.refused:
        lines.append(f"  REFUSED: {r.refused}")
        return "\n".join(lines)
    lines.append(f"  behaviour: {r.behaviour}")
    per = f"{u}/s per %" if r.behaviour == "integrating" else f"{u} per %"
    if r.gains:
        steps = ", ".join(f"{k}: {_g(v, 6)}" for k, v in r.gains.items())
        spread = (
            f"no response to {', '.join(r.unmoved)}: a deadband"
            if r.unmoved
            else "the steps disagree in sign"
            if r.nonlinearity is not None and not math.isfinite(r.nonlinearity)
            else _spread(r.nonlinearity)
            if r.nonlinearity is not None
            else ""
        )
        verdict = ""
        if r.nonlinearity is not None:
            verdict = "linear" if r.nonlinearity <= 0.01 else "NONLINEAR"
        lines.append(f"  gain ({per}): {steps}  ({verdict}{', ' if verdict else ''}{spread})")
    if r.gain is not None:
        which = "small steps"
        if r.unmoved and r.linear_step is not None:  # the small ones moved nothing
            which = f"the ±{_g(r.linear_step)} % steps: the smaller moved nothing"
        lines.append(f"  gain at op0 ({which}, up and down averaged): {_g(r.gain, 6)} {per}")
    if r.dead_time is not None:
        order = f", onset like t^{r.onset_order:.2g}" if r.onset_order is not None else ""
        lines.append(f"  dead time: {_g(r.dead_time)} s (first movement{order})")
    if r.behaviour == "self-regulating":
        lines.append(
            f"  time constants: T63 {_g(r.t63)} s after the dead time; mean residence time "
            f"− dead time {_g(r.lag_sum)} s (the sum of the lags, for a chain of lags alone)"
        )
        lines.append(
            f"  reaction curve (tangent at the inflection): apparent dead time "
            f"{_g(r.apparent_dead_time)} s, lag {_g(r.apparent_lag)} s"
        )
    elif r.behaviour == "integrating" and r.apparent_dead_time is not None:
        lines.append(f"  apparent dead time (the ramp's intercept): {_g(r.apparent_dead_time)} s")
    if r.doubling_time is not None:
        lines.append(f"  runs away: doubling every {_g(r.doubling_time)} s")
    if r.ku is not None:
        ku_u = f"% per {r.pv_units or 'PV unit'}"
        if r.ku_exact is not None:
            step = (
                f"; from the step response: K_u {_g(r.ku_step)}, P_u {_g(r.pu_step)} s"
                if r.ku_step is not None
                else ""
            )
            lines.append(
                f"  ultimate point: K_u {_g(r.ku_exact)} {ku_u}, P_u {_g(r.pu_exact)} s "
                f"(exact, from the transfer function{step})"
            )
        else:
            finer = (
                f", sampled every {_g(r.step_sample_time)} s: the loop's "
                f"{_g(r.sample_time)} s samples blur it"
                if r.step_sample_time is not None and r.step_sample_time < r.sample_time
                else ""
            )
            lines.append(
                f"  ultimate point: K_u {_g(r.ku_step)} {ku_u}, P_u {_g(r.pu_step)} s "
                f"(from the step response: the linear part at op0{finer})"
            )
        lines.append(f"  sample time: {_g(r.samples_per_period, 4)} samples per ultimate period")
    elif r.behaviour in ("self-regulating", "integrating"):
        lines.append("  ultimate point: none (the phase never reaches −180° below Nyquist)")
    lines += [f"  warning: {w}" for w in r.warnings]
    if not r.warnings:
        lines.append("  ok: nothing stands in the way of tuning it")
    return "\n".join(lines)


def plot_reports(reports: list[ModelReport], path: Path) -> None:
    """Each loop's step responses (PV change per % of output) against time, one panel each."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # only --plot needs it
    from matplotlib.figure import Figure

    shown = [r for r in reports if r.responses]
    fig = Figure(figsize=(8.0, 2.8 * max(len(shown), 1)), constrained_layout=True)
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(max(len(shown), 1), 1, squeeze=False)[:, 0]
    for ax, r in zip(axes, shown, strict=False):
        for resp in r.responses:
            t = [k * r.sample_time for k in range(len(resp.pv))]
            ax.plot(t, (resp.pv - resp.pv[0]) / resp.size, lw=1.0, label=f"{resp.label} step")
        ax.set_title(f"{r.loop}: {r.model} ({r.behaviour})", fontsize=9)
        ax.set_xlabel("time after the step, s")
        ax.set_ylabel(f"ΔPV per % ({r.pv_units})" if r.pv_units else "ΔPV per %")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    try:
        canvas.print_png(str(path))
    except OSError as err:
        raise ConfigError(f"--plot {path}: cannot write it: {err.strerror or err}") from None
