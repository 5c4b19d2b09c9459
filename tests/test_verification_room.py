"""The verification's steps fit the output's room, and a slow loop is called slow.

A setpoint step's kick and a load step drive the output toward a limit: on a narrow output
range (a valve throttled to 45-53 %) the old sizes, 20 % of output and the relay's 5 %, sat
the output at a limit, so the overshoot read was the limited loop's (1.4 % where the linear
loop overshoots 15.5 %) and the load step was judged "saturated" on gains that were fine.
Every step now takes at most half the room from where the output rests to that limit, and a
response that touches a limit anyway is said to be not the linear one.

A loop that creeps toward its setpoint is given more time to settle before the step, and a
verification that could not step says why (swinging, creeping, resting off the setpoint)
with no IAE of a step that was never made.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.autotuner.tuning import (
    VERIFY_ROOM,
    TuningRun,
    creeping,
    crossings,
    limited_step_note,
    load_step_size,
    swinging,
    unsettled,
)
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import PidGains, TuneRequest, Verification

OP_LIMITS = (45.0, 53.0)


def narrow_valve_loop(action: str = "reverse"):
    """±e^{−s}/(5s+1) through an output limited to 45-53 % (resting at 50 %); the gain's sign
    is the controller's action's (a direct-acting loop's process gain is negative)."""
    spec = {
        "model": "fopdt",
        "gain": 1.0 if action == "reverse" else -1.0,
        "time_constant": 5.0,
        "delay": 1.0,
        "sample_time": 0.1,
        "noise_std": 0.01,
        "op_limits": list(OP_LIMITS),
        "action": action,
    }
    return build_plant({"seed": 1, "loops": {"x": spec}})["x"]


@pytest.mark.parametrize("action", ["reverse", "direct"])
def test_the_verification_on_a_narrow_output_range_stays_linear(action):
    client = LocalLoopClient(narrow_valve_loop(action))
    rest = client.sync().op
    r = TuningRun(client, TuneRequest(loop="x", method="ramp"), "unit").run()
    assert r.status == "ok", r.reason
    after = r.after
    # a reverse-acting output moves with the setpoint, a direct-acting one against it
    up = (after.sp_step > 0) == (action == "reverse")
    room = OP_LIMITS[1] - rest if up else rest - OP_LIMITS[0]
    assert after.op_rest == pytest.approx(rest, abs=0.05)
    assert after.kick <= VERIFY_ROOM * room + 0.05
    assert after.op_limited == 0.0
    # the load step within half the room from where the output is after the setpoint step
    # (|K| = 1 %/%: it moved by the step; its noise at that sample, σ 0.02 %, in the slack),
    # toward the limit the load drives it to (down for a load up)
    op = rest + (after.sp_step if action == "reverse" else -after.sp_step)
    load_room = op - OP_LIMITS[0] if after.load_step > 0 else OP_LIMITS[1] - op
    assert 0 < abs(after.load_step) <= VERIFY_ROOM * load_room + 0.05
    assert not after.saturated and after.stable
    # the linear loop's overshoot, as predicted: not the limited loop's few per cent
    predicted = r.acceptance["predicted_overshoot"]
    assert after.overshoot == pytest.approx(predicted, abs=5.0)
    assert not any("sat at a limit" in w for w in r.warnings)


@pytest.mark.parametrize(
    ("op", "want"),
    [
        (50.0, 2.5),  # down 5 % of room: half of it
        (80.0, 5.0),  # room enough: the relay's 5 %
        (46.0, -3.5),  # down 1 %, up 7 %: the other way, half of that
        (45.0, -4.0),  # at the low limit: up only
        (53.0, 4.0),
    ],
)
def test_a_load_step_takes_at_most_half_the_room_it_drives_the_output_into(op, want):
    assert load_step_size(5.0, op, OP_LIMITS) == pytest.approx(want)


def test_no_load_step_where_the_output_has_no_room():
    assert load_step_size(5.0, 50.0, (50.0, 50.1)) is None
    assert load_step_size(5.0, math.nan, OP_LIMITS) is None


def test_a_limited_step_is_said_to_be_not_the_linear_response():
    v = Verification(
        gains=PidGains(kc=1.9, ti=3.1), sp_step=2.0, overshoot=1.44, decay_ratio=None,
        rise_time=None, settling_time=None, iae_sp=1.0, load_step=None, iae_load=None,
        max_deviation_load=None, recovery_time=None, stable=True, saturated=False, score=1.0,
        op_limited=1.0, op_rest=49.0, kick=3.8,
    )  # fmt: skip
    note = limited_step_note(v, OP_LIMITS, 15.0)
    assert "for 1 s" in note and "1.44 %; 15 % predicted" in note and "not the linear" in note
    assert limited_step_note(v.model_copy(update={"op_limited": 0.0}), OP_LIMITS, 15.0) is None


K, BAND = 100, 0.1
TIME = np.arange(4 * K, dtype=float)


def test_a_loop_creeping_to_its_setpoint_is_slow_not_unsettled():
    y = 50.0 + 1.0 * np.exp(-TIME / 150.0)  # still 0.07 off, coming nearer
    assert creeping(y, 50.0, K, BAND)
    why = unsettled(y, 50.0, K, BAND, 152.1, "degC")
    assert why.startswith("the loop did not settle at its setpoint within 152.1 s")
    assert "creeping toward it: slow, not swinging" in why


def test_a_loop_resting_off_its_setpoint_is_not_creeping():
    """P-only control under a load: it settles to an offset and comes no nearer."""
    y = 52.5 - 2.5 * np.exp(-TIME / 20.0)
    assert not creeping(y, 50.0, K, BAND)
    assert "it rests +2.5 m off it" in unsettled(y, 50.0, K, BAND, 40.0, "m")


def test_a_loop_swinging_slower_than_its_time_scale_is_not_said_to_rest():
    """A random field case: ±0.08 about the setpoint with a period of 3.5 time scales, read
    at a trough, was "resting −0.0609 off it"."""
    time = np.arange(12 * K, dtype=float)
    y = 50.0 - 0.8 * np.cos(2 * np.pi * (time - 12 * K) / (5 * K))  # ends at a trough
    assert not swinging(y, 50.0, K, BAND)  # too slow for the last two time scales
    assert not creeping(y, 50.0, K, BAND)  # the last of them further off than the one before
    assert crossings(y, 50.0, K // 10, BAND) >= 2
    why = unsettled(y, 50.0, K, BAND, 400.0, "m")
    assert "it swings about it, slower than the loop's time scale" in why
    assert "rests" not in why


def test_a_loop_swinging_about_its_setpoint_is_not_creeping():
    y = 50.0 + 1.0 * np.sin(2 * np.pi * TIME / 30.0)
    assert not creeping(y, 50.0, K, BAND)
    assert "it still swings about it" in unsettled(y, 50.0, K, BAND, 40.0, "m")


def test_an_output_resting_at_its_limit_steps_the_other_way():
    """Noise-free, the output resting at 100 % and the setpoint in the lower half of the PV's
    range (the step would go up, and the output with it): the kick's room was 0, the step 0,
    and the verification divided by it (ZeroDivisionError, the run failed). The step now
    goes the way the output has room."""
    spec = {"model": "fopdt", "gain": 0.5, "time_constant": 5.0, "delay": 1.0,
            "sample_time": 0.1, "noise_std": 0.0, "op0": 100.0,
            "pv_range": [0.0, 200.0]}  # fmt: skip
    client = LocalLoopClient(build_plant({"seed": 1, "loops": {"x": spec}})["x"])
    assert client.sync().op == 100.0
    r = TuningRun(client, TuneRequest(loop="x", method="step", step_size=-5.0), "unit").run()
    assert r.status == "ok", r.reason
    assert r.after.sp_step < 0 and r.after.op_rest == 100.0
    assert 0 < r.after.kick <= VERIFY_ROOM * 100.0 and r.after.op_limited == 0.0
