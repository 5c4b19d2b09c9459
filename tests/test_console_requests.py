"""The console's tune form is validated exactly as ``autotune tune``'s flags: the same
TuneRequest for the same values, and the same refusal, naming the flag, for a bad one."""

from __future__ import annotations

import pytest

from services.autotuner.commands.tune import request_from_args
from services.cli import build_parser, main
from services.console.requests import SOURCE, flag_names, tune_request
from shared.errors import ConfigError

PREFIX = "autotune"


def cli_request(*argv: str):
    args = build_parser().parse_args(["tune", "hx1", *argv])
    return request_from_args(args, source=SOURCE)


@pytest.mark.parametrize(
    ("fields", "argv"),
    [
        ({}, []),
        (
            {"method": "ramp", "rule": "tl-pid", "aim": "robust", "amplitude": "3.5"},
            ["--method", "ramp", "--rule", "tl-pid", "--aim", "robust", "--amplitude", "3.5"],
        ),
        (
            {"pv-limits": ["40", "80"], "max-time": 900, "no-apply": True, "force": False},
            ["--pv-limits", "40", "80", "--max-time", "900", "--no-apply"],
        ),
        ({"method": "step", "repeat": "auto", "step-size": -4}, ["--method", "step",
         "--repeat", "auto", "--step-size", "-4"]),
        ({"max-op-noise": "4.5"}, ["--max-op-noise", "4.5"]),
    ],
)  # fmt: skip
def test_the_form_gives_the_request_the_cli_gives(fields, argv):
    assert tune_request(PREFIX, "hx1", fields) == cli_request(*argv)


BAD = [
    ({"amplitude": "-1"}, ["--amplitude", "-1"]),
    ({"amplitude": "abc"}, ["--amplitude", "abc"]),
    ({"method": "sine"}, ["--method", "sine"]),
    ({"rule": "nonsense"}, ["--rule", "nonsense"]),
    ({"cycles": "1"}, ["--cycles", "1"]),
    ({"max-time": "-5"}, ["--max-time", "-5"]),
    ({"pv-limits": ["80", "40"]}, ["--pv-limits", "80", "40"]),
    ({"step-size": "0"}, ["--step-size", "0"]),
    ({"max-overshoot": "nan"}, ["--max-overshoot", "nan"]),
    ({"max-op-noise": "0"}, ["--max-op-noise", "0"]),
    # negative numbers in exponent form are values, refused by their bound (argparse took
    # them for flags: "--amplitude: expected one argument"; helper trial)
    ({"amplitude": "-1e3"}, ["--amplitude", "-1e3"]),
    ({"max-time": "-1E3"}, ["--max-time", "-1E3"]),
    ({"amplitude": "-inf"}, ["--amplitude", "-inf"]),
]


def test_a_negative_exponent_is_the_flags_value_and_its_bound_says_why():
    with pytest.raises(ConfigError) as refused:
        tune_request(PREFIX, "hx1", {"amplitude": "-1e3"})
    assert "expected one argument" not in str(refused.value)
    assert str(refused.value).startswith("--amplitude")


@pytest.mark.parametrize(("fields", "argv"), BAD)
def test_a_bad_value_is_refused_with_the_cli_s_own_line(fields, argv, capsys):
    with pytest.raises(ConfigError) as refused:
        tune_request(PREFIX, "hx1", fields)
    try:  # the CLI refuses before it opens a session: nothing is sent either way
        code = main(["tune", "hx1", *argv, "--wait", "1"])
    except SystemExit as stop:  # argparse's own refusal
        code = stop.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(refused.value) in err, (str(refused.value), err)


@pytest.mark.parametrize(
    ("loop", "fields", "says"),
    [
        ("hx 1", {}, "loop id 'hx 1' is not valid"),
        (None, {}, "loop: None is not a loop id"),
        ("hx1", ["--method"], "tune: the form's fields must be an object of flag names"),
        ("hx1", {"bogus": 1}, "unrecognized arguments: --bogus"),
        ("hx1", {"wait": 1}, "--wait: not a flag the console's form sends"),
        ("hx1", {"amplitude": {"x": 1}}, "--amplitude: {'x': 1} is not a value"),
        ("hx1", {"amplitude": float("inf")}, "--amplitude: inf is not a finite number"),
    ],
)
def test_what_is_not_a_form_is_refused_in_one_line(loop, fields, says):
    with pytest.raises(ConfigError, match="^" + says.replace("(", r"\(").replace("[", r"\[")):
        tune_request(PREFIX, loop, fields)


def test_the_form_s_flags_are_the_tune_command_s():
    names = flag_names()
    assert {"method", "rule", "aim", "amplitude", "pv-limits", "max-time", "no-apply"} <= set(names)
    assert not {"json", "wait", "detach", "node", "prefix"} & set(names)
