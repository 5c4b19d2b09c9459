"""Command-line pieces every service and client shares: flags, logging, clean stops, ids."""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import re
import signal
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

from shared import keys
from shared.control.forms import MIN_STEP
from shared.errors import ConfigError, one_line
from shared.session import add_zenoh_arguments

# a value that is a negative number, as argparse should see it: its own pattern takes -5 and
# -.5 but not -1e3 or -inf, which it then reads as flags ("--amplitude -1e3": "expected one
# argument", where the bound's own refusal says what is wrong; helper trial)
NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-inf(inity)?$", re.IGNORECASE)


class OneLineParser(argparse.ArgumentParser):
    """argparse whose errors are one line (the usage is what --help is for); its subparsers
    are of this class too. A negative number in exponent form (or -inf) is a value."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self._negative_number_matcher = NEGATIVE_NUMBER

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {one_line(message, 500)} (see {self.prog} --help)\n")


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    """``--prefix``, ``-v`` and the Zenoh flags (``-m -e -l -c --cfg --no-multicast-scouting``)."""
    parser.add_argument(
        "--prefix",
        default=keys.DEFAULT_PREFIX,
        help="root of every key expression (default: %(default)s)",
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)"
    )
    add_zenoh_arguments(parser)


def setup_logging(verbose: int, name: str) -> None:
    level = logging.WARNING if verbose <= 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format=f"%(asctime)s {name} %(levelname)s %(message)s")


def install_stop_handlers(stop: threading.Event) -> None:
    """SIGINT and SIGTERM end a service cleanly (tokens withdrawn, session closed).

    The handler hands ``stop.set()`` to a thread: run in the handler itself it could
    deadlock, because the main thread may be inside ``stop.wait()`` holding the event's
    (non-reentrant) lock when the signal is handled.
    """

    def handler(*_: object) -> None:
        threading.Thread(target=stop.set, daemon=True).start()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    watch_parent(stop)


# set by ``launcher.start_service`` in a service it starts: the pid of the process that
# started it (``autotune up``, ``demo``, ``perf``, a test), which stops it in order
PARENT_ENV = "AUTOTUNE_PARENT_PID"
PARENT_POLL = 1.0  # s between looks at whether that process is still there


def watch_parent(stop: threading.Event) -> None:
    """A service started by another autotune process stops when that process is gone (its
    parent pid changes: re-parented): ``autotune up`` killed with SIGKILL left plant_sim,
    the tuner and the logger running, holding the bus's port. A service started by hand (no
    ``PARENT_ENV``) is not watched: ``nohup autotune plant &`` outlives its shell, as it
    should. (The launcher starts the service's interpreter itself, no wrapper between: a
    parent pid other than the launcher's is the launcher gone, even at start-up.)"""
    expected = os.environ.pop(PARENT_ENV, "")  # not for what this service starts in turn
    if not expected.isdigit():
        return
    parent = int(expected)

    def watch() -> None:
        while os.getppid() == parent:
            if stop.wait(PARENT_POLL):
                return
        logging.getLogger("autotune").warning(
            "the process that started this service (pid %d) is gone: stopping", parent
        )
        stop.set()

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def check_ids(prefix: str, **ids: str) -> None:
    """ConfigError naming the flag when the prefix or an id cannot be a key chunk."""
    try:
        keys.check_prefix(prefix)
        for what, value in ids.items():
            keys.check_id(value, what)
    except ValueError as err:
        raise ConfigError(str(err)) from None


def check_tuner_node(node: str) -> None:
    """ConfigError naming ``--node`` unless it is a tuner's id, or one with ``*`` wildcards
    (``*``: any tuner): ``--node ""`` made the key ``tuner//alive`` (exit 70)."""
    try:
        keys.check_id(node.replace("*", "x"), "--node: tuner")
    except ValueError as err:
        raise ConfigError(str(err)) from None


MAX_SPEED = 1000.0  # realtime speed-up: beyond, the wall clock cannot pace the samples
MAX_SECONDS = 1e7  # any duration given on the command line (115 days)


@dataclass(frozen=True)
class Bound:
    """What a numeric flag accepts: ``low`` (refused itself when ``low_open``) to ``high``;
    ``nonzero`` refuses 0, and ``least`` any value smaller in size; ``why`` says why ``high``
    is the limit."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    nonzero: bool = False
    least: float | None = None
    unit: str = ""
    why: str = ""


_SECONDS = Bound(0.0, MAX_SECONDS, low_open=True, unit="s")
_SEED = Bound(0)
_SPEED = Bound(
    0.0,
    MAX_SPEED,
    low_open=True,
    why="beyond it the wall clock cannot pace the samples: use the lockstep clock, which "
    "runs as fast as the loop allows",
)
_TUNE = {
    "step_size": Bound(-100.0, 100.0, nonzero=True, least=MIN_STEP, unit="%"),
    "max_time": _SECONDS,
    "rest_window": _SECONDS,
    "hysteresis": Bound(0.0),
    "bump": Bound(0.0, low_open=True),
    "kc_start": Bound(0.0, low_open=True),
    "lambda_s": _SECONDS,
}

# Per command: every numeric flag's bounds (NaN and ±inf are refused for every flag anyway).
FLAG_BOUNDS: dict[str, dict[str, Bound]] = {
    "plant": {"seed": _SEED, "noise_std": Bound(0.0), "speed": _SPEED},
    "demo": {**_TUNE, "seed": _SEED, "noise": Bound(0.0), "speed": _SPEED},
    "up": {"seed": _SEED, "speed": _SPEED},
    "step": {
        "size": Bound(-100.0, 100.0, nonzero=True, least=MIN_STEP, unit="%"),
        "baseline": Bound(0.0, MAX_SECONDS, unit="s"),
        "timeout": _SECONDS,
        "wait": _SECONDS,
    },
    "tune": {**_TUNE, "wait": _SECONDS},
    "health": {"timeout": _SECONDS},
    "replay": {
        "rate": Bound(0.0, low_open=True),
        "start_offset": Bound(0.0, unit="s"),
        "wait": Bound(0.0, MAX_SECONDS, unit="s"),
    },
    "report": {"dpi": Bound(10, 1200, why="the page is about 13 × 23 inches")},
    "benchmark": {"seed": _SEED},
}
ORDERED_PAIRS = ("pv_limits",)  # LO HI flags: LO must be below HI


# flags whose name is not their destination's (``--lambda``, also ``--lambda-s``)
FLAG_NAMES = {"lambda_s": "--lambda"}


def flag_name(dest: str) -> str:
    return FLAG_NAMES.get(dest, "--" + dest.replace("_", "-"))


def _check_number(flag: str, value: float, bound: Bound | None) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{flag} {value}: must be a finite number")
    if bound is None:
        return
    unit = f" {bound.unit}" if bound.unit else ""
    if bound.low is not None and (value <= bound.low if bound.low_open else value < bound.low):
        op = ">" if bound.low_open else "≥"
        raise ConfigError(f"{flag} {value:g}: must be {op} {bound.low:g}{unit}")
    if bound.high is not None and value > bound.high:
        why = f" ({bound.why})" if bound.why else ""
        raise ConfigError(f"{flag} {value:g}: must be at most {bound.high:g}{unit}{why}")
    if bound.nonzero and value == 0:
        raise ConfigError(f"{flag} 0: must not be zero")
    if bound.least is not None and abs(value) < bound.least:
        raise ConfigError(f"{flag} {value:g}: must be at least {bound.least:g}{unit} in size")


def check_flags(command: str, args: argparse.Namespace) -> None:
    """ConfigError naming the first numeric flag of ``command`` that is NaN, infinite, or out
    of its bounds (FLAG_BOUNDS): called before anything is opened or sent."""
    bounds = FLAG_BOUNDS.get(command, {})
    for dest, value in vars(args).items():
        values = value if isinstance(value, list | tuple) else [value]
        numbers = [v for v in values if isinstance(v, int | float) and not isinstance(v, bool)]
        for v in numbers:
            _check_number(flag_name(dest), v, bounds.get(dest))
        if dest in ORDERED_PAIRS and len(numbers) == 2 and not numbers[0] < numbers[1]:
            lo, hi = numbers
            raise ConfigError(f"{flag_name(dest)} {lo:g} {hi:g}: LO must be below HI")


def check_runs_dir(flag: str, path: str) -> None:
    """ConfigError unless ``path`` is a directory we may write into, or one that can be made
    (its nearest existing ancestor is a writable directory); an empty one names none (the
    logger's ``--runs ""`` recorded into the directory it ran in)."""
    if not path.strip():
        raise ConfigError(f"{flag} {path!r}: must name a directory")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{flag} {path}: exists and is not a directory")
    probe = p
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise ConfigError(f"{flag} {path}: {probe} is not a directory")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag} {path}: {probe} is not writable")


def exit_now(code: int | str | None) -> None:
    """Leave the process with ``code`` once its output is flushed, without the interpreter's
    teardown: every session is closed by then, and Zenoh's native threads, caught between
    callbacks as Python finalises, could otherwise abort the process (SIGABRT, "exception not
    rethrown") after a clean run — an exit code a script would read as a crash."""
    if isinstance(code, str):  # SystemExit("message"): printed, exit 1 as Python does
        print(code, file=sys.stderr)
        code = 1
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe: nothing more to say
            stream.flush()
    os._exit(code if isinstance(code, int) else 0)
