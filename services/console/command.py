"""``autotune console [--port 8050] [--host 127.0.0.1] [--runs DIR]``: the commissioning
console, a web page served by this process (open http://127.0.0.1:8050/).

The page shows the loops on the bus with live trends of PV, setpoint and output (the last
``--history`` s of sim time), their mode and gains; starts a tune (method, rule or aim,
amplitude, limits: the request is validated exactly as ``autotune tune``'s flags), follows its
progress (phase, cycles, running K_u and P_u) and cancels it; shows the result (K_u, P_u, the
model, every rule's gains with Ms, margins and predicted step response, the recommended one
marked) and applies, rejects or reverts it (as ``autotune apply`` and ``revert`` do, through
the autotuner and the plant's lease); lists the recorded runs of ``--runs`` and opens each as
its report figure, two side by side. It is a client of the bus like the CLI, and shows which
services are up; they may come and go.

Bound to 127.0.0.1 (this machine only) unless ``--host`` says otherwise: the page can start
tunes, so whoever reaches it commands the loops (``--host 0.0.0.0`` only on a trusted network).
Exit 2 with one line on bad flags or a port in use.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import signal
import sys
from pathlib import Path

from services.console.trends import HISTORY
from shared.cli import add_common_arguments, check_ids, setup_logging
from shared.errors import ConfigError, one_line
from shared.identity import auth_user
from shared.session import open_session, settings_from_args

HELP = "the commissioning console: a web page with live trends, tuning and the runs"
DEFAULT_PORT = 8050
DEFAULT_HOST = "127.0.0.1"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--port",
        type=int,
        default=DEFAULT_PORT,
        help="TCP port of the page (default: %(default)s; 0: any free port, printed)",
    )
    parser.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help="address to serve on (default: %(default)s, this machine only; 0.0.0.0 serves "
        "every interface: whoever reaches the page can tune the loops)",
    )
    parser.add_argument(
        "--runs",
        default="runs",
        metavar="DIR",
        help="the logger's runs directory: the recorded runs and the change history that "
        "apply and revert read (default: %(default)s)",
    )
    parser.add_argument(
        "--history",
        type=float,
        default=HISTORY,
        metavar="S",
        help="seconds of sim time the trends keep (default: %(default)s)",
    )
    add_common_arguments(parser)


def check(args: argparse.Namespace) -> None:
    """ConfigError naming the first bad flag."""
    check_ids(args.prefix)
    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: must be 0 to 65535")
    if not (math.isfinite(args.history) and 0 < args.history <= 86400):
        raise ConfigError(f"--history {args.history}: must be > 0 and at most 86400 s")
    if not args.host:
        raise ConfigError("--host: empty")
    runs = Path(args.runs)
    if runs.exists() and not runs.is_dir():
        raise ConfigError(f"--runs {runs}: not a directory")


async def _serve(args: argparse.Namespace) -> None:
    # imported here: every autotune command imports this module through the CLI
    from websockets.asyncio.server import serve

    from services.console.bridge import Bridge
    from services.console.server import MAX_MESSAGE, TICK, Hub, console_hosts

    hub = Hub(Path(args.runs), console_hosts(args.host))
    try:
        server = await serve(
            hub.page,
            args.host,
            args.port,
            process_request=hub.route,
            max_size=MAX_MESSAGE,
        )
    except OSError as err:
        raise ConfigError(
            f"--port {args.port}: cannot serve on {args.host}:{args.port}: "
            f"{one_line(err.strerror or err)}"
        ) from None
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    settings = settings_from_args(args)
    async with server:
        session = await asyncio.to_thread(open_session, settings)
        bridge = None
        try:
            bridge = Bridge(
                session,
                args.prefix,
                Path(args.runs),
                hub.emitter(),
                args.history,
                auth_user(settings),
            )
            hub.bridge = bridge
            hub.ready.set()
            port = server.sockets[0].getsockname()[1]
            print(
                f"console on http://{_url_host(args.host)}:{port}/ (prefix {args.prefix}, "
                f"runs {args.runs})",
                flush=True,
            )
            while not stop.is_set():
                for msg in bridge.tick():
                    hub.broadcast(msg)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), TICK)
        finally:
            server.close()
            if bridge is not None:
                bridge.close()
            # a worker may still be inside a call of the session (a run the page is
            # following): closing then is refused, and the process ends all the same
            with contextlib.suppress(RuntimeError):
                session.close()
    print("console stopped", file=sys.stderr)


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def run(args: argparse.Namespace) -> int:
    check(args)
    setup_logging(args.verbose, "console")
    asyncio.run(_serve(args))
    return 0
