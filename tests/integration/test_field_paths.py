"""Issue 10's user paths over the bus: the product's own presets, each method, as the README
runs them (plant_sim with its default loops and the autotuner as separate processes, the CLI
as a third). Every run ends ``ok`` with gains that are safe on the true plant, or with a
clear reason; whatever the outcome, the loop is left where it was.

Expected figures come from closed forms: the heat exchanger's exact ultimate point, the
linearised tanks (lvl1: K = 2h₀/q₀·q_max/100 = 0.06 m/%, τ = 2A·h₀/q₀ = 600 s; lvl2:
K' = q_max/(100·A) = 1e-4 m/s per %), and the true sampled loop's stability and Ms from the
independent oracle of ``tests/field_cases``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest

from services.autotuner.loop_client import LoopClient
from services.launcher import free_tcp_port, start_service, stop_service
from shared import keys
from shared.messages import LoopStatus
from shared.session import open_session
from tests.exact import ultimate_point
from tests.field_cases import Case, true_loop
from tests.running_services import RunningPlant, wait_for_tokens

pytestmark = pytest.mark.integration

PRESETS = ("hx1", "hx2", "lvl1", "lvl2", "flow1")
HX1 = ((1.0,), (600.0, 70.0, 1.0), 5.0, 0.25)  # num, den, delay, sample time
LVL1 = ((0.06,), (600.0, 1.0), 1.0, 1.0)
LVL2 = ((1e-4,), (1.0, 0.0), 2.0, 1.0)


def cli(plant, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", *args, *plant.cli_args()],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def result(proc: subprocess.Popen, timeout: float = 300) -> dict:
    out, err = proc.communicate(timeout=timeout)
    assert out, err
    assert "Traceback" not in err, err
    return json.loads(out)


def state(plant, loop: str) -> LoopStatus:
    with open_session(plant.client_settings()) as s, LoopClient(s, plant.prefix, loop) as c:
        return c.last_status


def safe_on(plant_model: tuple, r: dict) -> tuple[bool, float]:
    """The applied gains on the true (linear or linearised) plant's sampled loop."""
    num, den, delay, ts = plant_model
    ku, pu = ultimate_point(list(num), list(den), delay)
    case = Case(0, "preset", num, den, delay, ts, 0.0, "rest", r["method"], 0, ku, pu)
    isa = r["chosen"]["isa"]
    return true_loop(case, isa["kc"], isa["ti"], isa["td"])


def assert_left_where_it_was(r: dict, before: LoopStatus, after: LoopStatus) -> None:
    """Manual before: back in manual at its output (not ok), or in auto at the PV it rested
    at (ok); auto before: its setpoint kept. The result says what it left, truthfully."""
    assert r["left"]["mode"] == after.mode and r["left"]["op"] == pytest.approx(after.op)
    if r["status"] == "ok" and r["applied"]:
        assert after.mode == "auto"
        if before.mode == "auto":
            assert after.sp == before.sp
        else:
            noise = 4 * 0.02 + 0.005 * 150  # generous: the rest PV's mean, not one sample
            assert after.sp == pytest.approx(before.pv, abs=noise)
    else:  # restored; in auto the controller moves its output, in manual nothing does
        assert (after.mode, after.sp, after.gains) == (before.mode, before.sp, before.gains)
        if before.mode == "manual":
            assert after.op == before.op
    assert r["left"]["returned"] is True, r["left"]


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """One plant with every preset (the README's `autotune plant`) and one autotuner, for the
    whole module: each test tunes its own loops."""
    tmp = tmp_path_factory.mktemp("field")
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = f"test{os.getpid()}/field"
    common = ["--prefix", prefix, "--no-multicast-scouting"]
    procs = []
    try:
        log = tmp / "plant.log"
        with log.open("w") as f:
            procs.append(start_service("services.plant_sim", [*common, "-l", endpoint], stderr=f))
        plant = RunningPlant(endpoint, prefix, procs[0], log)
        alive = [keys.loop_alive(prefix, lp) for lp in PRESETS]
        wait_for_tokens(plant.client_settings(), alive, 20.0, log)
        tlog = tmp / "tuner.log"
        with tlog.open("w") as f:
            procs.append(
                start_service(
                    "services.autotuner",
                    [*common, "-e", endpoint, "--cfg", "connect/timeout_ms:10000"],
                    stderr=f,
                )
            )
        wait_for_tokens(plant.client_settings(), [keys.tuner_alive(prefix, "tuner")], 20.0, tlog)
        yield plant
    finally:
        for proc in reversed(procs):
            stop_service(proc)


def test_step_then_relay_waits_for_rest_and_applies_safe_gains(field):
    """The README's order: a step test, then a relay tune at once. The step waits for the PV
    to come back; with --no-wait it does not, and the tune's drift check waits instead (the
    relay once fitted K = 0.135 for a true 1.0 on the moving PV). K_u right, gains safe on
    the plant's sampled loop, the loop in auto at the PV it rested at."""
    before = state(field, "hx1")
    step = result(cli(field, "step", "hx1", "--size", "5", "--json"))
    assert step["returned_to_rest"] is True and step["restored"] is True
    assert step["pv_end"] == pytest.approx(before.pv, abs=0.2)
    # --no-wait leaves at once, the PV still ~5 °C away: the tune must wait for it
    step = result(cli(field, "step", "hx1", "--size", "5", "--no-wait", "--json"))
    assert step["returned_to_rest"] is None
    moving = state(field, "hx1")
    assert abs(moving.pv - before.pv) > 1.0
    r = result(cli(field, "tune", "hx1", "--method", "relay", "--json"))
    assert r["rest"]["at_rest"] is True and r["rest"]["waited"] > 2 * r["rest"]["window"]
    ku, pu = ultimate_point(*HX1[:3])
    assert r["status"] == "ok", r["reason"]
    assert r["ku"] == pytest.approx(ku, rel=0.03) and r["pu"] == pytest.approx(pu, rel=0.02)
    stable, ms = safe_on(HX1, r)
    assert stable and ms <= 2.0
    assert r["acceptance"]["passed"] is True
    assert r["after"]["overshoot"] <= 35.0
    after = state(field, "hx1")
    assert_left_where_it_was(r, before, after)


def test_level_presets_by_relay_finish_with_safe_gains_or_a_reason(field):
    """lvl1 and lvl2 by relay (the README's method for level loops): the noise needs more
    hysteresis than the dead time's overshoot, so the cycle never nears −180°: K_u and P_u
    are said not measured (never inf), and the result is safe gains or a clear refusal; the
    level is back where it was either way (lvl2, integrating, by a pulse of the output)."""
    before = {lp: state(field, lp) for lp in ("lvl1", "lvl2")}
    runs = {lp: cli(field, "tune", lp, "--method", "relay", "--json") for lp in before}
    for lp, proc in runs.items():
        r = result(proc)
        assert r["status"] in ("ok", "rejected"), r["reason"]
        assert r["status"] == "ok" or r["reason"]
        assert r["ku"] is None and any("not measured" in w for w in r["warnings"])
        if r["applied"]:
            stable, ms = safe_on(LVL1 if lp == "lvl1" else LVL2, r)
            assert stable and ms <= 2.2, (lp, ms)
        assert_left_where_it_was(r, before[lp], state(field, lp))


def test_level_presets_by_step_stop_safely(field):
    """lvl2's step test reads the reaction curve of an integrator (the true K' is 1e-4 m/s
    per %, L = 2 s), gives the level back by an equal and opposite pulse, and tunes it with
    gains safe on the true plant (or refuses); lvl1's gives a dead time no shorter than half a
    sample, and safe gains or a refusal."""
    before = {lp: state(field, lp) for lp in ("lvl1", "lvl2")}
    runs = {lp: cli(field, "tune", lp, "--method", "step", "--json") for lp in before}
    r2 = result(runs["lvl2"])
    assert r2["status"] in ("ok", "rejected"), r2["reason"]
    step = r2["step"]
    assert step["method"] == "integrating" and step["returned"] is True
    assert step["reaction_rate"] == pytest.approx(1e-4, rel=0.05)
    assert step["dead_time"] == pytest.approx(2.0, abs=4 * step["dead_time_se"] + 0.5)
    assert step["pv_after"] == pytest.approx(before["lvl2"].pv, abs=0.02 * 3.0)
    assert r2["experiment"]["model"] == "ipdt"
    if r2["applied"]:
        stable, ms = safe_on(LVL2, r2)
        assert stable and ms <= 2.2, ms
    assert_left_where_it_was(r2, before["lvl2"], state(field, "lvl2"))
    r1 = result(runs["lvl1"])
    assert r1["status"] in ("ok", "rejected"), r1["reason"]
    assert r1["step"]["dead_time"] >= 0.5
    if r1["applied"]:
        stable, ms = safe_on(LVL1, r1)
        assert stable and ms <= 2.2
    assert_left_where_it_was(r1, before["lvl1"], state(field, "lvl1"))


def test_manual_loops_are_left_at_their_operating_point(field):
    """hx2 by ramp and by step, flow1 by ramp: an ok tune of a loop that was in manual puts
    it in auto at the PV it rested at before the test (not where the test left it)."""
    for loop, method in (("hx2", "ramp"), ("flow1", "ramp"), ("hx2", "step")):
        before = state(field, loop)
        r = result(cli(field, "tune", loop, "--method", method, "--json"))
        assert r["status"] in ("ok", "rejected"), r["reason"]
        assert_left_where_it_was(r, before, state(field, loop))
        for k in ("rest", "left"):
            assert r[k] is not None


def test_a_ramp_from_an_absurd_gain_backs_off_or_aborts_within_its_budget(field):
    """`--kc-start 900` on flow1 (K_u ≈ 2.5 %/(m³/h), P_u ≈ 5 s; 900 % of output per % of
    its 0-100 span, just within what any write of gains may ask): the output saturates at
    once; the ramp backs off or aborts with a reason in a few hundred periods at most, never
    the 36,000 s of valve at 100 % seen before. Past 1000 % per % (1e6) the request is bad
    input, refused in one line before anything is sent."""
    before = state(field, "flow1")
    refused = cli(field, "tune", "flow1", "--method", "ramp", "--kc-start", "1e6")
    _, err = refused.communicate(timeout=60)
    assert refused.returncode == 2 and len(err.strip().splitlines()) == 1, err
    assert "kc_start: 1e+06 (1e+06 % of output per % of span): a gain must be at most" in err
    now = state(field, "flow1")
    assert (now.mode, now.sp, now.op, now.gains, now.leased_by) == (
        before.mode,
        before.sp,
        before.op,
        before.gains,
        None,
    )
    r = result(cli(field, "tune", "flow1", "--method", "ramp", "--kc-start", "900", "--json"))
    assert r["status"] in ("ok", "rejected", "aborted")
    assert r["status"] == "ok" or r["reason"]
    assert r["sim_duration"] < 200 * 5.3 + 1000  # ramp ≤ 200 P_u, plus its verification
    assert_left_where_it_was(r, before, state(field, "flow1"))


def test_no_number_in_a_result_is_not_finite(field):
    """Every figure of every run above came through pydantic's finite-number check; the
    JSON here is re-read to be sure no NaN or Infinity slipped into a free-form dict."""
    r = result(cli(field, "tune", "lvl1", "--method", "relay", "--no-apply", "--json"))

    def walk(v):
        if isinstance(v, dict):
            for x in v.values():
                walk(x)
        elif isinstance(v, list):
            for x in v:
                walk(x)
        elif isinstance(v, float):
            assert math.isfinite(v)

    walk(r)
