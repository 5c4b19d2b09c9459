"""The console's bridge on a real Zenoh session of its own (nothing else on it): the page's
requests that cannot be carried out are answered in one line, and nothing is sent."""

from __future__ import annotations

import queue

import pytest

from services.console.bridge import Bridge
from shared.session import ZenohSettings, open_session

ALONE = ZenohSettings(listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    """One bridge for the module: closing one joins its threads, which takes a query's wait."""
    with open_session(ALONE) as session:
        b = Bridge(session, "consoletest", tmp_path_factory.mktemp("runs"), lambda msg: None)
        yield b
        b.close()  # its threads joined: none is inside a call of the session as it closes


def answer(bridge: Bridge, msg: dict) -> dict:
    replies: queue.Queue[dict] = queue.Queue()
    bridge.act(msg, replies.put)
    return replies.get(timeout=10.0)


@pytest.mark.parametrize(
    ("msg", "says"),
    [
        ({"type": "launch"}, "type: 'launch' is not a request the console takes"),
        ({"type": "tune", "loop": "hx1", "fields": {"amplitude": "-1"}},
         "--amplitude: Input should be greater than 0"),
        ({"type": "tune", "loop": "h x", "fields": {}}, "loop id 'h x' is not valid"),
        # a form that is not one was taken as no flags at all: a tune that applied its gains
        ({"type": "tune", "loop": "hx1", "fields": []},
         "tune: the form's fields must be an object of flag names"),
        ({"type": "tune", "loop": "hx1", "fields": ""},
         "tune: the form's fields must be an object of flag names"),
        ({"type": "cancel"}, "loop: None is not a loop"),
        ({"type": "apply", "run_id": 7}, "run_id: 7 is not a run id"),
        ({"type": "reject", "run_id": "r1"}, "loop: None is not a loop"),
        ({"type": "revert", "loop": ""}, "loop: '' is not a loop"),
        ({"type": "revert", "loop": "hx1", "gains": {"kc": -1}},
         "gains: kc: Input should be greater than or equal to 0"),
    ],
)  # fmt: skip
def test_a_request_that_cannot_be_carried_out_is_refused_in_one_line(bridge, msg, says):
    got = answer(bridge, {**msg, "id": 3})
    assert (got["type"], got["id"], got["ok"]) == ("action", 3, False)
    assert got["message"].startswith(says), got["message"]


def test_a_new_page_gets_the_form_s_choices_and_who_is_up(bridge):
    hello, services = bridge.snapshot()[:2]
    assert hello["type"] == "hello" and "tl-pid" in {r["name"] for r in hello["rules"]}
    assert services == {"type": "services", "plant_sim": [], "tuner": [], "logger": [],
                        "loops": [], "running": []}  # fmt: skip
    assert bridge.tick() == []  # nothing on this bus


def test_a_new_page_gets_the_last_results_as_earlier_ones_not_news(bridge):
    """Each page load posted every loop's last result to Messages as if just come, stamped
    with the load's time ("9:01:06 PM result of run … aborted" for a run over minutes
    before). A result that comes while the page is open is news; those a page finds are not."""
    from shared.messages import TuneResult

    r = TuneResult(
        run_id="abc123abc123", loop="hx9", t=1.0, method="relay", rule="auto", status="aborted"
    )
    bridge._publish_result(r)
    news = [m for m in bridge.tick() if m.get("type") == "result"]
    assert news and not news[-1].get("earlier"), news
    found = [m for m in bridge.snapshot() if m.get("type") == "result"]
    assert found and all(m["earlier"] for m in found), found


def test_a_reject_of_a_run_not_on_record_or_of_another_loop_is_refused(bridge):
    """Reject of run "zzz" on flow1 was answered ok, "run zzz rejected: its gains were not
    applied, flow1 unchanged", for a run that does not exist (helper trial): it is looked up
    among the recorded runs as `autotune apply` does, and refused naming the loop and run."""
    import json

    from shared.history_file import HISTORY_FILE

    got = answer(bridge, {"type": "reject", "loop": "flow1", "run_id": "zzz", "id": 4})
    assert got["ok"] is False, got
    assert got["message"].startswith("reject run zzz of flow1: zzz: no run of that id in")
    path = bridge.runs / HISTORY_FILE
    rec = {"record": "tune", "loop": "hx1", "prefix": "consoletest", "run_id": "r0a1b2c3d4e5",
           "status": "proposed", "applied": False}  # fmt: skip
    path.write_text(json.dumps(rec) + "\n")
    try:
        got = answer(bridge, {"type": "reject", "loop": "flow1", "run_id": "r0a1b2c3d4e5"})
        assert got["ok"] is False and "tuned hx1, not flow1" in got["message"], got
        got = answer(bridge, {"type": "reject", "loop": "hx1", "run_id": "r0a1b2c3d4e5"})
        assert got["ok"] is True, got
        assert (
            got["message"] == "run r0a1b2c3d4e5 rejected: its gains were not applied, hx1 unchanged"
        )
    finally:
        path.unlink()


def test_a_cancel_with_no_run_going_on_the_loop_is_refused(bridge):
    """Cancel on flow1 with no run going was answered ok, "cancel sent to flow1's run: the
    tuner restores the loop" (helper trial): the run's token tells whether one is going."""
    from shared import keys

    got = answer(bridge, {"type": "cancel", "loop": "flow1", "id": 5})
    assert (got["ok"], got["message"]) == (False, "no run going on flow1: nothing to cancel")
    token = bridge.session.liveliness().declare_token(keys.tune_running("consoletest", "flow2"))
    try:
        got = answer(bridge, {"type": "cancel", "loop": "flow2", "run_id": None})
        assert got["ok"] is True, got
        assert got["message"] == "cancel sent to flow2's run: the tuner restores the loop"
    finally:
        token.undeclare()


def test_two_reverts_pressed_at_once_write_one_after_the_other(bridge, monkeypatch):
    """Two Reverts pressed at once ran side by side in the page's workers: both read the loop
    before either wrote, both passed the check of the gains the page showed, and both said
    "hx1 reverted" (helper trial). The page's writes of gains go one at a time, so the second
    reads what the first wrote (and is refused by that check)."""
    import threading
    import time

    from services.console import actions

    inside, most = [0], [0]
    guard = threading.Lock()

    def revert(*args, **kwargs):
        with guard:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.3)
        with guard:
            inside[0] -= 1
        return {"after": {"kc": 2.0, "ti": 60.0, "td": 0.0}}

    monkeypatch.setattr(actions, "revert", revert)
    replies: queue.Queue[dict] = queue.Queue()
    for ident in (1, 2):
        bridge.act({"type": "revert", "loop": "hx1", "id": ident}, replies.put)
    got = [replies.get(timeout=10.0) for _ in range(2)]
    assert all(g["ok"] for g in got), got
    assert most[0] == 1
