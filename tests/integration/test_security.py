"""Security: the secure deployment refuses rogues; the local default stays on this machine.

The secure stack is the one ``autotune up --secure`` starts: the router (``autotune router -c
router.json5``, user/password, access control with default deny) on a free loopback port,
and plant_sim, the autotuner and the logger as its clients, each with its role's config.
A command that reaches the plant shows in its counters; a message the router lets in shows
on a viewer's subscriber (it hands a viewer every put of the prefix), so "refused" is
measured as "delivered to nobody".
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from services.autotuner.commands.tune import submit
from services.autotuner.loop_client import LoopClient, PlantLost, wait_for_token
from services.launcher import free_tcp_port, start_service, stop_service
from services.logger.mcap_io import read_run
from services.up import ROLES, reference_configs, write_secure
from shared import keys, wire
from shared.errors import AutotuneError, ConfigError
from shared.messages import (
    LoggerStatus,
    LoopStatus,
    ServiceStatus,
    TuneAccepted,
    TuneRequest,
    TuneResult,
)
from shared.session import RENDEZVOUS_ENV, ZenohSettings, open_session, zenoh_config
from tests.tools import rogue

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


# --- sockets of a process, from /proc ------------------------------------------------------


def _address(hex_addr: str) -> tuple[str, int]:
    host, port = hex_addr.split(":")
    raw = bytes.fromhex(host)
    if len(raw) == 4:
        ip = socket.inet_ntop(socket.AF_INET, raw[::-1])
    else:  # four little-endian 32-bit words
        words = b"".join(raw[i : i + 4][::-1] for i in range(0, 16, 4))
        ip = socket.inet_ntop(socket.AF_INET6, words)
    return ip, int(port, 16)


def sockets(pid: int, table: str, state: str | None = None) -> set[tuple[str, int]]:
    """Local addresses of ``pid``'s sockets in /proc/net/``table`` (``state`` 0A: listening)."""
    mine = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            mine.add(link[8:-1])
    found = set()
    for name in (table, table + "6"):
        lines = Path(f"/proc/{pid}/net/{name}").read_text().splitlines()[1:]
        for line in lines:
            f = line.split()
            if f[9] in mine and (state is None or f[3] == state):
                found.add(_address(f[1]))
    return found


def listening(pid: int) -> set[tuple[str, int]]:
    return sockets(pid, "tcp", "0A")


def outside_address() -> str | None:
    """An address of this machine that is not loopback (how another host would reach it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.1", 9))  # no packet is sent: it picks the outgoing interface
            ip = s.getsockname()[0]
        except OSError:
            return None
    return None if ip.startswith("127.") else ip


# --- the secure stack ------------------------------------------------------------------------


@dataclass
class SecureStack:
    directory: Path
    prefix: str
    endpoint: str
    procs: dict
    logs: Path
    runs: Path

    def settings(self, role: str) -> ZenohSettings:
        return ZenohSettings(config_file=str(self.directory / f"{role}.json5"))

    def session(self, role: str) -> zenoh.Session:
        return open_session(self.settings(role))


@pytest.fixture(scope="module")
def secure(tmp_path_factory):
    base = tmp_path_factory.mktemp("secure")
    port = free_tcp_port()
    prefix = f"sec{os.getpid()}"
    deployment = write_secure(base / "secure", prefix, f"tcp/127.0.0.1:{port}")
    d = deployment.directory
    runs = base / "runs"
    logs = base / "logs"
    logs.mkdir()
    procs = {}
    plan = [
        ("router", "services.cli", ["router", "-c", str(deployment.router)]),
        ("plant", "services.plant_sim", ["--prefix", prefix, "-c", str(d / "plant.json5")]),
        ("tuner", "services.autotuner", ["--prefix", prefix, "-c", str(d / "tuner.json5")]),
        (
            "logger",
            "services.logger",
            ["--prefix", prefix, "--runs", str(runs), "-c", str(d / "logger.json5")],
        ),
    ]
    for name, module, args in plan:
        with (logs / f"{name}.log").open("w") as f:
            procs[name] = start_service(module, args, stderr=f)
    stack = SecureStack(d, prefix, deployment.endpoint, procs, logs, runs)
    try:
        watcher = ZenohSettings(
            config_file=str(d / "viewer.json5"), cfg=("connect/timeout_ms:20000",)
        )
        with open_session(watcher) as s:
            for key in (
                keys.service_alive(prefix, "plant_sim", "plant"),
                keys.tuner_alive(prefix, "tuner"),
                keys.logger_alive(prefix, "logger"),
            ):
                if not wait_for_token(s, key, 20.0):
                    text = "\n".join(p.read_text() for p in logs.iterdir())
                    raise AssertionError(f"{key} did not come up:\n{text}")
        yield stack
    finally:
        for name in ("tuner", "logger", "plant", "router"):
            stop_service(procs[name])


def counters(s: zenoh.Session, prefix: str, loop: str) -> tuple:
    """What a command reaching the plant would change: the loop's and the plant's counters."""
    st = wire.query_one(s, keys.status(prefix, loop), LoopStatus, 5.0)
    sv = wire.query_one(s, keys.service_status(prefix, "plant_sim", "plant"), ServiceStatus, 5.0)
    assert st is not None and sv is not None, "the plant does not answer a viewer"
    return st.mode, st.op, st.accepted, st.rejected, sv.accepted, sv.rejected


def request_tune(s: zenoh.Session, prefix: str, req: TuneRequest) -> TuneAccepted:
    replies = list(
        s.get(
            keys.tuner_request(prefix, "tuner"),
            payload=wire.encode(req),
            encoding=wire.encoding_for(TuneRequest),
            timeout=10.0,
        )
    )
    assert replies and replies[0].ok is not None, [r.err.payload.to_bytes() for r in replies]
    return wire.decode_sample(TuneAccepted, replies[0].ok)


class Results:
    """The results a client on ``<prefix>/tune/<loop>/result`` accepts (valid TuneResults)."""

    def __init__(self, s: zenoh.Session, prefix: str, loop: str):
        self.got: list[TuneResult] = []
        self.arrived = threading.Event()
        self.sub = s.declare_subscriber(keys.tune_result(prefix, loop), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        try:
            self.got.append(wire.decode_sample(TuneResult, sample))
        except Exception:
            return
        self.arrived.set()

    def wait(self, run_id: str, timeout: float = 60.0) -> TuneResult:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            mine = [r for r in self.got if r.run_id == run_id]
            if mine:
                return mine[0]
            self.arrived.wait(0.1)
            self.arrived.clear()
        raise AssertionError(f"no result for run {run_id} in {timeout:g} s")


# --- the secure deployment -------------------------------------------------------------------


def test_the_router_listens_where_its_config_file_says(secure):
    port = int(secure.endpoint.rsplit(":", 1)[1])
    assert listening(secure.procs["router"].pid) == {("127.0.0.1", port)}
    for name in ("plant", "tuner", "logger"):  # clients: they listen on nothing
        assert listening(secure.procs[name].pid) == set()


def test_a_rogue_without_credentials_connects_to_nothing(secure):
    before_session = secure.session("viewer")
    try:
        before = counters(before_session, secure.prefix, "hx1")
        client = ZenohSettings(mode="client", connect=(secure.endpoint,))
        with pytest.raises(ConfigError, match="cannot open zenoh session"):
            open_session(client)
        wrong = ZenohSettings(
            config_file=str(secure.directory / "operator.json5"),
            cfg=('transport/auth/usrpwd/password:"guess"', "connect/timeout_ms:0"),
        )
        with pytest.raises(ConfigError, match="cannot open zenoh session"):
            open_session(wrong)
        # a peer opens without a connection and so sees nothing and reaches no one
        with open_session(ZenohSettings(mode="peer", connect=(secure.endpoint,))) as peer:
            assert list(peer.info.routers_zid()) == [] and list(peer.info.peers_zid()) == []
            assert list(peer.get(keys.status(secure.prefix, "hx1"), timeout=0.5)) == []
            report = rogue.hammer(peer, secure.prefix, "hx1", rate=1000.0, duration=0.3)
            assert report["sent"] > 100
        time.sleep(0.2)
        assert counters(before_session, secure.prefix, "hx1") == before
    finally:
        before_session.close()


def test_a_viewer_can_neither_command_release_nor_publish_a_result(secure):
    """During an operator's tune, a viewer hammers every rogue write at 1 kHz, in the name
    of the run it watches: nothing of it reaches anyone; the run and the loop are as without
    it, and the one result accepted is the tuner's."""
    p = secure.prefix
    operator, viewer, watcher = (secure.session(r) for r in ("operator", "viewer", "viewer"))
    try:
        assert counters(viewer, p, "hx1")[0] in ("auto", "manual")  # a viewer reads
        logger_before = wire.query_one(watcher, keys.logger_status(p, "logger"), LoggerStatus, 5)
        plant_before = counters(watcher, p, "hx1")
        results = Results(operator, p, "hx1")
        watch_stop, hammer_stop = threading.Event(), threading.Event()
        watched: dict = {}
        hammered: dict = {}
        th_watch = threading.Thread(
            target=lambda: watched.update(rogue.watch(watcher, p, 120.0, watch_stop))
        )
        th_watch.start()
        time.sleep(0.1)
        th_hammer = threading.Thread(
            target=lambda: hammered.update(
                rogue.hammer(viewer, p, "hx1", 1000.0, 120.0, hammer_stop)
            )
        )
        th_hammer.start()
        # a viewer's tune request and cancel are refused too (no reply; nothing cancelled)
        assert list(viewer.get(keys.tuner_request(p, "tuner"), payload=b"{}", timeout=0.5)) == []
        accepted = request_tune(operator, p, TuneRequest(loop="hx1", verify=False))
        result = results.wait(accepted.run_id)
        # while the hammer still runs: the operator gets only the plant's status, no fake one
        answers = [r.ok for r in operator.get(keys.status(p, "hx1"), timeout=1.0) if r.ok]
        tuners = list(operator.liveliness().get(keys.tuner_alive(p, "*"), timeout=1.0))
        hammer_stop.set()
        th_hammer.join()
        time.sleep(0.3)
        watch_stop.set()
        th_watch.join()
        assert hammered["sent"] > 200 and hammered["run_seen"] == f"tuner:{accepted.run_id}"
        assert watched["rogue_delivered"] == 0, watched
        assert watched["rogue_tokens"] == [] and watched["seen"] > 0
        events = watched["token_events"]  # the run's token came once, the rogue's never
        assert hammered["by_kind"]["token/running"] > 2
        assert events.get("tune/hx1/running PUT") == 1, events
        assert events.get("tune/hx1/running DELETE", 0) <= 1, events
        assert result.status == "unverified" and result.applied  # verify=False: not ok
        assert [r.run_id for r in results.got] == [accepted.run_id]  # the tuner's only
        assert len(answers) == 1 and wire.decode_sample(LoopStatus, answers[0]).node == "plant"
        assert [str(t.ok.key_expr) for t in tuners] == [keys.tuner_alive(p, "tuner")]
        after = counters(watcher, p, "hx1")
        assert after[3] == plant_before[3] and after[5] == plant_before[5]  # nothing refused
        assert after[0] == "auto"  # the run applied its gains, no rogue's manual
        files = list(secure.runs.glob(f"*_{accepted.run_id}.mcap"))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            st = wire.query_one(watcher, keys.logger_status(p, "logger"), LoggerStatus, 5)
            files = list(secure.runs.glob(f"*_{accepted.run_id}.mcap"))
            if files and st is not None and accepted.run_id not in st.open_runs:
                break
            time.sleep(0.1)
        meta, records = read_run(files[0])
        assert meta["status"] == "unverified"
        assert not [r for r in records if rogue.is_rogue(r.topic[1:], r.data)]
        assert st.invalid == logger_before.invalid  # the logger was handed nothing forged
    finally:
        for s in (operator, viewer, watcher):
            s.close()


def test_the_operator_tunes_and_cancels_but_cannot_write_to_the_plant(secure):
    p = secure.prefix
    operator, watcher = secure.session("operator"), secure.session("viewer")
    try:
        before = counters(watcher, p, "hx2")
        stop, watched = threading.Event(), {}
        th = threading.Thread(target=lambda: watched.update(rogue.watch(watcher, p, 60.0, stop)))
        th.start()
        time.sleep(0.1)
        report = rogue.hammer(operator, p, "hx2", rate=1000.0, duration=0.3)
        time.sleep(0.3)
        stop.set()
        th.join()
        # of every rogue write, only the cancel is an operator's to make (and the watcher sees
        # what gets through); no command reached the plant
        assert set(watched["by_key"]) == {"tune/hx2/cancel"}, watched
        assert watched["rogue_delivered"] == report["by_kind"]["cancel"]
        assert counters(watcher, p, "hx2") == before
        # what the refused hear: not a dead plant, nor "is the tuner running?" (helper 52)
        refused = pytest.raises(PlantLost, match="the router may not let user 'operator' write")
        with refused, LoopClient(operator, p, "hx2", source="t", timeout=1.0, user="operator") as c:
            c.sync()
        with pytest.raises(AutotuneError, match=r"^an autotuner is there .* or the router does"):
            submit(watcher, p, "tuner", TuneRequest(loop="hx2"), timeout=1.0)
        results = Results(operator, p, "hx2")
        req = TuneRequest(loop="hx2", cycles=20, tolerance=0.0005, source="operator")
        accepted = request_tune(operator, p, req)
        operator.put(keys.tune_cancel(p, "hx2"), accepted.run_id.encode())
        result = results.wait(accepted.run_id)
        assert result.status == "aborted" and result.reason == "cancelled" and result.restored
        after = counters(watcher, p, "hx2")
        assert after[:2] == before[:2]  # mode and output as before the run
    finally:
        operator.close()
        watcher.close()


def test_the_secure_files_are_private_and_their_passwords_kept(tmp_path):
    d = write_secure(tmp_path / "s", "pfx", "tcp/0.0.0.0:7999").directory
    assert d.stat().st_mode & 0o777 == 0o700
    names = {f.name for f in d.iterdir()}
    assert names == {"users.txt", "router.json5"} | {f"{r}.json5" for r in ROLES}
    assert all(f.stat().st_mode & 0o777 == 0o600 for f in d.iterdir())
    users = (d / "users.txt").read_text()
    assert "operator.json5" not in users and len(users.splitlines()) == len(ROLES)
    conf = zenoh_config(ZenohSettings(config_file=str(d / "operator.json5")))
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7999"]
    write_secure(d, "pfx", "tcp/0.0.0.0:7999")
    assert (d / "users.txt").read_text() == users  # copies already handed out keep working


def test_the_shipped_configs_are_what_autotune_up_secure_writes():
    for name, text in reference_configs().items():
        assert (ROOT / "deploy" / "zenoh" / name).read_text() == text, name
        zenoh.Config.from_file(str(ROOT / "deploy" / "zenoh" / name))  # Zenoh reads them
    compose = (ROOT / "compose.yaml").read_text()
    # the bus on this machine only unless AUTOTUNE_BUS_BIND names an interface
    assert '"${AUTOTUNE_BUS_BIND:-127.0.0.1}:7447:7447"' in compose
    # each container its own files, read-only (tests/test_compose.py: no other role's)
    for role in ("router", "plant", "tuner", "logger", "viewer"):
        assert f"./.autotune/secure/{role}.json5:/secure/{role}.json5:ro" in compose


@pytest.mark.parametrize(
    "text, expected",
    [
        ('{ mode: "router", listen: { endpoints: [ }', "line 1, column"),
        ('{ transport: { auth: { usrpwd: { user: "viewer" } } } }', "usrpwd/password: missing"),
        ('{ transport: { auth: { usrpwd: { dictionary_file: "no.txt" } } } }', "no.txt: no such"),
    ],
)
def test_a_bad_config_file_is_one_line_and_exit_2(tmp_path, capsys, text, expected):
    from services.cli import main

    bad = tmp_path / "bad.json5"
    bad.write_text(text)
    assert main(["router", "-c", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(bad) in err and expected in err, err


# --- the local default -----------------------------------------------------------------------


@pytest.fixture
def rendezvous(monkeypatch):
    """The default sessions' meeting point moved to a free port (AUTOTUNE_RENDEZVOUS)."""
    port = free_tcp_port()
    monkeypatch.setenv(RENDEZVOUS_ENV, f"tcp/127.0.0.1:{port}")
    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
    return port


def test_the_default_session_is_loopback_only_without_multicast(rendezvous):
    conf = zenoh_config(ZenohSettings())
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    listen = json.loads(conf.get_json("listen/endpoints"))
    assert all(e.startswith("tcp/127.0.0.1:") for e in listen), listen
    for mode in ("client", "router"):
        c = zenoh_config(ZenohSettings(mode=mode))
        assert json.loads(c.get_json("scouting/multicast/enabled")) is False
    assert json.loads(zenoh_config(ZenohSettings(mode="router")).get_json("listen/endpoints")) == [
        f"tcp/127.0.0.1:{rendezvous}"
    ]
    with open_session(ZenohSettings()):
        ours = listening(os.getpid())
        assert ("127.0.0.1", rendezvous) in ours
        assert {ip for ip, _ in ours} == {"127.0.0.1"}, ours
        assert not [a for a in sockets(os.getpid(), "udp") if a[1] == 7446]  # no scouting
        ip = outside_address()
        if ip is not None:  # from another host: nothing answers on any of its ports
            for _, port in ours:
                with socket.socket() as s, pytest.raises(ConnectionRefusedError):
                    s.settimeout(1.0)
                    s.connect((ip, port))


def test_services_with_no_flags_find_each_other_and_survive_the_rendezvous_holder(
    rendezvous, tmp_path
):
    """``autotune plant &``, ``autotune tuner &`` and a client, no flags: they meet on the
    loopback rendezvous; when its holder (the plant) goes, a newcomer still finds the tuner."""
    prefix = f"dflt{os.getpid()}"
    logs = {n: (tmp_path / f"{n}.log").open("w") for n in ("plant", "tuner")}
    plant = start_service("services.plant_sim", ["--prefix", prefix], stderr=logs["plant"])
    tuner = None
    try:
        deadline = time.monotonic() + 20.0  # the first process takes the rendezvous
        while ("127.0.0.1", rendezvous) not in listening(plant.pid):
            assert time.monotonic() < deadline and plant.poll() is None, "no rendezvous"
            time.sleep(0.05)
        tuner = start_service("services.autotuner", ["--prefix", prefix], stderr=logs["tuner"])
        with open_session(ZenohSettings()) as s:
            assert wait_for_token(s, keys.tuner_alive(prefix, "tuner"), 20.0)
            assert wait_for_token(s, keys.loop_alive(prefix, "hx1"), 20.0)
            assert wire.query_one(s, keys.status(prefix, "hx1"), LoopStatus, 5.0) is not None
        for proc in (plant, tuner):
            assert {ip for ip, _ in listening(proc.pid)} == {"127.0.0.1"}
        stop_service(plant)
        with open_session(ZenohSettings()) as s:  # the newcomer takes the rendezvous over
            assert ("127.0.0.1", rendezvous) in listening(os.getpid())
            assert wait_for_token(s, keys.tuner_alive(prefix, "tuner"), 10.0)
    finally:
        for proc in (tuner, plant):
            if proc is not None:
                stop_service(proc)
        for f in logs.values():
            f.close()
