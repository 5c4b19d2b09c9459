"""Services started as processes on loopback: the plant's handle, and waiting for tokens."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from services.autotuner.loop_client import wait_for_token
from shared.session import ZenohSettings, open_session


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


def wait_for_tokens(
    settings: ZenohSettings, key_exprs: list[str], timeout: float, log: Path
) -> None:
    """Block until a liveliness token is seen on every key (event-driven, no polling)."""
    with open_session(settings) as s:
        for key in key_exprs:
            if not wait_for_token(s, key, timeout):
                raise AssertionError(f"{key} did not come up:\n{log.read_text()}")
