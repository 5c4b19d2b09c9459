"""A tune request read by a tuner after its client stopped waiting is refused, never started:
a tuner paused for 55 s (SIGSTOP) read the request of a client that had reported "did not
answer" and exited 2, and tuned hx1 with no one watching, applying new gains (helper trial).
The request carries the wall-clock time its client waits until (``answer_by``)."""

from __future__ import annotations

import json
import signal
import time

import pytest

from services.autotuner.loop_client import wait_for_token
from services.autotuner.service import stale_by
from shared import keys, wire
from shared.messages import LoopStatus, TuneRequest
from shared.session import open_session
from tests.integration.tuning_cli import THIRD, plant_toml

pytestmark = pytest.mark.integration


def test_stale_by_the_clock():
    req = TuneRequest(loop="x1", answer_by=1000.0)
    assert stale_by(req, now=999.0) is None
    assert stale_by(req, now=1002.5) == pytest.approx(2.5)
    assert stale_by(TuneRequest(loop="x1"), now=1e12) is None  # no bound asked: in time
    assert "answer_by" not in wire.encode(TuneRequest(loop="x1")).decode()  # off the wire


def test_a_request_whose_checks_outlast_its_client_is_not_started(monkeypatch):
    """Read in time, but its checks (the loop's token, up to 4 s; its status, up to 2 s)
    ran past ``answer_by``: its client has asked the next tuner by then (``submit``), whose
    run is to be the only one on the loop. Refused, not started."""
    from services.autotuner import service

    def slow_token(session, key, timeout):
        time.sleep(0.3)  # past the request's answer_by, 0.1 s after it was read
        return True

    monkeypatch.setattr(service, "wait_for_token", slow_token)
    monkeypatch.setattr(service.wire, "query_one", lambda *a, **k: None)
    tuner = service.TunerService(None, "p", "t", workers=0)  # type: ignore[arg-type]
    req = TuneRequest(loop="x1", answer_by=time.time() + 0.1)
    with pytest.raises(ValueError, match=r"after its client stopped waiting.*not started"):
        tuner._start(req)
    assert tuner.active == {}


def test_a_request_its_client_gave_up_on_is_not_started(start_plant, start_tuner, tmp_path):
    p = start_plant(plant_toml("x1", THIRD), loops=("x1",))
    tuner = start_tuner(p)
    with open_session(p.client_settings()) as s:
        before = wire.query_one(s, keys.status(p.prefix, "x1"), LoopStatus, 5.0)
    assert before is not None
    with open_session(p.client_settings()) as s:
        # the tuner's declarations known to this session before it stops (as a console's
        # long-open session knows them)
        assert wait_for_token(s, keys.tuner_alive(p.prefix, "tuner"), 10.0)
        tuner.send_signal(signal.SIGSTOP)
        try:  # what ``submit`` sends, its answer awaited until its ``answer_by``
            req = TuneRequest(loop="x1", answer_by=time.time() + 1.0)
            replies = s.get(
                keys.tuner_request(p.prefix, "tuner"),
                payload=wire.encode(req),
                encoding=wire.encoding_for(TuneRequest),
                timeout=2.0,
            )
            assert all(r.ok is None for r in replies)  # paused: no answer, the client gives up
        finally:
            tuner.send_signal(signal.SIGCONT)
    log = tmp_path / "tuner0.log"
    deadline = time.monotonic() + 30.0
    while "request refused" not in log.read_text():  # the tuner reads it once resumed
        assert time.monotonic() < deadline, log.read_text()
        time.sleep(0.05)
    text = log.read_text()
    assert "after its client stopped waiting" in text and "not started" in text, text
    assert "tuning x1" not in text, text
    with open_session(p.client_settings()) as s:
        after = wire.query_one(s, keys.status(p.prefix, "x1"), LoopStatus, 5.0)
    assert after is not None and after.leased_by is None
    assert (after.mode, after.gains, after.op) == (before.mode, before.gains, before.op)


def test_a_tuner_of_a_version_before_answer_by_is_asked_again_without_it():
    """A tuner whose TuneRequest has no ``answer_by`` refuses a request carrying it (its
    models forbid unknown fields): every request of today's clients was refused by it
    (review). The client asks again without the field."""
    from services.autotuner.commands.tune import UNKNOWN_ANSWER_BY, submit
    from services.launcher import free_tcp_port
    from shared.messages import TuneAccepted
    from shared.session import ZenohSettings

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = "oldtuner"
    asked: list[dict] = []

    def old_tuner(query) -> None:
        body = query.payload.to_bytes().decode()
        asked.append(json.loads(body))
        if "answer_by" in body:  # as pydantic's extra="forbid" words it
            query.reply_err(f"{UNKNOWN_ANSWER_BY} [type=extra_forbidden]".encode())
            return
        ok = TuneAccepted(run_id="abcdef123456", loop="x1", t=0.0, method="relay", rule="auto")
        wire.reply(query, str(query.key_expr), ok)

    listen = ZenohSettings(listen=(endpoint,), no_multicast_scouting=True)
    connect = ZenohSettings(connect=(endpoint,), no_multicast_scouting=True)
    with open_session(listen) as tuner_side, open_session(connect) as client:
        q = tuner_side.declare_queryable(keys.tuner_request(prefix, "old"), old_tuner)
        token = tuner_side.liveliness().declare_token(keys.tuner_alive(prefix, "old"))
        try:
            accepted = submit(client, prefix, "old", TuneRequest(loop="x1"), timeout=5.0)
        finally:
            token.undeclare()
            q.undeclare()
    assert accepted.run_id == "abcdef123456"
    assert "answer_by" in asked[0] and "answer_by" not in asked[-1], asked
