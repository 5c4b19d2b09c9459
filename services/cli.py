"""The ``autotune`` command: one entry point, a subcommand per job."""

from __future__ import annotations

import argparse
import sys

from services import demo, health, router, up
from services.autotuner import benchmark_command, step_command, tune_command
from services.autotuner import service as tuner_service
from services.logger import (
    analyze_command,
    recover_command,
    replay_command,
    report,
    runs_command,
)
from services.logger import service as logger_service
from services.plant_sim import service as plant_service
from shared.errors import AutotuneError

SUBCOMMANDS = {
    "demo": demo,
    "up": up,
    "router": router,
    "health": health,
    "plant": plant_service,
    "step": step_command,
    "tuner": tuner_service,
    "tune": tune_command,
    "logger": logger_service,
    "runs": runs_command,
    "replay": replay_command,
    "analyze": analyze_command,
    "report": report,
    "recover": recover_command,
    "benchmark": benchmark_command,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="autotune",
        description="PID auto-tuning against simulated process plants, over Eclipse Zenoh.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, module in SUBCOMMANDS.items():
        p = sub.add_parser(
            name,
            help=module.HELP,
            description=module.__doc__,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(p)
        p.set_defaults(run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except AutotuneError as err:
        print(f"autotune {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"autotune {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
