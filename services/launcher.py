"""Start services as separate processes on loopback, and stop them cleanly."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
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
    """SIGTERM, wait, then SIGKILL if it does not finish; return its exit code. Then wait
    (``timeout`` s at most) for what it started in its process group (a tuner's compute
    workers and their fork server) to go, and kill what is left: nothing outlives a stop
    (a fork server still importing on its way out took CPU from what ran next)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    _reap_group(proc.pid, timeout)
    return proc.returncode


def _reap_group(pgid: int, timeout: float) -> None:
    """Wait until no live process is left in process group ``pgid`` (a service started by
    ``start_service`` leads its own), SIGKILL the group after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    killed = False
    while _group_alive(pgid):
        if time.monotonic() > deadline:
            if killed:
                return  # not gone a second after SIGKILL: not ours to wait for
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(pgid, signal.SIGKILL)
            killed, deadline = True, time.monotonic() + 1.0
        time.sleep(0.02)


def _group_alive(pgid: int) -> bool:
    """A process of group ``pgid`` that is not a zombie exists (read from /proc: a zombie
    that nobody reaps would otherwise keep the group alive for ever)."""
    try:
        entries = os.listdir("/proc")
    except OSError:  # no /proc: ask the kernel (a zombie counts there)
        try:
            os.killpg(pgid, 0)
        except (ProcessLookupError, PermissionError):
            return False
        return True
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rfind(b")") + 2 :].split()  # state, ppid, pgrp, …
        if len(fields) > 2 and fields[0] != b"Z" and int(fields[2]) == pgid:
            return True
    return False
