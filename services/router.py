"""``autotune router``: a Zenoh router in Python, for machines without zenohd.

Services in client mode connect to it (``-m client -e tcp/HOST:7447``); it routes between
them. It listens where ``-l`` says, else where its config file (``-c``) says, else on
loopback only (``tcp/127.0.0.1:7447``): ``-l tcp/0.0.0.0:7447`` makes it reachable from other
machines. ``autotune up --secure`` starts it with the access-control config it writes; the
compose file uses the official ``eclipse/zenoh`` image with the same config instead.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading

from shared.cli import add_common_arguments, install_stop_handlers, setup_logging
from shared.session import ZenohSettings, open_config, settings_from_args, zenoh_config

HELP = "run a Zenoh router (for services in client mode; loopback unless told otherwise)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser)


def router_settings(args: argparse.Namespace) -> ZenohSettings:
    s = settings_from_args(args)
    return ZenohSettings(
        mode="router",
        connect=s.connect,
        listen=s.listen,
        config_file=s.config_file,
        cfg=s.cfg,
        no_multicast_scouting=s.no_multicast_scouting,
        multicast_scouting=s.multicast_scouting,
    )


def run(args: argparse.Namespace) -> int:
    setup_logging(args.verbose + 1, "router")
    conf = zenoh_config(router_settings(args))
    listen = json.loads(conf.get_json("listen/endpoints"))
    acl = json.loads(conf.get_json("access_control/enabled")) is True
    auth = json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file")) is not None
    stop = threading.Event()
    install_stop_handlers(stop)
    with open_config(conf):
        logging.getLogger("router").info(
            "routing on %s%s%s",
            ", ".join(listen) if isinstance(listen, list) else listen,
            ", user/password required" if auth else "",
            ", access control on" if acl else "",
        )
        while not stop.wait(0.5):
            pass
    return 0
