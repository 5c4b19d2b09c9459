"""``launcher.stop_service``: a stopped service leaves nothing behind in its process group (a
tuner's compute workers and their fork server), whether its helpers go by themselves or have
to be killed; ``launcher.free_tcp_port``: a listener's port no outgoing connection takes."""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap

from services import launcher
from services.launcher import _group_alive, stop_service

# a "service" that starts a helper in its own process group, then waits to be stopped
PARENT = textwrap.dedent(
    """
    import os, subprocess, sys, time
    helper = subprocess.Popen([sys.executable, "-c", sys.argv[1], str(os.getpid())])
    print(helper.pid, flush=True)
    time.sleep(60)
    """
)
# a helper that ignores SIGTERM and would outlive its parent by a minute
STUBBORN = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(60)"
# a helper that notices at once that its parent is gone, and goes
FOLLOWS = "import os, sys, time\nwhile os.getppid() == int(sys.argv[1]): time.sleep(0.01)\n"


def _start(helper: str) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen(
        [sys.executable, "-c", PARENT, helper],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    helper_pid = int(proc.stdout.readline())
    return proc, helper_pid


def test_a_helper_that_outlives_its_service_is_killed_with_the_group():
    proc, _ = _start(STUBBORN)
    assert _group_alive(proc.pid)
    stop_service(proc, timeout=1.0)
    assert proc.returncode is not None
    assert not _group_alive(proc.pid)


def test_a_helper_that_goes_by_itself_is_waited_for():
    proc, _ = _start(FOLLOWS)
    stop_service(proc, timeout=30.0)
    assert not _group_alive(proc.pid)


def test_a_service_already_gone_is_only_reaped():
    proc, _ = _start(FOLLOWS)
    proc.kill()
    proc.wait()
    assert stop_service(proc, timeout=30.0) == proc.returncode
    assert not _group_alive(proc.pid)


def test_free_ports_lie_below_the_ephemeral_range_and_are_never_handed_out_twice():
    """Outgoing connections take their local ports from the ephemeral range: a listener's
    port picked there could be taken before the listener binds it."""
    low = launcher._ephemeral_low()
    ports = [launcher.free_tcp_port() for _ in range(50)]
    assert len(set(ports)) == len(ports)
    for port in ports:
        assert low - launcher.PORT_SPAN <= port < low
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))
