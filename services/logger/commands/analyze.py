"""``autotune analyze RUN.mcap [--rule RULE] [--json]``: re-identify a recorded run offline
through the live tuner's code; the gains of any rule without a new experiment."""

from __future__ import annotations

import argparse

from services.autotuner.design.rules import RULES
from services.logger.analysis import EndedEarly, analyze_file, dumps, format_analysis
from shared import json_text
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
    try:
        a = analyze_file(args.file)
    except EndedEarly as ended:
        if not ended.matches_live():  # not the live run's end: the record is not the run's
            raise
        # re-run to the live run's own abort: the file is fine, and that is its analysis (an
        # aborted run gave exit 2 and, with --json, nothing: helper trial)
        if args.json:
            print(json_text.dumps(ended.to_dict(), indent=2))
        elif ended.stopped_by_run:
            print(
                f"{ended.path}: {ended.method} test of {ended.loop}, re-run offline on the "
                f"record: the live run stopped the test before it found anything "
                f"({ended.live.status}: {ended.reason}), and the record ends there"
            )
        else:
            print(
                f"{ended.path}: {ended.method} test of {ended.loop}, re-run offline: it ends "
                f"as the live run did (identical), aborted: {ended.reason}"
            )
        return 0
    if args.rule and args.rule not in a.gains:  # it printed an empty table, exit 0
        given = ", ".join(a.gains) or "none"
        raise AutotuneError(
            f"--rule {args.rule}: not given by this {a.method} test's findings (it gives: {given})"
        )
    print(dumps(a, args.rule) if args.json else format_analysis(a, args.rule))
    return 0
