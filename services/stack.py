"""Start plant_sim, the autotuner, the logger (and a router) as processes; stop them cleanly.

Used by ``autotune demo`` and ``autotune up``. Each service runs in its own process group,
so a Ctrl-C reaches only the parent, which stops them in order: the autotuner first (it
cancels its runs, restoring their loops, while the plant still runs), then the logger (which
finishes its files), then plant_sim, then the router.
"""

from __future__ import annotations

import subprocess
import time
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
        """Wait (``timeout`` s at most) for every service's token; AutotuneError as soon as
        one of the services has exited (its own error is on stderr above: a bad setting
        refused by the plant was followed by 40 s of waiting, then the tuner blamed)."""
        deadline = time.monotonic() + timeout
        with open_session(self.client) as s:
            for key in tokens:
                # (a second at least: a token already up is seen a moment after the subscriber
                # is declared, from its history)
                left = max(1.0, deadline - time.monotonic())
                if wait_for_token(s, key, left, abandon=lambda: bool(self._ended())):
                    continue
                if ended := self._ended():
                    raise AutotuneError(
                        f"{', '.join(ended)} ended as the stack started, before {key} came up "
                        "(its own error says why)"
                    )
                raise AutotuneError(f"{key} did not come up within {timeout:g} s")

    def _ended(self) -> list[str]:
        """The services that have exited, with their exit codes."""
        return [f"{n} (exit {p.returncode})" for n, p in self.procs.items() if p.poll() is not None]

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
