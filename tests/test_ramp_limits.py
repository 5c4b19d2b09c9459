"""The P-gain ramp's limits: budgets that hold, an output that saturates, a start gain far
too high, K_u on a lag-dominated plant whose trials would saturate the output, and a process
that drifts whatever the loop does.

Each test drives ``RampTest`` in-process against a plant stepped in the same process (the
loop's own P-only PID block), with fixed seeds. Expected ultimate points come from closed
forms computed here, never from the code under test.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
from scipy.optimize import brentq

from services.autotuner.identify import experiments, methods
from services.autotuner.identify.driver import drive as drive_experiment
from services.autotuner.identify.experiments import DEFAULT_BUMP_FRACTION, Settings, Setup
from services.autotuner.identify.ramp import RampConfig, RampTest
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient, Reading, SimLoopPort
from services.plant_sim.plant_file import build_plant
from services.plant_sim.simulation.loop import SimLoop
from shared.messages import GainsCommand, ModeCommand, PidGains, TuneRequest
from tests.plants import transfer_function_loop

RELAY_SWING = 8.0 * 5.0 / math.pi  # × 1/K_u: a 5 % relay's peak-to-peak PV swing (benchmark)


def fopdt_ultimate(k: float, t: float, lag: float) -> tuple[float, float]:
    """K·e^{−Ls}/(Ts+1): atan(ωT) + ωL = π, K_u = √(1 + (ωT)²)/K; (K_u, P_u)."""
    w = brentq(lambda w: math.atan(w * t) + w * lag - math.pi, 1e-9, math.pi / lag)
    return math.hypot(1.0, w * t) / k, 2.0 * math.pi / w


def lags_ultimate(n: int) -> tuple[float, float]:
    """1/(s+1)ⁿ: each lag gives π/n of phase, ω = tan(π/n), K_u = (1 + ω²)^{n/2}."""
    w = math.tan(math.pi / n)
    return (1.0 + w * w) ** (n / 2), 2.0 * math.pi / w


def make_loop(num, den, delay, ts, noise=0.0, seed=0, kc=1.0) -> SimLoop:
    """A transfer-function loop (PV 0–100, output 0–100 %) in auto, P-only at ``kc``."""
    loop = transfer_function_loop(num, den, delay, ts, noise, seed)
    loop.apply(GainsCommand(loop="x", gains=PidGains(kc=kc)))
    loop.apply(ModeCommand(loop="x", mode="auto"))
    return loop


def ramp_for(loop: SimLoop, kc_start: float | None = None, bump: float | None = None) -> RampTest:
    """The ramp as the live tuner builds it, with its defaults: kc_start half the loop's
    gain, bump 1 % of the PV range, the loop's output limits."""
    lo, hi = loop.settings.pv_range
    setup = Setup(
        sample_time=loop.sample_time,
        op_lo=loop.settings.op_limits[0],
        op_hi=loop.settings.op_limits[1],
        pv_lo=lo,
        pv_hi=hi,
        kc_start=kc_start or 0.5 * loop.pid.gains.kc,
        bump=bump or DEFAULT_BUMP_FRACTION * (hi - lo),
        sp_start=loop.pv,
    )
    test = methods.build("ramp", Settings.of(TuneRequest(loop="x", method="ramp")), setup)
    assert isinstance(test, RampTest)
    loop.apply(GainsCommand(loop="x", gains=PidGains(kc=test.kc)))
    return test


def drive(test: RampTest, loop: SimLoop, limit: float) -> np.ndarray:
    """Apply the test's demands (through the driver, from the loop's present state) until it
    finishes or ``limit`` s of sim time pass; the outputs fed to it."""
    port = SimLoopPort(loop, present_first=True, limit=limit)
    drive_experiment(test, port, held=port.held_now())
    return np.asarray(test._u)


def length(test: RampTest) -> float:
    """s of sim time the test ran."""
    return test._t[-1] - test._t[0]


def kinds(test: RampTest) -> list[str]:
    return [e[1] for e in test.events]


def assert_ended(test: RampTest) -> None:
    assert test.finished
    if test.phase == "aborted":
        assert test.reason and test.events[-1][1] == "aborted"
    else:
        assert test.result is not None


def assert_json_finite(test: RampTest) -> None:
    """Every number the result and the events carry is finite (a trial's growth may be ±inf:
    the tuner maps it to None), as the messages' JSON needs."""
    if test.result is not None:
        for k, v in dataclasses.asdict(test.result).items():
            if isinstance(v, float):
                assert math.isfinite(v), k
    for _, kind, data in test.events:
        for k, v in data.items():
            if isinstance(v, float) and not (kind == "trial_result" and k == "growth"):
                assert math.isfinite(v), (kind, k)


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_lag_dominated_ku_within_two_percent(noise):
    """e^{−s}/(50s+1) (L/T = 0.02, K_u ≈ 79): a bump of 1 % of the PV range kicks the output
    by Kc·bump ≈ 79 % near K_u. Trials sized to the output's room keep the loop linear."""
    ku, pu = fopdt_ultimate(1.0, 50.0, 1.0)
    ts = pu / 400
    loop = make_loop([1.0], [50.0, 1.0], 1.0, ts, noise=noise * RELAY_SWING / ku, seed=3)
    test = ramp_for(loop)
    assert test.config.bump == 1.0 and test.config.kc_start == 0.5  # the defaults
    ops = drive(test, loop, limit=400 * pu)
    r = test.result
    assert r is not None, test.reason
    assert r.ku == pytest.approx(ku, rel=0.02)
    assert r.pu == pytest.approx(pu, rel=0.02)
    trials = [e for e in test.events if e[1] == "trial"]
    assert min(e[2]["bump"] for e in trials) < 0.5  # fitted to the output's room
    assert np.mean((ops <= 0.0) | (ops >= 100.0)) < 0.01
    assert_json_finite(test)


def test_the_loop_calms_before_the_findings_are_fitted():
    """The closing fit takes a quarter of a second or more while a realtime loop runs on; it
    must not hold the last trial's gain, which may lie above K_u: the loop is at a gain below
    every trial seen to decay (the bracket's low end) before it starts."""
    ku, pu = fopdt_ultimate(1.0, 1.0, 1.0)
    loop = make_loop([1.0], [1.0, 1.0], 1.0, pu / 400)
    test = ramp_for(loop)
    fitted = test._conclude
    held_then: list[float] = []

    def conclude() -> None:
        held_then.append(loop.pid.gains.kc)
        fitted()

    test._conclude = conclude  # type: ignore[method-assign]
    drive(test, loop, limit=200 * pu)
    assert test.phase == "done" and test.result is not None, test.reason
    assert test.result.ku == pytest.approx(ku, rel=0.03)
    lo = max(tr.kc for tr in test.trials if tr.growth < 0)
    assert len(held_then) == 1 and held_then[0] <= test.config.calm_gain * lo + 1e-12
    assert held_then[0] < test.trials[-1].kc


def test_huge_start_gain_backs_off_within_a_few_periods():
    """``kc_start`` 10⁶ on e^{−s}/(s+1) with noise: the output bangs between its limits at
    rest. The test backs the gain off within 5 P_u, and then finishes within 150 P_u."""
    ku, pu = fopdt_ultimate(1.0, 1.0, 1.0)
    ts = pu / 400
    loop = make_loop([1.0], [1.0, 1.0], 1.0, ts, noise=0.01 * RELAY_SWING / ku, seed=1)
    test = ramp_for(loop, kc_start=1e6)
    drive(test, loop, limit=200 * pu)
    assert_ended(test)
    backs = [e for e in test.events if e[1] == "back_off"]
    assert backs and backs[0][0] - test._t[0] <= 5 * pu
    assert length(test) <= 150 * pu
    if test.result is not None:
        assert test.result.ku == pytest.approx(ku, rel=0.03)
    assert_json_finite(test)


def test_huge_start_gain_without_noise_backs_off_at_the_first_trial():
    """At rest without noise nothing excites the loop; the first trial's kick would saturate
    the output, so the gain backs off to one whose kick fits before any bump."""
    _, pu = fopdt_ultimate(1.0, 1.0, 1.0)
    ts = pu / 400
    loop = make_loop([1.0], [1.0, 1.0], 1.0, ts)
    test = ramp_for(loop, kc_start=1e6)
    ops = drive(test, loop, limit=200 * pu)
    assert_ended(test)
    assert kinds(test)[:2] == ["back_off", "trial"]
    assert test.events[1][2]["kc"] * test.events[1][2]["bump"] <= 25.0 + 1e-9  # ½ of 50 %
    assert length(test) <= 150 * pu
    assert np.mean((ops <= 0.0) | (ops >= 100.0)) < 0.05
    assert_json_finite(test)


def test_saturating_trial_halves_the_bump_and_still_finishes():
    """The heat exchanger e^{−5s}/((10s+1)(60s+1)) from Kc = 2 with a bump of 1: a growing
    trial's output reaches its limit before its record shows the growth. It is repeated at
    the same gain with half the bump, and the test still finds K_u."""
    ku, pu = hx_ultimate()
    loop = make_loop([1.0], [600.0, 70.0, 1.0], 5.0, 0.05, kc=4.0)
    test = ramp_for(loop)
    drive(test, loop, limit=200 * pu)
    assert_ended(test)
    sat = [e for e in test.events if e[1] == "saturated"]
    assert sat
    t_sat, _, data = sat[0]
    bump = next(e for e in test.events if e[1] == "bump" and e[0] == t_sat)
    assert bump[2]["bump"] == pytest.approx(0.5 * data["bump"])
    assert bump[2]["reason"] == "output saturated"
    repeat = next(e for e in test.events if e[1] == "trial" and e[0] > t_sat)
    assert repeat[2]["kc"] == data["kc"]  # the same gain again
    if test.result is not None:
        assert test.result.ku == pytest.approx(ku, rel=0.02)
    assert_json_finite(test)


def hx_ultimate() -> tuple[float, float]:
    """e^{−5s}/((10s+1)(60s+1)): atan(10ω) + atan(60ω) + 5ω = π; K_u = |(10jω+1)(60jω+1)|."""
    w = brentq(lambda w: math.atan(10 * w) + math.atan(60 * w) + 5 * w - math.pi, 1e-6, 0.6)
    return math.hypot(1, 10 * w) * math.hypot(1, 60 * w), 2 * math.pi / w


def test_eight_lags_at_one_percent_noise_end_within_budget():
    """1/(s+1)⁸ at 1 % noise, the generic loop's defaults: done (K_u within 2 %) or aborted
    with a reason within 150 P_u of the exact P_u."""
    ku, pu = lags_ultimate(8)
    ts = pu / 400
    den = [float(c) for c in np.poly([-1.0] * 8)]
    loop = make_loop([1.0], den, 0.0, ts, noise=0.01 * RELAY_SWING / ku, seed=2)
    test = ramp_for(loop)
    ops = drive(test, loop, limit=200 * pu)
    assert_ended(test)
    assert length(test) <= 150 * pu
    if test.result is not None:
        assert test.result.ku == pytest.approx(ku, rel=0.02)
    assert np.mean((ops <= 0.0) | (ops >= 100.0)) < 0.01
    assert_json_finite(test)


def test_period_budget_aborts_on_time_with_its_reason():
    """Once a period is known the test may run ``total_periods`` of it; a budget too short
    for a bracket aborts at its end, naming it."""
    ku, pu = lags_ultimate(4)
    ts = pu / 400
    loop = make_loop([1.0], [float(c) for c in np.poly([-1.0] * 4)], 0.0, ts)
    cfg = RampConfig(kc_start=0.3 * ku, bump=1.0, total_periods=6.0)
    test = RampTest(cfg, (0.0, 100.0), ts, sp_start=loop.pv, op_limits=(0.0, 100.0))
    loop.apply(GainsCommand(loop="x", gains=PidGains(kc=cfg.kc_start)))
    drive(test, loop, limit=200 * pu)
    assert test.phase == "aborted" and "periods" in test.reason
    first = next(e for e in test.events if e[1] == "trial_result" and e[2]["period"])
    assert test._t[-1] - first[0] <= 6.0 * first[2]["period"] + ts  # the first one sets it


def test_max_time_caps_every_budget():
    ku, pu = lags_ultimate(4)
    ts = pu / 400
    loop = make_loop([1.0], [float(c) for c in np.poly([-1.0] * 4)], 0.0, ts)
    cfg = RampConfig(kc_start=0.3 * ku, bump=1.0, max_time=5 * pu)
    test = RampTest(cfg, (0.0, 100.0), ts, sp_start=loop.pv, op_limits=(0.0, 100.0))
    loop.apply(GainsCommand(loop="x", gains=PidGains(kc=cfg.kc_start)))
    drive(test, loop, limit=200 * pu)
    assert test.phase == "aborted" and "max_time" in test.reason
    assert length(test) <= 5 * pu + ts


def test_output_that_cannot_move_aborts_with_a_reason():
    """A loop whose output rests at its limit leaves a trial no room: abort, not a wait."""
    ts = 0.01
    test = RampTest(RampConfig(kc_start=1.0, bump=1.0), (0.0, 100.0), ts, op_limits=(0, 100))
    for k in range(2000):
        test.feed(Reading(k * ts, 50.0, 100.0))
        if test.finished:
            break
    assert test.phase == "aborted" and test.reason


def test_the_no_bump_abort_gives_the_kick_it_judged() -> None:
    """On lvl1 no bump the noise allows fits below K_u. The abort read as a contradiction
    (Kc × the least bump, 1483 × 0.012, is under half of the 48.7 % room): it now gives the
    kick it judged, the noise's 3σ with the bump, against half the room."""
    sim = build_plant({"seed": 1, "loops": {"lvl1": {"model": "tank_level"}}}, "nb")["lvl1"]
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="lvl1", method="ramp"), "nb").run()
    assert r.status == "aborted", r.reason
    m = re.search(
        r"\(≥ ([0-9.e-]+)\) fits the output's room at Kc = ([0-9.e+]+): its kick with the "
        r"noise's, Kc·\(bump \+ 3σ\) = ([0-9.]+) %, is over 50% of the room to the output's "
        r"limit \(([0-9.]+) %\)",
        r.reason,
    )
    assert m, r.reason
    least, kc, kick, room = (float(g) for g in m.groups())
    assert kick > 0.5 * room  # what stopped it
    assert kc * least < kick  # the noise's share counted: the bump's kick alone may fit
    assert r.reason.endswith("need no gain on the loop (--method relay, --method step)")


def test_the_saturation_abort_names_the_methods_that_need_no_gain() -> None:
    """e^{−10s}/(5000s + 1) has K_u near 785: its trials saturate the output even with the
    least bump the noise allows, and the abort says what to use instead, as the no-bump abort
    does."""
    sim = transfer_function_loop([1.0], [5000.0, 1.0], 10.0, 1.0, 0.002, name="s")
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="s", method="ramp"), "sat").run()
    assert r.status == "aborted", r.reason
    assert "the output saturates at Kc = " in r.reason, r.reason
    assert r.reason.endswith("need no gain on the loop (--method relay, --method step)")


def _pure_delay(seed: int) -> SimLoop:
    """e^{−3s}/(0.01s + 1): a transport delay (K_u 1, P_u 6 s), sampled at 0.1 s, σ 0.005."""
    return transfer_function_loop([1.0], [0.01, 1.0], 3.0, 0.1, 0.005, seed=seed, name="puredl")


@pytest.mark.parametrize("seed", [0, 2])
def test_a_pure_delays_trials_are_watched_past_its_dead_time(seed) -> None:
    """e^{−3s}/(0.01s + 1) (K_u 1, P_u 6 s): the first trial's fit of its staircase and noise
    gave a period of 0.84 s, and every trial after was watched for 4.5 of those, 3.8 s, closed
    before its response came back, and judged "did not oscillate" up to 1.7 K_u; the loop,
    calmed at 0.7 of that, ran from 50 to the end of its range (seed 0). A period shorter than
    the dead time the first trial showed is not the loop's: the trials run their length, the
    PV stays within a few bumps of its rest, and K_u is found (the exact K_u is 1/|G| at
    −180°, computed here)."""
    w = brentq(lambda w: math.atan(0.01 * w) + 3.0 * w - math.pi, 1e-6, math.pi / 3.0)
    ku = math.hypot(1.0, 0.01 * w)
    sim = _pure_delay(seed)
    client = LocalLoopClient(sim)
    seen: list[float] = []
    advance = client.advance

    def watched(*a, **k):
        out = advance(*a, **k)
        seen.extend(s.pv for s in out)
        return out

    client.advance = watched  # type: ignore[method-assign]
    req = TuneRequest(loop="puredl", method="ramp", apply=False)
    r = TuningRun(client, req, "pd").run()
    assert r.status == "proposed", r.reason
    assert max(abs(pv - 50.0) for pv in seen) < 5.0
    assert r.ku == pytest.approx(ku, rel=0.03)


def test_a_pure_delays_ramp_recorded_before_replays_as_it_ran(monkeypatch) -> None:
    """A ramp recorded before ``ramp_period_floor`` rebuilds the experiment that ran: on the
    pure delay above (seed 0), every period taken, the PV ran to the end of its range."""
    live = experiments.live_flags
    monkeypatch.setattr(
        experiments,
        "live_flags",
        lambda method: {
            k: v
            for k, v in live(method).items()
            # each came after that run
            if k not in ("ramp_period_floor", "pv_allowance", "ramp_calm_guard")
        },
    )
    sim = _pure_delay(0)
    req = TuneRequest(loop="puredl", method="ramp", apply=False)
    r = TuningRun(LocalLoopClient(sim), req, "pd").run()
    assert r.status == "aborted" and "clipped there" in r.reason, r.reason


def test_a_ramp_on_a_drifting_process_aborts_naming_the_process_and_restores():
    """A hidden load swinging ±0.5 % every 40 s keeps the PV moving whatever the loop's gain:
    the calming's gain is halved to 1/16 of its first and the test aborts, saying that at such
    a gain it is the process that moves the PV (it said only "does not calm"), the loop left
    as it was."""
    spec = {"model": "tests.drifting_plant:Drifting", "sample_time": 0.1, "noise_std": 0.02}
    sim = build_plant({"seed": 0, "loops": {"d": spec}}, "t")["d"]
    before = (sim.mode, sim.op, sim.sp, sim.pid.gains)
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="d", method="ramp"), "t", RunHooks()).run()
    assert r.status == "aborted", r.reason
    assert "does not calm between trials" in r.reason, r.reason
    assert "the process does: a drift or an upset during the test" in r.reason, r.reason
    assert (sim.mode, sim.op, sim.sp, sim.pid.gains) == before


def test_a_ramp_start_gain_too_small_to_move_the_output_is_refused_before_the_test():
    """--kc-start 1e-300 was taken, and the ramp, doubling its gain toward the ultimate
    point, ran a day of sim time before it gave up (helper trial): a start below 0.001 % of
    output per % of span (a proportional band of 100,000 %) is refused before anything is
    sent, as one above 1000 % per % is."""
    from services.autotuner.identify.experiments import start_gain_problem

    why = start_gain_problem("ramp", 1e-300, 100.0)
    assert why is not None and why.startswith("kc_start: 1e-300 (1e-300 % of output per % of")
    assert "at least 0.001 % per % of span" in why
    assert start_gain_problem("ramp", 1.1e-3, 100.0) is None  # 0.0011 %/%: taken
    assert start_gain_problem("relay", 1e-300, 100.0) is None  # no gain to start from
    sim = build_plant({"seed": 0, "loops": {"hx1": {"model": "heat_exchanger"}}}, "t")["hx1"]
    before = (sim.mode, sim.op, sim.sp, sim.pid.gains)
    req = TuneRequest(loop="hx1", method="ramp", kc_start=1e-300)
    r = TuningRun(LocalLoopClient(sim), req, "t", RunHooks()).run()
    assert r.status == "failed" and "kc_start: 1e-300" in r.reason, r.reason
    assert r.sim_duration < 60.0  # refused at the start, not after a day of trials
    assert (sim.mode, sim.op, sim.sp, sim.pid.gains) == before
