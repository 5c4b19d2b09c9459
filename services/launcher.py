"""Start services as separate processes on loopback, and stop them cleanly."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_service(
    module: str, args: Sequence[str], *, stderr=None, stdout=None, source: Path | None = None
) -> subprocess.Popen:
    """``python -m <module> <args>`` in its own process group (Ctrl-C reaches it through us);
    with ``source``, run from that source tree (its code first on the path: an older
    checkout's services, for a before/after in one run)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if source is not None:
        env["PYTHONPATH"] = str(source)
    return subprocess.Popen(
        [sys.executable, "-m", module, *args],
        stdin=subprocess.DEVNULL,
        stdout=stdout,
        stderr=stderr,
        start_new_session=True,
        env=env,
        cwd=source,
    )


def stop_service(proc: subprocess.Popen, timeout: float = 5.0) -> int:
    """SIGTERM, wait, then SIGKILL if it does not finish; return its exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode
