"""`autotune loops` and `autotune set` (issue 14, items 1 and 2): the pure parts.

The flags' values, the plan of writes (their order, the loop's ranges, gains kept from the
present ones), the run of the writes against a scripted client (a refusal stops them, the
plant lost is said), the loop object's keys (a contract) and its % of span figures (by hand:
Kc·span/100 and PB = 100/that), and every refusal before anything reaches the bus.
"""

from __future__ import annotations

import argparse
import subprocess

import pytest
import zenoh

from services.autotuner.commands import loops, set_loop
from services.autotuner.commands.set_loop import Asked, execute, plan
from services.autotuner.loop_client import CommandRefused, PlantLost
from services.cli import main
from shared.messages import (
    GainsCommand,
    LoopInfo,
    LoopStatus,
    ModeCommand,
    OutputCommand,
    PidGains,
    SetpointCommand,
)

GAINS = PidGains(kc=2.0, ti=60.0, td=1.5, n=8.0, beta=0.8)


def status(**over) -> LoopStatus:
    """A status of a loop ``hx1``: manual, SP 60, PV 59.5, OP 40 %, PV range 0–150 degC."""
    fields = dict(
        loop="hx1",
        node="plant",
        seq=12,
        t=3.0,
        pv=59.5,
        sp=60.0,
        op=40.0,
        mode="manual",
        action="reverse",
        gains=GAINS,
        op_limits=(5.0, 95.0),
        pv_range=(0.0, 150.0),
        disturbances={"load": 0.0},
        clock="lockstep",
        accepted=0,
        rejected=0,
        reason="query",
    )
    return LoopStatus(**{**fields, **over})


def info(**over) -> LoopInfo:
    fields = dict(
        loop="hx1",
        node="plant",
        t=3.0,
        model="heat_exchanger",
        description="Heat exchanger outlet temperature",
        model_params={},
        sample_time=0.25,
        pv_units="degC",
        pv_range=(0.0, 150.0),
        op_limits=(5.0, 95.0),
        disturbances=["load"],
        noise_std=0.0,
        clock="lockstep",
        speed=1.0,
    )
    return LoopInfo(**{**fields, **over})


# --- the flags' values ---------------------------------------------------------------------------

BAD_VALUES = [
    (set_loop.finite, ["nan", "inf", "-inf", "1e999", "abc", ""]),
    (set_loop.gain, ["nan", "inf", "0", "-0", "-1", "1e999", "x"]),
    (set_loop.integral_time, ["nan", "inf", "0", "-5", "off", "1e999"]),
    (set_loop.derivative_time, ["nan", "inf", "-0.1", "-1e-300"]),
    (set_loop.weight, ["nan", "-0.01", "1.01", "inf"]),
    (loops.seconds, ["nan", "inf", "0", "-1", "1e300"]),
]


@pytest.mark.parametrize(("parse", "bad"), BAD_VALUES, ids=lambda x: getattr(x, "__name__", ""))
def test_bad_values_are_refused_by_the_flags_types(parse, bad):
    for text in bad:
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)


def test_good_values_pass_as_given():
    assert set_loop.finite("-5") == -5.0
    assert set_loop.gain("3.3") == 3.3
    assert set_loop.integral_time("96.09") == 96.09
    assert set_loop.integral_time("none") == set_loop.integral_time(" NONE ") == "none"
    assert set_loop.derivative_time("0") == 0.0
    assert set_loop.weight("0") == 0.0 and set_loop.weight("1") == 1.0
    assert loops.seconds("0.5") == 0.5


# --- the plan ------------------------------------------------------------------------------------


def kinds(writes) -> list[str]:
    return [f"{w.what}:{getattr(w.cmd, 'mode', '')}" for w in writes]


def test_every_write_in_its_order_with_the_source_label():
    asked = Asked(mode="auto", sp=65.0, op=45.0, kc=3.0)
    writes = plan(asked, status(), "degC")
    assert kinds(writes) == ["output:", "gains:", "setpoint:", "mode:auto"]
    assert all(w.cmd.source == "autotune-set" and w.cmd.loop == "hx1" for w in writes)
    assert all(w.cmd.t == 3.0 for w in writes)
    asked = Asked(mode="manual", sp=65.0, op=45.0, beta=0.0)
    writes = plan(asked, status(mode="auto"), "degC")
    assert kinds(writes) == ["mode:manual", "output:", "gains:", "setpoint:"]
    assert isinstance(writes[0].cmd, ModeCommand) and isinstance(writes[1].cmd, OutputCommand)
    assert isinstance(writes[2].cmd, GainsCommand) and isinstance(writes[3].cmd, SetpointCommand)
    assert writes[0].change == "auto → manual"
    # the mode the loop is in already is said so (it read "auto → auto applied")
    (w,) = plan(Asked(mode="auto"), status(mode="auto"), "degC")
    assert w.change == "auto (already)"


def test_a_setpoint_is_written_before_the_switch_to_auto_and_gains_before_a_setpoint():
    writes = plan(Asked(mode="auto", sp=62.0), status(), "degC")
    assert kinds(writes) == ["setpoint:", "mode:auto"]
    writes = plan(Asked(sp=62.0, kc=4.0), status(mode="auto"), "degC")
    assert kinds(writes) == ["gains:", "setpoint:"]


def test_gains_not_given_are_kept_exactly_and_ti_none_turns_integral_off():
    (w,) = plan(Asked(kc=3.3), status(), "degC")
    assert w.cmd.gains == PidGains(kc=3.3, ti=60.0, td=1.5, n=8.0, beta=0.8)
    (w,) = plan(Asked(ti="none", td=0.0, beta=0.25), status(), "degC")
    assert w.cmd.gains == PidGains(kc=2.0, ti=None, td=0.0, n=8.0, beta=0.25)
    assert w.change == "Ti 60 s → none, Td 1.5 s → 0 s, β 0.8 → 0.25 (Kc 2 kept)"
    (w,) = plan(Asked(ti=96.09), status(gains=PidGains(kc=1.0)), "degC")
    assert w.cmd.gains == PidGains(kc=1.0, ti=96.09)


@pytest.mark.parametrize(
    ("asked", "st", "needles"),
    [
        (Asked(op=95.5), status(), ["--op 95.5", "output limits [5, 95] %"]),
        (Asked(op=4.9, mode="manual"), status(mode="auto"), ["--op 4.9", "output limits"]),
        (Asked(op=40.0), status(mode="auto"), ["--op 40", "in auto", "--mode manual"]),
        (Asked(op=40.0, mode="auto"), status(mode="auto"), ["--op 40", "--mode manual"]),
        # held by a run: the lease said first (following "add --mode manual" was refused for
        # it: helper trial)
        (
            Asked(op=70.0),
            status(mode="auto", leased_by="tuner:5effba391d85"),
            ["--op 70", "in auto", "'tuner:5effba391d85' holds its lease", "until that ends"],
        ),
        (Asked(sp=150.1), status(), ["--sp 150.1", "PV range [0, 150] degC"]),
        (Asked(sp=-1.0, kc=3.0), status(), ["--sp -1", "PV range"]),
        # hx1's span is 150 degC: 1000 % per % is Kc 666.67 % per degC
        (
            Asked(kc=667.0),
            status(),
            ["--kc 667", "1000.5 % of output per % of span", "at most 666.6 here"],
        ),
        (Asked(kc=1e9, sp=61.0), status(), ["--kc 1e+09", "proportional band of 6.7e-08 %"]),
        (Asked(), status(), ["nothing to set"]),
    ],
)
def test_values_the_loop_cannot_take_are_refused_naming_the_flag(asked, st, needles):
    with pytest.raises(set_loop.ConfigError) as err:
        plan(asked, st, "degC")
    assert all(n in str(err.value) for n in needles), str(err.value)


def test_an_integral_time_shorter_than_a_sample_is_refused_naming_the_flag():
    """`set hx1 --kc 2 --ti 0.001` was applied: each sample's integral step, Kc·T/Ti of the
    error, took the output from 40 % to 0 % in three samples."""
    with pytest.raises(set_loop.ConfigError, match=r"--ti 0\.001: shorter than the loop's"):
        plan(Asked(kc=2.0, ti=0.001), status(), "degC", sample_time=0.25)
    (w,) = plan(Asked(ti=0.25), status(), "degC", sample_time=0.25)  # one sample: taken
    assert w.cmd.gains.ti == 0.25
    (w,) = plan(Asked(ti="none"), status(), "degC", sample_time=0.25)
    assert w.cmd.gains.ti is None


def test_an_output_with_a_switch_to_auto_from_manual_is_written_before_it():
    writes = plan(Asked(op=30.0, mode="auto"), status(), "degC")
    assert kinds(writes) == ["output:", "mode:auto"]


def test_values_at_the_limits_are_taken():
    writes = plan(Asked(op=5.0, sp=150.0), status(), "degC")
    assert [w.cmd.op if w.what == "output" else w.cmd.sp for w in writes] == [5.0, 150.0]
    (w,) = plan(Asked(kc=1000.0 * 100.0 / 150.0), status(), "degC")  # PB 0.1 % exactly
    assert w.cmd.gains.kc == pytest.approx(666.6667, rel=1e-6)
    (w,) = plan(Asked(kc=33_000.0), status(pv_range=(0.0, 3.0)), "m")  # 990 % per % of 3 m
    assert w.cmd.gains.kc == 33_000.0


# --- running the writes --------------------------------------------------------------------------


class ScriptedClient:
    """A LoopClient stand-in: applies writes to a status, or raises what it is told to at
    the n-th command."""

    loop = "hx1"

    def __init__(self, st: LoopStatus, fail_at: int | None = None, error=None, track=False):
        self.last_status = st
        self.sent: list = []
        self.fail_at, self.error, self.track = fail_at, error, track

    def command(self, cmd):
        if self.fail_at is not None and len(self.sent) == self.fail_at:
            raise self.error
        self.sent.append(cmd)
        st = self.last_status
        match cmd:
            case ModeCommand(mode=mode):
                # a loop whose setpoint tracks its PV in manual: the PV came in before the switch
                st = st.model_copy(update={"mode": mode, **({"sp": st.pv} if self.track else {})})
            case OutputCommand(op=op):
                st = st.model_copy(update={"op": op})
            case SetpointCommand(sp=sp):
                st = st.model_copy(update={"sp": sp})
            case GainsCommand(gains=gains):
                st = st.model_copy(update={"gains": gains})
        self.last_status = st
        return st


def test_all_writes_confirmed():
    client = ScriptedClient(status())
    out = execute(client, plan(Asked(mode="auto", sp=65.0, kc=3.0), status(), "degC"))
    assert [w.what for w in out.applied] == ["gains", "setpoint", "mode"]
    assert out.refused is None and out.not_sent == [] and out.lost is None
    assert (out.status.mode, out.status.sp, out.status.gains.kc) == ("auto", 65.0, 3.0)
    text = set_loop.format_outcome(out, "degC")
    assert text.count("applied") == 3 and "hx1 now: auto, SP 65 degC" in text


def test_a_refusal_stops_the_writes_and_says_what_was_applied():
    reason = "setpoint refused: the loop is leased by 'tuner:abc' (user 'bob')"
    client = ScriptedClient(status(), fail_at=2, error=CommandRefused(f"loop hx1: {reason}"))
    writes = plan(Asked(mode="auto", sp=65.0, op=30.0, kc=3.0), status(), "degC")
    out = execute(client, writes)
    assert [w.what for w in out.applied] == ["output", "gains"]
    assert out.refused == (writes[2], reason)
    assert [w.what for w in out.not_sent] == ["mode"]
    assert [type(c) for c in client.sent] == [OutputCommand, GainsCommand]
    line = set_loop.refusal_line(out)
    assert "\n" not in line and reason in line and "applied before it: output, gains" in line
    assert "not sent: mode" in line
    assert f"REFUSED by the plant: {reason}" in set_loop.format_outcome(out, "degC")


def test_the_plant_lost_midway_leaves_the_write_unconfirmed():
    client = ScriptedClient(status(), fail_at=1, error=PlantLost("loop hx1: no answer"))
    out = execute(client, plan(Asked(mode="manual", op=30.0, kc=3.0), status(mode="auto"), ""))
    assert [w.what for w in out.applied] == ["mode"]
    assert out.unconfirmed is not None and out.unconfirmed.what == "output"
    assert out.lost == "loop hx1: no answer" and [w.what for w in out.not_sent] == ["gains"]
    text = set_loop.format_outcome(out, "")
    assert "sent, not confirmed" in text and "hx1 last confirmed:" in text


def test_a_setpoint_the_loop_tracked_away_before_the_switch_is_written_again_in_auto():
    client = ScriptedClient(status(), track=True)
    out = execute(client, plan(Asked(mode="auto", sp=65.0), status(), "degC"))
    assert [type(c) for c in client.sent] == [SetpointCommand, ModeCommand, SetpointCommand]
    assert out.status.sp == 65.0 and out.status.mode == "auto" and out.notes


# --- the loop object and the table ---------------------------------------------------------------

CONTRACT = {
    "loop",
    "node",
    "description",
    "model",
    "mode",
    "action",
    "sp",
    "pv",
    "op",
    "pv_units",
    "pv_range",
    "op_limits",
    "gains",
    "gains_percent",
    "disturbances",
    "clock",
    "sample_time",
    "t",
    "leased_by",
    "lease_user",
    "fault",
    "accepted",
    "rejected",
    "last_reject",
}


def test_the_loop_object_keys_and_values():
    o = loops.loop_object(status(leased_by="tuner:abc", lease_user="bob"), info())
    assert set(o) == CONTRACT
    assert o["gains"] == {"kc": 2.0, "ti": 60.0, "td": 1.5, "n": 8.0, "beta": 0.8}
    # by hand: 2 % per degC on a 150 degC span is 3 % per %, PB 100/3 % of span
    assert o["gains_percent"] == {
        "kc": pytest.approx(3.0, rel=1e-15),
        "ti": 60.0,
        "td": 1.5,
        "pb": pytest.approx(100 / 3, rel=1e-15),
    }
    assert (o["pv_range"], o["op_limits"]) == ([0.0, 150.0], [5.0, 95.0])
    assert (o["sample_time"], o["pv_units"], o["model"]) == (0.25, "degC", "heat_exchanger")
    assert (o["leased_by"], o["lease_user"], o["fault"]) == ("tuner:abc", "bob", None)


def test_the_loop_object_carries_the_plants_counts_of_refused_commands():
    """The plant counts the commands it refused on each loop (a bad payload, a loop held by a
    run) and keeps the last reason, but no command showed them: a user could not see that a
    malformed command had been refused without the plant's log (helper h2)."""
    why = "output: op: Input should be a finite number"
    o = loops.loop_object(status(accepted=5, rejected=3, last_reject=why), info())
    assert (o["accepted"], o["rejected"], o["last_reject"]) == (5, 3, why)


def test_a_loop_without_its_info_or_a_usable_span():
    o = loops.loop_object(status(pv_range=(5.0, 5.0)), None)
    assert set(o) == CONTRACT
    assert o["gains_percent"] is None
    assert (o["description"], o["model"], o["sample_time"], o["pv_units"]) == (None,) * 4


def test_the_table():
    rows = [
        loops.loop_object(status(), info()),
        loops.loop_object(
            status(
                loop="lvl2",
                mode="manual",
                gains=PidGains(kc=10.0),
                pv_range=(0.0, 3.0),
                leased_by="tuner:r1",
                fault="the model's step() raised ValueError (at t = 4 s)",
            ),
            info(loop="lvl2", pv_units="m", description="Feed tank level"),
        ),
    ]
    lines = loops.format_table(rows).splitlines()
    assert lines[0].split()[:6] == ["loop", "mode", "SP", "PV", "units", "OP"]
    assert lines[1].startswith("hx1 ") and lines[1].endswith("Heat exchanger outlet temperature")
    assert lines[2].startswith("lvl2") and "manual!" in lines[2] and "tuner:r1" in lines[2]
    assert " — " in lines[2]  # Ti none
    assert lines[3] == "lvl2: FAULT: the model's step() raised ValueError (at t = 4 s)"
    # columns line up: each row's lease column starts under its heading
    at = lines[0].index("lease")
    assert lines[1][at] == "—" and lines[2][at:].startswith("tuner:r1")


def test_the_holder_is_named_with_its_user():
    o = loops.loop_object(status(leased_by="tuner:abc", lease_user="bob"), info())
    assert loops.holder(o) == "tuner:abc (user bob)"
    assert loops.holder(loops.loop_object(status(), info())) == "—"


def test_not_found_names_the_loops_there():
    line = loops.not_found("nope", "autotune", ["hx1", "lvl1"], 2.0)
    assert "'nope' not found" in line and "hx1, lvl1" in line
    line = loops.not_found("nope", "autotune", [], 2.0)
    assert "autotune/plant/nope/status within 2 s" in line and "autotune plant" in line


# --- refusals before anything reaches the bus ----------------------------------------------------


@pytest.fixture
def no_bus(monkeypatch):
    def refuse(*_a, **_k):
        raise AssertionError("a session or a process was started before the flags were judged")

    monkeypatch.setattr(zenoh, "open", refuse)
    monkeypatch.setattr(subprocess, "Popen", refuse)


REFUSED = [
    (["set", "hx1", "--kc", "nan"], ["--kc", "finite"]),
    (["set", "hx1", "--kc", "inf"], ["--kc", "finite"]),
    (["set", "hx1", "--kc", "0"], ["--kc", "> 0"]),
    (["set", "hx1", "--kc", "-2"], ["--kc", "> 0"]),
    (["set", "hx1", "--ti", "0"], ["--ti", "> 0", "none"]),
    (["set", "hx1", "--ti", "-inf"], ["--ti"]),
    (["set", "hx1", "--ti", "nan"], ["--ti"]),
    (["set", "hx1", "--td", "-1"], ["--td", "≥ 0"]),
    (["set", "hx1", "--td", "nan"], ["--td"]),
    (["set", "hx1", "--beta", "1.5"], ["--beta", "0–1"]),
    (["set", "hx1", "--beta", "-0.1"], ["--beta"]),
    (["set", "hx1", "--sp", "nan"], ["--sp", "finite"]),
    (["set", "hx1", "--op", "-inf"], ["--op"]),  # argparse: "-inf" reads as a flag
    (["set", "hx1", "--op=-inf"], ["--op", "finite"]),
    (["set", "hx1", "--op", "1e999"], ["--op", "finite"]),
    (["set", "hx1", "--mode", "cascade"], ["--mode", "invalid choice"]),
    (["set", "hx1", "--timeout", "0"], ["--timeout"]),
    (["set", "hx1", "--timeout", "nan"], ["--timeout"]),
    (["set", "hx1"], ["nothing to set"]),
    (["set", "bad/loop", "--kc", "1"], ["loop"]),
    (["set", "hx1", "--kc", "1", "--prefix", "a//b"], ["prefix"]),
    (["set", "--kc", "nan"], ["--kc"]),
    (["set", "--kc", "1"], ["LOOP"]),
    (["loops", "--timeout", "nan"], ["--timeout"]),
    (["loops", "--timeout", "-1"], ["--timeout"]),
    (["loops", "--timeout", "inf"], ["--timeout"]),
    (["loops", "bad/loop"], ["loop"]),
    (["loops", "--prefix", ""], ["prefix"]),
]


@pytest.mark.parametrize(("argv", "needles"), REFUSED, ids=[" ".join(a) for a, _ in REFUSED])
def test_bad_input_is_one_line_exit_2_before_the_bus(no_bus, capsys, argv, needles):
    try:
        code = main(argv)
    except SystemExit as stop:
        code = stop.code
    err = capsys.readouterr().err
    assert code == 2, (argv, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert all(n in err for n in needles), (needles, err)


def test_the_loop_mode_and_the_zenoh_mode_are_both_there():
    """`set --mode` is the loop's (as on a faceplate); the Zenoh session's stays -m."""
    from services.cli import build_parser

    args = build_parser().parse_args(["set", "hx1", "--mode", "auto", "-m", "client"])
    assert (args.loop_mode, args.mode) == ("auto", "client")
    args = build_parser().parse_args(["loops", "--mode", "client"])
    assert args.mode == "client"


def test_a_message_names_twenty_loops_at_most():
    """With 600 loops every "not found" named all of them, in a line of 4,000 characters."""
    from services.autotuner.loop_client import listed

    ids = [f"f{i:03d}" for i in range(600)]
    assert listed(ids[:20]) == ", ".join(ids[:20])
    line = listed(ids)
    assert line.startswith("f000, f001") and "f020" not in line
    assert line.endswith("… (600 in all: `autotune loops` lists them)")


def test_the_most_a_refusal_names_is_a_gain_the_check_takes():
    """`set hx1 --kc 666.7` was refused "… at most 666.7 here" (1000.05 % per % printed
    "1000 % … above the 1000 %": helper trial): the figures are printed so that they differ
    where the check does, and the most is rounded down to one it takes."""
    from services.autotuner.commands.set_loop import check_kc, rounded_down
    from shared.errors import ConfigError

    with pytest.raises(ConfigError) as err:
        check_kc(666.7, (0.0, 150.0), " degC")
    assert "1000.05 % of output per % of span" in str(err.value)
    most = str(err.value).split("at most ")[1].split()[0]
    check_kc(float(most), (0.0, 150.0), " degC")  # taken
    assert rounded_down(666.6667) == "666.6" and rounded_down(0.0123456) == "0.01234"


def test_a_gain_whose_proportional_band_is_no_number_is_refused():
    """`set hx1 --kc 1e-320` was taken and shown as a proportional band of inf %."""
    from services.autotuner.commands.set_loop import check_kc
    from shared.errors import ConfigError

    for kc in (1e-320, 5e-324):
        with pytest.raises(ConfigError, match="too wide to be a number"):
            check_kc(kc, (0.0, 150.0), " degC")
    check_kc(1e-300, (0.0, 150.0), " degC")  # 100/(1.5e-300) % is a number


def test_minus_zero_is_zero():
    """`set --td -0` was sent and shown as "Td -0"."""
    import math

    from services.autotuner.commands.set_loop import derivative_time, finite

    for parse in (finite, derivative_time):
        assert math.copysign(1.0, parse("-0")) == 1.0 and f"{parse('-0.0'):g}" == "0"


def test_a_refusal_names_the_commands_kind_once():
    """The plant's reason on a faulted loop, after the kind: "mode: mode refused: …" said the
    kind twice (helper review)."""
    said = "mode: mode refused: the loop is faulted and held in manual (model: step() raised)"
    client = ScriptedClient(status(), fail_at=0, error=CommandRefused(f"loop hx1: {said}"))
    out = execute(client, plan(Asked(mode="auto"), status(), "degC"))
    text = set_loop.format_outcome(out, "degC")
    assert "REFUSED by the plant: mode refused: the loop is faulted and held in manual" in text
    assert "mode: mode refused" not in text
