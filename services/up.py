"""``autotune up [--config FILE]``: start the three services (and a router) until Ctrl-C.

Without ``--router`` plant_sim listens on ``--endpoint`` and the autotuner and logger connect
to it as peers. With ``--router`` a Zenoh router listens there and all three services are its
clients, as they would be across machines. Ctrl-C (or SIGTERM) stops them in order: the
autotuner first, which cancels its runs and so restores their loops, then the logger, which
finishes its files, then plant_sim and the router. If a service dies, the others are
stopped too.

The config file (TOML) takes the same settings as the flags, which override it::

    prefix = "autotune"
    endpoint = "tcp/127.0.0.1:7447"
    router = false
    plant = "my_plant.toml"   # default: the presets
    clock = "lockstep"        # or "realtime"
    speed = 1.0
    seed = 1
    runs = "runs"
"""

from __future__ import annotations

import argparse
import sys
import threading
import tomllib
from pathlib import Path
from typing import Literal

import pydantic
from pydantic import BaseModel, ConfigDict, Field

from services.stack import Stack, runs_dir, service_tokens
from shared import keys
from shared.cli import check_ids, install_stop_handlers
from shared.errors import ConfigError
from shared.session import ZenohSettings

HELP = "start plant_sim, the autotuner and the logger (and a router) until Ctrl-C"


class UpConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    prefix: str = keys.DEFAULT_PREFIX
    endpoint: str = "tcp/127.0.0.1:7447"
    router: bool = False
    plant: str | None = None
    clock: Literal["lockstep", "realtime"] = "lockstep"
    speed: float = Field(default=1.0, gt=0.0)
    seed: int | None = None
    runs: str = "runs"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="settings file (TOML), see above")
    parser.add_argument("--prefix", help=f"root of every key (default: {keys.DEFAULT_PREFIX})")
    parser.add_argument(
        "--endpoint", help="where plant_sim (or the router) listens (default: tcp/127.0.0.1:7447)"
    )
    parser.add_argument(
        "--router",
        action="store_true",
        default=None,
        help="start a Zenoh router; the services are its clients",
    )
    parser.add_argument("--plant", metavar="FILE", help="plant file (default: the presets)")
    parser.add_argument("--clock", choices=("lockstep", "realtime"))
    parser.add_argument("--speed", type=float)
    parser.add_argument("--seed", type=int)
    parser.add_argument("--runs", metavar="DIR", help="the logger's directory (default: runs)")


def load_config(args: argparse.Namespace) -> UpConfig:
    data: dict = {}
    if args.config:
        try:
            data = tomllib.loads(Path(args.config).read_text())
        except OSError as err:
            raise ConfigError(f"--config {args.config}: cannot read it: {err.strerror}") from None
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"--config {args.config}: not valid TOML: {err}") from None
    for name in UpConfig.model_fields:
        value = getattr(args, name, None)
        if value is not None:
            data[name] = value
    try:
        cfg = UpConfig.model_validate(data)
    except pydantic.ValidationError as err:
        e = err.errors()[0]
        where = ".".join(str(p) for p in e["loc"])
        raise ConfigError(f"{args.config or 'settings'}: {where}: {e['msg']}") from None
    check_ids(cfg.prefix)
    if cfg.plant and not Path(cfg.plant).is_file():
        raise ConfigError(f"plant: {cfg.plant}: no such file")
    return cfg


def start(cfg: UpConfig, logs=None) -> Stack:
    connect = ["-e", cfg.endpoint, "--no-multicast-scouting", "--cfg", "connect/timeout_ms:30000"]
    client = ZenohSettings(
        mode="client" if cfg.router else "peer",
        connect=(cfg.endpoint,),
        cfg=("connect/timeout_ms:30000",),
        no_multicast_scouting=True,
    )
    stack = Stack(cfg.prefix, client, logs)
    plant = ["--prefix", cfg.prefix, "--clock", cfg.clock, "--speed", str(cfg.speed)]
    plant += ["--plant", cfg.plant] if cfg.plant else []
    plant += ["--seed", str(cfg.seed)] if cfg.seed is not None else []
    if cfg.router:
        stack.start(
            "router", "services.cli", ["router", "-l", cfg.endpoint, "--no-multicast-scouting"], []
        )
        mode = ["-m", "client", *connect]
        stack.start("plant", "services.plant_sim", plant, mode)
    else:
        mode = connect
        stack.start(
            "plant", "services.plant_sim", plant, ["-l", cfg.endpoint, "--no-multicast-scouting"]
        )
    stack.start(
        "logger",
        "services.logger",
        ["--prefix", cfg.prefix, "--runs", str(runs_dir(cfg.runs))],
        mode,
    )
    stack.start("tuner", "services.autotuner", ["--prefix", cfg.prefix], mode)
    return stack


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args)
    stop = threading.Event()
    install_stop_handlers(stop)
    stack = start(cfg)
    try:
        stack.wait_ready(service_tokens(cfg.prefix, None), timeout=40.0)
        pids = ", ".join(f"{n} pid {p.pid}" for n, p in stack.procs.items())
        print(
            f"running under {cfg.prefix}/ on {cfg.endpoint}"
            f"{' through a router' if cfg.router else ''}: {pids}; Ctrl-C stops them",
            file=sys.stderr,
            flush=True,
        )
        while not stop.wait(0.5):
            dead = [n for n, p in stack.procs.items() if p.poll() is not None]
            if dead:
                print(f"{', '.join(dead)} exited; stopping the others", file=sys.stderr)
                return 1
    finally:
        codes = stack.stop()
        print(
            "stopped: " + ", ".join(f"{n} exit {c}" for n, c in codes.items()),
            file=sys.stderr,
            flush=True,
        )
    return 0
