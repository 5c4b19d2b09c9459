"""Who says that a tuner was passed over: ``submit``'s failover line carried "autotune tune:"
from the demo and the console too (noticed, left open last session). Each caller now says it
as its own: the CLI's prefix by default, the demo's, the console's log."""

from __future__ import annotations

import pytest

from services.autotuner.commands import tune
from shared.messages import TuneAccepted, TuneRequest

OK = TuneAccepted(run_id="abcdef123456", loop="x1", t=0.0, method="relay", rule="auto")


@pytest.fixture
def one_silent(monkeypatch):
    """Two tuners, 'a' silent and 'b' answering; no run seen on the loop after 'a'."""

    def ask(session, prefix, name, req, until, timeout):
        if name == "a":
            raise tune._Silent("silent")
        return OK

    monkeypatch.setattr(tune, "_ask", ask)
    monkeypatch.setattr(tune, "wait_for_token", lambda s, key, t: "running" not in key)
    monkeypatch.setattr(tune, "tuner_candidates", lambda s, p, n, t: ["a", "b"])


def test_the_cli_says_it_as_autotune_tune(one_silent, capsys):
    assert tune.submit(None, "p", "*", TuneRequest(loop="x1")) == OK
    err = capsys.readouterr().err
    assert err.startswith("autotune tune: autotuner 'a' did not answer within")
    assert err.rstrip().endswith(": asking 'b'")


def test_a_caller_says_it_its_own_way(one_silent, capsys):
    said: list[str] = []
    assert tune.submit(None, "p", "*", TuneRequest(loop="x1"), say=said.append) == OK
    assert capsys.readouterr().err == ""
    (line,) = said
    assert line.startswith("autotuner 'a' did not answer within")


def test_the_demo_and_the_console_say_it_as_theirs(one_silent, monkeypatch, capsys, caplog):
    from services import demo
    from services.console import actions

    demo._say_as_demo("autotuner 'a' did not answer")
    assert capsys.readouterr().err == "autotune demo: autotuner 'a' did not answer\n"
    accepted: list[TuneAccepted] = []
    monkeypatch.setattr(actions, "follow", lambda session, prefix, loop, start, wait: start())
    with caplog.at_level("WARNING", logger="console"):
        actions.run_tune(None, "p", TuneRequest(loop="x1"), accepted.append)
    assert accepted == [OK]
    assert capsys.readouterr().err == ""
    assert any("autotuner 'a' did not answer within" in r.message for r in caplog.records)
