"""After the verification's setpoint goes back, a loop that does not hold it is not `ok`:
a process that failed high as the setpoint went back (its PV pegged at the top of the
transmitter's range, the output at 0 % until the run's end) was neither swinging nor slow,
and the run applied its gains with status `ok` (helper trial). ``lost_hold`` reads the
return's last time scale."""

from __future__ import annotations

import math

import numpy as np

from services.autotuner.tuning import RunHooks, TuningRun, lost_hold
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

K = 50  # samples in a time scale
LIMITS = (0.0, 100.0)


def _back(y: np.ndarray, u: np.ndarray) -> str | None:
    return lost_hold(y, u, 50.0, K, 0.1, LIMITS, 0.2)


def test_a_pv_pegged_with_the_output_at_its_limit_has_lost_its_setpoint():
    y = np.concatenate((np.linspace(50.4, 50.0, 100), np.full(200, 100.0)))
    u = np.concatenate((np.full(100, 48.0), np.zeros(200)))
    why = _back(y, u)
    assert why is not None and "the output at its limit (0 %)" in why, why
    assert "stayed +50 from it over the last 10 s" in why, why


def test_a_pv_going_away_with_the_output_inside_its_limits_has_lost_its_setpoint():
    y = np.linspace(50.4, 52.0, 300)  # the return started 0.4 off; 2 off and growing
    u = np.linspace(48.0, 30.0, 300)
    why = _back(y, u)
    assert why is not None and "farther than the 0.4 it started from" in why, why


def test_a_loop_at_its_setpoint_or_creeping_back_to_it_holds_it():
    rng = np.random.default_rng(0)
    at_rest = 50.0 + 0.02 * rng.standard_normal(300)
    assert _back(at_rest, np.full(300, 48.0)) is None
    creeping = 50.0 + 0.4 * np.exp(-np.arange(300) / 400.0)  # still 0.19 off, coming back
    assert _back(creeping, np.full(300, 48.0)) is None
    # at rest with the output at a limit (the load needs none): on its setpoint, held
    assert _back(at_rest, np.zeros(300)) is None


def _run(fail_at: float, marks: list | None = None):
    spec = {
        "model": "tests.failing_plant:FailsHigh",
        "sample_time": 0.1,
        "noise_std": 0.02,
        "fail_at": fail_at,
    }
    sim = build_plant({"seed": 0, "loops": {"f": spec}}, "t")["f"]
    hooks = (
        RunHooks(progress=lambda p: marks.append((p.phase, p.t)))
        if marks is not None
        else RunHooks()
    )
    before = (sim.mode, sim.op, sim.sp, sim.pid.gains)
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="f", method="relay"), "t", hooks).run()
    return r, sim, before


def test_a_process_failing_high_as_the_setpoint_goes_back_is_not_ok_and_the_loop_is_restored():
    marks: list = []
    clean, _, _ = _run(math.inf, marks)
    assert clean.status == "ok", clean.reason
    verify = next(t for phase, t in marks if phase == "verify")
    # in the last tenth of the verification: the setpoint's return, after both steps
    fail_at = verify + 0.9 * (clean.t - verify)
    r, sim, before = _run(fail_at)
    assert r.status == "rejected", r.reason
    assert "after the setpoint's return the PV stayed" in r.reason, r.reason
    assert "the output at its limit (0 %)" in r.reason, r.reason
    assert (sim.mode, sim.op, sim.sp, sim.pid.gains) == before


def test_a_pv_coming_back_from_the_load_steps_removal_holds_its_setpoint():
    # the return takes the load step off too: on a slow loop the PV goes 10 away from 0.84
    # off at the start, and is still 5 off at the end, coming back (1 − e^{−t/300}); it
    # holds its setpoint, slowly: not "farther than it started" (2·e^{−20s}/(s + 1), TL PI)
    t = 0.5 * np.arange(420)
    y = 50.0 - 0.84 + np.where(t < 20.0, 0.0, -10.0 * np.exp(-(t - 20.0) / 300.0))
    y = y + 0.01 * np.random.default_rng(1).standard_normal(t.size)
    assert lost_hold(y, np.full(t.size, 45.0), 50.0, 84, 0.043, LIMITS, 0.5) is None
    # the same PV stuck 5 off, not coming back, has lost it
    stuck = np.concatenate((y[:200], np.full(220, 45.0)))
    why = lost_hold(stuck, np.full(t.size, 45.0), 50.0, 84, 0.043, LIMITS, 0.5)
    assert why is not None and "farther than the" in why, why
