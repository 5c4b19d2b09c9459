"""A tune request from the page, validated exactly as ``autotune tune``'s flags are.

The page sends its form as ``{flag: value}`` (flag names as the CLI spells them without the
leading dashes, e.g. ``"max-overshoot": 25``); they become an argument list for the tune
command's own parser and ``request_from_args``, so a value the CLI refuses is refused here with
the same one line, naming the flag.
"""

from __future__ import annotations

import argparse
import math
from typing import Any, NoReturn

from services.autotuner.commands import tune as tune_command
from shared.cli import NEGATIVE_NUMBER, check_flags, check_ids
from shared.errors import ConfigError, one_line
from shared.messages import TuneRequest

SOURCE = "autotune-console"
# the flags of the form; others (--json, --wait, --detach, the Zenoh flags) are the CLI's own
NOT_FROM_PAGE = {"json", "wait", "detach", "node", "units", "prefix", "verbose"}


class _Parser(argparse.ArgumentParser):
    """The tune command's parser, its refusals raised as ConfigError (one line); a negative
    number in exponent form is a value, as on the CLI (``shared.cli.NEGATIVE_NUMBER``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_NUMBER

    def error(self, message: str) -> NoReturn:
        raise ConfigError(one_line(message, 500))  # as the CLI's OneLineParser


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="tune", add_help=False)
    p.add_argument("loop")
    tune_command.add_tune_options(p)
    return p


def flag_names() -> list[str]:
    """Every flag the form may send (the tune command's experiment, rule and limit flags)."""
    return sorted(
        s[2:]
        for a in _parser()._actions
        for s in a.option_strings
        if s.startswith("--") and s[2:] not in NOT_FROM_PAGE
    )


def _argv(loop: str, fields: dict[str, Any]) -> list[str]:
    argv = [loop]
    for name, value in fields.items():
        if value is None or value is False or value == "":
            continue
        flag = f"--{name}"
        if value is True:
            argv.append(flag)
        elif isinstance(value, list | tuple):
            argv += [flag, *(_text(flag, v) for v in value)]
        else:
            argv += [flag, _text(flag, value)]
    return argv


def _text(flag: str, value: Any) -> str:
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        raise ConfigError(f"{flag}: {value!r} is not a value")
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{flag}: {value!r} is not a finite number")
    return str(value)


def tune_request(prefix: str, loop: Any, fields: Any) -> TuneRequest:
    """The TuneRequest of the page's form; ConfigError with one line naming the flag."""
    if not isinstance(loop, str):
        raise ConfigError(f"loop: {loop!r} is not a loop id")
    if not isinstance(fields, dict) or not all(isinstance(k, str) for k in fields):
        raise ConfigError("tune: the form's fields must be an object of flag names")
    check_ids(prefix, loop=loop)
    unknown = sorted(k for k in fields if k in NOT_FROM_PAGE or k.startswith("-"))
    if unknown:
        raise ConfigError(f"--{unknown[0].lstrip('-')}: not a flag the console's form sends")
    args = _parser().parse_args(_argv(loop, fields))
    check_flags("tune", args)  # the bounds the CLI checks before it sends anything
    return tune_command.request_from_args(args, source=SOURCE)
