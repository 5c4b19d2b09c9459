"""Every command's flags are judged before anything is opened or sent: NaN, ±inf, negative,
zero and huge numbers, wrong types, bad paths and ids each end in one line on stderr and exit
code 2, with no bus (a Zenoh session or a child process here fails the test). Most cases run
in-process through the CLI's entry point; a handful through real interpreters, at once."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]


class Opened(BaseException):
    """Raised by anything that would reach the bus or start a process: not an Exception, so
    no handler in the product can take it for an error of its own."""


@pytest.fixture
def no_bus(monkeypatch):
    import zenoh

    def refuse(*_a, **_k):
        raise Opened("a session or a process was started before the flags were judged")

    monkeypatch.setattr(zenoh, "open", refuse)
    monkeypatch.setattr(subprocess, "Popen", refuse)


def run_cli(capsys, argv: list[str]) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as stop:  # argparse's own refusals
        code = stop.code
    out = capsys.readouterr()
    return code, out.err


def one_line_refusal(code: int, err: str, argv: list[str], *needles: str) -> None:
    assert code == 2, (argv, code, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, (argv, err)
    for n in needles:
        assert n in err, (argv, n, err)


# The positional arguments each command needs to get as far as its flags.
POSITIONALS = {
    "health": ["plant"],
    "step": ["hx1"],
    "tune": ["hx1"],
    "replay": ["run.mcap"],
    "analyze": ["run.mcap"],
    "report": ["run.mcap"],
    "recover": ["run.mcap", "-o", "fixed.mcap"],
    "runs": ["runs"],
    "apply": ["r1"],
    "revert": ["hx1"],
    "history": ["hx1"],
    "loops": [],
    "set": ["hx1"],
    "watch": ["hx1"],
    "model": ["check", "plant.toml"],
}


def numeric_flags() -> list[tuple[str, str, type, int]]:
    """(command, flag, type, nargs) of every numeric flag of every command, from the parser
    itself: a flag added tomorrow is swept too."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    out = []
    for name, sp in sub.choices.items():
        for a in sp._actions:
            if a.type in (int, float):
                flag = next(o for o in a.option_strings if o.startswith("--"))
                out.append((name, flag, a.type, a.nargs if isinstance(a.nargs, int) else 1))
    return out


def test_every_numeric_flag_refuses_nan_and_infinities(no_bus, capsys):
    cases = 0
    for command, flag, _kind, nargs in numeric_flags():
        for bad in ("nan", "inf", "-inf", "1e999"):
            for where in range(nargs):  # each value of a LO HI pair in turn
                values = ["1"] * nargs
                values[where] = bad
                argv = [command, *POSITIONALS.get(command, []), flag, *values]
                code, err = run_cli(capsys, argv)
                # a float flag says which flag and that it must be finite; an int flag's
                # parser already refuses the text
                one_line_refusal(code, err, argv, flag)
                cases += 1
    print(f"nan/inf sweep: {cases} cases")
    assert cases > 150


# (argv, needles): each must be refused before anything starts. Bounds are the product's
# promises (README), not read from the code under test.
REFUSED = [
    (["plant", "--speed", "1e12"], ["--speed", "at most"]),
    (["plant", "--speed", "0"], ["--speed", "> 0"]),
    (["plant", "--speed", "-5"], ["--speed"]),
    (["plant", "--speed", "1e308"], ["--speed"]),
    (["plant", "--noise-std", "-0.1"], ["--noise-std", "≥ 0"]),
    (["plant", "--seed", "-1"], ["--seed"]),
    (["plant", "--seed", "1.5"], ["--seed", "invalid int"]),
    (["plant", "--clock", "sundial"], ["--clock", "invalid choice"]),
    (["plant", "--plant", "/no/such/plant.toml"], ["plant file", "cannot read"]),
    (["plant", "--prefix", "a//b"], ["prefix"]),
    (["plant", "--node", "x/y"], ["node"]),
    (["demo", "--speed", "0"], ["--speed"]),
    (["demo", "--speed", "1e12", "--realtime"], ["--speed", "at most"]),
    (["demo", "--noise", "-1"], ["--noise"]),
    (["demo", "--seed", "-3"], ["--seed"]),
    (["demo", "--amplitude", "0"], ["--amplitude"]),
    (["demo", "--plant", "/no/such/plant.toml"], ["--plant"]),
    # before, the services started and the demo waited 20 s for a loop that never came up
    (["demo", "--loop", "nope"], ["--loop nope", "it has: hx1, hx2, lvl1, lvl2, flow1"]),
    (["demo", "--plant", "unstable.toml", "--loop", "a"], ["loops.a.den", "open-loop unstable"]),
    # the file's own fault first, whatever the loop: it said "--loop hx1: not a loop of --plant"
    (["demo", "--plant", "unstable.toml"], ["loops.a.den", "open-loop unstable"]),
    (["up", "--speed", "-1"], ["--speed"]),
    (["up", "--speed", "5000"], ["--speed", "at most"]),
    (["up", "--seed", "-1"], ["--seed"]),
    (["up", "--config", "/no/such/up.toml"], ["--config", "cannot read"]),
    (["up", "--runs", "run.mcap"], ["--runs", "not a directory"]),
    (
        ["up", "--endpoint", "tcp/127.0.0.1:99999"],
        ["--endpoint", "port '99999'"],
    ),  # before any start
    # it said "No such file or directory: /proc/x/runs", not which flag
    (["up", "--runs", "/proc/x/runs"], ["--runs /proc/x/runs: cannot make it"]),
    # it waited 10 s for the loop on the bus first
    (["revert", "hx1", "--steps", "0"], ["--steps 0: must be ≥ 1"]),
    # the plant file is read before anything starts (a stack came up without its plant and
    # blamed the tuner 42 s later)
    (["up", "--plant", "unstable.toml"], ["loops.a.den", "open-loop unstable"]),
    (["step", "hx1", "--size", "0"], ["--size", "zero"]),
    # 1e-9 % read K −26 %/% off a noise-free PV's rounding, 1e-300 % waited past its timeout
    # with the loop held (helper review)
    (["step", "hx1", "--size", "1e-9"], ["--size 1e-09: must be at least 0.01 % in size"]),
    (["step", "hx1", "--size", "-1e-300"], ["--size -1e-300: must be at least 0.01 %"]),
    (["tune", "hx1", "--method", "step", "--step-size", "0.005"], ["--step-size 0.005"]),
    # what the tuner would refuse is refused before anything is sent
    (["tune", "hx1", "--rule", "zn-ol-pi"], ["--rule: zn-ol-pi needs a step test"]),
    (["step", "hx1", "--size", "1e9"], ["--size", "at most"]),
    (["step", "hx1", "--size", "-101"], ["--size"]),
    # a path is no run id ("no run of that id": helper review)
    (["apply", "../x"], ["RUN_ID '../x': not a run id"]),
    # 0 itself is refused: "0–100" said it was allowed (helper review)
    (
        ["step", "hx1", "--max-move", "0"],
        ["--max-move 0.0: must be a % of the range, > 0 and ≤ 100"],
    ),
    (["step", "hx1", "--baseline", "-1"], ["--baseline"]),
    (["step", "hx1", "--timeout", "0"], ["--timeout"]),
    (["step", "hx1", "--timeout", "-5"], ["--timeout"]),
    (["step", "hx1", "--timeout", "1e300"], ["--timeout", "at most"]),
    (["step", "hx1", "--wait", "-1"], ["--wait"]),
    (["step", "hx1", "--pv-limits", "5", "1"], ["--pv-limits", "LO must be below HI"]),
    (["step", "hx1", "--pv-limits", "1", "1"], ["--pv-limits"]),
    (["step", "bad/loop"], ["loop"]),
    (["tune", "hx1", "--wait", "-1"], ["--wait"]),
    (["tune", "hx1", "--wait", "0"], ["--wait"]),
    (["tune", "hx1", "--wait", "1e300"], ["--wait"]),
    (["tune", "hx1", "--amplitude", "-5"], ["--amplitude"]),
    (["tune", "hx1", "--amplitude", "1e9"], ["--amplitude"]),
    (["tune", "hx1", "--hysteresis", "-1"], ["--hysteresis"]),
    # the flag as the user typed it, not its alias (it named --lambda-s: helper trial)
    (["tune", "hx1", "--lambda", "-3"], ["--lambda -3: must be > 0 s"]),
    (["tune", "hx1", "--relay-bias", "2"], ["--relay-bias"]),
    (["tune", "hx1", "--cycles", "0"], ["--cycles"]),
    (["tune", "hx1", "--cycles", "100000"], ["--cycles"]),
    (["tune", "hx1", "--tolerance", "0"], ["--tolerance"]),
    (["tune", "hx1", "--tolerance", "-1"], ["--tolerance"]),
    (["tune", "hx1", "--bump", "0"], ["--bump"]),
    (["tune", "hx1", "--kc-start", "-1"], ["--kc-start"]),
    (["tune", "hx1", "--step-size", "0"], ["--step-size"]),
    (["tune", "hx1", "--step-size", "500"], ["--step-size"]),
    (["tune", "hx1", "--max-time", "0"], ["--max-time"]),
    (["tune", "hx1", "--max-time", "1e300"], ["--max-time"]),
    (["tune", "hx1", "--rest-window", "-3"], ["--rest-window"]),
    (["tune", "hx1", "--ms-bound", "0.5"], ["--ms-bound"]),
    (["tune", "hx1", "--max-overshoot", "-1"], ["--max-overshoot"]),
    (["tune", "hx1", "--max-decay-ratio", "0"], ["--max-decay-ratio"]),
    (["tune", "hx1", "--overshoot-miss", "0"], ["--overshoot-miss"]),
    (["tune", "hx1", "--pv-limits", "100", "0"], ["--pv-limits", "LO must be below HI"]),
    (["tune", "hx1", "--rule", "zn-banana"], ["--rule", "invalid choice"]),
    (["tune", "hx1", "--method", "guess"], ["--method", "invalid choice"]),
    (["tune", "not a loop"], ["loop"]),
    (["health", "plant", "--timeout", "-1"], ["--timeout"]),
    (["health", "plant", "--timeout", "0"], ["--timeout"]),
    (["health", "plant", "--node", "a/b"], ["node"]),
    (["health", "nothing"], ["invalid choice"]),
    (["logger", "--runs", "run.mcap"], ["--runs", "not a directory"]),
    (["logger", "--runs", "run.mcap/sub"], ["--runs", "not a directory"]),
    (["logger", "--runs", ""], ["--runs '': must name a directory"]),
    (["logger", "--prefix", ""], ["prefix"]),
    (["replay", "run.mcap", "--rate", "0"], ["--rate"]),
    (["replay", "run.mcap", "--rate", "-2"], ["--rate"]),
    (["replay", "run.mcap", "--start-offset", "-1"], ["--start-offset"]),
    (["replay", "run.mcap", "--wait", "-1"], ["--wait"]),
    (["report", "run.mcap", "--dpi", "0"], ["--dpi"]),
    (["report", "run.mcap", "--dpi", "-100"], ["--dpi"]),
    (["report", "run.mcap", "--dpi", "1000000"], ["--dpi", "at most"]),
    (["report", "run.mcap", "--dpi", "1.5"], ["--dpi", "invalid int"]),
    (["report", "run.mcap", "-o", "figure.txt"], ["-o", ".png"]),
    (["report", "/no/such/run.mcap", "-o", "r.png"], ["no such file"]),
    (["analyze", "/no/such/run.mcap"], ["no such file"]),
    (["analyze", "run.mcap", "--rule", "zn-banana"], ["--rule", "invalid choice"]),
    (["recover", "/no/such/run.mcap", "-o", "fixed.mcap"], ["no such file"]),
    (["recover", "run.mcap"], ["-o", "required"]),
    (["runs", "/no/such/dir"], ["no such directory"]),
    (["runs", "run.mcap"], ["not a directory"]),  # a file there, not a runs directory
    (["benchmark", "--seed", "-1"], ["--seed"]),
    (["benchmark", "--noise", "2"], ["--noise"]),
    (["benchmark", "--noise", "abc"], ["--noise"]),
    (["benchmark", "--ratios", "-1"], ["--ratios"]),
    (["benchmark", "--methods", "guess"], ["--methods"]),
    (["benchmark", "--plants", "no plant has this name"], ["--plants"]),
    (["benchmark", "--plot", "figs"], ["--plot", "only with --iinoya-hotta"]),
    (["benchmark", "--measure", "1"], ["--measure", "only with --iinoya-hotta"]),
    (["benchmark", "--iinoya-hotta", "--measure", "1000"], ["--measure"]),
    (["benchmark", "--iinoya-hotta", "--measure", "0"], ["--measure"]),
    (["benchmark", "--iinoya-hotta", "--measure", "nan"], ["--measure"]),
    (["benchmark", "--iinoya-hotta", "--measure", "one"], ["--measure"]),
    (["benchmark", "--iinoya-hotta", "--ratios", "inf"], ["--ratios"]),
    (["benchmark", "--iinoya-hotta", "--ratios", "", "--measure", ""], ["--ratios"]),
    (["benchmark", "--iinoya-hotta", "--plot", ""], ["--plot"]),
    (["benchmark", "--iinoya-hotta", "--plot", "run.mcap"], ["--plot", "not a directory"]),
    (["tuner", "--lease-timeout", "0"], ["--lease-timeout"]),
    (["router", "-l", "not-an-endpoint"], ["-l"]),
    (["plant", "-e", "nowhere"], ["-e"]),
    (["plant", "--cfg", "novalue"], ["--cfg"]),
    (["plant", "-c", "/no/such/zenoh.json5"], ["zenoh config"]),
    (["plant", "-m", "satellite"], ["--mode", "invalid choice"]),
    (["plant", "--no-such-flag"], ["unrecognized arguments"]),
    # named by the command it was given to, as the command's other refusals are
    (["tune", "hx1", "--bogus"], ["autotune tune: error: unrecognized arguments: --bogus"]),
    (["runs", "runs", "--prefix", "x"], ["autotune runs: error: unrecognized", "--prefix x"]),
    (["no-such-command"], ["invalid choice"]),
    (["--bogus", "tune"], ["autotune: error: unrecognized arguments: --bogus"]),
    ([], ["required"]),
]


@pytest.mark.parametrize(("argv", "needles"), REFUSED, ids=[" ".join(a) for a, _ in REFUSED])
def test_bad_flags_are_refused_in_one_line_before_anything_starts(
    no_bus, capsys, tmp_path, monkeypatch, argv, needles
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.mcap").write_bytes(b"")  # the commands' files exist; flags are judged
    (tmp_path / "unstable.toml").write_text(
        '[loops.a]\nmodel = "transfer_function"\nnum = [1.0]\nden = [1.0, -1.0]\n'
        "sample_time = 0.1\n"
    )
    code, err = run_cli(capsys, argv)
    one_line_refusal(code, err, argv, *needles)


def test_a_bad_zenoh_flag_names_itself_and_the_file_flags_their_path(no_bus, capsys, tmp_path):
    """What only opening a session would tell still comes as one line (the config is built,
    and refused, before any connection)."""
    bad = tmp_path / "z.json5"
    bad.write_text("{ this is not json5")
    code, err = run_cli(capsys, ["health", "plant", "-c", str(bad)])
    one_line_refusal(code, err, ["-c"], str(bad))
    code, err = run_cli(capsys, ["health", "plant", "--cfg", "mode:42"])
    one_line_refusal(code, err, ["--cfg"], "--cfg")
    # a value that is not JSON5: the parser's drawing of it came out with its escapes (1:1\n |…)
    code, err = run_cli(capsys, ["health", "plant", "--cfg", "foo:bar"])
    one_line_refusal(code, err, ["--cfg"], "--cfg 'foo:bar': line 1, column 1: expected array")
    assert "\\" not in err, err
    code, err = run_cli(capsys, ["health", "plant", "--cfg", 'connect/timeout_ms:"x"'])
    one_line_refusal(code, err, ["--cfg"], 'invalid type: string "x", expected i64')
    # an address no socket takes ended in "this client reached no peer or router at all"
    for endpoint, said in (
        ("tcp/127.0.0.1:99999", "port '99999' is not a number within 1–65535"),
        ("tcp/999.0.0.1:7447", "999.0.0.1 is not an IPv4 address"),
        ("tcp/127.0.0.1", "expected tcp/HOST:PORT"),
    ):
        code, err = run_cli(capsys, ["health", "plant", "-e", endpoint])
        one_line_refusal(code, err, ["-e"], f"-e {endpoint!r}: {said}")
    code, err = run_cli(capsys, ["health", "plant", "-l", "tcp/127.0.0.1:0", "--wait", "0.5"])
    assert "port" not in err, err  # listening on port 0: any free port


SUBPROCESS = [
    ["plant", "--speed", "1e12"],
    ["tune", "hx1", "--amplitude", "nan"],
    ["step", "hx1", "--size", "0"],
    ["report", "run.mcap", "--dpi", "0"],
    ["logger", "--runs", "run.mcap"],
    ["demo", "--speed", "inf"],
]


def test_through_real_interpreters_exit_2_one_line_no_traceback(tmp_path):
    (tmp_path / "run.mcap").write_bytes(b"")
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    runs = [(argv, [sys.executable, "-m", "services.cli", *argv]) for argv in SUBPROCESS]
    runs.append((["plant_sim"], [sys.executable, "-m", "services.plant_sim", "--speed", "1e12"]))
    procs = [
        (
            argv,
            subprocess.Popen(
                cmd,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                cwd=tmp_path,
                env=env,
            ),
        )
        for argv, cmd in runs
    ]
    for argv, proc in procs:  # started together: each is an interpreter's start-up
        out, err = proc.communicate(timeout=60)
        one_line_refusal(proc.returncode, err, argv, "error:")
        assert out == "", (argv, out)


def test_ctrl_c_while_the_modules_load_is_one_line(monkeypatch, capsys):
    """The console script's first step imports numpy, scipy and Zenoh: a Ctrl-C there printed
    a traceback through the imports (noticed last stop); it is one line and exit 130."""
    import builtins

    from services.entry import entry

    real = builtins.__import__

    def interrupted(name, globals=None, locals=None, fromlist=(), level=0):
        if name == "services" and fromlist and "cli" in fromlist:
            raise KeyboardInterrupt
        return real(name, globals, locals, fromlist, level)

    def leave(code: int) -> None:  # os._exit, as a SystemExit this test can see
        raise SystemExit(code)

    monkeypatch.setattr(builtins, "__import__", interrupted)
    monkeypatch.setattr(os, "_exit", leave)
    with pytest.raises(SystemExit) as stop:
        entry()
    assert stop.value.code == 130
    assert capsys.readouterr().err == "autotune: interrupted\n"


@pytest.mark.parametrize("delay", [0.5, 1.0])
def test_ctrl_c_early_in_python_m_services_cli_is_one_line(delay):
    """``python -m services.cli`` (the developer's path) loads as the console script does:
    a Ctrl-C within its first second (numpy, scipy, Zenoh loading) printed a traceback
    through the imports, 5 of 5 in a user's trial; now one line and exit 130."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "loops", "--prefix", "early"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(delay)  # the fault itself: a Ctrl-C this long after the start
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert err.strip().endswith("interrupted"), err


@pytest.mark.parametrize("delay", [0.2, 0.6])
def test_ctrl_c_early_in_python_m_services_plant_sim_is_one_line(delay):
    """``python -m services.plant_sim`` imports scipy and loads its plant file before it
    serves: a Ctrl-C then printed a traceback through the imports and died by SIGINT (-2);
    now one line and exit 130, or, once it serves, its clean stop (exit 0)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.plant_sim", "--prefix", f"early{os.getpid()}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert "Traceback" not in err, err
    if proc.returncode == 130:
        assert err == "autotune: interrupted\n", err
    else:
        assert proc.returncode == 0 and "stopped" in err, (proc.returncode, err)


# a Ctrl-C as pydantic builds the first validator after ``entry`` starts, its
# KeyboardInterrupt coming out as another exception (pydantic-core's SchemaError "… literal
# validator: KeyboardInterrupt" did, through ``except KeyboardInterrupt``: a CI run's
# traceback, exit 1)
_WRAPPED_CTRL_C = """
import os, signal, sys, time
from pydantic._internal import _model_construction as mc

real = mc.create_schema_validator

def interrupted(*args, **kwargs):
    mc.create_schema_validator = real
    try:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.5)
    except KeyboardInterrupt:
        raise RuntimeError("Error building 'literal' validator: KeyboardInterrupt") from None
    return real(*args, **kwargs)

mc.create_schema_validator = interrupted
sys.argv = ["autotune", "loops", "--prefix", "early"]
from services.entry import entry
entry()
"""


def test_ctrl_c_that_a_library_wraps_while_the_modules_load_is_one_line():
    proc = subprocess.run(
        [sys.executable, "-c", _WRAPPED_CTRL_C], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 130 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr == "autotune: interrupted\n", proc.stderr


def test_a_reader_that_leaves_the_pipe_early_is_no_error(monkeypatch):
    """``autotune … | head -1``: it printed "error: Broken pipe" (noticed last stop); now
    silent, exit 141 as a shell reports for any writer whose reader left."""
    import io

    class Left(io.StringIO):
        def write(self, s):
            raise BrokenPipeError(32, "Broken pipe")

    err = io.StringIO()
    monkeypatch.setattr(sys, "stdout", Left())
    monkeypatch.setattr(sys, "stderr", err)
    plant = ROOT / "services" / "plant_sim" / "plants" / "default.toml"
    assert main(["model", "check", str(plant), "--loop", "flow1"]) == 141
    assert err.getvalue() == ""


def test_up_on_an_endpoint_something_listens_on_is_one_line(no_bus, capsys, tmp_path):
    """`up --endpoint` on a port another stack held: 8 lines, exit 1, and its tuner and
    logger joined the other stack's bus for a second (two tuners of one name; helper trial)."""
    import socket

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        endpoint = f"tcp/127.0.0.1:{held.getsockname()[1]}"
        argv = ["up", "--endpoint", endpoint, "--runs", str(tmp_path / "runs")]
        code, err = run_cli(capsys, argv)
    one_line_refusal(code, err, argv, f"--endpoint {endpoint}", "another stack")
