"""The ``autotune`` command: one entry point, a subcommand per job.

Bad input never traces back: a wrong flag (argparse's own complaint, or a number out of its
bounds, checked here before any command opens a session or sends anything) and every error a
command raises as AutotuneError or OSError end in one line on stderr and exit code 2.
Anything else is a bug: one line too, exit 70, and the traceback only with AUTOTUNE_DEBUG=1.
"""

from __future__ import annotations

if __name__ == "__main__":  # `python -m services.cli` runs as the console script does: Ctrl-C
    # while the modules below load (seconds on a busy machine) ends in one line, exit 130
    from services.entry import entry as _console

    _console()  # imports this module under its own name and runs it; never returns

import argparse
import contextlib
import importlib
import os
import signal
import sys
import traceback
import warnings
from types import ModuleType

from services.entry import quit_while_loading
from shared.cli import OneLineParser, check_flags, check_runs_dir, exit_now
from shared.errors import AutotuneError, one_line

# each subcommand's module, imported only when it is the one run (or for `autotune --help`):
# a service or a small command does not load what the others need (scipy's fits, the
# console, the benchmarks); the plant started in 0.5 s instead of 1.2, the logger in 0.3 s
SUBCOMMANDS = {
    "demo": "services.demo",
    "up": "services.up",
    "router": "services.router",
    "health": "services.health",
    "plant": "services.plant_sim.service",
    "model": "services.plant_sim.commands.model_check",
    "loops": "services.autotuner.commands.loops",
    "set": "services.autotuner.commands.set_loop",
    "step": "services.autotuner.commands.step",
    "tuner": "services.autotuner.service",
    "tune": "services.autotuner.commands.tune",
    "watch": "services.autotuner.commands.watch",
    "apply": "services.autotuner.commands.apply",
    "revert": "services.autotuner.commands.revert",
    "logger": "services.logger.service",
    "runs": "services.logger.commands.runs",
    "history": "services.logger.commands.history",
    "replay": "services.logger.commands.replay",
    "analyze": "services.logger.commands.analyze",
    "report": "services.logger.report",
    "recover": "services.logger.commands.recover",
    "benchmark": "services.offline.benchmark_command",
    "wall-times": "services.offline.wall_times",
    "perf": "services.offline.perf_command",
    "console": "services.console.command",
}


def subcommand(name: str) -> ModuleType:
    """The module of subcommand ``name`` (its ``HELP``, ``add_arguments`` and ``run``)."""
    return importlib.import_module(SUBCOMMANDS[name])


class Refused(SystemExit):
    """A command's refusal by ``SystemExit(message)``, already printed: exit code 2 (not
    Python's 1 for a message), the message still its ``str`` for those who catch it."""

    def __init__(self, message: str):
        super().__init__(2)
        self.message = message

    def __str__(self) -> str:
        return self.message


RUNS_WRITERS = ("logger", "demo", "up")  # commands whose --runs is a directory they write
EX_SOFTWARE = 70  # sysexits.h: an internal error
EX_PIPE = 141  # 128 + SIGPIPE: what a shell reports for a writer whose reader left


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``autotune`` parser. Given the command line ``argv``, only the subcommand it names
    (its first word) is loaded and given its flags; the others stay names, never chosen by
    this parse. Without one (``--help``, a misspelt command) every subcommand is loaded."""
    only = argv[0] if argv and argv[0] in SUBCOMMANDS else None
    parser = OneLineParser(
        prog="autotune",
        description="PID auto-tuning against simulated process plants, over Eclipse Zenoh.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        if only is not None and name != only:
            sub.add_parser(name)
            continue
        module = subcommand(name)
        p = sub.add_parser(
            name,
            help=module.HELP,
            description=module.__doc__,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(p)
        p.set_defaults(run=module.run)
    return parser


def check_args(args: argparse.Namespace) -> None:
    """Every flag that can be judged without the bus; ConfigError naming the first bad one."""
    check_flags(args.command, args)
    if args.command in RUNS_WRITERS and getattr(args, "runs", None) is not None:
        check_runs_dir("--runs", args.runs)


def main(argv: list[str] | None = None) -> int:
    if not sys.warnoptions:  # a library's warning is not the user's business (-W shows them)
        warnings.simplefilter("ignore")
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0].startswith("-") and argv[0] not in ("-h", "--help"):
        # argparse would ask for the command and not name the flag it could not place
        print(
            f"autotune: error: unrecognized arguments: {argv[0]} (a command comes first: "
            "see autotune --help)",
            file=sys.stderr,
        )
        return 2
    try:
        args, unknown = build_parser(argv).parse_known_args(argv)
    except KeyboardInterrupt:  # while the command's modules load
        print("autotune: interrupted", file=sys.stderr)
        return 130
    finally:  # loaded: from here a Ctrl-C is the command's to handle (``entry``'s handler off)
        if signal.getsignal(signal.SIGINT) is quit_while_loading:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    name = f"autotune {args.command}"
    if isinstance(getattr(args, "action", None), str):  # `autotune model check`
        name += f" {args.action}"
    if unknown:  # named by the command they were given to, as its other errors are
        print(
            f"{name}: error: unrecognized arguments: {' '.join(unknown)} (see {name} --help)",
            file=sys.stderr,
        )
        return 2
    try:
        check_args(args)
        return args.run(args)
    except AutotuneError as err:
        print(f"{name}: error: {one_line(err, 2000)}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `autotune loops | head -1`: the reader had enough; no error
        with contextlib.suppress(OSError, ValueError, AttributeError):  # no file behind it
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EX_PIPE
    except OSError as err:  # a file or directory named on the command line, at the edge
        where = f": {err.filename}" if err.filename else ""
        print(f"{name}: error: {one_line(err.strerror or err)}{where}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if os.environ.get("AUTOTUNE_DEBUG"):  # where the signal landed
            traceback.print_exc()
        print(f"{name}: interrupted", file=sys.stderr)
        return 130
    except SystemExit as stop:  # a command's own one-line refusal (benchmark's flags)
        if isinstance(stop.code, str):
            print(one_line(stop.code, 2000), file=sys.stderr)
            raise Refused(stop.code) from None
        raise
    except Exception as err:  # a bug: still one line, the traceback on request
        if os.environ.get("AUTOTUNE_DEBUG"):
            traceback.print_exc()
        print(
            f"{name}: internal error (a bug, please report it; AUTOTUNE_DEBUG=1 shows the "
            f"traceback): {type(err).__name__}: {one_line(err)}",
            file=sys.stderr,
        )
        return EX_SOFTWARE


def entry(argv: list[str] | None = None) -> None:
    """The ``autotune`` console script and ``python -m`` entry: ``main`` then ``exit_now``.
    Until the command line is parsed (its command's modules loaded) a Ctrl-C is one line and
    exit 130 at once (``quit_while_loading``), as from the console script's start."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # a service's __main__
        signal.signal(signal.SIGINT, quit_while_loading)
    try:
        code = main(argv)
    except SystemExit as stop:
        code = stop.code
    exit_now(code)


if __name__ == "__main__":
    entry()
