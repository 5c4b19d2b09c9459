"""``autotune analyze RUN.mcap [--rule RULE] [--json]``: re-identify a recorded run offline
through the live tuner's code; the gains of any rule without a new experiment."""

from __future__ import annotations

import argparse

from services.autotuner.design.rules import RULES
from services.logger.analysis import analyze_file, dumps, format_analysis
from shared.errors import AutotuneError

HELP = "re-run identification and tuning rules on a recorded run"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="RUN.mcap")
    parser.add_argument(
        "--rule",
        choices=list(RULES),
        metavar="RULE",
        help=f"show this rule only: {', '.join(RULES)}",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> int:
    a = analyze_file(args.file)
    if args.rule and args.rule not in a.gains:  # it printed an empty table, exit 0
        given = ", ".join(a.gains) or "none"
        raise AutotuneError(
            f"--rule {args.rule}: not given by this {a.method} test's findings (it gives: {given})"
        )
    print(dumps(a, args.rule) if args.json else format_analysis(a, args.rule))
    return 0
