"""The autotuner and plant_sim as separate processes, in lockstep over Zenoh on loopback.

Exact answers come from the phase crossover of G(jω) (tests/exact.py). Plants are sampled
finely (≥ 400 samples per period) so that the sampled loop's ultimate point, which is what
the experiments measure, is within 0.6 % of the continuous plant's.
"""

from __future__ import annotations

import json
import math
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

from services.autotuner.commands.tune import Interrupted, follow, submit
from services.autotuner.loop_client import LoopClient, wait_for_token
from services.autotuner.tuning import RunHooks, TuningRun
from shared import keys, wire
from shared.messages import (
    AdvanceCommand,
    GainsCommand,
    LeaseCommand,
    LoopStatus,
    OutputCommand,
    PidGains,
    ProcessSample,
    ReleaseCommand,
    SetpointCommand,
    TuneProgress,
    TuneRequest,
    TuneResult,
)
from shared.session import open_session
from tests.exact import ultimate_point
from tests.field_cases import Case, true_loop
from tests.integration.tuning_cli import HX, THIRD, autotune, plant_toml, tune

pytestmark = pytest.mark.integration


def swing(plant: dict, d: float = 5.0) -> float:
    """The relay's expected PV amplitude, 4d/(π·K_u), to scale noise to 1 % of it."""
    ku, _ = ultimate_point(plant["num"], plant["den"], plant["delay"])
    return 4 * d / (math.pi * ku)


@pytest.mark.parametrize(("name", "plant"), [("third", THIRD), ("hx", HX)])
def test_relay_tune_within_one_percent(start_plant, start_tuner, name, plant):
    ku, pu = ultimate_point(plant["num"], plant["den"], plant["delay"])
    p = start_plant(plant_toml("x1", plant), loops=("x1",))
    start_tuner(p)
    r = tune(p, "x1", "--method", "relay", "--no-apply")
    assert r["status"] == "proposed", r["reason"]
    assert r["ku"] == pytest.approx(ku, rel=0.01)
    assert r["pu"] == pytest.approx(pu, rel=0.005)
    df = r["experiment"]["ku_describing_function"]
    assert abs(df / ku - 1) > 0.02  # the classic estimate, kept beside ours
    assert r["restored"] is True
    rec = r["recommended"]
    assert rec["rule"] == r["rule"] and r["requested_rule"] == "auto"
    assert r["robustness"][rec["rule"]]["ms"] <= 0.9 * 2.0
    g = r["gains"]["zn-pid"]["isa"]  # the rule applied to the measured point
    assert g["kc"] == pytest.approx(0.6 * r["ku"]) and g["ti"] == pytest.approx(r["pu"] / 2)


def test_the_compute_workers_are_up_before_the_first_run(start_plant, start_tuner):
    """Forked from the tuner at start-up (``ComputePool.fork_now``): its own children before
    it has been asked anything, so that no first run shares the cores with their start."""
    p = start_plant(plant_toml("x1", THIRD), loops=("x1",))
    tuner = start_tuner(p)
    with open(f"/proc/{tuner.pid}/task/{tuner.pid}/children") as f:
        children = f.read().split()
    assert len(children) == min(4, os.cpu_count() or 1)


@pytest.mark.parametrize(
    ("name", "plant", "noise", "tol"),
    [
        ("third", THIRD, 0.0, 0.02),
        ("hx", HX, 0.0, 0.02),
        ("third-noisy", THIRD, 0.01, 0.04),
        ("hx-noisy", HX, 0.01, 0.04),
    ],
)
def test_ramp_tune_finds_the_ultimate_point(start_plant, start_tuner, name, plant, noise, tol):
    """Noise is 1 % of the PV swing: the setpoint bump is 1 % of the 0–100 PV range."""
    ku, pu = ultimate_point(plant["num"], plant["den"], plant["delay"])
    p = start_plant(plant_toml("x1", plant, noise=noise), loops=("x1",))
    start_tuner(p)
    r = tune(p, "x1", "--method", "ramp", "--kc-start", str(0.2 * ku), "--no-apply")
    assert r["status"] == "proposed", r["reason"]
    assert r["ku"] == pytest.approx(ku, rel=tol)
    assert r["pu"] == pytest.approx(pu, rel=tol)


def loop_state(plant, loop: str) -> LoopStatus:
    with open_session(plant.client_settings()) as s, LoopClient(s, plant.prefix, loop) as c:
        return c.last_status


def test_pv_limit_aborts_and_restores_the_loop_exactly(start_plant, start_tuner):
    extra = 'mode = "auto"\nsetpoint = 50.0\n[loops.x1.pid]\nkc = 0.8\nti = 20.0\n'
    p = start_plant(plant_toml("x1", HX, extra=extra), loops=("x1",))
    start_tuner(p)
    before = loop_state(p, "x1")
    r = tune(p, "x1", "--method", "relay", "--amplitude", "20", "--pv-limits", "49.5", "50.5")
    assert r["status"] == "aborted" and "left its limits" in r["reason"]
    assert r["restored"] is True
    after = loop_state(p, "x1")
    assert (after.mode, after.sp, after.gains, after.disturbances) == (
        before.mode,
        before.sp,
        before.gains,
        before.disturbances,
    )


def tune_process(p, stdout=subprocess.PIPE) -> subprocess.Popen:
    """``autotune tune x1 --json`` against ``p``, running while the test watches the bus."""
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", "tune", "x1", "--json", *p.cli_args()],
        stdout=stdout,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.parametrize("other_run", [False, True])
def test_killed_tuner_is_caught_by_the_plant_watchdog(start_plant, start_tuner, other_run):
    """``other_run``: another session holds the loop's run token meanwhile (a second tuner's
    run waiting for the loop's rest declares it): the client watched that token alone and
    waited its whole --wait after its tuner was killed (helper trial); it watches its
    tuner's own token too."""
    p = start_plant(plant_toml("x1", HX), loops=("x1",))
    tuner = start_tuner(p)
    before = loop_state(p, "x1")
    with open_session(p.client_settings()) as s:
        held = (
            s.liveliness().declare_token(keys.tune_running(p.prefix, "x1")) if other_run else None
        )
        inbox: queue.Queue = queue.Queue()
        progress = s.declare_subscriber(keys.tune_progress(p.prefix, "x1"))
        status = s.declare_subscriber(keys.status(p.prefix, "x1"))
        for sub in (progress, status):
            threading.Thread(
                target=lambda sub=sub: [inbox.put(x) for x in sub], daemon=True
            ).start()
        cli = tune_process(p, stdout=subprocess.DEVNULL)
        try:
            while True:  # wait until the relay is running, then kill the tuner outright
                msg = inbox.get(timeout=30)
                if str(msg.key_expr).endswith("/progress") and b'"relay"' in msg.payload.to_bytes():
                    break
            tuner.send_signal(signal.SIGKILL)
            t_kill = time.monotonic()
            # the client sees its tuner's token vanish (or the run's): it says so and exits,
            # not after --wait; its exit timed by a thread, the plant's restore meanwhile
            done: list[float] = []
            exited = threading.Thread(
                target=lambda: (cli.wait(timeout=60), done.append(time.monotonic())),
                daemon=True,
            )
            exited.start()
            while True:
                msg = inbox.get(timeout=30)
                if str(msg.key_expr).endswith("/status"):
                    st = wire.decode_sample(LoopStatus, msg)
                    if st.reason == "watchdog":
                        break
            restored_after = time.monotonic() - t_kill
            exited.join(60)
            assert done, "the client did not leave within 60 s of its tuner's death"
            err = cli.stderr.read()
            client_after = done[0] - t_kill
        finally:
            cli.kill()
            progress.undeclare()
            status.undeclare()
            if held is not None:
                held.undeclare()
    assert cli.returncode == 2 and "its tuner is gone" in err, err
    assert client_after < 10.0, (client_after, err)
    if other_run:  # the plant's watchdog then waits for its lease to run out: bounded
        assert "the liveliness token of its tuner, node 'tuner', vanished" in err, err
        assert restored_after < 15.0
        return
    after = loop_state(p, "x1")
    assert (after.mode, after.op, after.sp, after.gains) == (
        before.mode,
        before.op,
        before.sp,
        before.gains,
    )
    assert restored_after < 5.0  # the run token vanished with the process


def test_whole_relay_tune_of_the_heat_exchanger_preset(start_plant, start_tuner):
    """Its wall time is measured by services.offline.wall_times, not asserted here."""
    p = start_plant(None, loops=("hx1",))
    start_tuner(p)
    r = tune(p, "hx1")
    assert r["status"] == "ok", r["reason"]
    assert r["applied"] is True and r["after"]["stable"] is True
    st = loop_state(p, "hx1")
    assert st.mode == "auto" and st.gains.kc == pytest.approx(r["chosen"]["isa"]["kc"])


def test_bad_requests_are_refused_with_the_field(start_plant, start_tuner):
    p = start_plant(plant_toml("x1", HX), loops=("x1",))
    start_tuner(p)
    run = autotune("tune", "x1", "--method", "step", "--rule", "zn-pid", *p.cli_args())
    assert run.returncode == 2 and "rule: zn-pid needs K_u and P_u" in run.stderr
    run = autotune("tune", "nope", "--json", *p.cli_args())
    assert run.returncode == 2 and "loop: no plant serves 'nope'" in run.stderr
    with open_session(p.client_settings()) as s:
        replies: list = []
        for _ in range(10):  # a new session's first query can reach nobody (gossip discovery)
            replies = list(
                s.get(keys.tuner_request(p.prefix, "tuner"), payload=b'{"loop": 5}', timeout=5)
            )
            if replies:
                break
            time.sleep(0.2)
        assert replies[0].err is not None and b"loop" in replies[0].err.payload.to_bytes()
        # the service still answers, and validates the next request on its own merits
        bad_rule = b'{"loop": "x1", "method": "step", "rule": "zn-pid"}'
        replies = list(s.get(keys.tuner_request(p.prefix, "tuner"), payload=bad_rule, timeout=5))
        assert len(replies) == 1 and replies[0].err is not None
        assert replies[0].err.payload.to_bytes().decode() == (
            "rule: zn-pid needs K_u and P_u (relay/ramp), not method step"
        )
        assert loop_state(p, "x1").mode == "manual"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_ctrl_c_on_the_client_cancels_and_restores(start_plant, start_tuner, sig, tmp_path):
    """Ctrl-C, and a SIGTERM or SIGHUP alike (a closed terminal, a service manager's stop),
    cancels the run: the tuner restores the loop before the client exits. The plant runs on
    the realtime clock at ×50, so the relay lasts seconds of wall time and the signal lands
    within it however late the test reads the progress (in lockstep a loaded machine could
    see the whole run end first)."""
    toml = plant_toml("x1", HX, extra='mode = "auto"\nsetpoint = 50.0\n')
    p = start_plant(toml, "--clock", "realtime", "--speed", "50", loops=("x1",))
    start_tuner(p)
    before = loop_state(p, "x1")
    with open_session(p.client_settings()) as s:
        inbox: queue.Queue = queue.Queue()
        progress = s.declare_subscriber(keys.tune_progress(p.prefix, "x1"))
        threading.Thread(target=lambda: [inbox.put(x) for x in progress], daemon=True).start()
        cli = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "tune", "x1", *p.cli_args()],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            # where the signal lands, in the message of a failure: twice in CI under load the
            # client printed only "interrupted" (no cancel sent, the loop left manual), and
            # no run here shows how (0 of 60 alone)
            env={**os.environ, "AUTOTUNE_DEBUG": "1"},
        )
        while b'"relay"' not in inbox.get(timeout=30).payload.to_bytes():
            pass
        cli.send_signal(sig)
        try:
            _, err = cli.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            # once in a full CI run under load (SIGHUP): the client said "cancelling" and
            # no result came within 30 s; what the tuner and the plant logged meanwhile
            cli.kill()
            _, err = cli.communicate()
            logs = {f.name: f.read_text()[-3000:] for f in sorted(tmp_path.glob("*.log"))}
            pytest.fail(f"no result within 30 s of the signal; client: {err!r}; logs: {logs}")
        progress.undeclare()
    assert cli.returncode == 130 and "interrupted" in err, err
    after = loop_state(p, "x1")
    # the client's own account in the message: a failure here (once in CI under load, the
    # loop found in manual) is otherwise not to be told apart from a restore not made
    assert (after.mode, after.sp, after.gains) == (before.mode, before.sp, before.gains), err


def test_a_signal_before_the_acceptance_still_cancels_and_restores(start_plant, start_tuner):
    """A signal that lands while the request is in flight (the run may already be going, its
    acceptance not yet back: the tuner publishes progress first) is held until the run's id
    is known; the run is then cancelled and its restore waited for. It used to send a cancel
    naming no run and leave at once: the loop was still manual, mid-restore, and the cancel
    could even reach the tuner before the run it meant. Realtime ×50, as above."""
    toml = plant_toml("x1", HX, extra='mode = "auto"\nsetpoint = 50.0\n')
    p = start_plant(toml, "--clock", "realtime", "--speed", "50", loops=("x1",))
    start_tuner(p)
    before = loop_state(p, "x1")
    handler = signal.getsignal(signal.SIGINT)
    with open_session(p.client_settings()) as s:
        runs: list[str] = []

        def start():
            accepted = submit(s, p.prefix, "tuner", TuneRequest(loop="x1"))
            runs.append(accepted.run_id)
            os.kill(os.getpid(), signal.SIGINT)  # the user's Ctrl-C, before start() returns
            return accepted

        # declared before follow's own subscriber: each result reaches this one first
        results = s.declare_subscriber(keys.tune_result(p.prefix, "x1"))
        with pytest.raises(Interrupted) as stop:
            follow(s, p.prefix, "x1", start, 600.0)
        # the client left after the run's result, not before: it had ended, cancelled, and
        # the client can say how, and where the loop is now
        ended = results.try_recv()
        results.undeclare()
        after = wire.query_one(s, keys.status(p.prefix, "x1"), LoopStatus, 5.0)
    assert ended is not None, "the client left before the run's result"
    ended = wire.decode_sample(TuneResult, ended)
    assert ended.run_id == runs[0] == stop.value.result.run_id
    said = stop.value.summary()
    assert f"run {runs[0]} cancelled, aborted" in said, said
    # a cancel that reached the run before it wrote says so (it said "restored" of a loop the
    # run never touched: helper trial); one that came after, restored
    back = "loop untouched (nothing was sent to it)" if ended.untouched else "loop restored"
    assert back in said, said
    assert "loop x1 now: auto, SP 50," in said, said
    assert ended.status == "aborted" and ended.restored is True, ended.reason
    assert signal.getsignal(signal.SIGINT) is handler  # held only while start() ran
    assert (after.mode, after.sp, after.gains, after.leased_by) == (
        before.mode,
        before.sp,
        before.gains,
        None,
    )


def test_a_run_no_logger_recorded_says_so(start_plant, start_tuner):
    """No logger on the bus: the run ends as it would, and its result warns that neither it
    nor its change of gains is on record (a tune ended ok with its logger killed, and
    revert then found no change to take back)."""
    p = start_plant(plant_toml("x1", THIRD), loops=("x1",))
    start_tuner(p)
    r = tune(p, "x1", "--no-apply")
    assert r["status"] == "proposed", r["reason"]
    said = [w for w in r["warnings"] if "logger" in w]
    assert len(said) == 1 and said[0].startswith("no logger recorded this run"), said
    assert f"{p.prefix}/logger/*/alive" in said[0]


def test_a_wait_that_runs_out_cancels_the_run_and_restores(start_plant, start_tuner):
    """``--wait`` bounds the run, not only the client: past it the run is cancelled, the loop
    restored, and tune exits 2 saying so (it exited 2 "no result within 5 s" while the run
    went on and applied its gains). Realtime ×1: the relay on HX lasts minutes of wall."""
    toml = plant_toml("x1", HX, extra='mode = "auto"\nsetpoint = 50.0\n')
    p = start_plant(toml, "--clock", "realtime", loops=("x1",))
    start_tuner(p)
    before = loop_state(p, "x1")
    run = autotune("tune", "x1", "--wait", "2", "--json", *p.cli_args())
    assert run.returncode == 2, run.stderr
    assert "within 2 s: cancelled, aborted" in run.stderr, run.stderr
    # the result all the same, as Ctrl-C gives it (--json printed nothing: helper review)
    result = json.loads(run.stdout)
    assert result["status"] == "aborted" and result["loop"] == "x1" and not result["applied"]
    after = loop_state(p, "x1")
    assert (after.mode, after.sp, after.gains, after.leased_by) == (
        before.mode,
        before.sp,
        before.gains,
        None,
    )


def test_detach_leaves_the_run_going(start_plant, start_tuner):
    """`--detach` submits, prints the acceptance and exits 0; the run goes on to its result."""
    p = start_plant(plant_toml("x1", THIRD), loops=("x1",))
    start_tuner(p)
    with open_session(p.client_settings()) as s:
        results: queue.Queue = queue.Queue()
        sub = s.declare_subscriber(keys.tune_result(p.prefix, "x1"))
        threading.Thread(target=lambda: [results.put(x) for x in sub], daemon=True).start()
        run = autotune("tune", "x1", "--detach", "--json", "--no-apply", *p.cli_args())
        assert run.returncode == 0, run.stderr
        accepted = json.loads(run.stdout)
        result = wire.decode_sample(TuneResult, results.get(timeout=120))
        sub.undeclare()
    assert result.run_id == accepted["run_id"] and result.status == "proposed", result.reason


def test_two_loops_tuned_at_once(start_plant, start_tuner):
    p = start_plant(None, loops=("hx1", "flow1"))
    start_tuner(p)
    runs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "services.cli",
                "tune",
                loop,
                "--json",
                "--no-verify",
                *p.cli_args(),
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        for loop in ("hx1", "flow1")
    ]
    results = [json.loads(r.communicate(timeout=120)[0]) for r in runs]
    assert [r["status"] for r in results] == ["unverified", "unverified"]  # --no-verify
    assert {r["loop"] for r in results} == {"hx1", "flow1"}


def test_gains_above_the_ms_bound_are_refused_unless_forced(start_plant, start_tuner):
    """ZN PI on the heat exchanger: Ms above 4 on the sampled loop. Refused, the loop is
    left as it was; with --force (on a twin loop, at rest) it is applied, with a warning."""
    twin = plant_toml("x1", HX) + plant_toml("x2", HX).split("\n", 1)[1]
    p = start_plant(twin, loops=("x1", "x2"))
    start_tuner(p)
    r = tune(p, "x1", "--method", "relay", "--rule", "zn-pi")
    assert r["status"] == "rejected" and r["applied"] is False and r["restored"] is True
    assert "refused" in r["reason"] and "above the bound 2 on the sampled loop" in r["reason"]
    # the refusal's Ms is the sampled loop's: ZN PI from the exact ultimate point on the true
    # plant, judged by the independent oracle, within what the identification's error allows
    ku, pu = ultimate_point(HX["num"], HX["den"], HX["delay"])
    case = Case(
        0,
        "hx",
        tuple(HX["num"]),
        tuple(HX["den"]),
        HX["delay"],
        HX["sample_time"],
        0.0,
        "rest",
        "relay",
        0,
        ku,
        pu,
    )
    _, ms_true = true_loop(case, 0.45 * ku, pu / 1.2, 0.0)
    ms_said = float(re.search(r"Ms ([0-9.]+) above", r["reason"]).group(1))
    assert ms_said == pytest.approx(ms_true, rel=0.1)
    assert loop_state(p, "x1").mode == "manual"  # as the plant file left it
    r = tune(p, "x2", "--method", "relay", "--rule", "zn-pi", "--force", "--no-verify")
    assert r["status"] == "unverified" and r["applied"] is True  # forced, and not verified
    assert any("forced" in w for w in r["warnings"]), r["warnings"]
    assert loop_state(p, "x2").mode == "auto"


def test_two_tuners_on_one_bus_make_one_run(start_plant, start_tuner):
    """'Any tuner' is one tuner: with two on the bus, `autotune tune` starts exactly one run
    (on the first by name); asked by name while the loop is held, the other refuses it,
    naming the holder; a lease the second takes behind the first's back is refused."""
    p = start_plant(plant_toml("x1", THIRD), loops=("x1",))
    start_tuner(p)  # node "tuner"
    start_tuner(p, "--node", "a-tuner")  # first by name
    wait_for_tokens_of(p, [keys.tuner_alive(p.prefix, "a-tuner")])
    with open_session(p.client_settings()) as s:
        started: list[str] = []
        sub = s.declare_subscriber(
            keys.tune_progress(p.prefix, "x1"),
            lambda m: started.append(m.payload.to_bytes().decode()),
        )
        run = autotune("tune", "x1", "--json", "--method", "relay", "--no-apply", *p.cli_args())
        sub.undeclare()
    result = json.loads(run.stdout)
    assert result["status"] == "proposed" and run.returncode == 0, run.stderr
    runs = {json.loads(m)["run_id"] for m in started}
    assert runs == {result["run_id"]}  # one run, nothing from the other tuner
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "x1", source="x") as c:
        c.command(LeaseCommand(loop="x1", source="x", timeout=60.0))
        refused = autotune("tune", "x1", "--json", "--node", "tuner", *p.cli_args())
        assert refused.returncode == 2 and "held by 'x'" in refused.stderr, refused.stderr
        c.command(ReleaseCommand(loop="x1", source="x"))


def wait_for_tokens_of(plant, key_exprs: list[str]) -> None:
    with open_session(plant.client_settings()) as s:
        for key in key_exprs:
            assert wait_for_token(s, key, 20.0), f"{key} did not come up"


def test_a_lease_lost_to_a_forger_is_not_called_restored(start_plant, start_tuner):
    """On a bus without credentials a client can put commands in the run's name (the
    README's Security section): it set Kc 50 and released the lease mid-relay, and the run
    said `restored: true`. Restored is now what the plant shows: as before the test, or not,
    and the reason says so; and the run aborts at the first command in its name it did not
    send (the gains), naming it. On the realtime clock (×50): the relay is still under way when
    the forged commands land."""
    p = start_plant(plant_toml("x1", HX), "--clock", "realtime", "--speed", "50", loops=("x1",))
    start_tuner(p)
    with open_session(p.client_settings()) as s:
        before = wire.query_one(s, keys.status(p.prefix, "x1"), LoopStatus, 10.0)
        inbox: queue.Queue = queue.Queue()
        progress = s.declare_subscriber(keys.tune_progress(p.prefix, "x1"))
        threading.Thread(target=lambda: [inbox.put(x) for x in progress], daemon=True).start()
        cli = tune_process(p)
        try:
            while True:  # the relay under way (its lease granted and confirmed)
                msg = inbox.get(timeout=30)
                if b'"relay"' in msg.payload.to_bytes():
                    break
            # who holds the lease, as every status shows it
            forged = wire.query_one(s, keys.status(p.prefix, "x1"), LoopStatus, 10.0).leased_by
            assert forged is not None
            for cmd in (
                GainsCommand(loop="x1", gains=PidGains(kc=50.0, ti=1.0), source=forged),
                ReleaseCommand(loop="x1", source=forged),
            ):
                wire.put(s, keys.command(p.prefix, "x1", cmd.kind), cmd)
            out, err = cli.communicate(timeout=120)
        finally:
            cli.kill()
            progress.undeclare()
        after = wire.query_one(s, keys.status(p.prefix, "x1"), LoopStatus, 10.0)
    r = json.loads(out)
    assert r["status"] == "aborted", (r["reason"], err)
    # the forged gains named first: the run saw a command in its name it had not sent
    assert "applied a gains command in this run's name that it did not send" in r["reason"]
    # what the run says it left is what the plant shows, and `restored` is true only if that
    # is the loop as before. Which lands first, the run's restore or the forged release, is
    # a race on a loaded machine: CI saw the run's Kc 1.0 back but the loop released short of
    # its restore (the test's old assertion of the forged Kc 50 was the test's race, not the
    # run's); on an idle one the forged release comes first and Kc 50 stays
    # (the output compared in manual only: in auto it follows the PV, which runs on)
    left = r["left"]
    assert (left["mode"], left["sp"], left["gains"]) == (
        after.mode,
        after.sp,
        after.gains.model_dump(),
    )
    assert after.mode == "auto" or left["op"] == after.op
    assert after.leased_by is None
    as_before = (after.mode, after.sp, after.gains) == (before.mode, before.sp, before.gains) and (
        after.mode == "auto" or after.op == before.op
    )
    assert r["restored"] is as_before, r["reason"]
    if not as_before:
        assert "the loop is NOT as it was before the test" in r["reason"]


def assert_as_before(after: LoopStatus, before: LoopStatus) -> None:
    """The loop as before the run (mode, output, gains), its lease let go."""
    assert (after.mode, after.op, after.gains, after.leased_by) == (
        before.mode,
        before.op,
        before.gains,
        None,
    )


def _forged_mid_relay(start_plant, kind: str, make) -> tuple[TuneResult, LoopStatus, LoopStatus]:
    """A relay tune of x1 with ``make(source)``, a command of ``kind`` in the holder's name,
    put on the bus by another publisher once the relay is under way: (result, the loop
    before, after)."""
    p = start_plant(plant_toml("x1", HX), loops=("x1",))
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "x1") as c:
        before = c.sync()
        forged = []

        def forge(progress: TuneProgress) -> None:
            if progress.phase == "relay" and not forged:  # the relay under way
                forged.append(make(c.source))
                wire.put(s, keys.command(p.prefix, "x1", kind), forged[0])

        hooks = RunHooks(progress=forge)
        r = TuningRun(c, TuneRequest(loop="x1", method="relay"), f"forge-{kind}", hooks).run()
        after = c.sync()
    assert forged
    return r, before, after


def test_a_forged_output_in_the_runs_name_aborts_the_run_and_the_loop_is_restored(start_plant):
    """A client put an output of 100 % in the holder's name mid-relay: the plant took it as
    the run's, the valve went to 100 %, and the run, none the wiser, ended blaming its own
    --amplitude for the PV at the top of its range. It now aborts at the status of that
    command and restores the loop (its lease still held)."""
    r, before, after = _forged_mid_relay(
        start_plant, "output", lambda src: OutputCommand(loop="x1", op=100.0, source=src)
    )
    assert r.status == "aborted"
    assert "applied an output command in this run's name that it did not send" in r.reason
    assert r.restored is True
    assert_as_before(after, before)


def test_a_forged_lease_in_the_runs_name_aborts_the_run_and_the_loop_is_restored(start_plant):
    """A client put a lease in the holder's name mid-relay, its PV limits ±1e300: the plant
    took it as the holder's renewal and set the limits at which it restores the loop by
    itself (realtime), and the run, none the wiser, went on to `ok` without that safety net
    (helper h2). It now aborts at the status of that lease, as at any command in its name
    that it did not send, and restores the loop."""
    r, before, after = _forged_mid_relay(
        start_plant,
        "lease",
        lambda src: LeaseCommand(loop="x1", source=src, pv_limits=(-1e300, 1e300)),
    )
    assert r.status == "aborted", r.reason
    assert "applied a lease command in this run's name that it did not send" in r.reason
    assert r.restored is True
    assert_as_before(after, before)


def test_a_refused_command_forged_in_the_runs_name_is_not_taken_for_the_runs(start_plant):
    """A client put a setpoint outside the PV range in the holder's name mid-relay: the plant
    refused it and counted the refusal against the holder's name, and the run aborted at its
    next command blaming itself: "setpoint: sp 1000000.0 is outside the PV range" (helper trial).
    The run never sent a setpoint: the refusal is one more than its own commands could have
    had, so it is another client's, said so, and aborted on as for any command in its name
    that it did not send; the loop restored."""
    r, before, after = _forged_mid_relay(
        start_plant, "setpoint", lambda src: SetpointCommand(loop="x1", sp=1e6, source=src)
    )
    assert r.status == "aborted", r.reason
    assert "refused command(s) in this run's name that it did not send (1; " in r.reason
    assert "sp 1000000.0 is outside the PV range" in r.reason, r.reason  # the refusal, named
    assert r.restored is True
    assert_as_before(after, before)


def test_a_loop_announced_but_never_answering_is_said_untouched(start_plant, start_tuner):
    """A loop whose token is up but whose plant never answers (paused; here a token of
    another client): the run failed before its first command, and the result said "WARNING:
    the loop may not have been restored" (helper h2). Nothing was sent to the loop."""
    p = start_plant(plant_toml("x1", HX), loops=("x1",))
    start_tuner(p)
    with open_session(p.client_settings()) as s:
        token = s.liveliness().declare_token(keys.loop_alive(p.prefix, "zz9"))
        try:
            r = tune(p, "zz9")
        finally:
            token.undeclare()
    assert r["status"] == "failed", r["reason"]
    assert r["untouched"] is True and r["restored"] is False


def test_a_status_forged_as_the_watchdogs_leaves_the_loop_restored_by_the_run(start_plant):
    """A client published, mid-relay, a copy of the loop's status saying no one holds it
    (reason watchdog): the run took it for its lease lost and wrote nothing more; the plant
    still held the loop for it, in manual at the relay's output, until the lease lapsed, and
    the run said it "may not have been restored" (helper h2). Asked, the plant says it still
    holds the loop for this run: the run restores it under that lease, and says so."""
    p = start_plant(plant_toml("x1", HX), loops=("x1",))
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "x1") as c:
        before = c.sync()
        forged: list[LoopStatus] = []

        def forge(progress: TuneProgress) -> None:
            if progress.phase == "relay" and not forged and c.last_status is not None:
                fake = c.last_status.model_copy(update={"leased_by": None, "reason": "watchdog"})
                forged.append(fake)
                wire.put(s, keys.status(p.prefix, "x1"), fake)

        hooks = RunHooks(progress=forge)
        r = TuningRun(c, TuneRequest(loop="x1", method="relay"), "forge-status", hooks).run()
        after = c.sync()
    assert forged and r.status == "aborted", r.reason
    assert "still held it for this run: that status was not the plant's" in r.reason, r.reason
    assert r.restored is True
    assert after.leased_by is None
    assert_as_before(after, before)


def test_a_forged_sample_shadowing_the_plants_aborts_the_run_and_the_loop_is_restored(
    start_plant,
):
    """A client published, on the realtime clock, a sample numbered as the plant's last one
    and a PV 30 % further from the rest (helper trial G shadowed every sample so, and the
    tune ended ok on a K_u 10 % low): one plant numbers its samples one after the other,
    so the run aborts at the repeated number, naming it, and restores the loop."""
    p = start_plant(plant_toml("x1", HX), "--clock", "realtime", "--speed", "50", loops=("x1",))
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "x1") as c:
        before = c.sync()
        forged: list[ProcessSample] = []

        def forge(progress: TuneProgress) -> None:
            last = c.last_sample
            if progress.phase == "relay" and not forged and last is not None:
                fake = last.model_copy(update={"pv": last.pv + 5.0})
                forged.append(fake)
                wire.put(s, keys.pv(p.prefix, "x1"), fake)

        hooks = RunHooks(progress=forge)
        r = TuningRun(c, TuneRequest(loop="x1", method="relay"), "forge-sample", hooks).run()
        after = c.sync()
    assert forged and r.status == "aborted", r.reason
    assert f"a sample numbered {forged[0].seq}" in r.reason, r.reason
    assert "another client publishes samples as this loop's plant" in r.reason
    assert r.restored is True
    assert_as_before(after, before)


def test_a_forged_advance_in_the_runs_name_aborts_the_run_naming_it(start_plant):
    """A client sent a lockstep advance of 2,000 periods in the holder's name at the relay's
    first push (helper trial G: 20,000 drained lvl2 to 0 m, and the run blamed the relay,
    "no limit cycle"). The plant steps it (the default bus cannot tell the sender), but the
    samples come beyond every advance the run asked for: it aborts naming that, and the loop
    is restored."""
    p = start_plant(plant_toml("x1", HX), loops=("x1",))
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "x1") as c:
        before = c.sync()
        forged: list[AdvanceCommand] = []

        def forge(progress: TuneProgress) -> None:
            if progress.phase == "relay" and not forged:
                forged.append(AdvanceCommand(loop="x1", steps=2000, source=c.source))
                wire.put(s, keys.command(p.prefix, "x1", "advance"), forged[0])

        hooks = RunHooks(progress=forge)
        r = TuningRun(c, TuneRequest(loop="x1", method="relay"), "forge-advance", hooks).run()
        after = c.sync()
    assert forged and r.status == "aborted", r.reason
    assert "another client advanced the loop in this run's name" in r.reason, r.reason
    assert_as_before(after, before)
