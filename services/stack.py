"""Start plant_sim, the autotuner, the logger (and a router) as processes; stop them cleanly.

Used by ``autotune demo`` and ``autotune up``. Each service runs in its own process group,
so a Ctrl-C reaches only the parent, which stops them in order: the autotuner first (it
cancels its runs, restoring their loops, while the plant still runs), then the logger (which
finishes its files), then plant_sim, then the router.
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from services.autotuner.loop_client import wait_for_token
from services.launcher import start_service, stop_service
from shared import keys
from shared.errors import AutotuneError, ConfigError
from shared.session import ZenohSettings, open_session

STOP_ORDER = ("tuner", "logger", "plant", "router")


@dataclass
class Stack:
    prefix: str
    client: ZenohSettings  # how a client (and each service) joins the bus
    logs: IO[str] | None = None
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    source: Path | None = None  # run the services from this source tree (default: this one)

    def start(self, name: str, module: str, args: list[str], zenoh_args: list[str]) -> None:
        self.procs[name] = start_service(
            module, [*args, *zenoh_args], stderr=self.logs, source=self.source
        )

    def wait_ready(self, tokens: list[str], timeout: float = 20.0) -> None:
        with open_session(self.client) as s:
            for key in tokens:
                if not wait_for_token(s, key, timeout):
                    dead = [n for n, p in self.procs.items() if p.poll() is not None]
                    raise AutotuneError(
                        f"{key} did not come up within {timeout:g} s"
                        + (f" ({', '.join(dead)} exited)" if dead else "")
                    )

    def stop(self) -> dict[str, int]:
        codes = {}
        for name in STOP_ORDER:
            if name in self.procs:
                codes[name] = stop_service(self.procs[name], timeout=30.0)
        return codes


def service_tokens(prefix: str, loop: str | None) -> list[str]:
    tokens = [keys.tuner_alive(prefix, "tuner"), keys.logger_alive(prefix, "logger")]
    tokens.append(
        keys.loop_alive(prefix, loop) if loop else keys.service_alive(prefix, "plant_sim", "plant")
    )
    return tokens


def runs_dir(path: str) -> Path:
    """``--runs``, made if it is not there; ConfigError naming the flag if it cannot be."""
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"--runs {path}: cannot make it ({err.strerror or err})") from None
    return p
