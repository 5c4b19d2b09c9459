"""``autotune up --console`` and ``autotune demo --console``: the console as one more process
of their stack, on 127.0.0.1 (``autotune console --host`` serves elsewhere), stopped first.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

from services.console.command import DEFAULT_HOST, DEFAULT_PORT
from services.launcher import stop_service
from services.stack import Stack
from shared.errors import ConfigError

NAME = "console"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--console`` and ``--console-port``."""
    parser.add_argument(
        "--console",
        action="store_true",
        help="also serve the commissioning console (autotune console) on 127.0.0.1",
    )
    parser.add_argument(
        "--console-port",
        type=int,
        default=None,
        metavar="PORT",
        help=f"with --console: its port (default: {DEFAULT_PORT})",
    )


def port_of(args: argparse.Namespace) -> int:
    """The console's port (``--console-port``, default DEFAULT_PORT), checked: ConfigError
    naming the flag when it is given without ``--console`` (`demo --console-port 70000` was
    taken, and meant nothing: helper trial) or the console could not serve on it."""
    if args.console_port is not None and not args.console:
        raise ConfigError(f"--console-port {args.console_port}: only with --console")
    port = DEFAULT_PORT if args.console_port is None else args.console_port
    if args.console:
        check_port(port)
    return port


def check_port(port: int) -> None:
    """ConfigError naming ``--console-port`` when the console could not serve on it."""
    if not 1 <= port <= 65535:
        raise ConfigError(f"--console-port {port}: must be 1 to 65535")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((DEFAULT_HOST, port))
        except OSError as err:
            raise ConfigError(
                f"--console-port {port}: {DEFAULT_HOST}:{port} is not free "
                f"({err.strerror}); choose another"
            ) from None


def start(stack: Stack, prefix: str, runs: Path, port: int, zenoh_args: list[str]) -> str:
    """Start the console in ``stack`` (its own line on stdout left out: the caller says where
    it is, and ``--json`` output stays clean); return its URL."""
    args = ["--prefix", prefix, "--runs", str(runs), "--port", str(port), *zenoh_args]
    stack.procs[NAME] = subprocess.Popen(
        [sys.executable, "-m", "services.console", *args],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=stack.logs,
        start_new_session=True,  # as every service of the stack: Ctrl-C reaches the parent
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    return f"http://{DEFAULT_HOST}:{port}/"


def stop(stack: Stack) -> None:
    """Stop the console first: it only watches, the others then stop in their order."""
    proc = stack.procs.pop(NAME, None)
    if proc is not None:
        stop_service(proc)


def hold(url: str) -> None:
    """Keep everything up for the page until Ctrl-C or SIGTERM (a normal end, not an error)."""
    print(f"the console is at {url}: Ctrl-C stops it and the services", file=sys.stderr)
    done = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: done.set())
    try:
        while not done.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
