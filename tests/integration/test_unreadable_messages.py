"""Messages a run cannot read, and a release it did not send, from another client on a bus
without credentials (the README's Security section): the run goes on past the first, and
puts the loop back after the second."""

from __future__ import annotations

import pytest

from services.autotuner.loop_client import LoopClient
from services.autotuner.tuning import RunHooks, TuningRun
from shared import keys, wire
from shared.messages import ReleaseCommand, TuneProgress, TuneRequest
from shared.session import open_session
from tests.integration.test_tuner import assert_as_before
from tests.integration.tuning_cli import HX, plant_toml

pytestmark = pytest.mark.integration


def test_unreadable_messages_on_the_loops_keys_are_rejected_and_the_run_goes_on(start_plant):
    """A sample without its fields, an empty status and an empty batch on the loop's keys
    mid-relay: each aborted the run with pydantic's complaint as its reason (helper trial),
    and one sent before the experiment ended it as `failed`. They are now rejected, counted
    and named in a warning; the run ends as it would have."""
    p = start_plant(plant_toml("x1", HX), loops=("x1",))
    garbage = [
        (keys.pv(p.prefix, "x1"), b'{"loop": "x1"}'),
        (keys.status(p.prefix, "x1"), b""),
        (keys.pv_batch(p.prefix, "x1"), b'{"loop": "x1", "samples": []}'),
    ]
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "x1") as c:
        sent: list[str] = []

        def send(progress: TuneProgress) -> None:
            if progress.phase == "relay" and not sent:
                for key, payload in garbage:
                    s.put(key, payload)
                    sent.append(key)

        hooks = RunHooks(progress=send)
        r = TuningRun(c, TuneRequest(loop="x1", method="relay"), "garbage", hooks).run()
    assert len(sent) == 3
    assert r.status == "ok", r.reason
    assert c.rejected == 3
    said = [w for w in r.warnings if "on the loop's keys could not be read" in w]
    assert said and said[0].startswith("3 message(s)"), r.warnings


def test_a_release_forged_in_the_runs_name_is_undone_and_the_loop_restored(start_plant):
    """A client released the lease in the run's name mid-relay: the run aborted, said the
    loop was not as before, and left it in manual at the relay's output, unleased (helper
    trial). No one holds it then, so the run takes it again and restores it."""
    p = start_plant(plant_toml("x1", HX), loops=("x1",))
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "x1") as c:
        before = c.sync()
        forged: list[ReleaseCommand] = []

        def forge(progress: TuneProgress) -> None:
            if progress.phase == "relay" and not forged:
                forged.append(ReleaseCommand(loop="x1", source=c.source))
                wire.put(s, keys.command(p.prefix, "x1", "release"), forged[0])

        hooks = RunHooks(progress=forge)
        r = TuningRun(c, TuneRequest(loop="x1", method="relay"), "forge-release", hooks).run()
        after = c.sync()
    assert forged and r.status == "aborted", r.reason
    assert "lease lost" in r.reason and "the run took it again and restored it" in r.reason
    assert r.restored is True
    assert_as_before(after, before)
