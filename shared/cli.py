"""Command-line pieces every service and client shares: flags, logging, clean stops, ids."""

from __future__ import annotations

import argparse
import logging
import signal
import threading

from shared import keys
from shared.errors import ConfigError
from shared.session import add_zenoh_arguments


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    """``--prefix``, ``-v`` and the Zenoh flags (``-m -e -l -c --cfg --no-multicast-scouting``)."""
    parser.add_argument(
        "--prefix",
        default=keys.DEFAULT_PREFIX,
        help="root of every key expression (default: %(default)s)",
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)"
    )
    add_zenoh_arguments(parser)


def setup_logging(verbose: int, name: str) -> None:
    level = logging.WARNING if verbose <= 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format=f"%(asctime)s {name} %(levelname)s %(message)s")


def install_stop_handlers(stop: threading.Event) -> None:
    """SIGINT and SIGTERM end a service cleanly (tokens withdrawn, session closed).

    The handler hands ``stop.set()`` to a thread: run in the handler itself it could
    deadlock, because the main thread may be inside ``stop.wait()`` holding the event's
    (non-reentrant) lock when the signal is handled.
    """

    def handler(*_: object) -> None:
        threading.Thread(target=stop.set, daemon=True).start()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)


def check_ids(prefix: str, **ids: str) -> None:
    """ConfigError naming the flag when the prefix or an id cannot be a key chunk."""
    try:
        keys.check_prefix(prefix)
        for what, value in ids.items():
            keys.check_id(value, what)
    except ValueError as err:
        raise ConfigError(str(err)) from None
