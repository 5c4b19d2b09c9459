"""``autotune router``: a Zenoh router in Python, for machines without zenohd.

Services in client mode connect to it (``-m client -e tcp/HOST:7447``); it routes between
them, across machines. The compose file uses the official ``eclipse/zenoh`` image instead.
"""

from __future__ import annotations

import argparse
import logging
import threading

from shared.cli import add_common_arguments, install_stop_handlers, setup_logging
from shared.session import ZenohSettings, open_session, settings_from_args

HELP = "run a Zenoh router (for services in client mode, across machines)"
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.verbose + 1, "router")
    s = settings_from_args(args)
    settings = ZenohSettings(
        mode="router",
        connect=s.connect,
        listen=s.listen or (DEFAULT_LISTEN,),
        config_file=s.config_file,
        cfg=s.cfg,
        no_multicast_scouting=s.no_multicast_scouting,
    )
    stop = threading.Event()
    install_stop_handlers(stop)
    with open_session(settings):
        logging.getLogger("router").info("routing on %s", ", ".join(settings.listen))
        while not stop.wait(0.5):
            pass
    return 0
