"""`autotune tune` following a run (``commands.tune.follow``) on a session of its own on
loopback: a message on the run's keys that is not valid is said and ignored, and the run is
followed to its result (one malformed progress message killed the client, exit 2, the run
going on with no one to cancel it: helper trial G)."""

from __future__ import annotations

from services.autotuner.commands import tune
from shared import keys, wire
from shared.messages import TuneAccepted, TuneProgress, TuneResult
from shared.session import ZenohSettings, open_session

ALONE = ZenohSettings(listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)
P, LOOP = "fm1", "hx1"


def test_a_malformed_progress_or_result_is_ignored_and_the_run_followed_on(capsys):
    with open_session(ALONE) as s:
        token = s.liveliness().declare_token(keys.tune_running(P, LOOP))

        def start() -> TuneAccepted:
            for key in (keys.tune_progress(P, LOOP), keys.tune_result(P, LOOP)):
                s.put(key, b'{"hello": "world"}')
            wire.put(
                s,
                keys.tune_progress(P, LOOP),
                TuneProgress(run_id="r1", loop=LOOP, t=1.0, phase="relay"),
            )
            wire.put(
                s,
                keys.tune_result(P, LOOP),
                TuneResult(
                    run_id="r1", loop=LOOP, t=2.0, method="relay", rule="zn-pid", status="ok"
                ),
            )
            return TuneAccepted(run_id="r1", loop=LOOP, t=0.0, method="relay", rule="zn-pid")

        seen: list[str] = []
        r = tune.follow(s, P, LOOP, start, wait=30.0, on_progress=lambda p: seen.append(p.phase))
        token.undeclare()
    assert (r.run_id, r.status, seen) == ("r1", "ok", ["relay"])
    err = capsys.readouterr().err
    assert err.count("ignored a malformed message on") == 2, err
