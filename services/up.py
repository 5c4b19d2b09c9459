"""``autotune up [--config FILE] [--secure]``: start the three services (and a router) until Ctrl-C.

Without ``--router`` plant_sim listens on ``--endpoint`` and the autotuner and logger connect
to it as peers. With ``--router`` a Zenoh router listens there and all three services are its
clients, as they would be across machines. Ctrl-C (or SIGTERM) stops them in order: the
autotuner first, which cancels its runs and so restores their loops, then the logger, which
finishes its files, then plant_sim and the router. If a service dies, the others are
stopped too.

``--secure`` runs the secure deployment: a router with user/password authentication and
access control (default deny), and every service its client under its own role (plant,
tuner, logger). The credentials (random passwords) and the Zenoh configs of every role, the
operator's and the viewer's included, are written to ``--secure-dir`` (default
``.autotune/secure``, mode 0700, files 0600) and reused on the next start; the operator then
connects with ``autotune tune hx1 -c .autotune/secure/operator.json5``. ``--configs-only``
writes them and starts nothing (compose.yaml mounts that directory).

The config file (TOML) takes the same settings as the flags, which override it::

    prefix = "autotune"
    endpoint = "tcp/127.0.0.1:7447"
    router = false
    secure = false
    secure_dir = ".autotune/secure"
    plant = "my_plant.toml"   # default: the presets
    clock = "lockstep"        # or "realtime"
    speed = 1.0
    seed = 1
    runs = "runs"
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import socket
import sys
import threading
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Literal

import pydantic
from pydantic import BaseModel, ConfigDict, Field

from services.console import launch as console_launch
from services.stack import Stack, runs_dir, service_tokens
from shared import keys
from shared.cli import MAX_SPEED, check_ids, install_stop_handlers
from shared.errors import AutotuneError, ConfigError
from shared.session import ZenohSettings, check_endpoint, rendezvous

HELP = "start plant_sim, the autotuner and the logger (and a router) until Ctrl-C"

# --- the secure deployment: ACL rules, role configs, credentials ----------------------------

SERVICE_ROLES = ("plant", "tuner", "logger")
TUNER_USER = "tuner"  # the tuner role's Zenoh user: its commands' keys end in it
ROLES = (*SERVICE_ROLES, "operator", "viewer")
USERS_FILE = "users.txt"
DEFAULT_SECURE_DIR = ".autotune/secure"
PLACEHOLDER = "CHANGE-ME"


def acl_rules(prefix: str) -> list[dict[str, Any]]:
    """Every rule of the router's access control, by id (see ``ROLE_RULES`` for who gets
    which). Flows are the router's: ingress is what a client sends, egress what the router
    hands it. A rule's key expression must include the message's."""
    p = prefix

    def rule(rid: str, messages: list[str], flows: list[str], key_exprs: list[str]) -> dict:
        return {
            "id": rid,
            "permission": "allow",
            "messages": messages,
            "flows": flows,
            "key_exprs": key_exprs,
        }

    status = [f"{p}/plant/*/status", f"{p}/plant/*/info", f"{p}/plant_sim/*/status"]
    return [
        # everyone may watch the bus: subscribe, follow tokens, get what they asked for
        rule(
            "watch",
            ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            ["ingress"],
            [f"{p}/**"],
        ),
        rule(
            "deliver",
            ["put", "declare_subscriber", "declare_queryable", "liveliness_token", "reply"],
            ["egress"],
            [f"{p}/**"],
        ),
        rule(
            "ask-status",
            ["query"],
            ["ingress"],
            [*status, f"{p}/logger/*/status", f"{p}/tune/*/result"],
        ),
        # plant_sim: publishes samples and statuses, answers their queries, announces loops
        rule(
            "plant-publish",
            ["put"],
            ["ingress"],
            [
                f"{p}/plant/*/pv",
                f"{p}/plant/*/pv_batch",
                f"{p}/plant/*/status",
                f"{p}/plant/*/info",
            ],
        ),
        rule("plant-serve", ["declare_queryable", "reply"], ["ingress"], status),
        rule("plant-queries", ["query"], ["egress"], status),
        rule(
            "plant-alive",
            ["liveliness_token"],
            ["ingress"],
            [f"{p}/plant/*/alive", f"{p}/plant_sim/*/alive", f"{p}/plant_sim/*/instance/*"],
        ),
        # the autotuner: the only one to command loops, each command's key ending in its
        # own user name (the plant reads who commanded from that chunk), and to publish runs
        rule("tuner-command", ["put"], ["ingress"], [f"{p}/plant/*/cmd/*/{TUNER_USER}"]),
        rule(
            "tuner-publish",
            ["put"],
            ["ingress"],
            [f"{p}/tune/*/progress", f"{p}/tune/*/event", f"{p}/tune/*/result"],
        ),
        # its request queryable, and each loop's last result for a client cut off when it
        # was published
        rule(
            "tuner-serve",
            ["declare_queryable", "reply"],
            ["ingress"],
            [f"{p}/tuner/*/**", f"{p}/tune/*/result"],
        ),
        rule("tuner-queries", ["query"], ["egress"], [f"{p}/tuner/*/**", f"{p}/tune/*/result"]),
        rule(
            "tuner-alive",
            ["liveliness_token"],
            ["ingress"],
            [f"{p}/tuner/*/alive", f"{p}/tune/*/running"],
        ),
        # the logger: answers its status, announces itself (it only reads the rest)
        rule("logger-serve", ["declare_queryable", "reply"], ["ingress"], [f"{p}/logger/*/status"]),
        rule("logger-queries", ["query"], ["egress"], [f"{p}/logger/*/status"]),
        rule("logger-alive", ["liveliness_token"], ["ingress"], [f"{p}/logger/*/alive"]),
        # the operator: requests to the tuner (tune; set and revert to come) and cancels
        rule("operator-request", ["query", "put"], ["ingress"], [f"{p}/tuner/*/**"]),
        rule("operator-cancel", ["put"], ["ingress"], [f"{p}/tune/*/cancel"]),
    ]


READ = ["watch", "deliver", "ask-status"]
ROLE_RULES: dict[str, list[str]] = {
    "plant": [*READ, "plant-publish", "plant-serve", "plant-queries", "plant-alive"],
    "tuner": [
        *READ,
        "tuner-command",
        "tuner-publish",
        "tuner-serve",
        "tuner-queries",
        "tuner-alive",
    ],
    "logger": [*READ, "logger-serve", "logger-queries", "logger-alive"],
    "operator": [*READ, "operator-request", "operator-cancel"],
    "viewer": READ,
}


def router_config(prefix: str, listen: str, users_file: str = USERS_FILE) -> dict[str, Any]:
    """The router's Zenoh config: loopback by default, user/password, default-deny ACL."""
    return {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"dictionary_file": users_file}}},
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": acl_rules(prefix),
            "subjects": [{"id": role, "usernames": [role]} for role in ROLES],
            "policies": [
                {"id": role, "rules": ROLE_RULES[role], "subjects": [role]} for role in ROLES
            ],
        },
    }


def role_config(role: str, endpoint: str, password: str) -> dict[str, Any]:
    """A client's Zenoh config for ``role``: services wait for the router for ever, the
    operator's and viewer's commands give up after 3 s."""
    wait = -1 if role in SERVICE_ROLES else 3000
    return {
        "mode": "client",
        "connect": {"endpoints": [endpoint], "timeout_ms": wait},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": role, "password": password}}},
    }


HEADERS = {
    "router": "Zenoh router: user/password authentication ({users}) and access control, "
    "default deny.\n`autotune router -c router.json5`, or zenohd -c router.json5 run in this "
    "directory.",
    "plant": "plant_sim: publishes samples and statuses, answers their queries.",
    "tuner": "autotuner: the only role that commands loops and publishes runs.",
    "logger": "logger: reads everything, answers its status.",
    "operator": "operator: reads; requests to the tuner (autotune tune LOOP -c operator.json5) "
    "and cancels.",
    "viewer": "viewer: reads only (autotune health, watching the bus).",
}


def to_json5(value: Any, indent: int = 0, width: int = 96) -> str:
    """``value`` as JSON5 laid out for reading: bare keys, short lists and objects on one
    line, trailing commas."""
    pad = "  " * indent
    inline = _inline(value)
    if inline is not None and len(pad) + len(inline) <= width:
        return inline
    if isinstance(value, dict):
        items = [f"{pad}  {_key(k)}: {to_json5(v, indent + 1, width)}," for k, v in value.items()]
        return "{\n" + "\n".join(items) + f"\n{pad}}}"
    if isinstance(value, list):
        items = [f"{pad}  {to_json5(v, indent + 1, width)}," for v in value]
        return "[\n" + "\n".join(items) + f"\n{pad}]"
    return json.dumps(value)


def _key(key: str) -> str:
    return key if key.isidentifier() else json.dumps(key)


def _inline(value: Any) -> str | None:
    """One-line form of a scalar, or of a list or object of scalars; None for deeper ones."""
    if isinstance(value, dict):
        if any(isinstance(v, dict | list) for v in value.values()):
            return None
        return "{ " + ", ".join(f"{_key(k)}: {json.dumps(v)}" for k, v in value.items()) + " }"
    if isinstance(value, list):
        if any(isinstance(v, dict | list) for v in value):
            return None
        return "[" + ", ".join(json.dumps(v) for v in value) + "]"
    return json.dumps(value)


WRITTEN = "Written by `autotune up --secure`; keep it private."
REFERENCE = "Reference copy: `autotune up --secure` writes it with random passwords."


def render(name: str, config: dict[str, Any], prefix: str, note: str = WRITTEN) -> str:
    """A config as JSON5 text, with a comment header."""
    head = HEADERS[name].format(users=USERS_FILE)
    lines = [f"// {line}" for line in head.splitlines()]
    lines.append(f"// Key prefix {prefix}/. {note}")
    return "\n".join(lines) + "\n" + to_json5(config) + "\n"


def client_endpoint(listen: str) -> str:
    """Where a client on this machine reaches a router listening on ``listen``."""
    proto, _, addr = listen.partition("/")
    host, _, port = addr.rpartition(":")
    if host in ("0.0.0.0", "[::]", ""):
        host = "127.0.0.1"
    return f"{proto}/{host}:{port}"


def _text(path: Path, what: str) -> str:
    """The UTF-8 text of ``path``; ConfigError names ``what`` (the file as the user gave it)
    and why it cannot be read (a file of other bytes was an internal error, exit 70)."""
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ConfigError(f"{what}: cannot read it: {err.strerror}") from None
    try:
        return raw.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as err:
        raise ConfigError(
            f"{what}: not UTF-8 text (byte 0x{raw[err.start]:02x} at offset {err.start})"
        ) from None


def read_users(path: Path) -> dict[str, str]:
    """``user:password`` lines; ConfigError names the file and line of a bad one."""
    users: dict[str, str] = {}
    text = _text(path, str(path))
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise ConfigError(f"{path}: line {n}: expected user:password")
        users[user] = password
    return users


@dataclass(frozen=True)
class SecureDeployment:
    """The files of a secure deployment (every one readable by its owner only)."""

    directory: Path
    endpoint: str  # where clients connect

    def config(self, role: str) -> Path:
        return self.directory / f"{role}.json5"

    @property
    def router(self) -> Path:
        return self.directory / "router.json5"

    @property
    def users(self) -> Path:
        return self.directory / USERS_FILE


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(fd, 0o600)  # also when the file was there before
    with os.fdopen(fd, "w") as f:
        f.write(text)


def write_secure(
    directory: Path, prefix: str, listen: str, passwords: dict[str, str] | None = None
) -> SecureDeployment:
    """Write the credentials and every role's config to ``directory`` (0700, files 0600).

    The passwords of an existing users file are kept (operators' copies of their config go
    on working); missing ones are drawn at random. ``passwords`` forces them (tests, the
    placeholder set shipped in deploy/zenoh)."""
    check_ids(prefix)
    try:
        directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        directory.chmod(0o700)
    except OSError as err:
        raise ConfigError(f"--secure-dir {directory}: {err.strerror}") from None
    deployment = SecureDeployment(directory, client_endpoint(listen))
    if passwords is None:
        passwords = read_users(deployment.users) if deployment.users.is_file() else {}
        passwords = {r: passwords.get(r) or secrets.token_urlsafe(24) for r in ROLES}
    _write_private(deployment.users, "".join(f"{r}:{passwords[r]}\n" for r in ROLES))
    _write_private(deployment.router, render("router", router_config(prefix, listen), prefix))
    for role in ROLES:
        text = render(role, role_config(role, deployment.endpoint, passwords[role]), prefix)
        _write_private(deployment.config(role), text)
    return deployment


def reference_configs(prefix: str = keys.DEFAULT_PREFIX) -> dict[str, str]:
    """The configs of deploy/zenoh/ (file name → text): those ``write_secure`` writes for
    the default prefix and endpoint, with placeholder passwords."""
    endpoint = "tcp/127.0.0.1:7447"
    router = router_config(prefix, endpoint)
    texts = {"router.json5": render("router", router, prefix, REFERENCE)}
    for role in ROLES:
        config = role_config(role, endpoint, f"{PLACEHOLDER}-{role}")
        texts[f"{role}.json5"] = render(role, config, prefix, REFERENCE)
    return texts


# --- autotune up -----------------------------------------------------------------------------


class UpConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    prefix: str = keys.DEFAULT_PREFIX
    endpoint: str = "tcp/127.0.0.1:7447"
    router: bool = False
    secure: bool = False
    secure_dir: str = DEFAULT_SECURE_DIR
    plant: str | None = None
    clock: Literal["lockstep", "realtime"] = "lockstep"
    # the plant's own bounds on its flags (``seed = -4`` in a config file came back from the
    # plant as its flag's error, and the stack waited 40 s and blamed the tuner)
    speed: float = Field(default=1.0, gt=0.0, le=MAX_SPEED, allow_inf_nan=False)
    seed: int | None = Field(default=None, ge=0)
    runs: str = "runs"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="settings file (TOML), see above")
    parser.add_argument("--prefix", help=f"root of every key (default: {keys.DEFAULT_PREFIX})")
    parser.add_argument(
        "--endpoint",
        help="where plant_sim (or the router) listens (default: the rendezvous, "
        "tcp/127.0.0.1:7447 or AUTOTUNE_RENDEZVOUS)",
    )
    parser.add_argument(
        "--router",
        action="store_true",
        default=None,
        help="start a Zenoh router; the services are its clients",
    )
    parser.add_argument(
        "--secure",
        action="store_true",
        default=None,
        help="a router with authentication and access control; each service under its role",
    )
    parser.add_argument(
        "--secure-dir",
        metavar="DIR",
        help=f"with --secure: where the credentials and configs go (default: {DEFAULT_SECURE_DIR})",
    )
    parser.add_argument(
        "--configs-only",
        action="store_true",
        help="with --secure: write the credentials and configs, start nothing",
    )
    parser.add_argument("--plant", metavar="FILE", help="plant file (default: the presets)")
    parser.add_argument("--clock", choices=("lockstep", "realtime"))
    parser.add_argument("--speed", type=float)
    parser.add_argument("--seed", type=int)
    parser.add_argument("--runs", metavar="DIR", help="the logger's directory (default: runs)")
    console_launch.add_arguments(parser)


def load_config(args: argparse.Namespace) -> UpConfig:
    data: dict = {}
    if args.config:
        text = _text(Path(args.config), f"--config {args.config}")
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"--config {args.config}: not valid TOML: {err}") from None
    for name in UpConfig.model_fields:
        value = getattr(args, name, None)
        if value is not None:
            data[name] = value
    # where the processes of this machine meet unless told (AUTOTUNE_RENDEZVOUS moves it): `up`
    # stayed on 7447 while the commands a user then typed in the same shell met on the
    # moved point, and found no tuner ("reached no peer or router at all")
    # (read only then: a malformed AUTOTUNE_RENDEZVOUS refused `up --endpoint X` too)
    if data.get("endpoint") is None:
        data["endpoint"] = rendezvous()
    try:
        cfg = UpConfig.model_validate(data)
    except pydantic.ValidationError as err:
        e = err.errors()[0]
        where = ".".join(str(p) for p in e["loc"])
        raise ConfigError(f"{args.config or 'settings'}: {where}: {e['msg']}") from None
    try:
        check_ids(cfg.prefix)
    except ConfigError as err:  # named where it came from: the file, or the flag
        where = f"--config {args.config}: " if args.prefix is None and args.config else ""
        raise ConfigError(f"{where}{err}") from None
    if cfg.plant and not Path(cfg.plant).is_file():
        raise ConfigError(f"plant: {cfg.plant}: no such file")
    if cfg.plant:  # read and built here first: its one line, not a stack that comes up
        # without its plant and blames the tuner 40 s later
        from services.plant_sim.load_bound import LOAD_TIMEOUT, load_bound
        from services.plant_sim.plant_file import load_plant_file

        # bounded as plant_sim bounds it (a model whose reset() blocked held `up` silent)
        with load_bound(LOAD_TIMEOUT, f"plant file {cfg.plant}", flag="as plant_sim bounds it"):
            load_plant_file(cfg.plant, seed=cfg.seed)
    proto, sep, addr = cfg.endpoint.partition("/")
    if not sep or not proto or ":" not in addr:
        raise ConfigError(f"endpoint {cfg.endpoint!r}: expected PROTOCOL/HOST:PORT")
    # before any service starts (a bad port came back from the first of them, as "-e")
    check_endpoint("--endpoint" if args.endpoint else "endpoint", cfg.endpoint)
    if getattr(args, "configs_only", False) and not cfg.secure:
        raise ConfigError("--configs-only: only with --secure")
    return cfg


def _service_args(cfg: UpConfig) -> dict[str, list[str]]:
    plant = ["--prefix", cfg.prefix, "--clock", cfg.clock, "--speed", str(cfg.speed)]
    plant += ["--plant", cfg.plant] if cfg.plant else []
    plant += ["--seed", str(cfg.seed)] if cfg.seed is not None else []
    return {
        "plant": plant,
        "logger": ["--prefix", cfg.prefix, "--runs", str(runs_dir(cfg.runs))],
        "tuner": ["--prefix", cfg.prefix],
    }


MODULES = {
    "plant": "services.plant_sim",
    "logger": "services.logger",
    "tuner": "services.autotuner",
}


def _host_port(endpoint: str) -> tuple[str, int]:
    host, _, port = endpoint.partition("/")[2].rpartition(":")
    return host.strip("[]"), int(port)


def check_free(endpoint: str) -> None:
    """ConfigError if something on this machine already listens on a tcp ``endpoint``."""
    host, port = _host_port(endpoint)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as err:
            raise ConfigError(
                f"--endpoint {endpoint}: {err.strerror} (another stack, or another program, "
                "listens there: stop it or choose another port)"
            ) from None


def wait_listening(stack: Stack, name: str, endpoint: str, timeout: float = 30.0) -> None:
    """Block until ``endpoint`` (tcp) accepts connections; AutotuneError if the process
    ``name`` exits first or after ``timeout``."""
    host, port = _host_port(client_endpoint(endpoint))
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        code = stack.procs[name].poll()
        if code is not None:
            raise AutotuneError(f"the {name} exited ({code}) before listening on {endpoint}")
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.05)
    raise AutotuneError(f"the {name} does not listen on {endpoint} after {timeout:g} s")


def start_secure(cfg: UpConfig, deployment: SecureDeployment, logs: IO[str] | None = None) -> Stack:
    """The router with the ACL first (the services, its clients, wait for it for ever), then
    each service under its role's config."""
    watcher = ZenohSettings(
        config_file=str(deployment.config("viewer")), cfg=("connect/timeout_ms:30000",)
    )
    tcp = cfg.endpoint.startswith("tcp/")
    if tcp:
        check_free(cfg.endpoint)
    stack = Stack(cfg.prefix, watcher, logs)
    stack.start("router", "services.cli", ["router", "-c", str(deployment.router)], [])
    if tcp:
        try:
            wait_listening(stack, "router", cfg.endpoint)
        except AutotuneError:
            stack.stop()
            raise
    for name, args in _service_args(cfg).items():
        if name == "tuner":
            _wait_for_logger(stack, cfg.prefix)
        stack.start(name, MODULES[name], args, ["-c", str(deployment.config(name))])
    return stack


def _wait_for_logger(stack: Stack, prefix: str) -> None:
    """The logger's token up before the tuner starts: a run accepted by the tuner is then
    heard from its start by the logger, which records only the runs it sees start (seen: a
    tune sent as soon as the tuner answered was never recorded, and the logger, first
    hearing the loop under the run's lease, filed the rejected run's restore as a change)."""
    try:
        stack.wait_ready([keys.logger_alive(prefix, "logger")], timeout=40.0)
    except AutotuneError:
        stack.stop()
        raise


def start(cfg: UpConfig, logs: IO[str] | None = None) -> Stack:
    if cfg.endpoint.startswith("tcp/"):
        # the plant (or the router) cannot listen there, and the tuner and logger would join
        # whatever does: another stack's bus (seen: two tuners of one name, for a second)
        check_free(cfg.endpoint)
    connect = ["-e", cfg.endpoint, "--no-multicast-scouting", "--cfg", "connect/timeout_ms:30000"]
    client = ZenohSettings(
        mode="client" if cfg.router else "peer",
        connect=(cfg.endpoint,),
        cfg=("connect/timeout_ms:30000",),
        no_multicast_scouting=True,
    )
    stack = Stack(cfg.prefix, client, logs)
    services = _service_args(cfg)
    if cfg.router:
        stack.start(
            "router", "services.cli", ["router", "-l", cfg.endpoint, "--no-multicast-scouting"], []
        )
        mode = ["-m", "client", *connect]
        stack.start("plant", "services.plant_sim", services["plant"], mode)
    else:
        mode = connect
        stack.start(
            "plant",
            "services.plant_sim",
            services["plant"],
            ["-l", cfg.endpoint, "--no-multicast-scouting"],
        )
    stack.start("logger", "services.logger", services["logger"], mode)
    _wait_for_logger(stack, cfg.prefix)
    stack.start("tuner", "services.autotuner", services["tuner"], mode)
    return stack


def _client_args(cfg: UpConfig, deployment: SecureDeployment | None) -> list[str]:
    """How a client joins this stack's bus (the console: as an operator when secure)."""
    if deployment is not None:
        return ["-c", str(deployment.config("operator"))]
    connect = ["-e", cfg.endpoint, "--no-multicast-scouting", "--cfg", "connect/timeout_ms:30000"]
    return ["-m", "client", *connect] if cfg.router else connect


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args)
    # every flag judged before the bus is probed (the endpoint's check_free): a bad --runs
    # was said as "endpoint in use" when another stack held the default port (a parallel run)
    runs_dir(cfg.runs)
    console_port = console_launch.port_of(args)
    deployment = None
    if cfg.secure:
        deployment = write_secure(Path(cfg.secure_dir), cfg.prefix, cfg.endpoint)
        if args.configs_only:
            print(f"secure configs written to {deployment.directory}/", file=sys.stderr)
            return 0
    stop = threading.Event()
    install_stop_handlers(stop)
    stack = start_secure(cfg, deployment) if deployment else start(cfg)
    try:
        stack.wait_ready(service_tokens(cfg.prefix, None), timeout=40.0)
        if args.console:
            url = console_launch.start(
                stack,
                cfg.prefix,
                runs_dir(cfg.runs),
                console_port,
                _client_args(cfg, deployment),
            )
            print(f"the commissioning console: {url}", file=sys.stderr, flush=True)
        pids = ", ".join(f"{n} pid {p.pid}" for n, p in stack.procs.items())
        how = " through a router" if cfg.router else ""
        if deployment:
            how = " through a router with authentication and access control"
        print(
            f"running under {cfg.prefix}/ on {cfg.endpoint}{how}: {pids}; Ctrl-C stops them",
            file=sys.stderr,
            flush=True,
        )
        if deployment:
            d = deployment.directory
            flags = f"--prefix {cfg.prefix} " if cfg.prefix != keys.DEFAULT_PREFIX else ""
            print(
                f"credentials and role configs in {d}/ (readable by you only):\n"
                f"  operator: autotune tune hx1 {flags}-c {d}/operator.json5\n"
                f"  viewer:   autotune health plant {flags}-c {d}/viewer.json5",
                file=sys.stderr,
                flush=True,
            )
        while not stop.wait(0.5):
            dead = [n for n, p in stack.procs.items() if p.poll() is not None]
            if dead:
                print(f"{', '.join(dead)} exited; stopping the others", file=sys.stderr)
                return 1
    finally:
        console_launch.stop(stack)
        codes = stack.stop()
        print(
            "stopped: " + ", ".join(f"{n} exit {c}" for n, c in codes.items()),
            file=sys.stderr,
            flush=True,
        )
    return 0
