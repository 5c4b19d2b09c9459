"""One plant file served by two plant processes through a router, and an overlap refused."""

from __future__ import annotations

import subprocess
import sys
import tomllib

import pytest

from services.autotuner.loop_client import LoopClient
from services.launcher import free_tcp_port, start_service, stop_service
from services.plant_sim.plant_file import build_plant
from shared import keys, wire
from shared.messages import OutputCommand, ServiceStatus
from shared.session import ZenohSettings, open_session
from tests.running_services import wait_for_tokens

pytestmark = pytest.mark.integration

PLANT = """
seed = 5
[loops.a1]
model = "fopdt"
gain = 2.0
time_constant = 3.0
delay = 0.35
sample_time = 0.1
noise_std = 0.1

[loops.b1]
model = "transfer_function"
num = [6.0]
den = [1.0, 6.0, 11.0, 6.0]
sample_time = 0.1

[loops.a2]
model = "tank_level"
sample_time = 0.5

[loops.b2]
model = "ipdt"
gain = 0.05
sample_time = 0.1
"""


def _client(endpoint: str) -> ZenohSettings:
    return ZenohSettings(
        mode="client",
        connect=(endpoint,),
        cfg=("connect/timeout_ms:20000",),
        no_multicast_scouting=True,
    )


def _plant_args(prefix: str, path, endpoint: str, *extra: str) -> list[str]:
    return [
        "--prefix",
        prefix,
        "--plant",
        str(path),
        "-m",
        "client",
        "-e",
        endpoint,
        "--no-multicast-scouting",
        "--cfg",
        "connect/timeout_ms:20000",
        *extra,
    ]


def test_two_plant_processes_serve_one_file_and_a_third_on_their_loops_is_refused(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = "shards"
    path = tmp_path / "plant.toml"
    path.write_text(PLANT)
    logs = {n: (tmp_path / f"{n}.log").open("w") for n in ("router", "one", "two")}
    router = start_service(
        "services.cli", ["router", "-l", endpoint, "--no-multicast-scouting"], stderr=logs["router"]
    )
    procs = [router]
    try:
        for name, shard in (("one", "1/2"), ("two", "2/2")):
            args = _plant_args(prefix, path, endpoint, "--shard", shard, "--node", name)
            procs.append(start_service("services.plant_sim", args, stderr=logs[name]))
        every = ("a1", "b1", "a2", "b2")
        wait_for_tokens(
            _client(endpoint),
            [keys.loop_alive(prefix, lp) for lp in every],
            30.0,
            tmp_path / "one.log",
        )
        twin = build_plant(tomllib.loads(PLANT))
        with (
            open_session(_client(endpoint)) as s,
            LoopClient(s, prefix, "a1") as a1,
            LoopClient(s, prefix, "b1") as b1,
        ):
            # round-robin in file order: a1, a2 in shard 1; b1, b2 in shard 2
            assert a1.info.instance != b1.info.instance
            served = {}
            for reply in s.get(keys.service_status(prefix, "plant_sim", "*"), timeout=10.0):
                st = wire.decode_sample(ServiceStatus, reply.ok)
                served[st.node] = sorted(st.loops)
            assert served == {"one": ["a1", "a2"], "two": ["b1", "b2"]}
            # each loop steps exactly as the file says, wherever it is served
            for client in (a1, b1):
                client.command(OutputCommand(loop=client.loop, op=63.0))
                twin[client.loop].apply(OutputCommand(loop=client.loop, op=63.0))
            for _ in range(25):
                assert a1.next_sample().pv == twin["a1"].advance().pv
                assert b1.next_sample().pv == twin["b1"].advance().pv
        # a third process asked for a loop that shard 2 serves: refused, one line, exit 2
        third = subprocess.run(
            [
                sys.executable,
                "-m",
                "services.plant_sim",
                *_plant_args(prefix, path, endpoint, "--loops", "b2", "--node", "three"),
            ],
            capture_output=True,
            text=True,
            timeout=60,
            stdin=subprocess.DEVNULL,
        )
        assert third.returncode == 2, third.stderr
        lines = third.stderr.strip().splitlines()
        assert len(lines) == 1 and "b2" in lines[0] and "already served" in lines[0], lines
        assert all(p.poll() is None for p in procs)  # the two shards serve on
    finally:
        for p in reversed(procs):
            stop_service(p)
        for f in logs.values():
            f.close()
