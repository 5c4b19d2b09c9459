"""``autotune demo``: the main job, end to end, on loopback.

Starts plant_sim, the autotuner and the logger as three processes connected over Zenoh;
tunes a loop (the heat-exchanger preset unless told otherwise) with live progress; applies
and verifies the gains; prints K_u and P_u beside the exact values where the plant's model
is linear, every Ziegler–Nichols and Tyreus–Luyben gain, the verification, and the paths of
the run's MCAP file and report figure; then stops every process. Ctrl-C cancels the run
(the loop is restored) and still stops everything cleanly.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from services.autotuner.commands.tune import (
    add_tune_options,
    follow,
    format_result,
    progress_line,
    request_from_args,
    submit,
)
from services.autotuner.recorder_watch import incomplete_line
from services.console import launch as console_launch
from services.launcher import free_tcp_port
from services.logger.report import render
from services.plant_sim.load_bound import LOAD_TIMEOUT, load_bound
from services.plant_sim.plant_file import default_plant_path, load_plant_file
from services.plant_sim.simulation.models import TransferFunctionModel
from services.plant_sim.simulation.presets import MODELS
from services.stack import Stack, runs_dir, service_tokens
from shared import json_text, keys, wire
from shared.control.transfer import model_ultimate_point
from shared.errors import AutotuneError, ConfigError
from shared.messages import IncompleteRun, LoggerStatus, LoopInfo, TuneProgress, TuneResult
from shared.session import ZenohSettings, open_session

HELP = "the main job: tune a simulated heat exchanger through the three services"
DEMO_RULES = ("zn-p", "zn-pi", "zn-pid", "tl-pi", "tl-pid")


def _say_as_demo(line: str) -> None:
    """A line of the tune's failover (a tuner passed over), as the demo's own."""
    print(f"autotune demo: {line}", file=sys.stderr)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--plant", metavar="FILE", help="your own plant file (default: presets)")
    parser.add_argument("--loop", default="hx1", help="loop to tune (default: %(default)s)")
    parser.add_argument(
        "--noise",
        type=float,
        metavar="SIGMA",
        help="measurement noise of the loops, PV units (default: the plant's)",
    )
    parser.add_argument("--seed", type=int, help="noise seed for the plant")
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="run the plant on the wall clock instead of lockstep",
    )
    parser.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="with --realtime: speed-up of the wall clock (default: %(default)s)",
    )
    parser.add_argument(
        "--runs",
        default="runs",
        metavar="DIR",
        help="where the logger writes the run (default: %(default)s)",
    )
    parser.add_argument(
        "--json",
        action="store_true",
        help="print the result as one JSON object (with mcap and report paths)",
    )
    add_tune_options(parser)
    console_launch.add_arguments(parser)


def check_loop(plant: str | None, loop: str, seed: int | None) -> None:
    """ConfigError, before anything starts, for a plant file or a loop of it the plant would
    refuse (in the plant's words) or a ``--loop`` the file does not have (naming those it
    has, once the file's other loops are known to load): the services would otherwise
    start, and the demo wait 20 s for a loop that never comes up."""
    path = plant or default_plant_path()
    ids: list[str] = []

    def note(file_ids: list[str]) -> list[str]:  # the loop to tune is built, as a check
        ids.extend(file_ids)
        return [loop] if loop in file_ids else []

    # bounded as plant_sim bounds its own load (a model whose reset() blocked held the demo
    # silent for good, before any service started: user trial)
    with load_bound(LOAD_TIMEOUT, f"plant file {path}", flag="as plant_sim bounds it"):
        load_plant_file(path, seed=seed, select=note)
    if loop not in ids:
        # the file's own faults first (the plant would refuse it whatever the loop): an
        # unstable model said only "--loop hx1: not a loop of --plant" (user trial)
        with load_bound(LOAD_TIMEOUT, f"plant file {path}", flag="as plant_sim bounds it"):
            load_plant_file(path, seed=seed)
        where = f"--plant {plant}" if plant else "the default plant"
        raise ConfigError(f"--loop {loop}: not a loop of {where}; it has: {', '.join(ids)}")


def exact_point(info: LoopInfo) -> tuple[float, float] | None:
    """The exact ultimate point when the loop's model is linear (None otherwise)."""
    cls = MODELS.get(info.model)
    if cls is None or not issubclass(cls, TransferFunctionModel):
        return None
    try:
        return model_ultimate_point(cls(**info.model_params))
    except (TypeError, ValueError):
        return None


def wait_for_file(
    session, prefix: str, runs: Path, run_id: str, timeout: float = 30.0
) -> tuple[Path, IncompleteRun | None]:
    """The run's MCAP file once the logger has finished it, and the logger's word that it
    could not write it whole (None: it did). A file the disk filled up under as it was
    finished was taken for the run's record: its report failed as "cut short … if a logger
    was killed", and the run's result went unprinted (helper trial)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st = wire.query_one(session, keys.logger_status(prefix, "logger"), LoggerStatus, 5.0)
        cut = next((r for r in st.incomplete_runs if r.run_id == run_id), None) if st else None
        if cut is not None:
            return Path(cut.path), cut
        files = list(runs.glob(f"*_{run_id}.mcap"))
        if st is not None and files and run_id not in st.open_runs:
            return files[0], None
        time.sleep(0.05)
    raise AutotuneError(f"the logger did not finish the run file for {run_id} in {timeout:g} s")


def announce(p: TuneProgress, last: list[str]) -> None:
    """A live line on a terminal; otherwise one line per phase."""
    if sys.stderr.isatty():
        progress_line(p)
    elif p.phase != (last[0] if last else None):
        last[:] = [p.phase]
        print(f"  {p.phase:<10} t = {p.t:8.1f} s  {p.message}", file=sys.stderr, flush=True)


def format_demo(
    r: TuneResult,
    exact: tuple[float, float] | None,
    model: str,
    mcap: Path | None,
    report: Path | None,
    incomplete: IncompleteRun | None = None,
) -> str:
    lines = [format_result(r)]
    if exact and r.ku is not None:
        ku, pu = exact
        lines.append(
            f"  exact ultimate point of the {model} model: K_u = {ku:.4g}, "
            f"P_u = {pu:.4g} s (measured: {100 * (r.ku / ku - 1):+.1f} %, "
            f"{100 * (r.pu / pu - 1):+.1f} %)"
        )
    if incomplete is not None:
        lines.append(f"  {incomplete_line(incomplete)}")
    elif mcap:
        lines.append(f"  run recorded in {mcap}")
    if report:
        lines.append(f"  report figure   {report}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.plant and not os.path.isfile(args.plant):
        raise ConfigError(f"--plant {args.plant}: no such file")
    if not (args.speed > 0 and args.speed < float("inf")):
        raise ConfigError(f"--speed {args.speed}: must be a finite number > 0")
    check_loop(args.plant, args.loop, args.seed)
    req = request_from_args(args, source="autotune-demo")
    console_port = console_launch.port_of(args)
    runs = runs_dir(args.runs)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    # the topics of `autotune up` (a Foxglove layout fits both), isolated by a namespace
    prefix = keys.DEFAULT_PREFIX
    namespace = f"namespace:{json.dumps(f'demo{os.getpid()}')}"
    client = ZenohSettings(
        mode="peer",
        connect=(endpoint,),
        cfg=("connect/timeout_ms:10000", namespace),
        no_multicast_scouting=True,
    )
    plant_args = ["--prefix", prefix]
    plant_args += ["--plant", args.plant] if args.plant else []
    plant_args += ["--seed", str(args.seed)] if args.seed is not None else []
    plant_args += ["--noise-std", str(args.noise)] if args.noise is not None else []
    plant_args += ["--clock", "realtime", "--speed", str(args.speed)] if args.realtime else []
    zenoh_client = ["-e", endpoint, "--no-multicast-scouting", "--cfg", "connect/timeout_ms:10000"]
    zenoh_client += ["--cfg", namespace]
    mcap = report = info = incomplete = None
    with tempfile.TemporaryFile("w+") as logs:
        stack = Stack(prefix, client, logs)
        try:
            stack.start(
                "plant",
                "services.plant_sim",
                plant_args,
                ["-l", endpoint, "--no-multicast-scouting", "--cfg", namespace],
            )
            stack.start("tuner", "services.autotuner", ["--prefix", prefix], zenoh_client)
            stack.start(
                "logger", "services.logger", ["--prefix", prefix, "--runs", str(runs)], zenoh_client
            )
            print(
                f"services started on {endpoint}: plant_sim pid {stack.procs['plant'].pid}, "
                f"autotuner pid {stack.procs['tuner'].pid}, logger pid "
                f"{stack.procs['logger'].pid}",
                file=sys.stderr,
                flush=True,
            )
            try:
                stack.wait_ready(service_tokens(prefix, args.loop))
            except AutotuneError as err:
                logs.seek(0)
                raise AutotuneError(f"{err}\n{logs.read().strip()}") from None
            if args.console:  # up before the run: the page shows it live, and after
                url = console_launch.start(stack, prefix, runs, console_port, zenoh_client)
                print(f"the commissioning console: {url}", file=sys.stderr, flush=True)
            with open_session(client) as session:
                info = wire.query_one(session, keys.info(prefix, args.loop), LoopInfo, 10.0)
                if info is None:
                    raise AutotuneError(f"loop {args.loop}: the plant does not answer")
                last: list[str] = []
                result = follow(
                    session,
                    prefix,
                    args.loop,
                    lambda: submit(session, prefix, "*", req, say=_say_as_demo),
                    3600.0,
                    None if args.json else (lambda p: announce(p, last)),
                )
                mcap, incomplete = wait_for_file(session, prefix, runs, result.run_id)
            if incomplete is None:  # the whole report: trends, model, Bode, before/after
                report = mcap.with_suffix(".png")
                report.write_bytes(render(mcap))
            if args.console:  # the outcome now, then the page stays up until Ctrl-C
                _print_outcome(args, result, info, mcap, report, incomplete)
                console_launch.hold(url)
        finally:
            console_launch.stop(stack)
            stack.stop()
    if not args.console:
        _print_outcome(args, result, info, mcap, report, incomplete)
    return 0 if result.status == "ok" else 1


def _print_outcome(
    args: argparse.Namespace,
    result: TuneResult,
    info: LoopInfo | None,
    mcap: Path,
    report: Path | None,
    incomplete: IncompleteRun | None = None,
) -> None:
    """The run's outcome on stdout: ``--json``'s object, or the demo's text; a run file the
    logger could not write whole (``incomplete``) has no report, and one line says so (on
    stderr too with ``--json``)."""
    if sys.stderr.isatty() and not args.json:
        print("\r" + " " * 100 + "\r", end="", file=sys.stderr)
    exact = exact_point(info) if info else None
    if args.json:
        out = result.model_dump(mode="json")
        out.update(
            mcap=str(mcap),
            report=None if report is None else str(report),
            mcap_incomplete=None if incomplete is None else incomplete.reason,
            exact={"ku": exact[0], "pu": exact[1]} if exact else None,
        )
        print(json_text.dumps(out, indent=2))
        if incomplete is not None:
            print(f"autotune demo: {incomplete_line(incomplete)}", file=sys.stderr)
    else:
        print(format_demo(result, exact, info.model, mcap, report, incomplete), flush=True)
