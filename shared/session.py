"""Open a Zenoh session from settings, with the flags of the zenoh examples and zenohd.

Precedence: a config file (``-c``) or else ``ZENOH_CONFIG``, or else Zenoh's defaults; then
``-m``, ``-e``, ``-l``, ``--(no-)multicast-scouting`` and ``--cfg KEY:VALUE`` override it.

Secure by default: whatever the user does not configure stays on this machine.

* Multicast scouting is off unless ``--multicast-scouting`` or the config turns it on.
* With no endpoints configured (no ``-l``/``-e``, none in the config file or ``--cfg``), a
  peer listens on loopback only: on the *rendezvous* ``tcp/127.0.0.1:7447`` if it is free
  (tried once: no error if another process holds it) and on an ephemeral loopback port; and
  it connects to the rendezvous, retrying every second until it gets there and again
  whenever that link drops. The first process takes the rendezvous, the next ones connect
  to it and learn each other's loopback ports by gossip, so they mesh and stay meshed when
  the holder exits; the next process to start takes the rendezvous over and the others
  reconnect to it within a second. A client connects to the rendezvous; a router listens
  on it. ``AUTOTUNE_RENDEZVOUS`` moves it (e.g. ``tcp/127.0.0.1:17447``).
* With ``-e`` only, a peer listens on an ephemeral loopback port; with ``-l`` only, it
  connects nowhere; a router listens on the rendezvous unless told otherwise.
* ``--multicast-scouting`` restores Zenoh's own discovery: multicast on, and a peer's own
  port on every interface (``tcp/[::]:0``) unless ``-l`` says where.
"""

from __future__ import annotations

import argparse
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from shared.errors import ConfigError

MODES = ("peer", "client", "router")
RENDEZVOUS = "tcp/127.0.0.1:7447"
RENDEZVOUS_ENV = "AUTOTUNE_RENDEZVOUS"
LOOPBACK_ANY = "tcp/127.0.0.1:0"  # an ephemeral port on loopback
# the rendezvous listener: tried once, no failure if another process holds the port
RENDEZVOUS_LISTEN = "#exit_on_failure=false"
OPEN_TIMEOUT = "transport/unicast/open_timeout"  # ms, a link's handshake (Zenoh: 10,000)
CONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}


@dataclass(frozen=True)
class ZenohSettings:
    """How a service joins the bus."""

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    cfg: tuple[str, ...] = field(default_factory=tuple)
    no_multicast_scouting: bool = False
    multicast_scouting: bool = False


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``-m/-e/-l/-c/--cfg/--(no-)multicast-scouting`` as zenohd and the zenoh examples do."""
    g = parser.add_argument_group("zenoh (default: this machine only, see `autotune --help`)")
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
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 to be reachable from other hosts "
        "(repeatable; default: loopback only)",
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
    m = g.add_mutually_exclusive_group()
    m.add_argument(
        "--no-multicast-scouting",
        action="store_true",
        help="disable multicast scouting (the default unless the config file enables it)",
    )
    m.add_argument(
        "--multicast-scouting",
        action="store_true",
        help="discover peers on the local network by UDP multicast, and listen on every "
        "interface unless -l says where (zenoh's own defaults)",
    )


def settings_from_args(ns: argparse.Namespace) -> ZenohSettings:
    return ZenohSettings(
        mode=ns.mode,
        connect=tuple(ns.connect),
        listen=tuple(ns.listen),
        config_file=ns.config,
        cfg=tuple(ns.cfg),
        no_multicast_scouting=ns.no_multicast_scouting,
        multicast_scouting=getattr(ns, "multicast_scouting", False),
    )


def check_endpoint(flag: str, endpoint: str) -> None:
    """ConfigError unless ``endpoint`` is PROTOCOL/ADDRESS; for an IP protocol's HOST:PORT, a
    port within 1–65535 and an IPv4 address's four numbers within 0–255 (tcp/127.0.0.1:99999
    was taken, and ended in "this client reached no peer or router at all")."""
    proto, sep, addr = endpoint.partition("/")
    if not sep or not proto or not addr:
        raise ConfigError(
            f"{flag} {endpoint!r}: expected PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447"
        )
    if proto not in ("tcp", "udp", "tls", "quic", "ws"):
        return
    address = addr.split("#", 1)[0].split("?", 1)[0]
    host, colon, port = address.rpartition(":")
    if not colon or not host:
        raise ConfigError(f"{flag} {endpoint!r}: expected {proto}/HOST:PORT")
    low = 0 if flag == "-l" else 1  # listening on port 0: any free port
    if not port.isdigit() or not low <= int(port) <= 65535:
        raise ConfigError(f"{flag} {endpoint!r}: port {port!r} is not a number within {low}–65535")
    numbers = host.split(".")
    ipv4 = len(numbers) == 4 and all(n.isdigit() for n in numbers)
    if ipv4 and not all(int(n) <= 255 for n in numbers):
        raise ConfigError(f"{flag} {endpoint!r}: {host} is not an IPv4 address (0–255 each)")


def rendezvous() -> str:
    """The well-known loopback endpoint default sessions meet on (``AUTOTUNE_RENDEZVOUS``)."""
    endpoint = os.environ.get(RENDEZVOUS_ENV) or RENDEZVOUS
    check_endpoint(RENDEZVOUS_ENV, endpoint)
    return endpoint


def zenoh_error(err: BaseException) -> str:
    """Zenoh's error text on one line, without the Rust source location it appends."""
    text = str(err)
    invalid = re.match(r"Invalid configuration: (\{.*\})", text, re.S)
    if invalid:
        return _invalid_config_reason(invalid.group(1))
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", text).strip()
    serde = re.search(r'msg: "(.*)", location: Some\(Location \{ line: (\d+), column: (\d+)', text)
    if serde:  # a value of the wrong kind, or a JSON5 syntax error drawn in the message
        msg = serde.group(1).replace("\\n", "\n").replace('\\"', '"')
        drawn = re.search(r"-->\s*(\d+):(\d+).*?=\s*(.+)$", msg, re.S)
        if drawn:  # `--cfg foo:bar` printed the drawing's escapes: 1:1\n |\n1 | bar…
            return f"line {drawn.group(1)}, column {drawn.group(2)}: {drawn.group(3).strip()}"
        return f"line {serde.group(2)}, column {serde.group(3)}: {' '.join(msg.split())}"
    parse = re.search(r"-->\s*(\d+):(\d+).*?=\s*(.+)$", text, re.S)
    if parse:  # a JSON5 syntax error, drawn over several lines
        return f"line {parse.group(1)}, column {parse.group(2)}: {parse.group(3).strip()}"
    return " ".join(text.split())


def _invalid_config_reason(dump: str) -> str:
    try:
        usrpwd = json.loads(dump)["transport"]["auth"]["usrpwd"]
    except (ValueError, KeyError, TypeError):
        usrpwd = {}
    if (usrpwd.get("user") is None) != (usrpwd.get("password") is None):
        missing = "password" if usrpwd.get("password") is None else "user"
        return f"transport/auth/usrpwd/{missing}: missing (user and password go together)"
    return "invalid configuration (zenoh's validation refused it)"


def _load(settings: ZenohSettings) -> tuple[zenoh.Config, str | None]:
    """The config of ``-c`` or ``ZENOH_CONFIG`` (or Zenoh's defaults) and its file name."""
    path = settings.config_file or os.environ.get("ZENOH_CONFIG") or None
    source = settings.config_file or (f"ZENOH_CONFIG={path}" if path else None)
    if path is None:
        return zenoh.Config(), None
    if not Path(path).is_file():
        raise ConfigError(f"zenoh config {source}: no such file")
    try:
        return zenoh.Config.from_file(path), path
    except Exception as err:
        raise ConfigError(f"zenoh config {source}: {zenoh_error(err)}") from None


FILE_KEYS = (
    "transport/auth/usrpwd/dictionary_file",
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/connect_certificate",
    "transport/link/tls/connect_private_key",
)


def _resolve_files(conf: zenoh.Config, path: str | None, source: str | None) -> None:
    """Credentials files named by the config: a relative path is taken from the config
    file's own directory (zenohd takes it from its working directory); a missing one is
    named with its key."""
    for key in FILE_KEYS:
        value = json.loads(conf.get_json(key))
        if not isinstance(value, str):
            continue
        file = Path(value)
        if path is not None and not file.is_absolute():
            file = Path(path).resolve().parent / file
            conf.insert_json5(key, json.dumps(str(file)))
        if not file.is_file():
            raise ConfigError(f"zenoh config {source or '--cfg'}: {key}: {value}: no such file")


def zenoh_config(settings: ZenohSettings, open_timeout: float | None = None) -> zenoh.Config:
    """Build the zenoh.Config that ``settings`` describe; ConfigError names the bad setting.

    The file, then the flags, then ``--cfg``; what none of them set gets the secure defaults
    of the module's docstring. ``open_timeout`` (s) bounds each link's handshake where the
    user left Zenoh's own 10 s (``transport/unicast/open_timeout``): a command told to wait
    2 s must not sit 10 s in the handshake of a peer that is paused (its port accepts, its
    process does not answer)."""
    conf, path = _load(settings)
    source = settings.config_file or (f"ZENOH_CONFIG={path}" if path else None)

    def insert(what: str, key: str, value: str) -> None:
        try:
            conf.insert_json5(key, value)
        except Exception as err:
            raise ConfigError(f"{what}: {zenoh_error(err)}") from None

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
                check_endpoint(flag, e)
            insert(flag, key, json.dumps(list(endpoints)))
    if settings.multicast_scouting or settings.no_multicast_scouting:
        flag = "--multicast-scouting" if settings.multicast_scouting else "--no-multicast-scouting"
        insert(flag, "scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    for item in settings.cfg:
        key, sep, value = item.partition(":")
        if not sep or not key or not value:
            raise ConfigError(f"--cfg {item!r}: expected KEY:VALUE, e.g. connect/timeout_ms:30000")
        insert(f"--cfg {item!r}", key, value)
    _secure_defaults(conf, insert)
    if open_timeout is not None and _get(conf, OPEN_TIMEOUT) == _get(zenoh.Config(), OPEN_TIMEOUT):
        ms = max(100, min(int(open_timeout * 1000), int(_get(conf, OPEN_TIMEOUT))))
        insert("--timeout", OPEN_TIMEOUT, str(ms))
    _resolve_files(conf, path, source)
    return conf


def _get(conf: zenoh.Config, key: str) -> object:
    return json.loads(conf.get_json(key))


def _secure_defaults(conf: zenoh.Config, insert) -> None:
    """Fill what the user left unset (Zenoh reports unset keys as null): no multicast, and
    loopback endpoints around the rendezvous."""
    mode = _get(conf, "mode") or "peer"
    multicast = _get(conf, "scouting/multicast/enabled")
    if multicast is None:
        insert("secure default", "scouting/multicast/enabled", "false")
    own_listen = _get(conf, "listen/endpoints") != _get(zenoh.Config(), "listen/endpoints")
    own_connect = _get(conf, "connect/endpoints") not in (None, [], {})
    anywhere = "tcp/[::]:0" if multicast is True else LOOPBACK_ANY
    if not own_listen:
        if mode == "router":
            point = rendezvous()
            if multicast is True:  # zenoh's own default: every interface
                point = "tcp/[::]:" + point.rsplit(":", 1)[-1]
            insert("default listen", "listen/endpoints", json.dumps([point]))
        elif mode == "peer" and own_connect:
            insert("default listen", "listen/endpoints", json.dumps([anywhere]))
        elif mode == "peer":
            points = [rendezvous() + RENDEZVOUS_LISTEN, anywhere]
            insert("default listen", "listen/endpoints", json.dumps(points))
    if not own_connect and not own_listen and mode in ("peer", "client"):
        insert("default connect", "connect/endpoints", json.dumps([rendezvous()]))
        if mode == "peer" and _get(conf, "connect/retry") is None:
            insert("default connect", "connect/retry", json.dumps(CONNECT_RETRY))


def open_config(conf: zenoh.Config) -> zenoh.Session:
    """Open a session; a failure (bad endpoint, no router reachable) becomes a ConfigError."""
    try:
        return zenoh.open(conf)
    except Exception as err:
        reason = zenoh_error(err)
        if reason.startswith("Unable to connect"):
            reason += " (nothing listens there, or it refused this session's credentials)"
        raise ConfigError(f"cannot open zenoh session: {reason}") from None


def unreached(session: zenoh.Session) -> str:
    """Why nothing answered, when this session reached no peer and no router at all (else
    empty): then no service is to blame but whatever it connects to — not running, paused
    (its port accepts, its process does not answer), or refusing this session."""
    info = session.info
    if list(info.peers_zid()) or list(info.routers_zid()):
        return ""
    return (
        "; this client reached no peer or router at all: is the process it connects to (-e) "
        "running, and not paused?"
    )


def open_session(settings: ZenohSettings, open_timeout: float | None = None) -> zenoh.Session:
    """Open a session as ``settings`` describe (see ``zenoh_config``)."""
    return open_config(zenoh_config(settings, open_timeout))
