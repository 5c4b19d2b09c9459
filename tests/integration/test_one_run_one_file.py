"""One run, one file (issue 11, item 3).

A run's MCAP file holds only that run's messages, from the plant instance it tuned: nothing
of a previous plant instance, of a previous run or of a replay, no sample twice, one result.
The recorder's rules are checked in-process on scripted traffic (exact and fast); one test
runs the real services through a router, restarts the plant between two runs and replays a
run onto the live bus. Replay's --prefix, its attachment, its checks of a damaged file and
the logger's --runs checks are exercised through the CLI's entry point.
"""

from __future__ import annotations

import collections
import json
import os
import queue
import socket
import threading
import time
from collections.abc import Iterable
from pathlib import Path

import pytest
import zenoh
from mcap.writer import Writer

from services.autotuner.commands.tune import submit
from services.cli import main
from services.launcher import free_tcp_port, start_service, stop_service
from services.logger import recorder as rec_mod
from services.logger.mcap_io import Record, read_run
from services.logger.recorder import Recorder, prepare_runs_dir
from shared import keys, wire
from shared.errors import ConfigError
from shared.messages import (
    AdvanceCommand,
    LeaseCommand,
    LoggerStatus,
    LoopStatus,
    Message,
    PidGains,
    ProcessSample,
    ReleaseCommand,
    SyncCommand,
    TuneProgress,
    TuneRequest,
    TuneResult,
    TunerEvent,
)
from shared.session import ZenohSettings, open_session
from shared.wire import replay_attachment, replay_source
from tests.integration.tuning_cli import THIRD, autotune, plant_toml
from tests.running_services import wait_for_tokens

PREFIX = "rec"
LOOP = "x1"
T = 0.1  # sample time of the scripted loop, s

# --- scripted traffic ---------------------------------------------------------------------


def sample(seq: int, pv: float = 50.0, loop: str = LOOP) -> tuple[str, Message]:
    return keys.pv(PREFIX, loop), ProcessSample(
        loop=loop, seq=seq, t=seq * T, pv=pv, sp=50.0, op=40.0, mode="manual"
    )


def status(
    seq: int,
    reason: str,
    node: str = "plant",
    leased_by: str | None = None,
    clock: str = "lockstep",
) -> tuple[str, Message]:
    return keys.status(PREFIX, LOOP), LoopStatus(
        loop=LOOP,
        node=node,
        seq=seq,
        t=seq * T,
        pv=50.0,
        sp=50.0,
        op=40.0,
        mode="manual",
        action="reverse",
        gains=PidGains(kc=1.0, ti=10.0),
        op_limits=(0.0, 100.0),
        pv_range=(0.0, 100.0),
        disturbances={},
        clock=clock,
        accepted=0,
        rejected=0,
        reason=reason,
        leased_by=leased_by,
    )


def command(msg: Message) -> tuple[str, Message]:
    return keys.command(PREFIX, LOOP, msg.kind), msg


def idle(first: int, last: int, pv: float = 50.0) -> list[tuple[str, Message]]:
    """Samples ``first``…``last`` of a loop nobody tunes."""
    return [sample(k, pv) for k in range(first, last + 1)]


def run_start(
    run_id: str, seq: int, node: str = "plant", lease_seq: int | None = None
) -> list[tuple[str, Message]]:
    """A run's opening as the tuner makes it: sync, its answer, start, lease, request."""
    src, t = f"tuner:{run_id}", seq * T
    request = TuneRequest(loop=LOOP).model_dump_json()
    return [
        command(SyncCommand(loop=LOOP, token=1, source=src, t=t)),
        status(seq, "sync", node),
        (
            keys.tune_progress(PREFIX, LOOP),
            TuneProgress(
                run_id=run_id, loop=LOOP, t=t, phase="start", message="relay test, rule auto"
            ),
        ),
        command(LeaseCommand(loop=LOOP, source=src, t=t)),
        status(seq if lease_seq is None else lease_seq, "lease", node, leased_by=src),
        (
            keys.tune_event(PREFIX, LOOP),
            TunerEvent(run_id=run_id, loop=LOOP, t=t, kind="request", data={"request": request}),
        ),
    ]


def run_steps(run_id: str, first: int, last: int, pv: float = 50.0) -> list[tuple[str, Message]]:
    """Lockstep advances and their samples, ``first``…``last``."""
    src = f"tuner:{run_id}"
    out: list[tuple[str, Message]] = []
    for k in range(first, last + 1):
        out += [command(AdvanceCommand(loop=LOOP, source=src, t=(k - 1) * T)), sample(k, pv)]
    return out


def result(run_id: str, seq: int, state: str = "ok") -> tuple[str, Message]:
    return keys.tune_result(PREFIX, LOOP), TuneResult(
        run_id=run_id, loop=LOOP, t=seq * T, method="relay", rule="tl-pid", status=state
    )


def run_end(run_id: str, seq: int, state: str = "ok") -> list[tuple[str, Message]]:
    src = f"tuner:{run_id}"
    return [
        command(ReleaseCommand(loop=LOOP, source=src, t=seq * T)),
        status(seq, "release"),
        result(run_id, seq, state),
    ]


def whole_run(run_id: str, first: int, last: int, pv: float = 50.0) -> list[tuple[str, Message]]:
    return [
        *run_start(run_id, first),
        *run_steps(run_id, first + 1, last, pv),
        *run_end(run_id, last),
    ]


def feed(rec: Recorder, traffic: Iterable[tuple[str, Message]], replay: str | None = None):
    for key, msg in traffic:
        rec.handle(key, wire.encode(msg), replay)


class Clock:
    """A monotonic clock the test moves by hand (the grace after a run's token vanished)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def recorder(tmp_path: Path, **kw) -> tuple[Recorder, Clock]:
    clock = Clock()
    return Recorder(tmp_path / "runs", PREFIX, clock=clock, **kw), clock


def pv_seqs(records: list[Record]) -> list[int]:
    return [
        ProcessSample.model_validate_json(r.data).seq for r in records if r.topic.endswith("/pv")
    ]


def check_one_run(
    path: Path, run_id: str, others: tuple[str, ...] = ()
) -> tuple[dict[str, str], list[Record]]:
    """The file holds one run: its own tuner messages, one result, no PV time twice, and
    nothing that names the ``others`` runs."""
    meta, records = read_run(path)
    assert meta["run_id"] == run_id
    pv_times = collections.Counter(
        ProcessSample.model_validate_json(r.data).t for r in records if r.topic.endswith("/pv")
    )
    assert [t for t, n in pv_times.items() if n > 1] == [], "PV times recorded twice"
    assert sum(r.topic.endswith("/result") for r in records) == 1
    for r in records:
        if "/tune/" in r.topic:
            assert r.json()["run_id"] == run_id, r
        assert not any(other.encode() in r.data for other in others), r
    return meta, records


def only_file(rec: Recorder) -> Path:
    assert len(rec.finished) == 1, rec.finished
    return rec.finished[0]


# --- the recorder, on scripted traffic ----------------------------------------------------


@pytest.mark.parametrize("evidence", ["numbering", "token-and-start"])
def test_a_restarted_plant_leaves_nothing_in_the_next_run(tmp_path, evidence):
    """The old instance ran to sample 400, the new one starts again at 0: the second run's
    file has nothing of the first instance (before: every buffered message of it, as the
    old sim times were all past the new run's start). "numbering": the logger missed the
    new plant's start status and the token's coming and going; only the numbering tells."""
    rec, _ = recorder(tmp_path)
    feed(rec, [*idle(1, 10), *whole_run("aaa", 10, 300), *idle(301, 400)])
    first = only_file(rec)
    if evidence == "token-and-start":
        rec.plant_token(LOOP, False)
        feed(rec, [status(0, "start")])
        rec.plant_token(LOOP, True)
    feed(rec, [*idle(1, 5, pv=20.0), *whole_run("bbb", 5, 80, pv=20.0)])
    second = rec.finished[1]
    _, records = check_one_run(second, "bbb", others=("aaa",))
    assert pv_seqs(records) == list(range(5, 81))  # from the one at the start time
    assert all(r.json()["pv"] == 20.0 for r in records if r.topic.endswith("/pv"))
    assert all(r.json()["seq"] <= 80 for r in records if r.topic.endswith("/status"))
    check_one_run(first, "aaa", others=("bbb",))


@pytest.mark.parametrize("evidence", ["numbering", "node"])
def test_a_plant_replaced_mid_run_is_left_out_of_that_run(tmp_path, evidence):
    """The plant restarts (numbering from 0 again) or another plant node takes the loop
    over (numbering on from 205) under a run: nothing of the new instance goes into it."""
    rec, _ = recorder(tmp_path)
    feed(rec, [*run_start("aaa", 10), *run_steps("aaa", 11, 200)])
    rec.plant_token(LOOP, False)
    rec.plant_token(LOOP, True)
    first = 1 if evidence == "numbering" else 206
    node = "plant" if evidence == "numbering" else "plant2"
    replaced = [
        status(first - 1, "query", node=node),
        *idle(first, first + 29, pv=20.0),
        *run_steps("aaa", first + 30, first + 39, pv=20.0),  # the tuner still commanding
    ]
    feed(rec, [*replaced, result("aaa", 40, "aborted")])  # it noticed and gave up
    meta, records = check_one_run(only_file(rec), "aaa")
    assert pv_seqs(records) == list(range(11, 201))
    assert meta["status"] == "aborted"
    assert ("went back" if evidence == "numbering" else "plant2") in meta["plant_changed"]
    assert int(meta["left_out"]) == len(replaced)


def test_a_reconnected_plant_that_numbers_on_is_the_same_plant(tmp_path):
    """The token vanishes and comes back (a link lost a while) and the samples go on from
    where they were (with a gap): the run keeps recording, the gap counted as dropped."""
    rec, _ = recorder(tmp_path)
    feed(rec, [*run_start("aaa", 10), *run_steps("aaa", 11, 100)])
    rec.plant_token(LOOP, False)
    rec.plant_token(LOOP, True)
    feed(rec, [*run_steps("aaa", 106, 150), *run_end("aaa", 150)])
    meta, records = check_one_run(only_file(rec), "aaa")
    assert pv_seqs(records) == [*range(11, 101), *range(106, 151)]
    assert (meta["dropped"], meta["plant_changed"], meta["left_out"]) == ("5", "", "0")


def test_realtime_statuses_crossing_samples_are_the_same_plant(tmp_path):
    """In realtime a status (answered on one thread) can trail or lead the samples (paced on
    another) by a few numbers: no new instance, nothing left out (before: 4 false restarts
    in a 14 s run at ×5, and every sample of the run left out after the first)."""
    rec, _ = recorder(tmp_path)
    lag = [status(k - 3 + 5 * (k % 2), "sync", clock="realtime") for k in range(11, 60)]
    traffic = [x for pair in zip(idle(11, 59), lag, strict=True) for x in pair]
    feed(rec, [*run_start("aaa", 10), *traffic, result("aaa", 59)])
    meta, records = check_one_run(only_file(rec), "aaa")
    assert pv_seqs(records) == list(range(11, 60))
    assert (meta["plant_changed"], meta["left_out"]) == ("", "0")
    assert rec.counts["plant_instances"] == 0


def test_pre_run_context_is_bounded_to_the_run(tmp_path):
    """A sample that overtakes the run's start message is kept; what came before the
    previous run ended is not (its last sample, release and result share the new run's
    start time); a sample delivered twice is written once."""
    rec, _ = recorder(tmp_path)
    feed(rec, [*idle(1, 20), *whole_run("aaa", 20, 60)])
    sync, answer, start, *rest = run_start("bbb", 60, lease_seq=61)
    feed(rec, [sample(60), sync, answer, sample(61), start, *rest, sample(61)])
    feed(rec, [*run_steps("bbb", 62, 90), *run_end("bbb", 90)])
    _, records = check_one_run(rec.finished[1], "bbb", others=("aaa",))
    assert pv_seqs(records) == list(range(61, 91))
    assert [r.json()["reason"] for r in records if r.topic.endswith("/status")] == [
        "sync",
        "lease",
        "release",
    ]
    assert rec.counts["duplicates"] == 2  # samples 60 and 61, each delivered again


def test_a_watchdog_restore_closes_a_run_only_when_its_tuner_is_gone(tmp_path):
    rec, clock = recorder(tmp_path)
    src = "tuner:aaa"
    rec.run_token(LOOP, True)
    feed(rec, [*run_start("aaa", 10), *run_steps("aaa", 11, 50)])
    feed(rec, [status(50, "watchdog", leased_by=src)])  # the lease still held: nothing
    assert rec.open_runs() == ["aaa"]
    feed(rec, [status(50, "watchdog")])  # restored, but the tuner lives: it will say
    clock.now += 60
    rec.tick()
    assert rec.open_runs() == ["aaa"]
    feed(rec, [*run_steps("aaa", 51, 60), result("aaa", 60, "aborted")])
    meta, records = check_one_run(only_file(rec), "aaa")
    assert meta["status"] == "aborted" and pv_seqs(records)[-1] == 60


@pytest.mark.parametrize("after", ["nothing", "result", "watchdog"])
def test_a_vanished_run_token_closes_the_run_after_a_grace(tmp_path, after):
    rec, clock = recorder(tmp_path)
    rec.run_token(LOOP, True)
    feed(rec, [*run_start("aaa", 10), *run_steps("aaa", 11, 50)])
    rec.run_token(LOOP, False)
    rec.tick()
    if after == "nothing":
        assert rec.open_runs() == ["aaa"]
        clock.now += rec_mod.RESULT_GRACE
        rec.tick()
    elif after == "result":  # the result came the other way round, a moment later
        clock.now += 0.5 * rec_mod.RESULT_GRACE
        feed(rec, [result("aaa", 50, "ok")])
    else:  # the plant saw the token go too, and restored the loop
        feed(rec, [status(50, "watchdog")])
    meta, records = read_run(only_file(rec))
    assert (
        meta["status"] == {"nothing": "tuner lost", "result": "ok", "watchdog": "tuner lost"}[after]
    )
    assert records[-1].topic.endswith({"nothing": "/pv", "result": "/result"}.get(after, "/status"))


def test_a_watchdog_with_no_token_seen_closes_at_once(tmp_path):
    rec, _ = recorder(tmp_path)
    feed(rec, [*run_start("aaa", 10), *run_steps("aaa", 11, 50), status(50, "watchdog")])
    assert read_run(only_file(rec))[0]["status"] == "tuner lost"


def test_a_new_run_on_the_loop_supersedes_an_open_one(tmp_path):
    """A run whose end never came (its result lost) is closed once the plant shows the next
    one holding the loop; each file has its own run only, the next one's from its start (the
    sample at its start's sim time, aaa's last, in both)."""
    rec, _ = recorder(tmp_path)
    feed(rec, [*run_start("aaa", 10), *run_steps("aaa", 11, 50)])
    feed(rec, whole_run("bbb", 50, 90))
    first, second = rec.finished
    meta, records = read_run(first)
    assert meta["status"] == "superseded" and pv_seqs(records) == list(range(11, 51))
    meta, records = check_one_run(second, "bbb", others=("aaa",))
    assert pv_seqs(records) == list(range(50, 91)) and meta["status"] == "ok"
    assert any(r.topic.endswith("/progress") and r.json()["phase"] == "start" for r in records)


def test_replays_are_recorded_only_when_asked_each_on_its_own(tmp_path):
    traffic = [*idle(1, 10), *whole_run("aaa", 10, 120), *idle(121, 150)]
    plain, _ = recorder(tmp_path / "plain")
    keeper, _ = recorder(tmp_path / "keeper", record_replays=True)
    for rec in (plain, keeper):
        feed(rec, traffic)  # live
        feed(rec, traffic, replay="aaa.mcap")  # a replay of it, twice, and live again
        feed(rec, traffic, replay="aaa.mcap")
        feed(rec, [*idle(151, 160), *whole_run("aaa", 160, 170)])
    live = only_file(plain)
    check_one_run(live, "aaa")
    assert plain.counts["replayed_ignored"] == 2 * len(traffic)
    assert plain.counts["repeated_runs"] == 1  # the same run id again: not a new file
    assert len(keeper.finished) == 3
    for path in keeper.finished[1:]:
        meta, records = check_one_run(path, "aaa")
        assert meta["replay"] == "aaa.mcap" and "_aaa_replay" in path.stem
        assert pv_seqs(records) == list(range(10, 121))
    assert read_run(keeper.finished[0])[0]["replay"] == ""


def test_replay_attachment_round_trip():
    assert replay_source(replay_attachment("a b.mcap")) == "a b.mcap"
    for other in (None, b"", b"not json", b"[1]", b'{"other": 1}'):
        assert replay_source(other) is None


# --- replay: --prefix, the attachment, damaged files --------------------------------------


@pytest.fixture
def run_file(tmp_path) -> Path:
    """A recorded run: scripted traffic of a 30-sample run through the recorder."""
    rec, _ = recorder(tmp_path / "src")
    feed(rec, [*idle(1, 10), *whole_run("aaa", 10, 40)])
    return only_file(rec)


def listen(endpoint: str) -> ZenohSettings:
    return ZenohSettings(mode="peer", listen=(endpoint,), no_multicast_scouting=True)


def test_replay_publishes_under_the_prefix_given_marked_as_a_replay(run_file, capsys):
    _, records = read_run(run_file)
    expected = [r for r in records if "/cmd/" not in r.key]
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    got: dict[str, list[zenoh.Sample]] = {"new": [], "old": []}
    all_in = threading.Event()

    def take(name: str, x: zenoh.Sample) -> None:
        got[name].append(x)
        if len(got["new"]) >= len(expected):
            all_in.set()

    with open_session(listen(endpoint)) as s:
        subs = [
            s.declare_subscriber(f"{root}/**", lambda x, n=name: take(n, x))
            for name, root in (("new", "site/b"), ("old", PREFIX))
        ]
        args = ["replay", str(run_file), "--rate", "1e6", "--prefix", "site/b", "-e", endpoint]
        assert main([*args, "--no-multicast-scouting"]) == 0
        assert "under site/b (recorded under rec)" in capsys.readouterr().out
        all_in.wait(10)
        for sub in subs:
            sub.undeclare()
    assert got["old"] == []
    assert [(str(x.key_expr), x.payload.to_bytes()) for x in got["new"]] == [
        ("site/b" + r.key[len(PREFIX) :], r.data) for r in expected
    ]
    marks = {replay_source(x.attachment.to_bytes()) for x in got["new"]}
    assert marks == {run_file.name}


def write_mcap(path: Path, messages: list[tuple[str, str, bytes]], prefix: str | None = PREFIX):
    """An MCAP file of (topic, schema name, payload) records, with the run's metadata."""
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        channels: dict[tuple[str, str], int] = {}
        for i, (topic, schema, data) in enumerate(messages):
            if (topic, schema) not in channels:
                sid = w.register_schema(schema, "jsonschema", b"{}")
                channels[(topic, schema)] = w.register_channel(topic, "json", sid)
            w.add_message(channels[(topic, schema)], log_time=i, data=data, publish_time=i)
        if prefix is not None:
            w.add_metadata("run", {"prefix": prefix})
        w.finish()


def altered(run_file: Path, index: int, change: str) -> list[tuple[str, str, bytes]]:
    _, records = read_run(run_file)
    out = [(r.topic, r.schema, r.data) for r in records]
    topic, schema, data = out[index]
    body = json.loads(data)
    if change == "not json":
        data = b"{not json"
    elif change == "missing field":
        del body["seq"]
        data = json.dumps(body).encode()
    elif change == "extra field":
        data = json.dumps({**body, "colour": "red"}).encode()
    elif change == "string for a number":
        data = json.dumps({**body, "pv": "hot"}).encode()
    elif change == "unknown topic":
        topic = f"/{PREFIX}/plant/{LOOP}/temp"
    elif change == "wrong schema":
        schema = "TuneResult"
    out[index] = (topic, schema, data)
    return out


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ("not json", "Invalid JSON"),
        ("missing field", "seq: Field required"),
        ("extra field", "colour: Extra inputs are not permitted"),
        ("string for a number", "pv: Input should be a valid number"),
        ("unknown topic", "not a topic autotune records"),
        ("wrong schema", "schema 'TuneResult'"),
    ],
)
def test_replay_of_an_altered_file_names_the_record(run_file, tmp_path, capsys, change, says):
    _, records = read_run(run_file)
    index = [i for i, r in enumerate(records) if r.topic.endswith("/pv")][2]
    bad = tmp_path / "bad.mcap"
    write_mcap(bad, altered(run_file, index, change))
    assert main(["replay", str(bad), "--wait", "0", "--no-multicast-scouting"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    topic = records[index].topic if change != "unknown topic" else f"/{PREFIX}/plant/{LOOP}/temp"
    # placed by its time into the recording (log time i ns here: message i is i ns in)
    assert f"{bad}: {topic} message {index} ({index * 1e-9:.6g} s in)" in err, err
    assert says in err, err


def test_replay_of_a_missing_or_truncated_file_is_one_line(run_file, tmp_path, capsys):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(run_file.read_bytes()[: run_file.stat().st_size // 2])
    nometa = tmp_path / "nometa.mcap"  # no metadata: the prefix comes from the topics
    _, records = read_run(run_file)
    write_mcap(nometa, [(r.topic, r.schema, r.data) for r in records], prefix=None)
    for path, code in ((tmp_path / "missing.mcap", 2), (cut, 2), (nometa, 0)):
        args = ["replay", str(path), "--rate", "1e6", "--wait", "0", "--no-multicast-scouting"]
        assert main([*args, "-l", f"tcp/127.0.0.1:{free_tcp_port()}"]) == code, path
        out = capsys.readouterr()
        if code == 2:
            assert len(out.err.strip().splitlines()) == 1 and str(path) in out.err
        else:
            assert out.out.startswith("replayed ") and out.err == ""


# --- the logger's --runs ------------------------------------------------------------------


def test_logger_runs_on_a_file_or_under_one_is_one_line(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    for bad in (a_file, a_file / "runs"):
        assert main(["logger", "--runs", str(bad), "--no-multicast-scouting"]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "--runs" in err and str(bad) in err
    run = autotune("logger", "--runs", str(a_file), "--no-multicast-scouting")
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1
    assert "--runs" in run.stderr and "Traceback" not in run.stderr


def test_a_missing_runs_directory_is_created(tmp_path):
    made = prepare_runs_dir(tmp_path / "new" / "runs")
    assert made.is_dir()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_an_unwritable_runs_directory_is_refused(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    with pytest.raises(ConfigError, match=r"--runs .*cannot write"):
        prepare_runs_dir(locked)


# --- the real services: a plant restarted between runs, and a replay onto the live bus -----


class Bus:
    """A Python router on loopback and the services as its clients (they survive a plant
    restart: only the plant's own link goes)."""

    def __init__(self, tmp_path: Path):
        self.tmp = tmp_path
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.prefix = f"test{os.getpid()}/{tmp_path.name}"
        self.procs: dict[str, object] = {}
        self.log = tmp_path / "services.log"
        self._log = self.log.open("w")
        self.settings = ZenohSettings(
            mode="client",
            connect=(self.endpoint,),
            cfg=("connect/timeout_ms:10000",),
            no_multicast_scouting=True,
        )

    def args(self) -> list[str]:
        return ["--prefix", self.prefix, "-m", "client", "-e", self.endpoint,
                "--no-multicast-scouting", "--cfg", "connect/timeout_ms:10000"]  # fmt: skip

    def start(self, name: str, module: str, *args: str) -> None:
        self.procs[name] = start_service(module, [*args], stderr=self._log)

    def stop(self, name: str) -> None:
        stop_service(self.procs.pop(name))

    def close(self) -> None:
        for name in ("tuner", "logger", "keeper", "plant", "router"):
            if name in self.procs:
                self.stop(name)
        self._log.close()


def wait_listening(endpoint: str, timeout: float) -> None:
    """Block until something accepts TCP connections on ``endpoint`` (the router is up: a
    client session opened before gives up at once)."""
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((host, int(port)), timeout=0.5).close()
            return
        except OSError:
            assert time.monotonic() < deadline, f"nothing listens on {endpoint}"
            time.sleep(0.02)


@pytest.fixture
def bus(tmp_path):
    b = Bus(tmp_path)
    b.start("router", "services.cli", "router", "-l", b.endpoint, "--no-multicast-scouting")
    wait_listening(b.endpoint, 30.0)
    yield b
    b.close()


def tune(session: zenoh.Session, prefix: str) -> TuneResult:
    """A relay tune without verification, asked for in-process; its result."""
    results: queue.Queue[zenoh.Sample] = queue.Queue()
    sub = session.declare_subscriber(keys.tune_result(prefix, LOOP), results.put)
    try:
        accepted = submit(session, prefix, "tuner", TuneRequest(loop=LOOP, verify=False))
        while True:
            r = wire.decode_sample(TuneResult, results.get(timeout=120))
            if r.run_id == accepted.run_id:
                return r
    finally:
        sub.undeclare()


def logger_status(session: zenoh.Session, prefix: str, node: str) -> LoggerStatus:
    st = wire.query_one(session, keys.logger_status(prefix, node), LoggerStatus, 10.0)
    assert st is not None, f"the logger {node} did not answer"
    return st


def wait_status(session, prefix, node, done, timeout: float = 30.0) -> LoggerStatus:
    """Poll the logger's own status until ``done(status)`` (its counters trail the bus)."""
    deadline = time.monotonic() + timeout
    while True:
        st = logger_status(session, prefix, node)
        if done(st):
            return st
        assert time.monotonic() < deadline, st
        time.sleep(0.02)


@pytest.mark.integration
def test_plant_restarted_between_runs_and_a_replay_on_the_live_bus(bus, tmp_path):
    runs, kept = tmp_path / "runs", tmp_path / "kept"
    toml = tmp_path / "plant.toml"
    toml.write_text(plant_toml(LOOP, {**THIRD, "sample_time": 0.01}))
    p = bus.prefix
    bus.start("plant", "services.plant_sim", *bus.args(), "--plant", str(toml))
    bus.start("tuner", "services.autotuner", *bus.args())
    bus.start("logger", "services.logger", *bus.args(), "--runs", str(runs))
    keeper = ["--runs", str(kept), "--node", "keeper", "--record-replays"]
    bus.start("keeper", "services.logger", *bus.args(), *keeper)
    wait_for_tokens(
        bus.settings,
        [keys.loop_alive(p, LOOP), keys.tuner_alive(p, "tuner")]
        + [keys.logger_alive(p, n) for n in ("logger", "keeper")],
        30.0,
        bus.log,
    )
    with open_session(bus.settings) as s:
        first = tune(s, p)
        assert first.status == "unverified" and first.applied, first.reason
        wait_status(s, p, "logger", lambda st: st.finished_runs == 1)
        # the plant restarts: the new instance numbers its samples from 0 again
        bus.stop("plant")
        bus.start("plant", "services.plant_sim", *bus.args(), "--plant", str(toml))
        wait_for_tokens(bus.settings, [keys.loop_alive(p, LOOP)], 30.0, bus.log)
        second = tune(s, p)
        assert second.status == "unverified" and second.applied, second.reason
        wait_status(s, p, "logger", lambda st: st.finished_runs == 2)
        final = wire.query_one(s, keys.status(p, LOOP), LoopStatus, 10.0)
        assert final is not None
        last_seq = final.seq
        f1 = next(runs.glob(f"*_{first.run_id}.mcap"))
        f2 = next(runs.glob(f"*_{second.run_id}.mcap"))
        _, rec1 = check_one_run(f1, first.run_id, others=(second.run_id,))
        meta2, rec2 = check_one_run(f2, second.run_id, others=(first.run_id,))
        seqs = pv_seqs(rec2)
        # every sample of the second run, from the new instance only (a lockstep plant's
        # first sample is number 1), once, in order
        assert seqs == list(range(1, last_seq + 1))
        assert all(r.json()["seq"] <= last_seq for r in rec2 if r.topic.endswith("/status"))
        assert meta2["dropped"] == "0" and meta2["plant_changed"] == ""
        print(f"run 1: {len(rec1)} messages; run 2 (after the restart): {len(rec2)}")

        # a replay of the first run onto the live bus, under the live prefix
        received = logger_status(s, p, "logger").received
        kept_received = logger_status(s, p, "keeper").received
        sent = [r for r in rec1 if "/cmd/" not in r.key]
        replay = ["replay", str(f1), "--rate", "1e6", "-m", "client", "-e", bus.endpoint]
        assert main([*replay, "--no-multicast-scouting"]) == 0  # under the recorded prefix
        try:
            st = wait_status(s, p, "logger", lambda st: st.received >= received + len(sent))
        except AssertionError as err:  # (seen twice in CI, under load: the services' logs)
            told = f"{err}\nexpected {received} + {len(sent)}; keeper: "
            told += f"{logger_status(s, p, 'keeper')}\n{bus.log.read_text()[-8000:]}"
            raise AssertionError(told) from None
        assert (st.finished_runs, st.open_runs) == (2, [])
        assert sorted(runs.glob("*.mcap")) == sorted([f1, f2])
        wait_status(s, p, "keeper", lambda st: st.received >= kept_received + len(sent))
        st = wait_status(s, p, "keeper", lambda st: st.finished_runs == 3)
    replayed = [f for f in kept.glob("*.mcap") if f.name.endswith("_replay.mcap")]
    assert len(replayed) == 1
    meta, records = check_one_run(replayed[0], first.run_id)
    assert meta["replay"] == f1.name
    assert [(r.topic, r.data) for r in records] == [(r.topic, r.data) for r in sent]
    # `runs` tells the replay from a live run (it listed it as one of the day it was replayed)
    listing = autotune("runs", str(kept), "--json")
    rows = {r["file"]: r for r in json.loads(listing.stdout)}
    assert rows[replayed[0].name]["replay"] == f1.name
    assert {r["replay"] for n, r in rows.items() if n != replayed[0].name} == {None}
    assert "(replay)  " + replayed[0].name in autotune("runs", str(kept)).stdout
