"""Step-test safety (issue 10): clipped PVs are never rest, integrating loops stop on their
ramp, dead times are floored at what the data resolve, the CLI waits for the return to rest.

In-process against the real preset models (``build_plant``), lockstep, seeded noise.
"""

import math

import numpy as np
import pytest

from services.autotuner.design.rules import apply_rules
from services.autotuner.identify.driver import drive as drive_experiment
from services.autotuner.identify.model_fit import StepModel
from services.autotuner.identify.reaction_curve import (
    IntegratingCurve,
    analyze_step,
    settled,
    steady_ramp,
)
from services.autotuner.identify.step_test import (
    ReturnWatch,
    StepTest,
    StepTestAborted,
    StepTestConfig,
    _approach_left,
)
from services.autotuner.step_run import run_step_test
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient, SimLoopPort
from services.plant_sim.plant_file import build_plant
from services.plant_sim.simulation.models import FirstOrderPlusDeadTime, IntegratingPlusDeadTime
from shared.control.signals import at_rest, no_response_floor, noise_level, range_end
from shared.messages import GainsCommand, ModeCommand, PidGains, TuneRequest
from tests.exact import sopdt_tangent

FOPDT_600 = {  # lvl1 linearised at 1.5 m: 0.06 m/%, τ = 600 s, 1 s delay, 1 s samples
    "model": "fopdt",
    "gain": 0.06,
    "time_constant": 600.0,
    "delay": 1.0,
    "sample_time": 1.0,
    "noise_std": 0.002,
    "pv0": 1.5,
    "pv_range": [0.0, 3.0],
}


def sim_loop(spec: dict, seed: int = 1):
    return build_plant({"seed": seed, "loops": {"x": spec}})["x"]


def drive(loop, size: float = 5.0, pv_range: bool = True, **cfg) -> StepTest:
    """Run a StepTest on a SimLoop in lockstep through the driver: an output command holds
    from the present sample on, as ``run_step_test`` reports it."""
    st = loop.settings
    test = StepTest(
        StepTestConfig(size=size, **cfg),
        loop.op,
        st.op_limits,
        st.pv_range,
        st.sample_time,
        pv_range=st.pv_range if pv_range else None,
        pv_units=st.pv_units,
    )
    drive_experiment(test, SimLoopPort(loop, limit=200_000 * st.sample_time))
    assert test.finished
    return test


def elapsed(test: StepTest) -> float:
    return test.t[-1] - test.t_step


# --- a PV at an end of its range is never rest ---------------------------------------------


def test_a_clipped_record_is_not_at_rest():
    rng = np.random.default_rng(0)
    clipped = np.minimum(3.0 + 0.002 * rng.standard_normal(40), 3.0)
    assert range_end(clipped, (0.0, 3.0)) == "top"
    assert not at_rest(clipped, (0.0, 3.0))
    assert at_rest(np.full(40, 3.0))  # without the range, a flat record looks at rest
    near = 2.995 + 0.002 * rng.standard_normal(40)  # 2.5σ below the top: within noise
    assert range_end(near, (0.0, 3.0), noise_std=0.002) == "top"
    inside = 1.5 + 0.002 * rng.standard_normal(40)
    assert range_end(inside, (0.0, 3.0)) is None and at_rest(inside, (0.0, 3.0))
    assert range_end(np.zeros(40), (0.0, 3.0)) == "bottom"


def test_settled_refuses_a_rest_at_the_range_top():
    t = np.arange(400.0)
    y = np.where(t < 100, 1.5 + t * 0.015, 3.0)  # ramps into the top and sits there, clipped
    assert settled(t, y, 0.0, 1.5, 0.002)[0]  # what the old check said
    assert not settled(t, y, 0.0, 1.5, 0.002, pv_range=(0.0, 3.0))[0]


@pytest.mark.parametrize(
    ("spec", "end"),
    [
        ({"model": "tank_level_integrating", "level0": 3.0}, "the top of its range (3 m)"),
        ({"model": "heat_exchanger", "pv_range": [0.0, 55.0]}, "the top of its range (55 degC)"),
        ({"model": "tank_level_integrating", "level0": 0.0}, "the bottom of its range (0 m)"),
    ],
    ids=["full-tank", "narrow-transmitter", "empty-tank"],
)
def test_a_pv_clipped_from_the_start_aborts_before_the_step(spec, end):
    test = drive(sim_loop(spec))
    assert test.phase == "aborted" and test.t_step is None  # the output never moved
    assert f"the PV sits at {end}" in test.reason


def test_without_pv_range_the_limits_stand_for_it():
    """experiments.build does not pass pv_range yet: pv_limits (the loop's range by default)
    are then taken as the ends."""
    test = drive(sim_loop({"model": "tank_level_integrating", "level0": 3.0}), pv_range=False)
    assert test.phase == "aborted" and "sits at its upper limit (3 m)" in test.reason


# --- integrating loops ----------------------------------------------------------------------


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_lvl2_reads_its_reaction_curve_and_gives_its_level_back(seed):
    """lvl2: A·dh/dt = q_in − q_pump, R = inflow_max/(100·A) = 1e-4 m/s per %, 2 s delay."""
    test = drive(sim_loop({"model": "tank_level_integrating"}, seed))
    assert test.phase == "done", test.reason
    rc = test.result
    assert isinstance(rc, IntegratingCurve) and rc.stopped_by == "precision"
    seen = next(e[0] for e in test.events if e[1] == "integrating") - test.t_step
    assert seen < 600.0  # bounded: ≈ 440 s at σ = 0.002 m, not the 7200 s timeout
    assert rc.held == pytest.approx(seen, abs=1.0) and rc.pulse_held == rc.held
    assert max(test.pv) < 2.0  # nowhere near the 3 m top, let alone clipped there
    # the equal and opposite pulse gave the volume back: the level rests where it did
    assert rc.returned and rc.pv_after == pytest.approx(rc.pv_before, abs=0.01)
    assert rc.reaction_rate == pytest.approx(1e-4, rel=0.03)
    assert rc.reaction_rate_precision <= 0.02
    assert rc.dead_time == pytest.approx(2.0, abs=4 * rc.dead_time_se + 1.0)
    assert rc.a == pytest.approx(rc.reaction_rate * rc.dead_time, rel=1e-12)


def test_noise_free_integrating_dead_time_is_exact():
    test = drive(sim_loop({"model": "tank_level_integrating", "noise_std": 0.0}))
    assert test.ramp is not None
    assert test.ramp.dead_time == pytest.approx(2.0, abs=1e-6)
    assert test.ramp.slope == pytest.approx(5e-4, rel=1e-9)


def test_integrating_near_the_top_stops_before_the_measurement_clips():
    """From 2.85 m the ramp reaches the top before it is told from a slow lag: the range
    guard stops it first, never taking the clipped PV for rest."""
    test = drive(sim_loop({"model": "tank_level_integrating", "level0": 2.85}))
    assert test.phase == "aborted" and test.result is None
    assert "would reach the top of its range (3 m)" in test.reason
    assert max(test.pv) < 3.0 - 0.004


def test_a_large_step_on_a_self_regulating_loop_stops_before_its_top():
    """lvl1 from 1.5 m, +40 %: its rest (≈ 4.9 m) lies above the 3 m transmitter."""
    test = drive(sim_loop({"model": "tank_level"}), size=40.0, max_move=1.0)
    assert test.phase == "aborted" and "would reach the top of its range" in test.reason
    assert max(test.pv) < 3.0


def test_the_default_allowance_stops_it_first_at_a_quarter_of_the_range():
    """The same step, with the default allowance: 25 % of 3 m above the 1.5 m rest."""
    test = drive(sim_loop({"model": "tank_level"}), size=40.0)
    assert test.phase == "aborted" and "would leave the test's allowance" in test.reason
    assert "25 % of its range" in test.reason
    assert max(test.pv) < 1.5 + 0.25 * 3.0


def test_ipdt_with_a_lag_is_integrating_with_the_lag_in_its_dead_time():
    spec = {
        "model": "ipdt",
        "gain": 0.01,
        "delay": 3.0,
        "sensor_lag": 5.0,
        "sample_time": 0.5,
        "noise_std": 0.05,
    }
    test = drive(sim_loop(spec), size=-5.0)
    assert test.ramp is not None, test.reason
    assert test.ramp.slope == pytest.approx(-0.05, rel=0.03)
    assert test.ramp.dead_time == pytest.approx(8.0, abs=1.0)  # delay + lag: the asymptote


@pytest.mark.parametrize("seed", [1, 2])
def test_an_integrator_with_a_long_dead_time_is_read_before_it_leaves_the_allowance(seed):
    """0.02 %/s per % with a 20 s dead time, stepped by 5 %: the PV ramps at 0.1 %/s and
    leaves the 25 % allowance 270 s after the step, before the usual steady window of 10
    dead times (20 dead times of travel, 400 s) is there: the step was aborted, its R and L
    unread. At the edge a ramp steady over 3 dead times is taken: R and L as the plant's."""
    spec = {"model": "ipdt", "gain": 0.02, "delay": 20.0, "sample_time": 0.5, "noise_std": 0.05}
    test = drive(sim_loop(spec, seed))
    assert test.ramp is not None, test.reason
    assert test.ramp.slope == pytest.approx(0.1, rel=0.03)
    assert test.ramp.dead_time == pytest.approx(20.0, abs=1.5)
    assert test.ramp.elapsed < 270.0 and test.ramp.window < 10 * 20.0
    assert max(test.pv) < 75.0


def test_steady_ramp_never_calls_a_600_s_lag_integrating():
    """Noise-free, every check up to 5 time constants: the decay of the slope is always seen."""
    model = FirstOrderPlusDeadTime(1.0, gain=0.06, time_constant=600.0, delay=1.0)
    model.reset()
    t = np.arange(1.0, 3001.0)
    y = np.array([model.step(model.op0 + 5.0) for _ in t])
    for n in range(80, t.size, 40):
        assert steady_ramp(t[:n], y[:n], 0.0, model.pv0, 0.0) is None, n
    ipdt = IntegratingPlusDeadTime(1.0, gain=1e-4, delay=2.0)
    ipdt.reset()
    yi = np.array([ipdt.step(ipdt.op0 + 5.0) for _ in t[:80]])
    ramp = steady_ramp(t[:80], yi, 0.0, ipdt.pv0, 0.0)  # PV = pv0 + 1e-4·5·(t − 2) from t = 2
    assert ramp is not None
    assert ramp.slope == pytest.approx(5e-4, rel=1e-9)
    assert ramp.dead_time == pytest.approx(2.0, abs=1e-5)


# --- self-regulating loops: figures as before, never integrating ---------------------------


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_hx1_is_not_integrating_and_keeps_its_figures(seed):
    """K = 1 °C/%; the tangent of e^{−5s}/((10s+1)(60s+1)): L ≈ 10.6 s, R ≈ 0.0116 per %."""
    L, R = sopdt_tangent(1.0, 60.0, 10.0, 5.0)
    test = drive(sim_loop({"model": "heat_exchanger"}, seed))
    r = test.result
    assert test.phase == "done" and test.ramp is None, test.reason
    assert r.gain == pytest.approx(1.0, rel=0.01)
    assert r.dead_time == pytest.approx(L, rel=0.03) and r.dead_time == r.dead_time_tangent
    assert r.reaction_rate == pytest.approx(R, rel=0.02)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_600_s_fopdt_is_not_integrating(seed):
    test = drive(sim_loop(FOPDT_600, seed))
    r = test.result
    assert test.phase == "done" and test.ramp is None, test.reason
    assert r.gain == pytest.approx(0.06, rel=0.01)
    assert r.time_constant_63 == pytest.approx(600.0, rel=0.03)
    assert r.reaction_rate == pytest.approx(0.06 / 600.0, rel=0.03)
    assert r.dead_time >= r.dead_time_floor == 0.5


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_lvl1_dead_time_is_floored_and_its_gains_are_finite(seed):
    """The gravity-drain tank: K = 2h/op·(1 + Δ/2op) = 1.5·(1.1² − 1)/5 = 0.063 m/%, initial
    slope inflow_max/(100·A) = 1e-4 m/s per %; its 1 s delay is below what σ = 0.002 m lets a
    fit resolve (the tangent gave 1e-11 s): floored at half a sample, 0.5 s."""
    test = drive(sim_loop({"model": "tank_level"}, seed))
    r = test.result
    assert test.phase == "done" and test.ramp is None, test.reason
    assert r.gain == pytest.approx(1.5 * (1.1**2 - 1) / 5.0, rel=0.01)
    assert r.reaction_rate == pytest.approx(1e-4, rel=0.03)
    assert r.dead_time_floor == 0.5 and r.dead_time >= 0.5
    assert r.dead_time_tangent < r.dead_time  # the raw figure is kept, and was ~0
    gains = apply_rules(None, StepModel(r.gain, r.dead_time, r.time_constant_tangent))
    for name in ("zn-ol-p", "zn-ol-pi", "zn-ol-pid"):
        g = gains[name]
        assert math.isfinite(g.kc) and 0 < g.kc < 1e5, (name, g)


def test_noise_free_lvl1_reads_its_one_second_delay():
    test = drive(sim_loop({"model": "tank_level", "noise_std": 0.0}))
    assert test.result.dead_time == pytest.approx(1.0, abs=0.05)


def quiet_fopdt(gain: float, time_constant: float) -> dict:
    """A noise-free FOPDT on a 0–100 range at 50, 2 s delay, 0.1 s samples."""
    return {
        "model": "fopdt",
        "gain": gain,
        "time_constant": time_constant,
        "delay": 2.0,
        "sample_time": 0.1,
        "noise_std": 0.0,
        "pv0": 50.0,
        "pv_range": [0.0, 100.0],
    }


def test_a_step_the_pv_does_not_answer_is_no_response_not_a_tiny_gain():
    """Noise-free, a 5 % step through a gain of 4e-8 moves the PV 2e-7 (2e-7 % of the range,
    below the 1e-5 of it a transmitter resolves): no response, not K = 4e-8 (a PI of Kc 1e9
    was verified on a loop whose valve stuck). Through a 1e6 s lag the PV moves 5e-4 in the
    100 s the test waits: the timeout says it did not respond."""
    floor = no_response_floor((0.0, 100.0))  # 0.001: what a live run's set-up gives
    test = drive(sim_loop(quiet_fopdt(4e-8, 15.0)), resolution=floor)
    assert test.phase == "aborted" and test.result is None
    assert "did not respond to the step" in test.reason and "within 0.001" in test.reason
    slow = drive(sim_loop(quiet_fopdt(1.0, 1e6)), timeout=100.0, resolution=floor)
    assert slow.phase == "aborted" and slow.result is None
    assert "did not respond to the step within 100 s" in slow.reason
    # a response just clear of the floor is read: 5 % × 0.001 = 0.005 > 0.001
    small = drive(sim_loop(quiet_fopdt(0.001, 15.0)), resolution=floor)
    assert small.phase == "done" and small.result.gain == pytest.approx(0.001, rel=0.01)
    # a run recorded before (no floor) read the 2e-7 as a gain, as it did then
    old = drive(sim_loop(quiet_fopdt(4e-8, 15.0)))
    assert old.phase == "done" and old.result.gain == pytest.approx(4e-8, rel=0.01)


def test_analyze_step_floors_an_unresolved_dead_time():
    """No delay at all, 1 s samples: L = 0 is floored at 0.5 s, the raw figure kept."""
    rng = np.random.default_rng(7)
    model = FirstOrderPlusDeadTime(1.0, gain=1.0, time_constant=50.0, delay=0.0)
    model.reset()
    base = model.pv0 + 0.01 * rng.standard_normal(40)
    t = np.arange(1.0, 501.0)
    y = np.array([model.step(model.op0 + 5.0) for _ in t]) + 0.01 * rng.standard_normal(t.size)
    r = analyze_step(t, y, 0.0, 5.0, base.mean(), model.pv0 + 5.0, noise_level(base), 1.0)
    assert r.dead_time == 0.5 == r.dead_time_floor
    assert r.dead_time_tangent < 0.5
    assert r.a == pytest.approx(r.reaction_rate * 0.5)
    assert r.to_dict()["dead_time_tangent"] == r.dead_time_tangent


# --- run_step_test: the return to rest ------------------------------------------------------
# (over LocalLoopClient: the LoopClient interface on a SimLoop in lockstep, lease included)


def test_run_step_test_waits_for_the_return_to_rest():
    loop = sim_loop({"model": "heat_exchanger"})
    report = run_step_test(LocalLoopClient(loop), StepTestConfig(size=5.0))
    d = report.to_dict()
    assert d["restored"] is True and d["returned_to_rest"] is True
    assert d["pv_end"] == pytest.approx(d["pv_before"], abs=0.05)  # back at 60 °C
    assert d["t_end"] < d["t_return"] <= d["t_end"] + 3 * (d["t_end"] - d["t_step"])
    assert d["gain"] == pytest.approx(1.0, rel=0.01)
    assert loop.op == 40.0 and loop.mode == "manual"
    assert abs(loop.pv - 60.0) < 0.1  # what runs next starts from rest


def test_run_step_test_no_wait_returns_at_once():
    loop = sim_loop({"model": "heat_exchanger"})
    report = run_step_test(LocalLoopClient(loop), StepTestConfig(size=5.0), wait_return=False)
    assert report.returned_to_rest is None and report.pv_end is None
    assert loop.t == report.t_end and loop.op == 40.0
    assert loop.pv > 64.0  # still at the stepped rest: the CLI says so


def test_run_step_test_on_lvl2_reports_the_integrating_curve_restored():
    loop = sim_loop({"model": "tank_level_integrating"})
    report = run_step_test(LocalLoopClient(loop), StepTestConfig(size=5.0))
    d = report.to_dict()
    assert d["method"] == "integrating" and d["restored"] and d["returned_to_rest"]
    assert d["pv_end"] == d["pv_after"] and d["t_return"] == d["t_end"]
    assert loop.op == 50.0 and loop.t < 1200.0
    assert abs(loop.pv - 1.5) < 0.01  # the level where it was


def test_return_watch_gives_up_at_its_timeout():
    watch = ReturnWatch(t_restore=0.0, pv_from=65.0, noise_std=0.02, timeout=50.0)
    t = 0.0
    while not watch.feed(t, 65.0 - 0.05 * t):  # still ramping: never at rest
        t += 0.25
    assert not watch.at_rest and t == 50.0 and watch.pv_end == pytest.approx(62.5)


def test_a_step_stops_before_the_pv_passes_its_limits():
    """e^{−2s}/(15s+1), a 20 % step with PV limits 45–55: the test aborted once the PV had
    crossed 55, and the PV, moving on for its dead time and lag, peaked at 57.0. It now
    stops where the trend would reach a limit within the time the PV keeps moving, as it
    does for the transmitter's range, and the PV never passes the limit."""
    spec = {"model": "fopdt", "gain": 1.0, "time_constant": 15.0, "delay": 2.0,
            "sample_time": 0.1, "noise_std": 0.01}  # fmt: skip
    loop = sim_loop(spec)

    pvs: list[float] = []

    class Watched(LocalLoopClient):
        def samples(self, *args, **kw):
            out = super().samples(*args, **kw)
            pvs.extend(s.pv for s in out)
            return out

    client = Watched(loop)
    req = TuneRequest(loop="x", method="step", step_size=20.0, pv_limits=(45.0, 55.0))
    r = TuningRun(client, req, "unit").run()
    assert r.status == "aborted" and "would leave its limits [45, 55]" in r.reason, r.reason
    assert r.restored
    assert min(pvs) > 45.0 and max(pvs) < 55.0  # the return included


def test_the_return_is_watched_past_the_dead_time():
    """e^{−10s}/(2s+1), noise-free, a 2 % step: the wait for the return ended 10 s after the
    restore, the PV still in its dead time (flat, bar the last of the step's creep), and
    said "returned to rest" at 52.0 for a rest of 50.0. The PV must now come at least half
    of the way back."""
    spec = {"model": "fopdt", "gain": 1.0, "time_constant": 2.0, "delay": 10.0,
            "sample_time": 0.25, "noise_std": 0.0}  # fmt: skip
    loop = sim_loop(spec)
    d = run_step_test(LocalLoopClient(loop), StepTestConfig(size=2.0)).to_dict()
    assert d["returned_to_rest"] is True
    assert d["pv_end"] == pytest.approx(d["pv_before"], abs=0.01), d
    assert d["t_return"] - d["t_end"] > 10.0 + 3 * 2.0  # past the dead time, and its lag


FO5 = {"model": "fopdt", "gain": 1.0, "time_constant": 2.0, "delay": 10.0,
       "sample_time": 0.25, "noise_std": 0.0}  # fmt: skip


def test_a_lag_slowing_down_is_not_extrapolated_past_its_end():
    """e^{−10s}/(2s+1), the default 5 % step from 50 %: its straight-line trend over twice
    the dead time (1.06 %/s at 54.89 %, the rise's average) took it past the allowance's
    75 %, and the test aborted; the PV ends at 55. A PV slowing down as a lag's approach
    does is extended to where that approach ends; the test completes. At 0.1 s samples the
    check's window also held the flat dead time before the onset, read the rise as speeding
    up, and the test aborted "within 20.6 s (now 53.17 %, moving 1.3 %/s)" (helper trial F):
    the approach is judged on the samples since the PV started moving."""
    for ts in (0.25, 0.1):
        spec = {**FO5, "sample_time": ts}
        d = run_step_test(LocalLoopClient(sim_loop(spec)), StepTestConfig()).to_dict()
        assert d["gain"] == pytest.approx(1.0, rel=1e-3)
        assert d["dead_time"] == pytest.approx(10.0, abs=ts)


@pytest.mark.parametrize(("noise", "seed"), [(0.0, 1), (0.005, 0), (0.005, 1), (0.005, 3)])
def test_a_pure_delays_jump_is_not_read_as_heading_out(noise, seed):
    """e^{−3s}/(0.01s + 1): the 5 % step's PV jumps from 50 to 55 in a sample, three seconds
    on, and stays. The check's straight line through the flat dead time and the jump read it
    as heading past the allowance's 75 % at 3.8 %/s, and the test aborted on every seed;
    where the PV's trend since it began to move is the slower, it is that one. The figures
    expected are the plant's own: K 1, L 3 s."""
    spec = {"model": "fopdt", "gain": 1.0, "time_constant": 0.01, "delay": 3.0,
            "sample_time": 0.1, "noise_std": noise}  # fmt: skip
    d = run_step_test(LocalLoopClient(sim_loop(spec, seed)), StepTestConfig()).to_dict()
    assert d["gain"] == pytest.approx(1.0, rel=0.01)
    assert d["dead_time"] == pytest.approx(3.0, abs=0.1)


def test_a_pure_delays_step_recorded_before_replays_as_it_ran():
    """A step recorded before ``step_trend_since_move`` rebuilds the check that ran: the
    pure delay's jump read as heading out, and the test aborted. (Such a run came before
    ``step_trend_error`` too: its trend was taken as fitted.)"""
    spec = {"model": "fopdt", "gain": 1.0, "time_constant": 0.01, "delay": 3.0,
            "sample_time": 0.1, "noise_std": 0.005}  # fmt: skip
    then = StepTestConfig(trend_since_move=False, trend_error=False)
    with pytest.raises(StepTestAborted, match="would leave the test's allowance"):
        run_step_test(LocalLoopClient(sim_loop(spec, 0)), then)


def test_a_pv_that_moved_and_stopped_goes_no_further():
    """The thirds' means of a PV that rose over the first third and has been flat (within its
    noise) since: nothing left to go, where the ratio of their steps is the noise's."""
    rng = np.random.default_rng(0)
    y = np.concatenate((np.linspace(50.0, 55.0, 12), np.full(24, 55.0)))
    y += rng.normal(0.0, 0.005, y.size)
    left = _approach_left(y)
    assert left is not None and abs(left) < 0.02
    # flat to the bit (no noise: the steps' ratio undefined)
    flat = np.concatenate((np.linspace(50.0, 55.0, 12), np.full(24, 55.0)))
    assert _approach_left(flat) == 0.0
    assert _approach_left(np.linspace(50.0, 55.0, 36)) is None  # a ramp keeps its line


def test_an_aborted_step_waits_for_the_pv_to_come_back():
    """A 20 % step with PV limits 45–55 stops early; the loop was restored and the command
    ended at once, the PV still moving for its dead time: a test started next measured
    K = −1.43 for +1. The abort now waits for the return, as a completed test does, and says
    where the PV came to rest."""
    loop = sim_loop(FO5)
    with pytest.raises(StepTestAborted, match="the PV back at rest at 50"):
        run_step_test(LocalLoopClient(loop), StepTestConfig(size=20.0, pv_limits=(45.0, 55.0)))
    assert loop.pv == pytest.approx(50.0, abs=0.01) and loop.op == 50.0
    d = run_step_test(LocalLoopClient(loop), StepTestConfig(size=2.0)).to_dict()
    assert d["gain"] == pytest.approx(1.0, rel=1e-3)


def test_an_aborted_steps_crest_is_not_taken_for_its_return():
    """e^{−5s}/((10s+1)(60s+1)), as hx1: stopped early, the PV carries on past where the
    test stopped (its lags), and its crest was taken for the PV back at rest ("back at rest
    at 62.76" for 60). The return must go the way back."""
    spec = {"model": "transfer_function", "num": [1.0], "den": [600.0, 70.0, 1.0],
            "delay": 5.0, "sample_time": 0.25, "noise_std": 0.0}  # fmt: skip
    loop = sim_loop(spec)
    with pytest.raises(StepTestAborted, match="the PV back at rest at 50"):
        run_step_test(LocalLoopClient(loop), StepTestConfig(size=20.0, pv_limits=(48.0, 52.0)))
    assert loop.pv == pytest.approx(50.0, abs=0.05)


# --- run_step_test on a loop in auto: held at the controller's mean output ------------------


def _in_auto(spec: dict, gains: PidGains, seed: int, settle: int):
    loop = sim_loop(spec, seed)
    loop.apply(GainsCommand(loop="x", gains=gains, source="t"))
    loop.apply(ModeCommand(loop="x", mode="auto", source="t"))
    for _ in range(settle):
        loop.advance()
    return loop


@pytest.mark.parametrize("seed", range(1, 7))
def test_a_loop_in_auto_is_stepped_from_its_mean_output_not_its_last(seed):
    """hx1 (K = 1 °C/%, at rest at 60 °C on 40 %) under TL PID, whose derivative feeds the
    noise to the output: held at the last sample's output (38.79 %), the PV drifted from
    that hold into the step and K read 0.73-1.08 over these seeds; the mean holds it."""
    gains = PidGains(kc=7.0, ti=96.0, td=6.9)
    loop = _in_auto({"model": "heat_exchanger"}, gains, seed, 2000)
    d = run_step_test(LocalLoopClient(loop), StepTestConfig(size=5.0)).to_dict()
    assert d["op_before"] == pytest.approx(40.0, abs=0.1)  # where hx1 rests at 60 °C
    assert d["op_step"] == pytest.approx(d["op_before"] + 5.0)
    assert d["gain"] == pytest.approx(1.0, rel=0.01)
    g = loop.pid.gains
    assert loop.mode == "auto" and (g.kc, g.ti, g.td) == (gains.kc, gains.ti, gains.td)


@pytest.mark.parametrize("seed", range(1, 5))
def test_an_integrating_loop_in_auto_is_stepped_from_its_balance(seed):
    """lvl2 (a pumped tank, R = 1e-4 m/s per %, balanced at 50 %) under tuned PI: held at
    its last output (up to 4.4 % off the balance), the level drained or filled by 0.25-0.35 m
    and the test aborted, "not at rest before the step", in two of these four seeds."""
    gains = PidGains(kc=2100.0, ti=19.0)
    loop = _in_auto({"model": "tank_level_integrating"}, gains, seed, 500)
    d = run_step_test(LocalLoopClient(loop), StepTestConfig(size=5.0)).to_dict()
    assert d["op_before"] == pytest.approx(50.0, abs=0.25)
    assert d["method"] == "integrating" and d["returned_to_rest"]
    assert d["reaction_rate"] == pytest.approx(1e-4, rel=0.01)
    assert loop.mode == "auto" and abs(loop.pv - 1.5) < 0.05


@pytest.mark.parametrize(
    ("gain", "action", "moved"), [(-2.0, "reverse", "fell"), (2.0, "direct", "rose")]
)
def test_a_step_answered_against_the_loops_action_aborts_asking_about_the_action(
    gain, action, moved
):
    """A reverse-acting loop on a process of gain −2 was refused with its model ("FOPDT
    gain -2: must be > 0") and sent to the relay test, which cannot tune it either (helper
    trial): the step's answer says the action is the wrong one, and the run aborts asking
    about it, as the relay and the ramp do, the loop as before."""
    spec = {"model": "transfer_function", "num": [gain], "den": [10.0, 1.0], "delay": 1.0}
    spec |= {"sample_time": 0.05, "noise_std": 0.01, "action": action}
    sim = build_plant({"seed": 0, "loops": {"x": spec}}, "t")["x"]
    before = (sim.mode, sim.op, sim.sp, sim.pid.gains)
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method="step"), "t", RunHooks()).run()
    assert r.status == "aborted", r.reason
    assert f"the output stepped up by 5 % and the PV {moved} (its gain " in r.reason, r.reason
    read = float(r.reason.split("(its gain ")[1].split()[0])
    assert math.isclose(read, gain, rel_tol=0.01)  # the noise's σ 0.01 on a change of 10
    other = "direct" if action == "reverse" else "reverse"
    assert f"is the process one for a {other}-acting PID?" in r.reason, r.reason
    assert (sim.mode, sim.op, sim.sp, sim.pid.gains) == before


def test_a_noise_free_integrator_behind_a_lag_reads_steady_and_one_recorded_before_as_it_ran():
    """0.05/(s(5s + 1))·e^{−s}, noise-free, stepped 5 %: its ramp's slope is e^{−W/5} short
    of its last across the window, which an exact record resolves to 1e-12; asked to be
    steady to 1e-6, it never was, and the test aborted at its allowance, the level left 25 %
    of span off (helper trial). Steady to 0.5 %, it reads R = 0.05 (the kink's dead time is
    the lag and the delay, 6 s) and gives the level back. A run recorded before the floor
    (``steady_floor`` off) replays the abort it had."""
    spec = {"model": "transfer_function", "num": [0.05], "den": [5.0, 1.0, 0.0], "delay": 1.0,
            "sample_time": 0.1, "noise_std": 0.0}  # fmt: skip
    d = run_step_test(LocalLoopClient(sim_loop(spec, 1)), StepTestConfig()).to_dict()
    assert d["method"] == "integrating", d
    assert d["reaction_rate"] == pytest.approx(0.05, rel=0.02)
    assert d["dead_time"] == pytest.approx(6.0, rel=0.05)
    assert abs(d["pv_end"] - d["pv_before"]) < 1.0  # the level given back (25 % off before)
    with pytest.raises(StepTestAborted, match="would leave the test's allowance"):
        run_step_test(LocalLoopClient(sim_loop(spec, 1)), StepTestConfig(steady_floor=False))
