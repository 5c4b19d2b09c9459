"""`autotune loops` and `autotune set` (issue 14, items 1 and 2) against plant_sim running as its
own process, in lockstep on loopback: the CLI runs as a process too.

Acceptance: `set` while a run holds the loop is refused with the reason, naming the holder,
and moves nothing; a bad value (NaN, Kc ≤ 0, Ti ≤ 0, an output outside the limits …) is
refused and moves nothing (read back with `loops --json`, and the plant's count of applied
commands); gains are read back exactly; mode, setpoint and output writes are bumpless, as
the lockstep clock lets the test see sample by sample (the PV held still by the dead time, so
any jump of the output would be the write's own).
"""

from __future__ import annotations

import json
import queue
import subprocess
import threading
import time

import pytest
import zenoh

from services.autotuner.loop_client import LoopClient
from services.cli import main
from shared import keys, wire
from shared.messages import LoopStatus
from shared.session import open_session
from tests.integration.tuning_cli import autotune
from tests.test_loops_set import CONTRACT  # the loops JSON keys, listed once

pytestmark = pytest.mark.integration

KC, TI, TS = 2.0, 30.0, 0.5
PLANT = f"""
seed = 3
[loops.a1]
model = "transfer_function"
num = [1.0]
den = [20.0, 1.0]
delay = 1.0
sample_time = {TS}
noise_std = 0.0
pv_range = [0.0, 200.0]
op_limits = [5.0, 95.0]
pv_units = "degC"
description = "A first-order loop with dead time"
[loops.a1.pid]
kc = {KC}
ti = {TI}

[loops.b1]
model = "transfer_function"
num = [2.0]
den = [10.0, 1.0]
delay = 0.5
sample_time = 0.25
noise_std = 0.0
mode = "auto"
setpoint = 50.0
op_limits = [10.0, 90.0]
pv_units = "m3/h"
description = "A flow in auto"
[loops.b1.pid]
kc = 0.5
ti = 12.0
td = 0.5
beta = 0.75
"""


class Cli:
    """`autotune` against a plant: through the CLI's entry point in this process (each command
    opens a session of its own, as it does in a process), or with ``process=True`` as a
    process of its own (an interpreter's start-up is seconds on a busy machine)."""

    def __init__(self, capsys):
        self.capsys = capsys

    def __call__(self, plant, *argv: str, process: bool = False) -> subprocess.CompletedProcess:
        argv = (*argv, *plant.cli_args())
        if process:
            return autotune(*argv, timeout=120)
        try:
            code = main(list(argv))
        except SystemExit as stop:  # argparse's own refusals
            code = stop.code
        out, err = self.capsys.readouterr()
        return subprocess.CompletedProcess(argv, code, out, err)

    def loops(self, plant, *args: str, process: bool = False):
        run = self(plant, "loops", "--json", *args, process=process)
        assert run.returncode == 0, run.stderr
        return json.loads(run.stdout)

    def set(self, plant, loop: str, *args: str, process: bool = False):
        return self(plant, "set", loop, *args, process=process)


@pytest.fixture
def cli(capsys) -> Cli:
    return Cli(capsys)


def one_line(run: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in run.stderr and len(run.stderr.strip().splitlines()) == 1, run.stderr
    return run.stderr


def accepted(plant, loop: str) -> int:
    """The plant's count of commands applied to ``loop`` (syncs are not counted)."""
    with open_session(plant.client_settings()) as s:
        st = wire.query_one(s, keys.status(plant.prefix, loop), LoopStatus, 10.0)
    assert st is not None
    return st.accepted


class Statuses:
    """Every status the loop publishes, in order, on a queue (every wait bounded)."""

    def __init__(self, session: zenoh.Session, prefix: str, loop: str):
        self.inbox: queue.Queue[LoopStatus] = queue.Queue()
        self.sub = session.declare_subscriber(
            keys.status(prefix, loop), zenoh.handlers.FifoChannel(4096)
        )
        threading.Thread(
            target=lambda: [self.inbox.put(wire.decode_sample(LoopStatus, x)) for x in self.sub],
            daemon=True,
        ).start()

    def wait(self, ok, timeout: float = 60.0) -> LoopStatus:
        """The first status ``ok`` accepts; queue.Empty after ``timeout`` s in all."""
        deadline = time.monotonic() + timeout
        while True:
            st = self.inbox.get(timeout=max(0.0, deadline - time.monotonic()))
            if ok(st):
                return st


def test_loops_lists_every_loop_as_its_faceplate_shows_it(start_plant, cli):
    p = start_plant(PLANT, loops=("a1", "b1"))
    objs = cli.loops(p)
    assert [o["loop"] for o in objs] == ["a1", "b1"]
    assert all(set(o) == CONTRACT for o in objs)
    a1, b1 = objs
    assert a1 == cli.loops(p, "a1")  # lockstep: nothing moved between the two reads
    assert (a1["mode"], a1["sp"], a1["pv"], a1["op"]) == ("manual", 50.0, 50.0, 50.0)
    assert a1["gains"] == {"kc": KC, "ti": TI, "td": 0.0, "n": 10.0, "beta": 1.0}
    # by hand: 2 % per degC on a 200 degC span is 4 % per %, a proportional band of 25 %
    assert a1["gains_percent"] == {"kc": 4.0, "ti": TI, "td": 0.0, "pb": 25.0}
    assert (a1["pv_range"], a1["op_limits"], a1["pv_units"]) == ([0.0, 200.0], [5.0, 95.0], "degC")
    assert (a1["description"], a1["model"]) == (
        "A first-order loop with dead time",
        "transfer_function",
    )
    assert (a1["clock"], a1["sample_time"], a1["t"]) == ("lockstep", TS, 0.0)
    assert (a1["leased_by"], a1["lease_user"], a1["fault"]) == (None, None, None)
    assert a1["node"] == "plant" and a1["action"] == "reverse"
    assert (b1["mode"], b1["sp"]) == ("auto", 50.0)
    assert b1["gains"] == {"kc": 0.5, "ti": 12.0, "td": 0.5, "n": 10.0, "beta": 0.75}
    # 0.5 % per m3/h on the default 0–100 span: 0.5 % per %, PB 200 %
    assert b1["gains_percent"] == {"kc": 0.5, "ti": 12.0, "td": 0.5, "pb": 200.0}
    table = cli(p, "loops", process=True)
    assert table.returncode == 0, table.stderr
    lines = table.stdout.splitlines()
    assert lines[0].split()[:2] == ["loop", "mode"] and len(lines) == 3
    assert lines[1].startswith("a1 ") and lines[1].endswith("A first-order loop with dead time")
    assert lines[2].startswith("b1 ") and " auto " in lines[2]
    missing = cli(p, "loops", "nope", "--json")
    assert missing.returncode == 2 and missing.stdout == ""
    assert "'nope' not found" in one_line(missing) and "a1, b1" in missing.stderr


def test_gains_are_read_back_exactly_and_the_change_is_signed(start_plant, cli):
    p = start_plant(PLANT, loops=("a1",))
    with open_session(p.client_settings()) as s:
        seen = Statuses(s, p.prefix, "a1")
        run = cli.set(p, "a1", "--kc", "3.3", "--td", "1.7", process=True)
        assert run.returncode == 0, run.stderr
        assert "Kc 2 → 3.3, Td 0 s → 1.7 s (Ti 30 s, β 1 kept)  applied" in run.stdout
        # no logger on this bus: the change is not on record, and set says so (a revert
        # with the logger stopped said nothing, and the history blamed no one: helper trial)
        assert run.stderr.startswith(f"warning: no logger is up on {p.prefix}/: this change")
        st = seen.wait(lambda st: st.reason == "gains")
        assert (st.by_source, st.by_user) == ("autotune-set", None)
    gains = cli.loops(p, "a1")["gains"]
    assert gains == {"kc": 3.3, "ti": TI, "td": 1.7, "n": 10.0, "beta": 1.0}
    run = cli.set(p, "a1", "--ti", "none", "--beta", "0.25")
    assert run.returncode == 0, run.stderr
    run = cli.set(p, "a1", "--sp", "50")  # no change of gains: nothing to say of a logger
    assert run.returncode == 0 and run.stderr == "", run.stderr
    assert cli.loops(p, "a1")["gains"] == {
        "kc": 3.3,
        "ti": None,
        "td": 1.7,
        "n": 10.0,
        "beta": 0.25,
    }
    run = cli.set(p, "a1", "--ti", "12.345678901234567", "--kc", "0.1")
    assert run.returncode == 0, run.stderr
    g = cli.loops(p, "a1")["gains"]
    assert (g["kc"], g["ti"], g["td"], g["beta"]) == (0.1, 12.345678901234567, 1.7, 0.25)


def test_mode_setpoint_output_and_gains_writes_are_bumpless(start_plant, cli):
    """a1 rests in manual at OP 50 %, PV 50 (= SP). Its dead time (2 samples) holds the PV at
    exactly 50 for two samples after the output first moves, so whatever the output does in
    them is the PID block's answer to the writes alone."""
    p = start_plant(PLANT, loops=("a1",))
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "a1", source="t") as c:
        run = cli.set(p, "a1", "--mode", "auto", "--sp", "55")
        assert run.returncode == 0, run.stderr
        out = run.stdout.splitlines()
        assert out[1].split()[0] == "setpoint" and out[2].split()[0] == "mode"  # SP first
        o = cli.loops(p, "a1")
        assert (o["mode"], o["sp"], o["op"]) == ("auto", 55.0, 50.0)
        # bumpless switch: no proportional kick Kc·(55 − 50) = 10 %, only the integral's ramp
        (s1,) = c.advance(1)
        assert s1.pv == 50.0 and s1.op == pytest.approx(50.0, abs=1e-12)
        (s2,) = c.advance(1)
        ramp = KC * TS / TI * 5.0
        assert s2.pv == 50.0 and s2.op == pytest.approx(50.0 + ramp, abs=1e-12)
        # a gain change in auto with an error of 5 (P ≠ 0): the output does not move either
        run = cli.set(p, "a1", "--kc", "4", "--ti", "20")
        assert run.returncode == 0, run.stderr
        o = cli.loops(p, "a1")
        assert o["gains"] == {"kc": 4.0, "ti": 20.0, "td": 0.0, "n": 10.0, "beta": 1.0}
        assert o["op"] == s2.op
        (s3,) = c.advance(1)
        assert s3.pv == 50.0 and s3.op == pytest.approx(s2.op, abs=1e-12)
        (s4,) = c.advance(1)  # and the new gains' integral from there: 4·0.5/20·5 per sample
        assert s4.pv == 50.0 and s4.op == pytest.approx(s2.op + 4.0 * TS / 20.0 * 5.0, abs=1e-12)
        # to manual and an output in one call: the mode first, then the output
        run = cli.set(p, "a1", "--mode", "manual", "--op", "40")
        assert run.returncode == 0, run.stderr
        o = cli.loops(p, "a1")
        assert (o["mode"], o["op"], o["sp"]) == ("manual", 40.0, 55.0)
        run = cli.set(p, "a1", "--op", "30", "--sp", "70")  # in manual: no --mode needed
        assert run.returncode == 0, run.stderr
        o = cli.loops(p, "a1")
        assert (o["mode"], o["op"], o["sp"]) == ("manual", 30.0, 70.0)
        (s5,) = c.advance(1)
        assert (s5.mode, s5.op, s5.sp) == ("manual", 30.0, 70.0)


BAD = [  # (loop, flags, what the one line names)
    ("a1", ["--kc", "nan"], "--kc"),
    ("a1", ["--kc", "0"], "--kc"),
    ("a1", ["--kc", "-1"], "--kc"),
    ("a1", ["--ti", "0"], "--ti"),
    ("a1", ["--ti", "inf"], "--ti"),
    ("a1", ["--td", "-1"], "--td"),
    ("a1", ["--beta", "1.5"], "--beta"),
    ("a1", ["--op", "96"], "--op 96: outside the loop's output limits [5, 95] %"),
    ("a1", ["--op", "4.5", "--mode", "auto"], "--op 4.5: outside"),
    ("a1", ["--sp", "200.5"], "--sp 200.5: outside the loop's PV range [0, 200] degC"),
    # 1e9 % per PV unit on a 200 degC span: a proportional band of 5e-8 % (500 is the most)
    ("a1", ["--kc", "1e9", "--mode", "auto"], "--kc 1e+09: 2e+09 % of output per % of span"),
    ("a1", ["--mode", "auto", "--kc", "3", "--op", "nan"], "--op"),
    ("b1", ["--op", "40"], "--op 40: b1 is in auto"),
    ("b1", ["--op", "40", "--mode", "auto"], "--mode manual"),
    ("b1", ["--mode", "manual", "--sp", "55", "--op", "90.5"], "--op 90.5: outside"),
    ("b1", ["--mode", "manual", "--kc", "1", "--sp", "-3"], "--sp -3: outside"),
    ("nope", ["--kc", "1", "--timeout", "1"], "'nope' not found"),
    ("nope", ["--kc", "1", "--timeout", "1"], "are a1, b1"),  # the loops there, named
]


def test_bad_values_are_refused_in_one_line_and_move_nothing(start_plant, cli):
    """Every case through the CLI's entry point, two of them through real interpreters too."""
    p = start_plant(PLANT, loops=("a1", "b1"))
    before = cli.loops(p)
    counts = (accepted(p, "a1"), accepted(p, "b1"))
    for loop, flags, needle in BAD:
        run = cli.set(p, loop, *flags)
        assert run.returncode == 2 and run.stdout == "", (run.args, run.stdout, run.stderr)
        assert needle in one_line(run), (needle, run.stderr)
    for loop, flags, needle in (BAD[1], BAD[7]):
        run = cli.set(p, loop, *flags, process=True)
        assert run.returncode == 2 and run.stdout == "" and needle in one_line(run)
    assert cli.loops(p) == before
    assert (accepted(p, "a1"), accepted(p, "b1")) == counts  # not one write reached the plant


SLOW = """
seed = 5
[loops.s1]
model = "transfer_function"
num = [1.0]
den = [600.0, 70.0, 1.0]
delay = 5.0
sample_time = 0.002
noise_std = 0.0
[loops.s1.pid]
kc = 2.0
ti = 60.0
"""


def test_set_while_a_tuning_run_holds_the_loop_is_refused_naming_the_holder(
    start_plant, start_tuner, cli
):
    """A relay run that must see 20 cycles agree to 0.05 %, on a loop sampled every 2 ms (some
    650,000 samples in all), holds s1 far longer than the test needs; it is cancelled at the
    end, and restores the loop before it lets go."""
    p = start_plant(SLOW, loops=("s1",))
    start_tuner(p)
    before = cli.loops(p, "s1")
    with open_session(p.client_settings()) as s:
        seen = Statuses(s, p.prefix, "s1")
        run = autotune(
            "tune",
            "s1",
            "--detach",
            "--json",
            "--method",
            "relay",
            "--cycles",
            "20",
            "--tolerance",
            "0.0005",
            "--rest-window",
            "5",
            *p.cli_args(),
            timeout=60,
        )
        assert run.returncode == 0, run.stderr
        run_id = json.loads(run.stdout)["run_id"]
        holder = f"tuner:{run_id}"
        seen.wait(lambda st: st.leased_by == holder)
        held = cli.loops(p, "s1")
        assert held["leased_by"] == holder
        refused = cli.set(p, "s1", "--kc", "5", "--ti", "90", process=True)
        assert refused.returncode == 1, (refused.stdout, refused.stderr)
        assert f"leased by {holder!r}" in one_line(refused)
        assert "gains refused by the plant" in refused.stderr
        assert "applied before it: nothing" in refused.stderr
        assert f"REFUSED by the plant: gains refused: the loop is leased by {holder!r}" in (
            refused.stdout
        )
        refused = cli.set(p, "s1", "--mode", "auto", "--sp", "60")
        assert refused.returncode == 1 and f"leased by {holder!r}" in refused.stderr
        assert "setpoint refused by the plant" in refused.stderr
        assert "not sent: mode" in refused.stderr
        during = cli.loops(p, "s1")
        assert during["leased_by"] == holder  # the run goes on, its loop untouched by set
        assert (during["gains"], during["sp"]) == (before["gains"], before["sp"])
        assert during["mode"] == "manual"  # the relay's
        table = cli(p, "loops", process=True)
        assert holder in table.stdout
        # cancelled, the run restores the loop and then lets it go
        s.put(keys.tune_cancel(p.prefix, "s1"), run_id.encode())
        released = seen.wait(lambda st: st.reason == "release", timeout=120)
        assert released.by_source == holder
    after = cli.loops(p, "s1")
    assert after["leased_by"] is None
    assert (after["gains"], after["sp"], after["mode"], after["op"]) == (
        before["gains"],
        before["sp"],
        before["mode"],
        before["op"],
    )
    run = cli.set(p, "s1", "--kc", "5")  # the loop is free again
    assert run.returncode == 0, run.stderr
    assert cli.loops(p, "s1")["gains"]["kc"] == 5.0


def test_loops_names_the_loops_a_paused_plant_announces_but_does_not_answer(cli, tmp_path):
    """One plant file's loops on two plant processes (--loops), clients of a router, the
    second paused (SIGSTOP): the router keeps its liveliness tokens up (until Zenoh's lease
    on its link runs out, 10 s), and `loops` listed a1 alone, exit 0, and `loops b1` said
    "not found". b1 is named: exit 1 beside the listing, 2 alone."""
    import os
    import signal

    from services.launcher import free_tcp_port, start_service, stop_service
    from tests.running_services import RunningPlant, wait_for_tokens

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = f"test{os.getpid()}/paused"
    path = tmp_path / "plant.toml"
    path.write_text(PLANT)
    client = ["--prefix", prefix, "-m", "client", "-e", endpoint, "--no-multicast-scouting"]
    procs = []
    try:
        with (tmp_path / "services.log").open("w") as log:
            procs.append(
                start_service(
                    "services.cli",
                    ["router", "-l", endpoint, "--no-multicast-scouting"],
                    stderr=log,
                )
            )
            for loop in ("a1", "b1"):
                procs.append(
                    start_service(
                        "services.plant_sim",
                        [*client, "--plant", str(path), "--loops", loop],
                        stderr=log,
                    )
                )
        plant = RunningPlant(endpoint, prefix, procs[1], tmp_path / "services.log")
        alive = [keys.loop_alive(prefix, lp) for lp in ("a1", "b1")]
        wait_for_tokens(plant.client_settings(), alive, 20.0, plant.log)

        def loops(*args: str) -> subprocess.CompletedProcess:
            return cli(plant, "loops", *args, "--timeout", "1", "-m", "client")

        assert loops().returncode == 0
        procs[2].send_signal(signal.SIGSTOP)
        every, one = loops(), loops("b1")
        procs[2].send_signal(signal.SIGCONT)
        assert every.returncode == 1, (every.stdout, every.stderr)
        said = "b1: announced on the bus (liveliness token up) but did not answer"
        assert said in one_line(every)
        assert every.stdout.splitlines()[1].startswith("a1 ")
        assert one.returncode == 2 and "b1: announced on the bus" in one_line(one)
    finally:
        for proc in reversed(procs):
            proc.send_signal(signal.SIGCONT)
            stop_service(proc)
