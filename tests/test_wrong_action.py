"""A process whose gain has the other sign than the loop's action.

The relay pushes
the PV up, and it falls, so the relay never switches. It used to hold the output to its time
budget (14,400 s) and say only that no cycle came; now, once the PV has come to rest against
the push beyond twice the hysteresis, it aborts and names the action. An inverse response
(a right-half-plane zero) also starts the wrong way, but turns back (on a noisy PV its turn
may read at rest for a check, so the rest must hold from some time T to 2T: the wrong way
aborts at 156 s, not 80), and its ultimate point is measured as before (``tests.exact``).

The ramp's closed loop is positive feedback there: no trial oscillates, and its abort says
why when two trials of three or more went the other way from their setpoint bumps."""

from __future__ import annotations

from dataclasses import replace

import pytest

from services.autotuner.identify import methods
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest
from tests.exact import ultimate_point
from tests.plants import run_relay

WRONG = ([-2.0], [10.0, 1.0], 1.0, 0.1)  # −2 e^{−s}/(10s + 1) under a reverse-acting loop
INVERSE = ([-2.0, 1.0], [1.0, 3.0, 3.0, 1.0], 0.0, 0.01)  # (1 − 2s)/(s + 1)³
SAYS = "against the push — the loop is reverse-acting; is the process one for a direct-acting PID?"


def test_a_pv_at_rest_against_the_push_aborts_and_names_the_action():
    test = run_relay(*WRONG)
    assert test.phase == "aborted"
    assert test.reason.startswith("no limit cycle: the PV fell from 50 to ")
    assert "and came to rest with the output raised" in test.reason and SAYS in test.reason
    # at rest at 50 − 2·5 = 40 after a few time constants, not at the end of the budget
    assert test.t[-1] < 400.0 < test.config.max_time


def test_recorded_before_it_held_the_output_to_its_budget():
    test = run_relay(*WRONG, wrong_way=False)
    assert test.phase == "aborted" and test.t[-1] >= test.config.max_time
    assert test.reason.startswith("no limit cycle that repeats within 2% after 0 cycles")
    assert SAYS in test.reason  # the budget's abort says what the PV did, too


def test_an_inverse_response_starts_the_wrong_way_and_is_measured():
    ku, pu = ultimate_point(*INVERSE[:3])
    test = run_relay(*INVERSE)
    r = test.result
    assert r is not None, test.reason
    assert r.ku == pytest.approx(ku, rel=0.02)
    assert r.pu == pytest.approx(pu, rel=0.02)


RAMP_WRONG = {"model": "fopdt", "gain": -2.0, "time_constant": 10.0, "delay": 1.0}


def _ramp(table: dict, monkeypatch=None, recorded_before: bool = False):
    """(the run's result, its trials' sim times) of a ramp on ``table`` at 0.1 s samples."""
    if recorded_before:  # as a run recorded before the flag: the ramp runs on
        method = methods.METHODS["ramp"]
        before = replace(
            method, build=lambda st, setup: method.build(st, replace(setup, ramp_wrong_way=None))
        )
        monkeypatch.setitem(methods.METHODS, "ramp", before)
    sim = build_plant({"loops": {"n1": {**table, "sample_time": 0.1}}})["n1"]
    trials: list[float] = []

    def event(e) -> None:
        if e.kind == "trial_result":
            trials.append(e.t)

    hooks = RunHooks(event=event)
    req = TuneRequest(loop="n1", method="ramp")
    return TuningRun(LocalLoopClient(sim), req, "wrong", hooks).run(), trials


def test_a_ramp_whose_trials_go_against_their_bumps_stops_there_and_says_why():
    r, trials = _ramp(RAMP_WRONG)
    assert (r.status, r.restored) == ("aborted", True)
    assert r.reason.startswith(
        "ramp test: the loop never oscillated: the trials' PV went the "
        "other way from their setpoint bumps"
    )
    assert SAYS.split("against the push — ")[1] in r.reason
    # both trials went against their bumps: no third (positive feedback only brackets the
    # gain, 1/|K| = 0.5, at which the loop runs away without a period). The first counted as
    # going neither way before: judged over while its move was under 5 % of the bump
    assert len(trials) == 2


def test_recorded_before_the_ramp_bracketed_the_runaway_gain_to_the_end(monkeypatch):
    r, trials = _ramp(RAMP_WRONG, monkeypatch, recorded_before=True)
    assert r.status == "aborted" and "the loop never oscillated" in r.reason
    assert len(trials) > 3


def test_a_slow_process_past_the_first_cycles_time_budget_is_told_so():
    """Lags of hours ran the relay into its 14,400 s budget before two cycles, and the abort
    said only "no limit cycle that repeats" (helper trial F): it names --max-time now. Here
    e^{−s}/(10s + 1)'s first cycles (P_u ≈ 3.7 s) cannot come within a 5 s budget."""
    test = run_relay([1.0], [10.0, 1.0], 1.0, 0.1, max_time=5.0)
    assert test.phase == "aborted"
    assert "--max-time 5 s, ran out: a slower process needs a longer one" in test.reason
