"""The run's safety logic (apply, verify, restore) against an in-process loop: the exact state
it leaves the loop in after an ok run, a refusal and an abort mid-test, and that nothing is
written to the loop once the run has let it go.

The plant is 6/((s+1)(s+2)(s+3)) (K_u = 10, P_u = 2π/√11 ≈ 1.9 s), noise-free, sampled at 20 ms
(~95 samples per period): a whole relay run takes a fraction of a second in process.
"""

from __future__ import annotations

import threading

import pytest

from services.autotuner.commands.tune import format_result
from services.autotuner.identify.step_test import StepTestAborted, StepTestConfig
from services.autotuner.loop_client import CommandRefused, LeaseLost, PlantLost
from services.autotuner.step_run import run_step_test
from services.autotuner.tuning import RunHooks, TuneRefused, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.control.record_stops import SettleRule
from shared.messages import (
    GainsCommand,
    LeaseCommand,
    ModeCommand,
    OutputCommand,
    PidGains,
    ReleaseCommand,
    SetpointCommand,
    TuneProgress,
    TuneRequest,
)
from tests.plants import transfer_function_loop

OLD_GAINS = {"kc": 2.0, "ti": 2.0}
WRITES = (GainsCommand, ModeCommand, OutputCommand, SetpointCommand)


def third_order_loop(mode: str = "manual", setpoint: float | None = None):
    cfg = {
        "model": "transfer_function",
        "num": [6.0],
        "den": [1.0, 6.0, 11.0, 6.0],
        "sample_time": 0.02,
        "noise_std": 0.0,
        "mode": mode,
        "pid": dict(OLD_GAINS),
    }
    if setpoint is not None:
        cfg["setpoint"] = setpoint
    return build_plant({"seed": 1, "loops": {"x": cfg}})["x"]


def state(client: LocalLoopClient) -> tuple:
    """What a supervisor sets: mode, setpoint, gains, and the output when in manual (in auto
    the PID block moves it)."""
    st = client.sync()
    return st.mode, st.sp, st.gains, st.op if st.mode == "manual" else None


def run(client: LocalLoopClient, hooks: RunHooks | None = None, **req):
    return TuningRun(client, TuneRequest(loop="x", **req), "unit", hooks).run()


def assert_let_go(client: LocalLoopClient) -> None:
    """The run's last command gives the lease back; no write follows it, and the loop holds
    what it was left with while it runs on."""
    kinds = [type(c) for c in client.commands]
    last_release = max(i for i, k in enumerate(kinds) if k is ReleaseCommand)
    assert not [k for k in kinds[last_release:] if k in WRITES]
    assert not client.holding
    left = state(client)
    client.advance(500)
    assert state(client) == left


def test_an_ok_run_applies_exactly_the_chosen_gains():
    loop = third_order_loop()
    client = LocalLoopClient(loop)
    before = client.sync()
    r = run(client, method="relay")
    assert (r.status, r.applied, r.restored) == ("ok", True, False), r.reason
    st = client.sync()
    chosen = r.chosen["isa"]
    assert st.mode == "auto"
    assert st.gains == PidGains(kc=chosen["kc"], ti=chosen["ti"], td=chosen["td"])
    # a loop that was in manual is held at the PV it rested at (noise-free: the PV itself)
    assert st.sp == pytest.approx(before.pv, abs=1e-9)
    assert r.previous_gains == before.gains
    assert isinstance(client.commands[0], LeaseCommand)
    assert_let_go(client)


def test_a_refusal_restores_an_auto_loop_exactly():
    """An Ms bound no rule can meet (1.01): the gains are refused and the loop is put back
    as it was — in auto, at its setpoint, with its old gains."""
    loop = third_order_loop("auto", setpoint=50.0)
    client = LocalLoopClient(loop)
    client.advance(2000)  # 40 s: at rest on its setpoint
    before = state(client)
    r = run(client, method="relay", ms_bound=1.01)
    assert (r.status, r.applied, r.restored) == ("rejected", False, True)
    assert r.reason.startswith("no rule could be recommended"), r.reason
    assert "predicted Ms" in r.reason and "above the bound 1.01" in r.reason
    assert state(client) == before
    assert before[:3] == ("auto", 50.0, PidGains(**OLD_GAINS))
    assert_let_go(client)
    # the identification is on record all the same: `autotune apply --rule` sizes its
    # verification on it (a refused run's record had none, and apply could not use it)
    assert r.timescale is not None and r.timescale > 0 and r.noise is not None


def test_a_refused_run_waits_for_the_return_on_the_time_scale_it_identified():
    """Every rule refused (an Ms bound of 1.01) on e^{−5s}/((10s+1)(60s+1)) from manual: the
    wait for the PV to come back was sized without the identification (refused, it was
    dropped): 60 s for a 60 s lag, and the crest of the relay's last swing, flat over a
    15 s window, was called "at rest off it" 0.45 up (on hx1). Sized on the relay's P_u (5
    P_u), the PV is seen back where it was."""
    cfg = {
        "model": "transfer_function",
        "num": [1.0],
        "den": [600.0, 70.0, 1.0],
        "delay": 5.0,
        "sample_time": 0.25,
        "noise_std": 0.0,
        "pid": dict(OLD_GAINS),
    }
    client = LocalLoopClient(build_plant({"seed": 1, "loops": {"x": cfg}})["x"])
    before = state(client)
    r = run(client, method="relay", ms_bound=1.01)
    assert (r.status, r.restored) == ("rejected", True), r.reason
    assert state(client) == before
    left = r.left
    assert left["returned"] is True, left
    assert abs(left["pv"] - left["pv_target"]) <= left["band"], left
    assert left["waited"] > 60.0  # longer than the 60 s it was cut to


def test_an_abort_mid_test_restores_a_manual_loop_exactly():
    """Cancelled at the relay's first reported cycle: the loop is back in manual at its old
    output, setpoint and gains."""
    loop = third_order_loop()
    client = LocalLoopClient(loop)
    before = state(client)
    cancel = threading.Event()
    phases: list[str] = []

    def progress(p: TuneProgress) -> None:
        phases.append(p.phase)
        if p.cycles >= 1:
            cancel.set()

    r = run(client, RunHooks(progress=progress, cancelled=cancel), method="relay")
    assert (r.status, r.reason, r.restored) == ("aborted", "cancelled", True)
    assert r.applied is not True
    assert state(client) == before
    # not waited for: where the PV heads is not known from one sample, so it is not "back
    # where it was" (a relay cancelled mid-swing was, at 50.17 for 49.99 ± 0.2 on its way to
    # 50.74: helper trial)
    assert r.left["pv_rest"] is None and r.left["returned"] is not True, r.left
    # it was mid-test: the relay had switched the output before the cancel
    assert any(isinstance(c, OutputCommand) and c.op != before[3] for c in client.commands)
    assert_let_go(client)


def test_an_abort_mid_test_puts_an_auto_loop_back_at_its_output_too():
    """Cancelled mid-relay, a loop that was in auto goes back to auto from the output it had
    at rest, not from the relay's level (auto from there upset the process for an integral
    time after "restored"); and the plant's own restore (a lease that lapsed) does the same."""
    loop = third_order_loop("auto", setpoint=50.0)
    client = LocalLoopClient(loop)
    client.advance(2000)  # 40 s: at rest on its setpoint
    op_rest = client.sync().op
    snap = loop.snapshot()
    cancel = threading.Event()

    def progress(p: TuneProgress) -> None:
        if p.cycles >= 1:
            cancel.set()

    r = run(client, RunHooks(progress=progress, cancelled=cancel), method="relay")
    assert (r.status, r.reason, r.restored) == ("aborted", "cancelled", True)
    # the output back where it rested before auto took over (the first sample after moves
    # it by Kc·(SP − PV) at most: the PV is back near its setpoint)
    assert r.left["mode"] == "auto"
    assert r.left["op"] == pytest.approx(op_rest, abs=0.5)
    relay = [c.op for c in client.commands if isinstance(c, OutputCommand)]
    assert any(abs(op - op_rest) > 2.0 for op in relay)  # the relay had moved it
    loop.pid.set_mode("manual", loop.sp, loop.pv)
    loop.pid.set_output(op_rest - 5.0)  # as a relay leaves it
    loop.restore(snap)
    assert (loop.mode, loop.op) == ("auto", snap.op)


def test_a_restore_the_plant_did_not_confirm_is_left_to_the_plant_with_the_release():
    """The plant fell silent mid-relay (paused), so the run's restore went unconfirmed; its
    release, queued behind the pause, reached the plant before the run token's disappearance
    and let go of a loop left in manual at the relay's output (helper trial, realtime ×20).
    The release now asks the plant to restore its snapshot from the lease: the loop is as
    before, and the run says the plant restored it."""

    class Silent(LocalLoopClient):
        silent = False

        def sync(self):
            if self.silent:
                raise PlantLost("loop 'x': no message from the plant for 5 s")
            return super().sync()

    loop = third_order_loop("auto", setpoint=50.0)
    client = Silent(loop)
    client.advance(2000)  # at rest on its setpoint
    before = state(client)
    releases: list[ReleaseCommand] = []

    def progress(p: TuneProgress) -> None:
        if p.cycles >= 1 and not releases:  # (the run's last progress keeps its cycles too)
            client.silent = True  # from here every confirmation fails

    send = client._apply

    def apply(cmd):
        if isinstance(cmd, ReleaseCommand):
            releases.append(cmd)
            client.silent = False  # the plant back: it reads the queued release
        send(cmd)

    client._apply = apply
    r = run(client, RunHooks(progress=progress), method="relay")
    assert r.status == "aborted" and "no message from the plant" in r.reason
    assert [c.restore for c in releases] == [True]
    assert r.restored and r.reason.endswith("the plant restored the loop"), r.reason
    assert state(client) == before


def test_an_abort_keeps_its_reason_when_the_plant_is_lost_as_the_test_lets_go():
    """The relay aborted at its PV limits, and the plant was lost as the test put its output
    back (the tuner paused there, helper trial E): the reason said only "lost the plant",
    the limits nowhere but in the record's events. Both are said, the abort first."""

    class Lost(LocalLoopClient):
        def command(self, cmd):
            moved = any(isinstance(c, OutputCommand) for c in self.commands)
            if isinstance(cmd, OutputCommand) and moved and cmd.op == self.start_op:
                raise PlantLost("loop 'x': lost the plant")
            return super().command(cmd)

    loop = third_order_loop()
    client = Lost(loop)
    client.start_op = client.sync().op
    pv = client.sync().pv
    r = run(client, method="relay", pv_limits=(pv - 0.05, pv + 0.05))
    assert r.status == "aborted"
    assert r.reason.startswith("relay test: PV "), r.reason
    assert "left its limits" in r.reason and "; then loop 'x': lost the plant" in r.reason
    # the relay's advice stays with its reason (on the realtime clock the plant's watchdog
    # trips at the same limits, and the advice was lost: helper trial)
    reason = r.reason.split("; then ")[0]
    assert "--amplitude" in reason or "too little" in reason, r.reason


def test_leaving_the_pv_limits_aborts_and_restores():
    """The relay drives the PV out of a ±0.05 band around its rest (its swing is 4d/(πK_u)
    ≈ 0.64 for d = 5 %): aborted, restored."""
    loop = third_order_loop()
    client = LocalLoopClient(loop)
    before = state(client)
    pv = client.sync().pv
    r = run(client, method="relay", pv_limits=(pv - 0.05, pv + 0.05))
    assert (r.status, r.restored) == ("aborted", True)
    assert state(client) == before
    assert_let_go(client)


def test_a_batched_record_stops_at_the_crossing_with_the_loop_left_there():
    """The verification's record advances in batches (to its next judging point), each
    banded by the PV limits: it stops at the first sample past them, and the loop has not
    run a sample further (the plant stopped the advance there)."""
    loop = third_order_loop("auto", setpoint=50.0)
    client = LocalLoopClient(loop)
    tuning = TuningRun(client, TuneRequest(loop="x", pv_limits=(40.0, 55.0)), "unit")
    start = client.sync().seq
    client.command(SetpointCommand(loop="x", sp=60.0, source=client.source))
    seconds = 20.0
    judge = round(seconds / loop.sample_time) // 100  # the record's judging interval
    never = SettleRule(10**6, 50.0, 0.0)  # a record far shorter than its settling window
    t, y, _, why = tuning._record(seconds, never)
    assert why is not None and why.startswith("the PV left its limits [40, 55]")
    assert y[-1] > 55.0 and (y[:-1] <= 55.0).all()
    k = y.size  # samples taken, the last one past the limit
    assert k % (8 * judge)  # mid-batch: the plant, not a judging point, ended it
    assert client.sync().seq - start == k
    assert tuning._t == t[-1] == client.sync().t  # the run's clock is the loop's


def test_gains_applied_without_verification_are_unverified_never_ok():
    """``ok`` means the gains were tried on the loop and passed. Applied without verification
    (``verify = false``, ``--no-verify``), the run says so: status ``unverified`` with the
    reason, the gains in the loop (``applied``), no verification figures; verified, ``ok``
    carries its acceptance."""
    unverified = TuningRun(
        LocalLoopClient(third_order_loop()), TuneRequest(loop="x", verify=False), "unit"
    ).run()
    assert unverified.status == "unverified" and unverified.applied is True
    assert "without verification" in unverified.reason and "not known to be safe" in (
        unverified.reason
    )
    assert unverified.after is None and unverified.acceptance is None
    verified = TuningRun(LocalLoopClient(third_order_loop()), TuneRequest(loop="x"), "unit").run()
    assert verified.status == "ok" and verified.applied is True and verified.reason is None
    assert verified.after is not None and verified.acceptance["passed"] is True


def test_a_request_refused_before_any_write_says_nothing_was_sent():
    """The PV already outside the limits asked for: the run ends before its first command,
    and says so (not "the loop may not have been restored")."""
    client = LocalLoopClient(third_order_loop())
    before = state(client)
    r = run(client, method="relay", pv_limits=(60.0, 70.0))
    assert r.status == "failed" and r.reason.startswith("pv_limits: the PV 50 is already outside")
    assert (r.untouched, r.restored, r.applied) == (True, True, False)
    assert client.commands == [] and state(client) == before
    assert "nothing was sent to the loop" in format_result(r)
    assert "WARNING" not in format_result(r)
    # a relay hysteresis that cannot be crossed within the limits (1e308 held the relay's
    # first push for hours of sim time: helper trial G)
    r = run(client, method="relay", pv_limits=(40.0, 60.0), hysteresis=10.0)
    assert r.status == "failed" and r.reason.startswith("hysteresis: 10 "), r.reason
    assert r.untouched and client.commands == [] and state(client) == before


class RunningOnClient(LocalLoopClient):
    """The loop on the realtime clock, as the run sees it: the plant's time goes on between
    the run's looks (here three samples at each sync, as if the run computed meanwhile)."""

    def __init__(self, loop):
        super().__init__(loop)
        self.info = loop.info("sim", "realtime", 1.0)

    def sync(self):
        if hasattr(self, "info") and self.info.clock == "realtime":
            self.advance(3)
        return super().sync()


def test_the_verifications_mark_and_gains_carry_the_time_the_plant_applied_them():
    """In realtime the gains under verification are stamped with the plant's time after a
    sync, and so is the ``verify`` mark that names them: the recording's mark and commands
    fall where the loop's response starts (the mark came first, seconds early at ×20)."""
    client = RunningOnClient(third_order_loop("auto", setpoint=50.0))
    marks: list[TuneProgress] = []
    result = run(client, RunHooks(progress=marks.append))
    assert result.status == "ok", result.reason
    verify = [p for p in marks if p.phase == "verify"]
    gains = [c for c in client.commands if isinstance(c, GainsCommand)]
    assert len(verify) == 2 and len(gains) >= 2  # the old gains, then the new
    for mark, cmd in zip(verify, gains, strict=False):
        kc = float(mark.message.split()[1].rstrip(","))
        assert (cmd.gains.kc, cmd.t) == (pytest.approx(kc, rel=1e-3), mark.t)


def test_a_slow_step_on_a_realtime_loop_in_process_is_watched_without_failing(monkeypatch):
    """A heavy step that outlasts the run's first check (a quarter of a second) on the
    realtime clock has the run look at the samples that came meanwhile: an in-process loop
    has none (it steps only when asked), where the look used to fail the run."""
    import services.autotuner.tuning as tuning

    monkeypatch.setattr(tuning, "COMPUTE_CHECK", 0.0)  # every step outlasts its first check
    client = RunningOnClient(third_order_loop("auto", setpoint=50.0))
    assert client.hold_arrived() == []
    result = run(client, RunHooks())
    assert result.status == "ok", result.reason


def test_a_plant_lost_before_the_lease_leaves_the_loop_untouched():
    """The plant was lost (the tuner paused 15 s in its rest check, its session's token
    gone) at the run's last sync before the lease: the run ended "failed", a traceback in
    the tuner's log. Nothing was sent to the loop: aborted, untouched."""

    class Lost(LocalLoopClient):
        lost = False  # from the rest check's first samples on

        def samples(self, *args, **kwargs):
            self.lost = True
            return super().samples(*args, **kwargs)

        def sync(self):
            if self.lost:
                raise PlantLost("loop 'x': the plant was lost; sync not sent")
            return super().sync()

    client = Lost(third_order_loop())
    r = run(client, method="relay")
    assert (r.status, r.restored, r.untouched) == ("aborted", True, True), r.reason
    assert r.reason == "loop 'x': the plant was lost; sync not sent"
    assert client.commands == []


class TrippingOnClient(RunningOnClient):
    """A realtime plant that restores the loop at the first sample outside its lease's PV
    limits (``PlantService.tick``), as it does for a paused tuner, and a client that learns
    of it as ``LoopClient`` does: the next sync or command raises LeaseLost (once: the
    client no longer holds the loop), and the plant refuses the holder's writes from then on
    (lapsed)."""

    tripped: str | None = None

    def advance(self, steps, band=None, record=None):
        out = []
        for s in super().advance(steps, band, record):
            out.append(s)
            limits = self.lease.pv_limits if self.lease is not None else None
            if limits is not None and self.tripped is None and not limits[0] <= s.pv <= limits[1]:
                self.sim.restore(self._held_from)
                self.tripped = f"the PV left the experiment's limits at t = {s.t:g} s"
                break
        return out

    def _told(self) -> None:
        if self.tripped is not None and self.lease is not None:
            self.lease, self._held_from = None, None
            raise LeaseLost(
                "loop 'x': lease lost: the plant's watchdog restored the loop to its state "
                f"before the test: {self.tripped}"
            )

    def sync(self):
        self._told()
        return super().sync()

    def command(self, cmd):
        self._told()
        if self.tripped is not None and not isinstance(cmd, LeaseCommand | ReleaseCommand):
            raise CommandRefused(f"loop 'x': {cmd.kind} refused: no longer holds the loop")
        return super().command(cmd)


def test_a_realtime_run_names_its_limits_and_waits_for_the_pv_the_plant_restored():
    """On the realtime clock the run's lease names its PV limits, and the plant restores the
    loop at the first sample outside them; the run says so, and waits for the PV's return as
    after its own restore (it had returned at once: "not waited for")."""
    client = TrippingOnClient(third_order_loop())
    before = state(client)
    pv = client.sync().pv
    r = run(client, method="relay", pv_limits=(pv - 0.05, pv + 0.05))
    lease = next(c for c in client.commands if isinstance(c, LeaseCommand))
    assert lease.pv_limits == (pv - 0.05, pv + 0.05)
    assert (r.status, r.restored) == ("aborted", True), r.reason
    # said once: the plant restored it, and why
    assert r.reason.count("restored the loop") == 1, r.reason
    assert r.reason.endswith(
        f"before the test: the PV left the experiment's limits at t = {r.pv_outside['first_t']:g} s"
    ), r.reason
    assert r.left["pv_target"] == pytest.approx(pv) and r.left["waited"] > 0.0
    assert state(client) == before
    # in lockstep the plant steps only as the run asks: the lease names no limits
    client = LocalLoopClient(third_order_loop())
    run(client, method="relay", pv_limits=(pv - 0.05, pv + 0.05))
    assert next(c for c in client.commands if isinstance(c, LeaseCommand)).pv_limits is None


def test_a_long_computation_on_a_realtime_loop_is_said(monkeypatch):
    """Its compute workers stopped 70 s: the realtime loop ran on at a held output, and the
    ok run said nothing of it (helper trial E). Here every computation counts as long."""
    import services.autotuner.tuning as tuning

    monkeypatch.setattr(tuning, "SLOW_COMPUTE", 0.0)
    r = run(RunningOnClient(third_order_loop("auto", setpoint=50.0)), RunHooks())
    assert r.status == "ok", r.reason
    assert any(w.startswith("a computation of this run took") for w in r.warnings), r.warnings
    # in lockstep the plant waits: nothing to say
    r = run(LocalLoopClient(third_order_loop("auto", setpoint=50.0)), RunHooks())
    assert not any(w.startswith("a computation of this run took") for w in r.warnings)


def test_an_ok_run_whose_release_the_plant_did_not_confirm_says_so():
    """The plant paused (SIGSTOP, 20 s) as an ok run ended: its release and last sync went
    unanswered, and the run said ok with no word, though a lease that lapses before the
    plant reads the release has its watchdog restore the state before the test, undoing
    the gains. Still ok (the gains were verified), with a warning that says so."""

    class Paused(LocalLoopClient):
        def command(self, cmd):
            if isinstance(cmd, ReleaseCommand):
                raise PlantLost("loop 'x': no message from the plant for 5 s")
            return super().command(cmd)

    r = run(Paused(third_order_loop()))
    assert r.status == "ok", r.reason
    (note,) = [w for w in r.warnings if w.startswith("the plant did not confirm the lease's")]
    assert "release (loop 'x': no message from the plant for 5 s)" in note
    assert "undoing these gains" in note


def test_an_apply_request_with_gains_no_tuning_gives_is_refused_by_the_tuner_itself():
    """`autotune apply` reads its gains from a run file; the request itself names them, and a
    hand-made one (an operator's, helper trial G) applied Kc 1e6 and Ti 0.01 s unverified:
    the valve banged 0↔100 %. The tuner holds them to what `set` allows, writing nothing, and
    before its wait for rest (a hand-made request without a time scale waited 48 s there
    for the refusal: helper trial)."""
    for gains, scale, field in (
        (PidGains(kc=1e6, ti=10.0), 10.0, "apply_gains.kc"),
        (PidGains(kc=1.0, ti=0.001), 10.0, "apply_gains.ti"),
        (PidGains(kc=1.0, ti=10.0), None, "apply: the request names no gains or time scale"),
    ):
        client = LocalLoopClient(third_order_loop("auto", setpoint=50.0))
        before = state(client)
        t0 = client.sync().t
        r = run(
            client,
            apply_from="000000000000",
            apply_gains=gains,
            apply_timescale=scale,
            verify=False,
        )
        assert r.status == "rejected" and r.reason.startswith(field), r.reason
        assert r.applied is not True and r.untouched
        assert "nothing was applied" in r.reason or scale is None
        assert not client.commands  # not even a lease
        assert r.t == t0 and state(client) == before  # no wait for rest


def test_a_step_test_the_plant_restored_at_its_limits_says_so_and_waits():
    """The plant restored the loop at the step's PV limits (realtime): the step test's own
    restore then met the lost lease, and it said "LOOP NOT RESTORED" of a restored loop and
    did not wait for the PV (helper review). Now: restored, by the plant, the PV waited for."""
    client = TrippingOnClient(third_order_loop())
    before = state(client)
    pv = client.sync().pv
    with pytest.raises(StepTestAborted) as aborted:
        run_step_test(client, StepTestConfig(size=5.0, pv_limits=(pv - 0.3, pv + 0.3)))
    said = str(aborted.value)
    assert "left its limits" in said and "; loop restored (manual, " in said, said
    assert "by the plant: loop 'x': lease lost" in said and "; the PV back at rest at" in said
    assert state(client) == before


def test_gains_the_plant_took_back_before_the_release_are_not_called_ok():
    """The plant took the loop back between the run's last write and its release (its
    watchdog, or the PV past the lease's limits in realtime) and restored the state before
    the test: the release found no lease to end, and the run said ok of gains the loop no
    longer held (review). The result says what the loop holds."""

    class TakenBack(LocalLoopClient):
        def _apply(self, cmd):
            if isinstance(cmd, ReleaseCommand) and self._held_from is not None:
                self.sim.restore(self._held_from)  # as the plant's watchdog does
            super()._apply(cmd)

    client = TakenBack(third_order_loop("auto", setpoint=50.0))
    client.advance(2000)  # at rest on its setpoint
    before = state(client)
    r = run(client)
    assert (r.status, r.applied, r.restored) == ("aborted", False, True), r.reason
    assert r.reason.startswith(
        "the new gains were applied and verified, but the loop does not hold them now (auto, "
        "Kc 2, Ti 2 s, Td 0 s): the plant restored its state before the test"
    ), r.reason
    assert state(client) == before
    # and an ok run's gains, held, stay ok
    assert run(LocalLoopClient(third_order_loop("auto", setpoint=50.0))).status == "ok"


def test_the_verification_steps_within_the_runs_pv_limits():
    """The verification's setpoint step was sized on the PV's range alone: told to keep hx1
    within [59, 61], a run stepped its setpoint to 62.88 and the PV went to 62.79 (helper
    trial). Here the relay's swing (±0.64) fits in ±1 about the rest, and the old 2.0 step
    did not; the step now fits with its overshoot up to --max-overshoot."""
    client = LocalLoopClient(third_order_loop("auto", setpoint=50.0))
    client.advance(2000)  # at rest on its setpoint
    r = run(client, method="relay", pv_limits=(49.0, 51.0))
    assert r.status == "ok", r.reason
    assert 0 < abs(r.after.sp_step) <= 1.0 / 1.35 and r.pv_outside is None
    # no room for a step the noise allows reading: refused, nothing stepped
    tight = TuningRun(client, TuneRequest(loop="x", pv_limits=(49.99, 50.01)), "unit")
    with pytest.raises(TuneRefused, match=r"verification: the PV limits \[49.99, 50.01\] "):
        tight._within_limits(50.0, 1, 2.0, 0.01)


def test_rejected_gains_whose_restore_failed_are_left_to_the_plant_to_restore():
    """Gains the verification rejects are taken off again; a run whose restore then failed
    (the plant lost as it was sent) still counted the loop as restored, from the rejection
    alone: its release did not ask the plant to restore its snapshot, and the loop kept the
    rejected gains. Now the release asks, and the run says what the plant shows."""

    class LostAtRestore(LocalLoopClient):
        def command(self, cmd):
            old = isinstance(cmd, GainsCommand) and cmd.gains == PidGains(**OLD_GAINS)
            sent = [c.gains for c in self.commands if isinstance(c, GainsCommand)]
            if old and any(g != cmd.gains for g in sent):  # the restore, after the new gains
                raise PlantLost("loop 'x': the plant was lost; gains not sent")
            return super().command(cmd)

    client = LostAtRestore(third_order_loop("auto", setpoint=50.0))
    client.advance(2000)
    before = state(client)
    # the recommended gains pass the noise's through them at a limit asked to be tiny:
    # rejected (no setpoint weight can cure it, as it may an overshoot over the limit).
    # (P-only gains, whose offset made them worse than before, were the case here; they are
    # now refused before they are switched: tests/test_p_only_offset.py)
    r = run(client, max_op_noise=0.0001)
    assert (r.status, r.restored) == ("rejected", True), r.reason
    assert "output noise" in r.reason and "above the limit 0.0001 %" in r.reason
    # not "previous gains restored" (the run's own restore failed): the plant's, said
    assert r.reason.endswith(
        "the run could not restore the state before the test itself (its release asks the "
        "plant to); the plant restored the loop"
    ), r.reason
    releases = [c for c in client.commands if isinstance(c, ReleaseCommand)]
    assert [c.restore for c in releases] == [True]
    assert state(client) == before


def test_a_step_whose_model_is_refused_points_to_the_relay():
    """1/(4s² + 0.8s + 1)·e^{−0.5s} (ζ 0.2): a step's SOPDT cannot follow its ringing, the
    model is refused and no rule is left; the refusal says which test needs no model, and the
    relay tunes the loop. The loop is left as it was."""

    def tune(method: str):
        client = LocalLoopClient(transfer_function_loop([1.0], [4.0, 0.8, 1.0], 0.5, 0.05, 0.005))
        before = state(client)
        return run(client, method=method), before, state(client)

    r, before, after = tune("step")
    assert (r.status, r.applied, r.restored) == ("rejected", False, True), r.reason
    assert "fit misses the record" in r.reason
    assert r.reason.endswith("(--method relay)")
    assert after[:3] == before[:3]
    assert tune("relay")[0].status == "ok"


def test_a_previous_integral_time_far_beyond_the_loop_is_watched_as_none():
    """hx1 in auto under Kc 2 with Ti 1e4 s, a DCS's "integral off" (228 of its 43.8 s time
    scales): the verification of those gains (the "before") watched each step for 8·Ti,
    80,000 s (125,000 s of sim time in all, review), where 15 time scales (657 s) is the
    bound the README gives; a Ti of 1e9 s never ended. Watched as no integral action, the run
    takes a few thousand seconds of sim time."""
    import tomllib

    from services.autotuner.tuning import VERIFY_TI_SCALES
    from services.plant_sim.plant_file import default_plant_path

    with open(default_plant_path(), "rb") as f:
        doc = tomllib.load(f)
    doc["seed"] = 0
    sim = build_plant(doc, "unit")["hx1"]
    client = LocalLoopClient(sim)
    client.command(GainsCommand(loop="hx1", gains=PidGains(kc=2.0, ti=1e4), source="x"))
    client.command(ModeCommand(loop="hx1", mode="auto", source="x"))
    client.advance(3000)  # at rest in auto
    r = run(client, method="relay", rule="amigo-pid")
    assert r.status == "ok", r.reason
    assert VERIFY_TI_SCALES * r.timescale < 1e4  # beyond the bound: off
    # the run from its start, the verifications' steps (15 scales each) and waits included
    assert r.sim_duration < 20 * 15 * r.timescale, (r.sim_duration, r.timescale)


def test_an_ok_run_is_back_where_it_was_as_its_verification_saw():
    """Gains that passed their verification were left on once it saw the loop back at rest
    on its setpoint: the run says so without a wait of its own (the demo's "the PV is back
    where it was")."""
    client = LocalLoopClient(third_order_loop("auto", setpoint=50.0))
    client.advance(2000)  # at rest on its setpoint
    r = run(client, method="relay")
    assert r.status == "ok", r.reason
    assert r.left["returned"] is True, r.left


class _TakenBack(LocalLoopClient):
    """As the plant's watchdog (or its lease's PV limits) would: the loop taken back to its
    state before the test as the run's release is read, then moved on (review)."""

    def _apply(self, cmd):
        if isinstance(cmd, ReleaseCommand) and self._held_from is not None:
            self.sim.restore(self._held_from)
            self.lease, self._held_from = None, None
            self.sim.apply(ModeCommand(loop=self.loop, mode="manual"))
            for _ in range(200):
                self.last_sample = self.sim.advance()
            return
        super()._apply(cmd)


def test_a_run_whose_loop_was_taken_back_is_not_back_as_its_verification_saw():
    """Verified, then taken back (to manual, its PV still near the setpoint) before the run
    let go: not "back where it was" on the verification's word, which was of another loop
    (it said so of a PV at 79.96 for 50 ± 0.1: review); its last sample alone, not waited
    for, says nothing."""
    spec = {"model": "fopdt", "gain": 1.0, "time_constant": 3.0, "delay": 0.5}
    cfg = {**spec, "sample_time": 0.1, "noise_std": 0.01, "pid": {"kc": 0.5, "ti": 5.0}}
    sim = build_plant({"seed": 0, "loops": {"x": cfg}}, "t")["x"]
    r = run(_TakenBack(sim), method="relay")
    assert r.status == "aborted", r.reason
    assert r.left["mode"] == "manual" and r.left["returned"] is None, r.left
