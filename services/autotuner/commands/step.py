"""``autotune step LOOP``: open-loop step test of a running loop; prints the reaction curve."""

from __future__ import annotations

import argparse
import secrets
import sys

from services.autotuner.design.rules import ZN_STEP_RANGE
from services.autotuner.identify.reaction_curve import IntegratingCurve
from services.autotuner.identify.repeated_steps import (
    AUTO_FIRST,
    AUTO_LIMIT,
    DEFAULT_TOLERANCE,
    MAX_REPEAT,
)
from services.autotuner.identify.step_test import StepTest, StepTestConfig
from services.autotuner.loop_client import LoopClient, wait_for_loop
from services.autotuner.step_run import StepInterrupted, StepTestReport, run_step_test
from shared import json_text
from shared.cli import add_common_arguments, check_ids
from shared.errors import ConfigError
from shared.identity import auth_user
from shared.session import open_session, settings_from_args

HELP = "open-loop step test of a loop: process gain, dead time, time constants, R, L, L/T"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("loop", metavar="LOOP", help="loop id, e.g. hx1")
    add_step_options(parser)
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    parser.add_argument(
        "--units",
        choices=("engineering", "percent"),
        default="engineering",
        help="engineering (PV units) or percent: the process gains also in %% of the PV's span "
        "per %% of output (--json carries both) (default: %(default)s)",
    )
    parser.add_argument(
        "--no-wait",
        action="store_true",
        help="exit once the loop is restored, without waiting for the PV to return to rest "
        "(by default it waits up to 3 times the step's settling time, capped by --timeout)",
    )
    parser.add_argument(
        "--wait",
        type=float,
        default=10.0,
        help="seconds to wait for the loop to appear on the bus (default: %(default)s)",
    )
    add_common_arguments(parser)


def add_step_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--size",
        type=float,
        default=5.0,
        help="output step, %% of span; negative steps down (default: %(default)s)",
    )
    parser.add_argument(
        "--baseline",
        type=float,
        help="seconds of rest measured before the step (default: 40 samples)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=7200.0,
        help="sim seconds to wait for the PV to settle after the step, and at most for its "
        "return to rest (default: %(default)s)",
    )
    parser.add_argument(
        "--pv-limits",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help="abort if the PV leaves [LO, HI] (default: the loop's PV range)",
    )
    parser.add_argument(
        "--max-move",
        type=float,
        default=25.0,
        metavar="PERCENT",
        help="the PV may move this %% of its range either way from its rest; the test stops "
        "before (an integrating loop: with R as known by then) (default: %(default)s)",
    )
    parser.add_argument(
        "--repeat",
        type=parse_repeat,
        default=1,
        metavar="N|auto",
        help="N step tests, up and down in turn, each from rest: every test's figures, their "
        f"mean and spread; auto: {AUTO_FIRST} tests, then more until the mean of every figure "
        f"is known to ± {100 * DEFAULT_TOLERANCE:g} %% (two standard errors), at most "
        f"{AUTO_LIMIT} (default: 1)",
    )


def parse_repeat(text: str) -> int | str:
    """``--repeat``: a whole number of tests, 1–20, or ``auto``."""
    if text == "auto":
        return "auto"
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a number of tests (1–20) or auto") from None
    if not 1 <= n <= MAX_REPEAT:
        raise argparse.ArgumentTypeError(f"{n}: must be 1–{MAX_REPEAT} tests, or auto")
    return n


def config_from_args(args: argparse.Namespace) -> StepTestConfig:
    for name in ("size", "timeout"):
        value = getattr(args, name)
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(f"--{name} {value}: must be a finite number")
    if args.timeout <= 0:
        raise ConfigError(f"--timeout {args.timeout}: must be > 0 s")
    if args.baseline is not None and not 0 <= args.baseline < float("inf"):
        raise ConfigError(f"--baseline {args.baseline}: must be a finite number ≥ 0 s")
    if args.pv_limits and not args.pv_limits[0] < args.pv_limits[1]:
        raise ConfigError(f"--pv-limits {args.pv_limits}: LO must be below HI")
    if not 0 < args.max_move <= 100:  # also refuses NaN
        raise ConfigError(f"--max-move {args.max_move}: must be a % of the range, > 0 and ≤ 100")
    return StepTestConfig(
        size=args.size,
        baseline=args.baseline,
        timeout=args.timeout,
        timeout_flag="--timeout",
        pv_limits=tuple(args.pv_limits) if args.pv_limits else None,
        max_move=args.max_move / 100.0,
        swing_check=True,
    )


def format_report(r: StepTestReport) -> str:
    if r.tests:
        return format_repeated(r)
    if isinstance(r.curve, IntegratingCurve):
        return format_integrating(r)
    c, u = r.curve, r.pv_units
    lo, hi = ZN_STEP_RANGE
    fit = (
        "ZN step rules suit it"
        if lo <= c.l_over_t <= hi
        else "outside the range where the ZN step rules work well"
    )
    how = (
        f"SOPDT fit of the whole response (RMS {c.fit_rms:.3g} {u})"
        if c.method == "model"
        else f"the samples (derivative window {c.smoothing_window})"
    )
    rows = [
        ("process gain K", f"{c.gain:.4g} {u}/%"),
        ("dead time L (tangent)", f"{c.dead_time:.4g} s"),
        ("reaction rate R", f"{c.reaction_rate:.4g} {u}/s per %"),
        ("time constant T = K/R", f"{c.time_constant_tangent:.4g} s"),
        ("time constant T63", f"{c.time_constant_63:.4g} s  (63 % at {c.t_63:.4g} s)"),
        ("a = R·L", f"{c.a:.4g} {u}/%"),
        ("L/T", f"{c.l_over_t:.3f}  ({fit}: {lo}–{hi})"),
        ("PV before → after", f"{c.pv_before:.4g} → {c.pv_after:.4g} {u}"),
        ("PV noise σ", f"{c.noise_std:.3g} {u}"),
        ("tangent taken from", how),
    ]
    head = (
        f"Step test of {r.loop} ({r.model}): output {r.op_before:g} → "
        f"{r.op_before + c.step_size:g} % at t = {r.t_step:g} s, at rest by t = {r.t_end:g} s"
    )
    width = max(len(k) for k, _ in rows)
    body = "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)
    floor = (
        f"Dead time: the tangent gave {c.dead_time_tangent:.3g} s, below what the data resolve; "
        f"floored at half a sample time, {c.dead_time_floor:.3g} s (the hold's effective delay)."
        if c.dead_time_tangent is not None and c.dead_time_tangent < c.dead_time_floor
        else None
    )
    tail = (
        f"Loop restored: {r.mode_before}, output {r.op_before:g} %."
        if r.restored
        else "WARNING: the loop could not be restored; check it."
    )
    lines = [head, body, *([floor] if floor else []), tail, return_line(r)]
    return "\n".join(line for line in lines if line)


def _percent(fraction: float) -> str:
    """A relative precision in % to two significant figures, as the tune's table prints it
    (a ramp known to ± 0.046 % printed "± 0.0%")."""
    return f"{100 * fraction:.2g} %"


def format_integrating(r: StepTestReport) -> str:
    """The reaction curve of an integrating loop (Ziegler and Nichols' original method)."""
    c, u = r.curve, r.pv_units
    why = (
        f"R known to ± {_percent(c.reaction_rate_precision)}"
        if c.stopped_by == "precision"
        else f"the PV's allowance reached; R known to ± {_percent(c.reaction_rate_precision)}"
    )
    rows = [
        (
            "reaction rate R = K'",
            f"{c.reaction_rate:.4g} {u}/s per %  (± {_percent(c.reaction_rate_precision)}, 2σ)",
        ),
        ("slope after the step", f"{c.slope:.4g} {u}/s"),
        ("dead time L", f"{c.dead_time:.4g} s  (± {c.dead_time_se:.2g} s)"),
        ("a = R·L", f"{c.a:.4g} {u}/%"),
        ("model", f"K'·e^(-Ls)/s, K' = {c.reaction_rate:.4g} {u}/s per %, L = {c.dead_time:.4g} s"),
        ("PV before → peak → after", f"{c.pv_before:.4g} → {c.pv_peak:.4g} → {c.pv_after:.4g} {u}"),
        ("PV noise σ", f"{c.noise_std:.3g} {u}"),
    ]
    moved = c.drifted(r.t_end - r.t_step)
    head = (
        f"Step test of {r.loop} ({r.model}): integrating. Output {r.op_before:g} → "
        f"{r.op_before + c.step_size:g} % at t = {r.t_step:g} s, held {c.held:.4g} s ({why}); "
        f"then a pulse of equal and opposite area ({c.pulse_op:g} % for {c.pulse_held:.4g} s) "
        f"gave {'the step' if moved is not None else 'the level'} back by "
        f"t = {r.t_end:g} s"
    )
    width = max(len(k) for k, _ in rows)
    body = "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)
    drift = None
    if moved is not None:
        # the output before the test does not hold the level: the pulse gives back the
        # step's area, and the level goes on drifting as it did before the step
        balance = r.op_before - c.drift / c.reaction_rate
        drift = (
            f"The level drifted at {c.drift:.3g} {u}/s before the step (the output "
            f"{r.op_before:g} % is off its balance, {balance:.4g} % by R), and went on so: "
            f"{moved:+.3g} {u} over the test, which the pulse does not give back."
        )
    tail = (
        f"Loop restored: {r.mode_before}, output {r.op_before:g} %."
        if r.restored
        else "WARNING: the loop could not be restored; check it."
    )
    lines = [head, body, *([drift] if drift else []), tail, return_line(r)]
    return "\n".join(line for line in lines if line)


_FIGURES = {  # name → (column heading, unit template)
    "gain": ("K", "{u}/%"),
    "dead_time": ("L s", "s"),
    "time_constant_tangent": ("T s", "s"),
    "time_constant_63": ("T63 s", "s"),
    "reaction_rate": ("R", "{u}/s per %"),
}


def format_repeated(r: StepTestReport) -> str:
    """Every test's figures, their mean, spread and the mean's precision."""
    u = r.pv_units
    names = list(r.spreads)
    integrating = isinstance(r.curve, IntegratingCurve)
    head = (
        f"{len(r.tests)} step tests of {r.loop} ({r.model}"
        + (", integrating" if integrating else "")
        + f"), ±{abs(r.tests[0].step_size):g} % in turn from {r.op_before:g} %, "
        f"t = {r.t_step:g} … {r.t_end:g} s"
    )
    cols = [_FIGURES[n][0] for n in names]
    lines = [head, "  " + f"{'test':<10}" + "".join(f"{c:>12}" for c in cols)]
    for i, c in enumerate(r.tests, 1):
        label = f"{i} ({c.step_size:+g} %)"
        lines.append("  " + f"{label:<10}" + "".join(f"{getattr(c, n):>12.4g}" for n in names))
    lines.append("  " + f"{'mean':<10}" + "".join(f"{r.spreads[n].mean:>12.4g}" for n in names))
    lines.append(
        "  " + f"{'spread %':<10}" + "".join(f"{100 * r.spreads[n].spread:>12.2g}" for n in names)
    )
    lines.append(
        "  "
        + f"{'mean ± %':<10}"
        + "".join(f"{100 * r.spreads[n].precision:>12.2g}" for n in names)
    )
    units = ", ".join(f"{_FIGURES[n][0].split()[0]} in {_FIGURES[n][1].format(u=u)}" for n in names)
    lines.append(
        f"  ({units}; spread: the tests' standard deviation, mean ±: two standard errors, "
        "both relative to the mean)"
    )
    if not integrating:
        c = r.curve
        lines.append(
            f"  mean curve: R = K/T = {c.reaction_rate:.4g} {u}/s per %, a = R·L = {c.a:.4g} "
            f"{u}/%, L/T = {c.l_over_t:.3f}"
        )
    else:
        c = r.curve
        lines.append(f"  mean curve: a = R·L = {c.a:.4g} {u}/%")
    lines += [f"  NOTE: {n}" for n in r.notes]
    lines.append(
        f"Loop restored: {r.mode_before}, output {r.op_before:g} %."
        if r.restored
        else "WARNING: the loop could not be restored; check it."
    )
    lines.append(return_line(r))
    return "\n".join(line for line in lines if line)


def percent_line(r: StepTestReport) -> str:
    """The process gains in % of span, the engineering figures beside them."""
    pct = r.percent
    if not pct:
        return "No usable PV range: no % of span figures."
    lo, hi = r.pv_range
    u = r.pv_units
    units = {"gain": ("K", "%/%", f"{u}/%"), "reaction_rate": ("R", "%/s per %", f"{u}/s per %")}
    units["a"] = ("a = R·L", "%/%", f"{u}/%")
    parts = [
        f"{units[k][0]} = {v:.4g} {units[k][1]} ({r.curve.to_dict()[k]:.4g} {units[k][2]})"
        for k, v in pct.items()
        if v is not None
    ]
    return f"In % of span (PV range {lo:g} to {hi:g} {u}, span {hi - lo:g}): " + ", ".join(parts)


def return_line(r: StepTestReport) -> str:
    """What the PV did after the restore (empty if the loop was not restored)."""
    if not r.restored:
        return ""
    if r.returned_to_rest is None:
        return (
            "Not waiting for the PV to return to rest (--no-wait): it is still moving back; "
            "let it settle before another test."
        )
    if r.returned_to_rest:
        moved = (
            r.curve.drifted(r.t_end - r.t_step) if isinstance(r.curve, IntegratingCurve) else None
        )
        if moved is not None:  # back on the drift it had, which is no rest of the level
            return (
                f"PV back on its drift before the test ({r.curve.drift:.3g} {r.pv_units}/s) at "
                f"{r.pv_end:.4g} {r.pv_units} by t = {r.t_return:g} s: not at rest."
            )
        return f"PV back at rest at {r.pv_end:.4g} {r.pv_units} by t = {r.t_return:g} s."
    return (
        f"WARNING: the PV was not back at rest by t = {r.t_return:g} s (last {r.pv_end:.4g} "
        f"{r.pv_units}); let it settle before another test."
    )


def progress_line(test: StepTest, s) -> None:
    if s.seq % 40 == 0 and sys.stderr.isatty():
        phase = "return" if test.finished else test.phase
        print(
            f"\r  {phase:<8} t = {s.t:8.1f} s  PV = {s.pv:9.4g}  OP = {s.op:5.1f} %",
            end="",
            file=sys.stderr,
            flush=True,
        )


def step_source() -> str:
    """This step test's name on the bus (its lease, its commands): its own, as a tuning run's
    is. Why: two step tests of one loop under one name were one holder to the plant; the
    second one's lease was taken for the first's renewal, each then took the other's
    commands for a forgery and aborted, and the loop was left in manual at the second
    test's step (helper trial)."""
    return f"autotune-step-{secrets.token_hex(4)}"


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    check_ids(args.prefix, loop=args.loop)
    settings = settings_from_args(args)
    with open_session(settings, args.wait) as session:
        wait_for_loop(session, args.prefix, args.loop, args.wait)
        try:
            with LoopClient(
                session, args.prefix, args.loop, source=step_source(), user=auth_user(settings)
            ) as client:
                report = run_step_test(
                    client,
                    config,
                    None if args.json else progress_line,
                    wait_return=not args.no_wait,
                    repeat=AUTO_LIMIT if args.repeat == "auto" else args.repeat,
                    auto=args.repeat == "auto",
                )
        except StepInterrupted as stop:  # what it left, in one line, as `tune` says it
            from services.autotuner.commands.tune import loop_state  # tune imports this module

            if sys.stderr.isatty() and not args.json:
                print("\r" + " " * 60 + "\r", end="", file=sys.stderr)
            print(
                f"{stop.summary()}; {loop_state(session, args.prefix, args.loop)}", file=sys.stderr
            )
            raise KeyboardInterrupt from None
    if sys.stderr.isatty() and not args.json:
        print("\r" + " " * 60 + "\r", end="", file=sys.stderr)
    text = format_report(report)
    if args.units == "percent" and not args.json:
        text += "\n" + percent_line(report)
    print(json_text.dumps(report.to_dict(), indent=2) if args.json else text)
    return 0
