"""Fixtures that start real services as separate processes on loopback."""

from __future__ import annotations

import itertools
import os
import signal
from pathlib import Path

import pytest

from services.autotuner.compute_pool import preload
from services.launcher import free_tcp_port, start_service, stop_service
from shared import keys
from tests.running_services import RunningPlant, wait_for_tokens

_counter = itertools.count()

# The suite tries Ctrl-C, a closed terminal and a service manager's stop on the product, which
# respects a signal ignored when it started (nohup's SIGHUP, a shell's SIGINT for a job in the
# background): a suite run that way would find them ignored in every process it starts. The
# default dispositions, for this process and (inherited) the services it starts.
signal.signal(signal.SIGINT, signal.default_int_handler)
signal.signal(signal.SIGHUP, signal.SIG_DFL)

# The numerics a run computes with, imported now as the tuner service imports them at its
# start (``compute_pool.preload``): the library imports scipy's modules where they are used,
# and a run in this process (an in-process TuningRun on a realtime plant) would otherwise pay
# for them inside its first step, holding a lease of half a second (it lost one so in CI)
preload()


@pytest.fixture(autouse=True)
def _signal_dispositions():
    """Each test's signal handlers put back after it: a CLI command run in this process
    (``autotune plant -e nowhere`` refused after its service installed its stop handlers)
    left them, and a later test that reads SIGINT's handler found a service's."""
    sigs = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    saved = {s: signal.getsignal(s) for s in sigs}
    yield
    for s, handler in saved.items():
        if signal.getsignal(s) is not handler:
            signal.signal(s, handler)


@pytest.fixture
def start_plant(tmp_path):
    """start_plant(toml_text or None, *extra_args, loops=(...)) → RunningPlant."""
    started: list[RunningPlant] = []

    def start(toml: str | None = None, *extra: str, loops: tuple[str, ...] = ()) -> RunningPlant:
        n = next(_counter)
        endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
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
        wait_for_tokens(
            plant.client_settings(), [keys.loop_alive(prefix, lp) for lp in loops], 20.0, log
        )
        return plant

    yield start
    for plant in started:
        stop_service(plant.proc)


def _client_service(tmp_path: Path, name: str, module: str, token, extra=()):
    """A start(plant) fixture body: the service as a peer of the plant, up when its token is."""
    started = []

    def start(plant: RunningPlant, *args):
        log = tmp_path / f"{name}{len(started)}.log"
        with log.open("w") as f:
            proc = start_service(
                module,
                [
                    "--prefix",
                    plant.prefix,
                    "-e",
                    plant.endpoint,
                    "--no-multicast-scouting",
                    *extra,
                    *[str(a) for a in args],
                ],
                stderr=f,
            )
        started.append(proc)
        wait_for_tokens(plant.client_settings(), [token(plant.prefix)], 20.0, log)
        return proc

    return start, started


@pytest.fixture
def start_tuner(tmp_path):
    """start_tuner(plant) → the autotuner as its own process, a peer of the plant's."""
    start, started = _client_service(
        tmp_path,
        "tuner",
        "services.autotuner",
        lambda p: keys.tuner_alive(p, "tuner"),
        ("--cfg", "connect/timeout_ms:10000"),
    )
    yield start
    for proc in started:
        stop_service(proc)


@pytest.fixture
def start_logger(tmp_path):
    """start_logger(plant, runs_dir) → the logger as its own process, a peer of the plant's."""
    start, started = _client_service(
        tmp_path, "logger", "services.logger", lambda p: keys.logger_alive(p, "logger"), ("-v",)
    )

    def with_runs(plant: RunningPlant, runs: Path):
        return start(plant, "--runs", runs)

    yield with_runs
    for proc in started:
        stop_service(proc)
