"""Fixtures that start real services as separate processes on loopback."""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from pathlib import Path

import pytest

from services.autotuner.loop_client import wait_for_loop
from services.launcher import free_tcp_port, start_service, stop_service
from shared.session import ZenohSettings, open_session

_counter = itertools.count()


@dataclass
class RunningPlant:
    endpoint: str
    prefix: str
    proc: object
    log: Path

    def client_settings(self) -> ZenohSettings:
        return ZenohSettings(
            mode="peer",
            connect=(self.endpoint,),
            cfg=("connect/timeout_ms:10000",),
            no_multicast_scouting=True,
        )

    def cli_args(self) -> list[str]:
        return ["--prefix", self.prefix, "-e", self.endpoint, "--no-multicast-scouting"]

    def stderr(self) -> str:
        return self.log.read_text()


@pytest.fixture
def start_plant(tmp_path):
    """start_plant(toml_text or None, *extra_args) → RunningPlant, stopped after the test."""
    started: list[RunningPlant] = []

    def start(toml: str | None = None, *extra: str, loops: tuple[str, ...] = ()) -> RunningPlant:
        n = next(_counter)
        port = free_tcp_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        prefix = f"test{os.getpid()}/p{n}"
        args = ["--prefix", prefix, "-l", endpoint, "--no-multicast-scouting", *extra]
        if toml is not None:
            path = tmp_path / f"plant{n}.toml"
            path.write_text(toml)
            args += ["--plant", str(path)]
        log = tmp_path / f"plant{n}.log"
        with log.open("w") as f:
            proc = start_service("services.plant_sim", args, stderr=f)
        plant = RunningPlant(endpoint, prefix, proc, log)
        started.append(plant)
        with open_session(plant.client_settings()) as s:
            for loop in loops:
                try:
                    wait_for_loop(s, prefix, loop, timeout=20.0)
                except Exception:
                    raise AssertionError(f"plant did not come up:\n{plant.stderr()}") from None
        return plant

    yield start
    for plant in started:
        stop_service(plant.proc)
