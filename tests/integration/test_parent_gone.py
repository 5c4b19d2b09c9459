"""A service started by another autotune process (``up``, ``demo``, ``perf``: the launcher)
stops when that process is gone without stopping it: ``autotune up`` killed with SIGKILL left
plant_sim, the tuner and the logger running, holding the bus's port (helper 59). One started
by hand is not watched (``nohup autotune plant &`` outlives its shell)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from services.launcher import free_tcp_port
from shared import keys
from shared.session import ZenohSettings
from tests.running_services import wait_for_tokens

ROOT = Path(__file__).resolve().parents[2]

PARENT = """
import sys
sys.path.insert(0, {root!r})
from services.launcher import start_service
p = start_service("services.plant_sim", {args!r})
print(p.pid, flush=True)
sys.stdin.read()  # until the test kills this process
"""


def _ended(pid: int) -> bool:
    """Process ``pid`` has exited: gone, or a zombie (a container's pid 1 may never reap it)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat.rsplit(")", 1)[1].split()[0] == "Z"


def _gone(pid: int, within: float) -> bool:
    """Whether process ``pid`` has exited within ``within`` s."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        if _ended(pid):
            return True
        time.sleep(0.1)  # polling for an event with a bound, not a synchronisation
    return False


def test_a_plant_started_by_a_process_that_is_killed_stops(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = f"parent{os.getpid()}"
    args = ["--prefix", prefix, "-l", endpoint, "--no-multicast-scouting"]
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT.format(root=str(ROOT), args=args)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        child = int(parent.stdout.readline())
        settings = ZenohSettings(mode="peer", connect=(endpoint,), no_multicast_scouting=True)
        log = tmp_path / "plant.log"
        log.write_text("(the plant's output is this test's)")
        wait_for_tokens(settings, [keys.loop_alive(prefix, "hx1")], 30.0, log)
        parent.send_signal(signal.SIGKILL)  # as `up` killed outright: nothing stops its children
        parent.wait(10)
        assert _gone(child, 30.0), "the plant outlived the process that started it"
    finally:
        parent.kill()
        with contextlib.suppress(ProcessLookupError, UnboundLocalError):
            os.kill(child, signal.SIGKILL)
