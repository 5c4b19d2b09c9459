"""``tune``'s submit with its stop signals held (``_held_start``): a signal while the request
is in flight is kept until the run's id is known (then the run is cancelled by it, see
tests/integration/test_tuner.py); a second one leaves at once; a signal the process ignores
stays ignored; the handlers are the caller's again afterwards."""

from __future__ import annotations

import os
import signal

import pytest

from services.autotuner.commands.tune import (
    Interrupted,
    _held_start,
    _interrupt,
    cancel_on_stop_signals,
)
from shared.messages import TuneResult

ACCEPTED = object()


def starting(*sigs: signal.Signals):
    """A start() that receives ``sigs`` while the request is in flight."""

    def start():
        for sig in sigs:
            os.kill(os.getpid(), sig)
        return ACCEPTED

    return start


@pytest.fixture
def handlers():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    yield before
    for s, h in before.items():
        signal.signal(s, h)


def test_a_signal_in_flight_is_held_and_reported(handlers):
    assert _held_start(starting(signal.SIGTERM)) == (ACCEPTED, True)
    assert {s: signal.getsignal(s) for s in handlers} == handlers


def test_no_signal_no_cancel(handlers):
    assert _held_start(starting()) == (ACCEPTED, False)


def test_a_second_signal_leaves_at_once(handlers):
    with pytest.raises(KeyboardInterrupt):
        _held_start(starting(signal.SIGINT, signal.SIGHUP))
    assert {s: signal.getsignal(s) for s in handlers} == handlers


def test_an_ignored_signal_stays_ignored(handlers):
    """SIGINT of a job a script put in the background is ignored: held, it cancelled runs."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    assert _held_start(starting(signal.SIGINT)) == (ACCEPTED, False)
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_nohup_keeps_the_run_going_through_a_hangup(handlers):
    """``nohup autotune tune``: SIGHUP ignored stays ignored (it cancelled the run); SIGTERM
    still cancels."""
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    cancel_on_stop_signals()
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    assert signal.getsignal(signal.SIGTERM) is _interrupt


def _result(**fields):
    base = dict(run_id="r1", loop="hx1", t=10.0, method="relay", rule="auto", status="ok")
    return TuneResult(**{**base, **fields})


def test_a_cancel_too_late_says_the_gains_are_in_the_loop():
    """Ctrl-C as a run ends ok: its gains stay (the cancel came after), and the client says so
    instead of "the tuner restores the loop" (it said only "interrupted")."""
    said = Interrupted(_result(applied=True), "loop hx1 now: auto").summary()
    assert said.startswith("run r1 had ended ok before the cancel reached it: its gains are in")
    assert "`autotune revert hx1`" in said and said.endswith("loop hx1 now: auto")


def test_a_cancelled_run_says_how_it_ended_and_whether_restored():
    r = _result(status="aborted", reason="cancelled", applied=False, restored=False)
    said = Interrupted(r, "loop hx1 now: manual").summary()
    assert said == "run r1 cancelled, aborted: cancelled; loop NOT restored; loop hx1 now: manual"


def test_a_run_that_ended_on_its_own_first_is_not_called_cancelled():
    r = _result(status="proposed", applied=False, restored=True)
    said = Interrupted(r, "loop hx1 now: manual").summary()
    assert said.startswith("run r1 had ended proposed before the cancel reached it; loop restored")


def test_a_run_cancelled_before_it_wrote_says_the_loop_untouched():
    """Ctrl-C in the rest wait: "nothing was sent to the loop", then "loop restored" of a
    loop the run never wrote to (helper trial)."""
    r = _result(status="aborted", reason="cancelled", applied=False, restored=True, untouched=True)
    said = Interrupted(r, "loop lvl2 now: manual").summary()
    assert "loop untouched (nothing was sent to it)" in said and "restored" not in said


def test_a_cancelled_run_whose_pv_is_not_back_says_so():
    """A cancelled ramp on a level: restored to manual at its output, its PV stays where the
    test left it, and the client said only "loop restored" (helper trial, lvl2)."""
    left = {"mode": "manual", "sp": 1.5, "op": 50.0, "pv": 1.525, "pv_target": 1.5}
    r = _result(
        status="aborted",
        reason="cancelled",
        applied=False,
        restored=True,
        left={**left, "band": 0.008, "returned": False, "gains": {"kc": 1.0}},
    )
    said = Interrupted(r, "loop lvl2 now: manual").summary()
    assert "loop restored, but its PV not back where it was (target 1.5 ± 0.008)" in said
