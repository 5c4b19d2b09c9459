"""Open a Zenoh session from settings, with the flags of the zenoh examples and zenohd.

Precedence: a config file (``-c``) or else ``ZENOH_CONFIG``, or else Zenoh's defaults; then
``-m``, ``-e``, ``-l``, ``--no-multicast-scouting`` and ``--cfg KEY:VALUE`` override it.
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import dataclass, field

import zenoh

from shared.errors import ConfigError

MODES = ("peer", "client", "router")


@dataclass(frozen=True)
class ZenohSettings:
    """How a service joins the bus."""

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    cfg: tuple[str, ...] = field(default_factory=tuple)
    no_multicast_scouting: bool = False


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``-m/-e/-l/-c/--cfg/--no-multicast-scouting`` as zenohd and the zenoh examples do."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("-m", "--mode", choices=MODES, help="the zenoh session mode (default: peer)")
    g.add_argument(
        "-e",
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    g.add_argument(
        "-l",
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    g.add_argument(
        "-c",
        "--config",
        metavar="FILE",
        help="a zenoh JSON5 configuration file (default: $ZENOH_CONFIG if set)",
    )
    g.add_argument(
        "--cfg",
        action="append",
        default=[],
        metavar="KEY:VALUE",
        help="set one configuration key to a JSON5 value, e.g. "
        "'connect/timeout_ms:30000' (repeatable)",
    )
    g.add_argument(
        "--no-multicast-scouting",
        action="store_true",
        help="disable multicast scouting (peers then need -e or -l)",
    )


def settings_from_args(ns: argparse.Namespace) -> ZenohSettings:
    return ZenohSettings(
        mode=ns.mode,
        connect=tuple(ns.connect),
        listen=tuple(ns.listen),
        config_file=ns.config,
        cfg=tuple(ns.cfg),
        no_multicast_scouting=ns.no_multicast_scouting,
    )


def _check_endpoint(flag: str, endpoint: str) -> None:
    proto, sep, addr = endpoint.partition("/")
    if not sep or not proto or not addr:
        raise ConfigError(
            f"{flag} {endpoint!r}: expected PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447"
        )


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """Build the zenoh.Config that ``settings`` describe; ConfigError names the bad setting."""
    try:
        if settings.config_file:
            conf = zenoh.Config.from_file(settings.config_file)
        elif os.environ.get("ZENOH_CONFIG"):
            conf = zenoh.Config.from_env()
        else:
            conf = zenoh.Config()
    except Exception as err:
        source = settings.config_file or f"ZENOH_CONFIG={os.environ.get('ZENOH_CONFIG')}"
        raise ConfigError(f"zenoh config {source}: {err}") from None

    def insert(what: str, key: str, value: str) -> None:
        try:
            conf.insert_json5(key, value)
        except Exception as err:
            raise ConfigError(f"{what}: {err}") from None

    if settings.mode:
        if settings.mode not in MODES:
            raise ConfigError(f"--mode {settings.mode!r}: must be one of {', '.join(MODES)}")
        insert("--mode", "mode", json.dumps(settings.mode))
    for flag, endpoints, key in (
        ("-e", settings.connect, "connect/endpoints"),
        ("-l", settings.listen, "listen/endpoints"),
    ):
        if endpoints:
            for e in endpoints:
                _check_endpoint(flag, e)
            insert(flag, key, json.dumps(list(endpoints)))
    if settings.no_multicast_scouting:
        insert("--no-multicast-scouting", "scouting/multicast/enabled", "false")
    for item in settings.cfg:
        key, sep, value = item.partition(":")
        if not sep or not key or not value:
            raise ConfigError(f"--cfg {item!r}: expected KEY:VALUE, e.g. connect/timeout_ms:30000")
        insert(f"--cfg {item!r}", key, value)
    return conf


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a session; a failure (bad endpoint, no router reachable) becomes a ConfigError."""
    conf = zenoh_config(settings)
    try:
        return zenoh.open(conf)
    except Exception as err:
        raise ConfigError(f"cannot open zenoh session: {err}") from None
