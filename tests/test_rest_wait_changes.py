"""The wait for rest before a tune takes the loop as it is when another client changes it
meanwhile (helper 60: an operator set hx1's setpoint 60 → 62 a second after `tune`; the run,
judging rest on the setpoint it read at its start, waited 990 s of sim time and ended "not
started: … +2 off its setpoint 59.9972: still settling" while the loop rested on 62).

In process (``LocalLoopClient``), the operator's commands applied to the plant's loop as
another client's reach it, its status seen by the run as the bus would show it."""

from __future__ import annotations

from services.autotuner.tuning import REST_RESTARTS, RunHooks, TuningRun
from services.offline.local_loop import NODE, LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import ModeCommand, SetpointCommand, TuneProgress, TuneRequest


class Operated(LocalLoopClient):
    """A loop another client writes to while the run waits: a setpoint at each of the run's
    first ``changes`` reads of samples."""

    def __init__(self, sim, setpoints: list[float]):
        super().__init__(sim)
        self.setpoints = list(setpoints)

    def samples(self, steps, band=None, record=None):
        if self.setpoints and self.lease is None:
            self.sim.apply(SetpointCommand(loop=self.loop, sp=self.setpoints.pop(0), source="op"))
            status = self.sim.status(NODE, "lockstep", "setpoint")
            self.last_status = status.model_copy(update={"by_source": "op"})
        return super().samples(steps, band, record)


def _hx1():
    """hx1 in auto on its PI, at rest on SP 60 (as after a tune)."""
    sim = build_plant({"seed": 1, "loops": {"hx1": {"model": "heat_exchanger"}}})["hx1"]
    sim.apply(ModeCommand(loop="hx1", mode="auto", source="op"))
    return sim


def test_a_setpoint_changed_while_the_run_waits_for_rest_is_waited_for_anew():
    sim = _hx1()
    assert sim.mode == "auto" and sim.sp == 60.0
    said: list[TuneProgress] = []
    client = Operated(sim, [62.0])
    req = TuneRequest(loop="hx1", method="relay")
    r = TuningRun(client, req, "x", RunHooks(progress=said.append)).run()
    assert r.status == "ok", r.reason
    rest = [p.message for p in said if p.phase == "rest"]
    assert any("the loop was changed by op as the run waited for its rest" in m for m in rest)
    assert any("SP 62" in m for m in rest)
    # the loop as the run found it after the change: restored to (and verified on) SP 62
    assert r.left["sp"] == 62.0


def test_an_operator_who_keeps_changing_it_is_left_to_finish():
    sim = _hx1()
    client = Operated(sim, [60.5 + k for k in range(REST_RESTARTS + 1)])
    r = TuningRun(client, TuneRequest(loop="hx1", method="relay"), "x", RunHooks()).run()
    assert r.status == "aborted" and r.untouched
    assert r.reason.startswith(
        f"not started: the loop was changed {REST_RESTARTS + 1} times while the run waited for "
        "its rest (last by op: now auto, SP 63.5"
    ), r.reason
    assert sim.sp == 63.5 and client.commands == []


class Watched(LocalLoopClient):
    """Another client only reads the loop (its sync's answer seen by the run at every read)."""

    def samples(self, steps, band=None, record=None):
        if self.lease is None:
            self.last_status = self.sim.status(NODE, "lockstep", "sync")
        return super().samples(steps, band, record)


def test_statuses_that_change_nothing_do_not_restart_the_wait():
    """A manual loop whose setpoint tracks its PV (``sp_track``) shows a new setpoint in every
    status: read by another client at each of the run's reads, it restarted the wait 3 times
    and aborted the run "changed 4 times" (helper 61's review). In manual the setpoint moves
    nothing: not a change."""
    spec = {"model": "heat_exchanger", "sp_track": True, "noise_std": 0.05}
    sim = build_plant({"seed": 1, "loops": {"hx1": spec}})["hx1"]
    assert sim.mode == "manual"
    said: list[TuneProgress] = []
    r = TuningRun(
        Watched(sim), TuneRequest(loop="hx1", method="relay"), "x", RunHooks(said.append)
    ).run()
    assert r.status == "ok", r.reason
    assert not any("changed" in (p.message or "") for p in said if p.phase == "rest")


def test_the_gains_before_the_run_are_those_the_lease_found():
    """An operator's gains set while the run waited for rest: the result's previous gains
    (the history's, the report's "before the run") were those read at the run's start."""
    from shared.messages import GainsCommand, PidGains

    sim = _hx1()
    mine = PidGains(kc=1.5, ti=80.0)

    class SetsGains(LocalLoopClient):
        def samples(self, steps, band=None, record=None):
            if self.lease is None and self.sim.pid.gains.kc != mine.kc:
                self.sim.apply(GainsCommand(loop="hx1", gains=mine, source="op"))
                status = self.sim.status(NODE, "lockstep", "gains")
                self.last_status = status.model_copy(update={"by_source": "op"})
            return super().samples(steps, band, record)

    req = TuneRequest(loop="hx1", method="relay", apply=False)
    r = TuningRun(SetsGains(sim), req, "x", RunHooks()).run()
    assert r.status == "proposed", r.reason
    assert r.previous_gains == mine and sim.pid.gains.kc == mine.kc  # restored to them


def test_the_wait_for_rest_says_how_long_it_watches():
    """A run first watches the PV over a window as long as the loop's Ti, even in manual
    (helper h6: lvl2 in manual, Ti 4000 s, watched 900 s of sim time — 3 minutes at ×5 —
    with nothing but "start" on the progress line). The wait says its window and why."""
    sim = build_plant({"seed": 1, "loops": {"lvl2": {"model": "tank_level_integrating"}}})["lvl2"]
    assert sim.mode == "manual" and sim.status(NODE, "lockstep", "x").gains.ti == 4000.0
    said: list[TuneProgress] = []
    req = TuneRequest(loop="lvl2", method="step")
    TuningRun(LocalLoopClient(sim), req, "x", RunHooks(progress=said.append)).run()
    rest = [p.message for p in said if p.phase == "rest"]
    # in the first 40 characters: what the CLI's progress line shows
    assert rest and rest[0][:40].startswith("rest window 900 s (Ti 4000 s, capped)"), rest
    assert "--rest-window" in rest[0], rest[0]
