"""`autotune tune` takes a run's result from the tuner that accepted the run: on a bus without
access control any client may publish on the run's keys, and a forged ``ok`` in the middle of
a run was printed as its result while the run went on (helper trial G). The client asks that
tuner (by the Zenoh id of its reply to the request) for its own copy of the result; one it
does not give is ignored, and one it cannot confirm is said to be unconfirmed.

One session on loopback plays the tuner and the client (and the forger: the client tells
the tuner's word by the replier of its queries, not by who published); a second session
plays another tuner."""

from __future__ import annotations

import threading
import time

import pytest

from services.autotuner.commands import tune
from services.launcher import free_tcp_port
from shared import keys, wire
from shared.messages import TuneAccepted, TuneRequest, TuneResult
from shared.session import ZenohSettings, open_session

P, LOOP, NODE = "ff1", "hx1", "tuner"
ALONE = ZenohSettings(listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)


class Puts:
    """Results published from threads of their own (as a tuner's come), joined before the
    session closes: a put still on its way as it closed raised "RuntimeError: Already
    borrowed" (once in a parallel run)."""

    def __init__(self, session):
        self.session, self.threads = session, []

    def later(self, msg: TuneResult) -> None:
        args = (self.session, keys.tune_result(P, LOOP), msg)
        self.threads.append(threading.Thread(target=wire.put, args=args))
        self.threads[-1].start()

    def join(self) -> None:
        for t in self.threads:
            t.join(10.0)


def _result(status: str, reason: str = "") -> TuneResult:
    return TuneResult(
        run_id="r1", loop=LOOP, t=2.0, method="relay", rule="zn-pid", status=status, reason=reason
    )


@pytest.mark.parametrize("answers", [True, False])
def test_a_forged_result_is_not_taken_for_the_runs(capsys, answers: bool) -> None:
    """``answers``: the tuner answers for its results (the run still going until it ends),
    or keeps no results to be asked for (then the first result stands, said unconfirmed)."""
    with open_session(ALONE) as s:
        ended = threading.Event()
        real = _result("aborted", "the PV left its limits")
        puts = Puts(s)

        def on_request(query) -> None:
            accepted = TuneAccepted(run_id="r1", loop=LOOP, t=0.0, method="relay", rule="zn-pid")
            wire.reply(query, keys.tuner_request(P, NODE), accepted)
            # the forger, who read the run id off its progress, says it ended ok (published
            # here, where the client's subscriber surely hears it: a publisher is not known
            # to its subscribers, so the client cannot tell it from the tuner either way)
            puts.later(_result("ok"))

        def on_results(query) -> None:
            if ended.is_set():
                wire.reply(query, keys.tune_result(P, LOOP), real)
                return
            query.reply_err(b"run r1 on hx1 is still going")
            ended.set()  # the client asked about the forged result: the run now ends
            puts.later(real)

        alive = s.liveliness().declare_token(keys.tuner_alive(P, NODE))
        running = s.liveliness().declare_token(keys.tune_running(P, LOOP))
        requests = s.declare_queryable(keys.tuner_request(P, NODE), on_request)
        results = s.declare_queryable(keys.tune_result(P, LOOP), on_results) if answers else None

        def start() -> TuneAccepted:
            return tune.submit(s, P, NODE, TuneRequest(loop=LOOP))

        try:
            r = tune.follow(s, P, LOOP, start, wait=30.0)
        finally:
            puts.join()
            for q in (requests, results, running, alive):
                if q is not None:
                    q.undeclare()
    err = capsys.readouterr().err
    if answers:
        assert (r.status, r.reason) == ("aborted", "the PV left its limits")
        assert "ignored a result for run r1 (ok) that its tuner does not give" in err, err
    else:
        assert r.status == "ok"
        assert (
            "run r1's result is not confirmed: it came on the bus, and its tuner did not" in err
        ), err


def test_the_runs_tuner_is_heard_beside_another_tuners_last_result(capsys) -> None:
    """Two tuners on the bus, each keeping its last result of the loop on the same key: a
    query's replies on one key are consolidated to one by default, and the other tuner's took
    the place of the run's own (3 of 3 runs said "not confirmed" once both had results)."""
    port = free_tcp_port()
    tuner_side = ZenohSettings(listen=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True)
    other_side = ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True)
    with open_session(tuner_side) as s, open_session(other_side) as other:
        real = _result("ok")
        earlier = real.model_copy(update={"run_id": "r0", "status": "aborted"})
        puts = Puts(s)

        def on_request(query) -> None:
            accepted = TuneAccepted(run_id="r1", loop=LOOP, t=0.0, method="relay", rule="zn-pid")
            wire.reply(query, keys.tuner_request(P, NODE), accepted)
            puts.later(real)

        alive = s.liveliness().declare_token(keys.tuner_alive(P, NODE))
        running = s.liveliness().declare_token(keys.tune_running(P, LOOP))
        requests = s.declare_queryable(keys.tuner_request(P, NODE), on_request)
        mine = s.declare_queryable(
            keys.tune_result(P, LOOP), lambda q: wire.reply(q, keys.tune_result(P, LOOP), real)
        )
        theirs = other.declare_queryable(
            keys.tune_result(P, LOOP), lambda q: wire.reply(q, keys.tune_result(P, LOOP), earlier)
        )
        # the other tuner's queryable known to the client's session before the run ends
        # (bounded: both answer one query within 5 s)
        deadline = time.monotonic() + 5.0
        while len(wire.query_all(s, keys.tune_result(P, LOOP), TuneResult, 0.5)) < 2:
            assert time.monotonic() < deadline, "the other tuner's queryable never answered"
        try:
            r = tune.follow(
                s, P, LOOP, lambda: tune.submit(s, P, NODE, TuneRequest(loop=LOOP)), 30.0
            )
        finally:
            puts.join()
            for q in (requests, mine, theirs, running, alive):
                q.undeclare()
    assert (r.run_id, r.status) == ("r1", "ok")
    assert "not confirmed" not in capsys.readouterr().err
