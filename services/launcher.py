"""Start services as separate processes on loopback, and stop them cleanly."""

from __future__ import annotations

import contextlib
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from shared.cli import PARENT_ENV

EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
PORT_SPAN = 12000  # listener ports are drawn from this many just below the ephemeral range
_given: set[int] = set()  # handed out by this process (never twice)
_draw = random.Random()


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, for a listener to bind soon.

    Drawn at random below the kernel's ephemeral range, not by binding port 0: the kernel
    gives port 0 from that range, where every outgoing connection (a Zenoh client's) takes
    its local port too, so between the pick and the listener's bind a connection could take
    it (seen: a test's plant_sim failing with "Address already in use"). Port 0 remains the
    fallback where that range leaves no room below it."""
    low = _ephemeral_low()
    if low - PORT_SPAN >= 1024:
        for _ in range(100):
            port = _draw.randint(low - PORT_SPAN, low - 1)
            if port not in _given and _bindable(port):
                _given.add(port)
                return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ephemeral_low() -> int:
    """The first port of the kernel's ephemeral range (Linux's default 32768 if unreadable)."""
    try:
        return int(EPHEMERAL_RANGE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _bindable(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def start_service(
    module: str, args: Sequence[str], *, stderr=None, stdout=None, source: Path | None = None
) -> subprocess.Popen:
    """``python -m <module> <args>`` in its own process group (Ctrl-C reaches it through us);
    with ``source``, run from that source tree (its code first on the path: an older
    checkout's services, for a before/after in one run)."""
    # the service stops if this process goes without stopping it (``cli.watch_parent``)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", PARENT_ENV: str(os.getpid())}
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
