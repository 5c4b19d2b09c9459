"""``autotune demo``: the main job, end to end on loopback.

Starts plant_sim as its own process, connects to it over Zenoh and, until the autotuner
lands, runs the open-loop step test on the heat-exchanger preset and prints the reaction
curve's figures; then stops the plant cleanly.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

from services.autotuner.loop_client import LoopClient, wait_for_loop
from services.autotuner.step_command import (
    add_step_options,
    config_from_args,
    format_report,
    progress_line,
)
from services.autotuner.step_test import run_step_test
from services.launcher import free_tcp_port, start_service, stop_service
from shared.errors import ConfigError
from shared.session import ZenohSettings, open_session

HELP = "run the demo: a simulated plant as its own process, tested over Zenoh on loopback"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--plant", metavar="FILE", help="your own plant file (default: presets)")
    parser.add_argument("--loop", default="hx1", help="loop to test (default: %(default)s)")
    parser.add_argument("--seed", type=int, help="noise seed for the plant")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    add_step_options(parser)


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    if args.plant and not os.path.isfile(args.plant):
        raise ConfigError(f"--plant {args.plant}: no such file")
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    prefix = f"autotune/demo{os.getpid()}"
    plant_args = ["--prefix", prefix, "-l", endpoint, "--no-multicast-scouting"]
    if args.plant:
        plant_args += ["--plant", args.plant]
    if args.seed is not None:
        plant_args += ["--seed", str(args.seed)]
    with tempfile.TemporaryFile("w+") as plant_log:
        plant = start_service("services.plant_sim", plant_args, stderr=plant_log)
        try:
            settings = ZenohSettings(
                mode="peer",
                connect=(endpoint,),
                cfg=("connect/timeout_ms:10000",),
                no_multicast_scouting=True,
            )
            with open_session(settings) as session:
                try:
                    wait_for_loop(session, prefix, args.loop, timeout=15.0)
                except Exception:
                    if plant.poll() is not None:
                        plant_log.seek(0)
                        raise ConfigError(
                            "the plant did not start:\n" + plant_log.read().strip()
                        ) from None
                    raise
                if not args.json:
                    print(
                        f"plant_sim started (pid {plant.pid}, {endpoint}); step test of "
                        f"{args.loop}…",
                        file=sys.stderr,
                    )
                with LoopClient(session, prefix, args.loop, source="autotune-demo") as client:
                    report = run_step_test(client, config, None if args.json else progress_line)
        finally:
            code = stop_service(plant)
    if sys.stderr.isatty() and not args.json:
        print("\r" + " " * 60 + "\r", end="", file=sys.stderr)
    print(json.dumps(report.to_dict(), indent=2) if args.json else format_report(report))
    if not args.json:
        print(f"plant_sim stopped (exit {code}).", file=sys.stderr)
    return 0
