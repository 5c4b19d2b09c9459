"""The realtime clock's vectorised stepping gives every loop the samples its own SimLoop does.

The reference is the per-loop stepping the realtime clock did before (``SimLoop.advance`` with
the output latched at the last tick): every sample of every loop must be equal to the bit,
through commands of every kind, noise, dead times whole and fractional, and a physical loop
among them (stepped one by one).
"""

from __future__ import annotations

import json
import math

import pytest

from services.plant_sim.plant_file import build_plant
from services.plant_sim.realtime import RealtimeSteppers, sample_head, sample_json
from shared.messages import (
    DisturbanceCommand,
    GainsCommand,
    ModeCommand,
    OutputCommand,
    PidGains,
    ProcessSample,
    SetpointCommand,
)

PLANT = {
    "seed": 7,
    "loops": {
        # second order, whole dead time (5 s = 20 samples), noise, auto with a full PID
        "hx1": {
            "model": "heat_exchanger",
            "sample_time": 0.25,
            "noise_std": 0.05,
            "mode": "auto",
            "setpoint": 61.0,
            "pid": {"kc": 3.0, "ti": 40.0, "td": 4.0, "n": 8.0, "beta": 0.7},
        },
        # the same order and sample time, a fractional dead time, direct action, narrow limits
        "hx2": {
            "model": "heat_exchanger",
            "sample_time": 0.25,
            "delay": 1.1,
            "action": "direct",
            "op_limits": [30.0, 45.0],
            "noise_std": 0.0,
        },
        # first order, fractional dead time; PI with the output driven into its limit
        "f1": {
            "model": "fopdt",
            "sample_time": 0.25,
            "gain": 2.0,
            "time_constant": 3.0,
            "delay": 0.6,
            "op_limits": [0.0, 60.0],
            "mode": "auto",
            "setpoint": 95.0,
            "pid": {"kc": 1.5, "ti": 2.0},
        },
        # integrating, setpoint tracking in manual
        "i1": {
            "model": "ipdt",
            "sample_time": 0.25,
            "gain": 0.02,
            "delay": 0.5,
            "sp_track": True,
            "noise_std": 0.2,
        },
        # third order at another sample time; P only (no integral) in auto
        "t3": {
            "model": "transfer_function",
            "num": [6.0],
            "den": [1.0, 6.0, 11.0, 6.0],
            "delay": 0.37,
            "sample_time": 0.1,
            "mode": "auto",
            "setpoint": 55.0,
            "pid": {"kc": 0.8},
        },
        # a static gain (order 0) and a physical loop: one by one
        "g0": {"model": "transfer_function", "num": [0.5], "den": [1.0], "sample_time": 0.1},
        "lvl": {"model": "tank_level", "sample_time": 0.5},
    },
}

COMMANDS = {  # tick number → commands applied just before it (mid-period, as on the bus)
    15: [SetpointCommand(loop="hx1", sp=58.0), OutputCommand(loop="hx2", op=44.0)],
    40: [
        ModeCommand(loop="hx2", mode="auto"),
        DisturbanceCommand(loop="f1", name="load", value=-8),
    ],
    70: [GainsCommand(loop="hx1", gains=PidGains(kc=1.2, ti=25.0, td=0.0))],
    90: [ModeCommand(loop="f1", mode="manual"), OutputCommand(loop="i1", op=70.0)],
    120: [ModeCommand(loop="f1", mode="auto"), SetpointCommand(loop="t3", sp=45.0)],
    150: [
        OutputCommand(loop="i1", op=50.0),
        DisturbanceCommand(loop="lvl", name="inflow", value=0.01),
    ],
}
TICKS = 200


def reference() -> dict[str, list[ProcessSample]]:
    """The per-loop stepping: every loop advanced with its output latched at the last tick."""
    loops = build_plant(PLANT)
    held = {lid: lp.op for lid, lp in loops.items()}
    out: dict[str, list[ProcessSample]] = {lid: [] for lid in loops}
    for k in range(TICKS):
        for cmd in COMMANDS.get(k, []):
            loops[cmd.loop].apply(cmd)
        for lid, lp in loops.items():
            s = lp.advance(held[lid])
            held[lid] = s.op
            out[lid].append(s)
    return out


def batched() -> tuple[dict[str, list[ProcessSample]], RealtimeSteppers]:
    steppers = RealtimeSteppers(build_plant(PLANT))
    out: dict[str, list[ProcessSample]] = {lid: [] for lid in steppers.loops}
    for k in range(TICKS):
        for cmd in COMMANDS.get(k, []):
            steppers.check_out(cmd.loop).apply(cmd)
        steppers.check_in()
        if k % 7 == 0:  # a status read between ticks (a query) changes nothing
            steppers.check_out("hx1").status("n", "realtime", "query")
            steppers.release()
        for group in steppers.groups:
            for lid, payload in steppers.tick(group).samples:
                out[lid].append(ProcessSample.model_validate_json(payload))
    return out, steppers


def test_batched_samples_equal_the_per_loop_stepping_to_the_bit():
    ref = reference()
    got, steppers = batched()
    batched_ids = {lid for b in (b for g in steppers.groups for b in g.batches) for lid in b.ids}
    assert batched_ids == {"hx1", "hx2", "f1", "i1", "t3", "g0"}  # all linear loops, not lvl
    for lid in ref:
        assert got[lid] == ref[lid], lid  # every field of every sample, floats exactly
    # the run went where the commands say: limits hit, setpoint tracked, modes switched
    assert max(s.op for s in ref["f1"]) == 60.0
    assert ref["i1"][-1].sp == ref["i1"][-1].pv
    assert ref["hx2"][-1].mode == "auto" and ref["hx2"][14].op == 40.0


def test_a_loop_checked_out_is_exact_and_its_status_reads_the_batch():
    ref = build_plant(PLANT)
    steppers = RealtimeSteppers(build_plant(PLANT))
    held = {lid: lp.op for lid, lp in ref.items()}
    for _ in range(30):
        for lid, lp in ref.items():
            held[lid] = lp.advance(held[lid]).op
        for group in steppers.groups:
            steppers.tick(group)
    for lid, lp in ref.items():
        mine = steppers.check_out(lid)
        assert mine.status("n", "realtime", "q") == lp.status("n", "realtime", "q"), lid
        assert mine.snapshot() == lp.snapshot()
        if lid != "lvl":  # a linear model: its state and delay line, exactly
            assert list(mine.process._sys._inputs) == list(lp.process._sys._inputs)
            assert list(mine.process._sys._x) == list(lp.process._sys._x)
    steppers.check_in()
    assert steppers.times() == {lid: lp.t for lid, lp in ref.items()}


@pytest.mark.parametrize("value", [0.1, 1e-5, 1e22, 123456.789, -0.0, 5e-324])
def test_sample_json_decodes_to_the_same_sample(value):
    s = ProcessSample(
        loop="a.b-c_1",
        seq=7,
        t=value if value >= 0 else 0.0,
        pv=value,
        sp=-value,
        op=50.0,
        mode="auto",
    )
    payload = sample_json(sample_head(s.loop), s.seq, s.t, s.pv, s.sp, s.op, True)
    assert ProcessSample.model_validate_json(payload) == s
    assert json.loads(payload) == json.loads(s.model_dump_json())


def _blow_up(loop, part: str) -> None:
    """Make ``loop``'s model state (an unstable user model's) or its integral term not finite."""
    if part == "model":
        loop.process._sys._x[:] = math.inf
    else:
        loop.pid.terms.i = math.nan


@pytest.mark.parametrize("part, says", [("model", "returned PV"), ("pid", "PID block's output")])
def test_a_loop_that_fails_is_faulted_as_its_own_simloop_faults_it(part, says):
    plant = {"seed": 3, "loops": {k: PLANT["loops"][k] for k in ("hx1", "hx2")}}
    ref = build_plant(plant)
    steppers = RealtimeSteppers(build_plant(plant))
    held = {lid: lp.op for lid, lp in ref.items()}
    got: dict[str, list[ProcessSample]] = {lid: [] for lid in ref}
    want: dict[str, list[ProcessSample]] = {lid: [] for lid in ref}
    faulted = []
    for k in range(12):
        if k == 5:  # the state blows up (as an unstable user model's would)
            _blow_up(ref["hx1"], part)
            _blow_up(steppers.check_out("hx1"), part)
            steppers.check_in()
        for lid, lp in ref.items():
            want[lid].append(lp.advance(held[lid]))
            held[lid] = want[lid][-1].op
        (group,) = steppers.groups
        tick = steppers.tick(group)
        faulted += [lp.settings.loop_id for lp in tick.faulted]
        for lid, payload in tick.samples:
            got[lid].append(ProcessSample.model_validate_json(payload))
    assert got == want
    assert faulted == ["hx1"]  # once, when it failed
    assert ref["hx1"].fault is not None and says in ref["hx1"].fault
    assert steppers.check_out("hx1").fault == ref["hx1"].fault
    assert steppers.check_out("hx2").fault is None
