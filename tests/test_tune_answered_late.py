"""`autotune tune` without ``--node``: a tuner that read the request past its ``answer_by``
refuses it as read late (its client's share of the wait for it nearly over). That refusal
comes in the second the client keeps for the answer's way back: it is that tuner's silence,
not a refusal of the request, and the next tuner is asked. It was taken for a refusal, and
tune failed ("the autotuner refused the request: the request for hx1 came 0.2 s after its
client stopped waiting …") with a live tuner next in line.

One session on loopback plays both tuners."""

from __future__ import annotations

import time

import pytest

from services.autotuner.commands import tune
from shared import keys, wire
from shared.errors import AutotuneError
from shared.messages import ANSWERED_LATE, TuneAccepted, TuneRequest
from shared.session import ZenohSettings, open_session

P, LOOP = "al1", "hx1"
ALONE = ZenohSettings(listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)


def _accepting(node: str, asked: list[str]):
    """A tuner ``node``'s queryable that accepts (run r1), noting that it was asked."""

    def accepts(query) -> None:
        asked.append(node)
        ok = TuneAccepted(run_id="r1", loop=LOOP, t=0.0, method="relay", rule="zn-pid")
        wire.reply(query, keys.tuner_request(P, node), ok)

    return accepts


def test_a_tuner_that_read_the_request_late_is_passed_over(capsys) -> None:
    asked: list[str] = []
    with open_session(ALONE) as s:

        def late(query) -> None:
            asked.append("a")
            query.reply_err(
                f"the request for {LOOP} came 0.2 s {ANSWERED_LATE} (this tuner was paused or "
                "starved): not started".encode()
            )

        accepts = _accepting("b", asked)

        held = [s.liveliness().declare_token(keys.tuner_alive(P, n)) for n in ("a", "b")]
        held.append(s.liveliness().declare_token(keys.loop_alive(P, LOOP)))
        held += [
            s.declare_queryable(keys.tuner_request(P, "a"), late),
            s.declare_queryable(keys.tuner_request(P, "b"), accepts),
        ]
        try:
            accepted = tune.submit(s, P, "*", TuneRequest(loop=LOOP), timeout=6.0)
        finally:
            for h in held:
                h.undeclare()
    assert accepted.run_id == "r1"
    assert asked == ["a", "b"]  # 'a' not asked again: it had read it late once
    assert "'a' did not answer" in capsys.readouterr().err


@pytest.mark.parametrize("why", ["loop: hx1 is already being tuned (run r0)"])
def test_a_refusal_is_still_an_answer(why) -> None:
    """Any other refusal ends the request with the tuner's reason (the next is not asked)."""
    asked: list[str] = []
    with open_session(ALONE) as s:

        def refuses(query) -> None:
            asked.append("a")
            query.reply_err(why.encode())

        held = [s.liveliness().declare_token(keys.tuner_alive(P, n)) for n in ("a", "b")]
        held.append(s.liveliness().declare_token(keys.loop_alive(P, LOOP)))
        held += [s.declare_queryable(keys.tuner_request(P, "a"), refuses)]
        try:
            with pytest.raises(tune.AutotuneError, match="already being tuned"):
                tune.submit(s, P, "*", TuneRequest(loop=LOOP), timeout=6.0)
        finally:
            for h in held:
                h.undeclare()
    assert asked == ["a"]


def test_a_request_is_never_to_be_answered_after_its_client_stops_waiting() -> None:
    """Each request's ``answer_by`` falls within its client's wait (with time left for the
    answer's way back), however little of the wait is left: with 0.5 s at least, one sent
    with 0.3 s left could be started by a tuner the client had given up on, and then the
    next tuner asked started a second run."""
    got: list[float] = []
    with open_session(ALONE) as s:

        def silent(query) -> None:  # read, never answered (a starved tuner)
            got.append(wire.decode(TuneRequest, query.payload.to_bytes()).answer_by)

        held = [
            s.liveliness().declare_token(keys.tuner_alive(P, "a")),
            s.declare_queryable(keys.tuner_request(P, "a"), silent),
        ]
        try:
            with pytest.raises(tune.AutotuneError, match="did not answer"):
                tune.submit(s, P, "a", TuneRequest(loop=LOOP), timeout=0.3)
            gave_up = time.time()
        finally:
            for h in held:
                h.undeclare()
    assert got
    assert max(got) < gave_up


def test_a_loop_no_plant_serves_is_said_so_whatever_the_number_of_tuners() -> None:
    """Three live tuners, no plant serving the loop: each tuner takes 4 s (its wait for the
    loop's token) to refuse it, more than its third of the wait, and tune said after the whole
    wait that all three were "paused or starved". The client tells it itself, asking none."""
    asked: list[str] = []
    with open_session(ALONE) as s:
        held = [s.liveliness().declare_token(keys.tuner_alive(P, n)) for n in "abc"]
        held += [
            s.declare_queryable(keys.tuner_request(P, n), lambda q, n=n: asked.append(n))
            for n in "abc"
        ]
        try:
            with pytest.raises(tune.AutotuneError, match=r"^loop: no plant serves 'nosuch'"):
                tune.submit(s, P, "*", TuneRequest(loop="nosuch"), timeout=3.0)
        finally:
            for h in held:
                h.undeclare()
    assert asked == []


def test_a_run_under_way_after_a_silent_tuner_stops_the_failover(capsys) -> None:
    """A tuner that accepted but whose answer was lost is silent to the client, and its run
    goes on: asking the next tuner started a second run, refused the loop's lease, and left
    the first unfollowed (review). With the loop's run token up after a silence, the next
    tuner is not asked, and the line says why."""
    asked: list[str] = []
    with open_session(ALONE) as s:
        accepts = _accepting("b", asked)

        # 'a' has no queryable (its answer lost), and its run's token is up
        held = [s.liveliness().declare_token(keys.tuner_alive(P, n)) for n in ("a", "b")]
        held.append(s.liveliness().declare_token(keys.loop_alive(P, LOOP)))
        held.append(s.liveliness().declare_token(keys.tune_running(P, LOOP)))
        held.append(s.declare_queryable(keys.tuner_request(P, "b"), accepts))
        try:
            with pytest.raises(AutotuneError) as err:
                tune.submit(s, P, "*", TuneRequest(loop=LOOP), timeout=6.0)
        finally:
            for h in held:
                h.undeclare()
    assert asked == []
    assert f"a run on {LOOP} is now under way" in str(err.value)
    assert "no other tuner is asked" in str(err.value)
