"""Every key expression the product uses, in one place: built here, and read back here.

Builders return a key; parsers (``parse_command``, ``parse_loop_key``, ``parse_tune_key``,
``service_node``...) return its parts, or None for a key that is not one. Nothing outside
this module splits a key on '/'.

Layout (IDs in their own chunks, most-varying part last)::

    <prefix>/plant/<loop>/pv               ProcessSample, one per sample period
    <prefix>/plant/<loop>/pv_batch         ProcessSamples: the samples of one lockstep
                                           advance of several periods, in one message
    <prefix>/plant/<loop>/status           LoopStatus, on every change (queryable too)
    <prefix>/plant/<loop>/info             LoopInfo (queryable)
    <prefix>/plant/<loop>/cmd/<kind>       commands to the loop (see shared.messages.COMMANDS)
    <prefix>/plant/<loop>/cmd/<kind>/<user>  the same, sent by a session authenticated as
                                           <user>: a secure deployment's access control lets
                                           each user put only on its own name, so the plant
                                           knows who commanded what (``source`` is a label)
    <prefix>/plant/<loop>/alive            liveliness token of a served loop
    <prefix>/plant_sim/<node>/status       ServiceStatus of one plant_sim process (queryable)
    <prefix>/plant_sim/<node>/alive        liveliness token of one plant_sim process
    <prefix>/plant_sim/<node>/instance/<id>  liveliness token of one plant_sim process's
                                           run (``ServiceStatus.instance``): two processes
                                           under one node name hold one ``alive`` between
                                           them, but each its own of these
    <prefix>/tuner/<node>/tune             TuneRequest → TuneAccepted (queryable)
    <prefix>/tuner/<node>/alive            liveliness token of one autotuner process
    <prefix>/tune/<loop>/progress          TuneProgress while a run goes on
    <prefix>/tune/<loop>/event             TunerEvent: the experiment's events
    <prefix>/tune/<loop>/result            TuneResult at the end of a run (queryable: the last)
    <prefix>/tune/<loop>/cancel            a put here cancels the loop's run (loop restored)
    <prefix>/tune/<loop>/running           liveliness token held while a run owns the loop
    <prefix>/tune/<loop>/run               a run file's metadata as a message (RunRecord):
                                           a channel of the MCAP file, never on the bus
    <prefix>/logger/<node>/status          LoggerStatus (queryable)
    <prefix>/logger/<node>/alive           liveliness token of one logger process
    <prefix>/monitor/<loop>                LoopMonitor: the tuner's assessment of a loop it
                                           tuned, every window of normal operation
"""

from __future__ import annotations

import re

DEFAULT_PREFIX = "autotune"

_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
_PREFIX = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")


def check_id(value: str, what: str = "loop") -> str:
    """Return ``value`` if it is usable as one key-expression chunk, else raise ValueError."""
    if not isinstance(value, str) or not _ID.match(value):
        raise ValueError(
            f"{what} id {value!r} is not valid: use letters, digits, '_', '-' or '.', "
            "starting with a letter, digit or '_' (it becomes one chunk of a key expression)"
        )
    return value


def check_prefix(prefix: str) -> str:
    """Return ``prefix`` if it is a wildcard-free key expression without leading/trailing '/'."""
    if not isinstance(prefix, str) or not _PREFIX.match(prefix):
        raise ValueError(
            f"prefix {prefix!r} is not valid: '/'-separated chunks of letters, digits, '_', '-', "
            "'.', no leading or trailing '/', no wildcards"
        )
    return prefix


def loop_root(prefix: str, loop: str) -> str:
    return f"{prefix}/plant/{loop}"


def pv(prefix: str, loop: str) -> str:
    return f"{loop_root(prefix, loop)}/pv"


def pv_batch(prefix: str, loop: str) -> str:
    """Lockstep: the samples of one advance of several periods, as one message."""
    return f"{loop_root(prefix, loop)}/pv_batch"


def status(prefix: str, loop: str) -> str:
    return f"{loop_root(prefix, loop)}/status"


def info(prefix: str, loop: str) -> str:
    return f"{loop_root(prefix, loop)}/info"


def command(prefix: str, loop: str, kind: str, user: str | None = None) -> str:
    """A command's key; with ``user``, the sender's authenticated Zenoh user as its last chunk."""
    key = f"{loop_root(prefix, loop)}/cmd/{kind}"
    return key if user is None else f"{key}/{user}"


def parse_command(prefix: str, key: str) -> tuple[str, str, str | None] | None:
    """(loop, kind, user or None) of a command key; None if ``key`` is not one."""
    parsed = split_loop_key(prefix, key)
    if parsed is None or parsed[1][0] != "cmd" or len(parsed[1]) not in (2, 3):
        return None
    rest = parsed[1]
    if not rest[1] or (len(rest) == 3 and not rest[2]):
        return None
    return parsed[0], rest[1], rest[2] if len(rest) == 3 else None


def loop_alive(prefix: str, loop: str) -> str:
    return f"{loop_root(prefix, loop)}/alive"


def loop_feed(prefix: str, loop: str) -> str:
    """What a driver of one loop listens to: its samples and its status, in order."""
    return f"{loop_root(prefix, loop)}/*"


ANY = "*"


def all_commands(prefix: str) -> str:
    """Every command to every loop, with or without a user: one subscriber keeps them in order."""
    return f"{loop_root(prefix, ANY)}/cmd/**"


def everything(prefix: str) -> str:
    """Every key under the prefix: what the logger records from."""
    return f"{prefix}/**"


def service_status(prefix: str, service: str, node: str) -> str:
    return f"{prefix}/{service}/{node}/status"


def service_alive(prefix: str, service: str, node: str) -> str:
    return f"{prefix}/{service}/{node}/alive"


def service_instance(prefix: str, service: str, node: str, instance: str) -> str:
    return f"{prefix}/{service}/{node}/instance/{instance}"


def parse_service_instance(prefix: str, service: str, key: str) -> tuple[str, str] | None:
    """(node, instance) of ``<prefix>/<service>/<node>/instance/<id>``; None if it is not one."""
    head = f"{prefix}/{service}/"
    if not key.startswith(head):
        return None
    parts = key[len(head) :].split("/")
    if len(parts) != 3 or parts[1] != "instance" or not parts[0] or not parts[2]:
        return None
    return parts[0], parts[2]


def split_loop_key(prefix: str, key: str) -> tuple[str, list[str]] | None:
    """Split ``<prefix>/plant/<loop>/<rest...>`` into (loop, rest); None if it is not one."""
    head = f"{prefix}/plant/"
    if not key.startswith(head):
        return None
    parts = key[len(head) :].split("/")
    if len(parts) < 2 or not parts[0]:
        return None
    return parts[0], parts[1:]


def parse_loop_key(prefix: str, key: str) -> tuple[str, str] | None:
    """(loop, leaf) of ``<prefix>/plant/<loop>/<leaf>`` (pv, status, info, alive); None if
    ``key`` is not one (a command's key has more chunks: see ``parse_command``)."""
    parsed = split_loop_key(prefix, key)
    if parsed is None or len(parsed[1]) != 1 or not parsed[1][0]:
        return None
    return parsed[0], parsed[1][0]


def parse_tune_key(prefix: str, key: str) -> tuple[str, str] | None:
    """(loop, leaf) of ``<prefix>/tune/<loop>/<leaf>`` (progress, event, result, cancel,
    running); None if ``key`` is not one."""
    head = f"{prefix}/tune/"
    if not key.startswith(head):
        return None
    parts = key[len(head) :].split("/")
    if len(parts) != 2 or not all(parts):
        return None
    return parts[0], parts[1]


def leaf(key: str) -> str:
    """The last chunk of a key (``pv``, ``event``, ``result`` …): what a recorded topic is,
    for readers of a file that may not say its prefix."""
    return key.rsplit("/", 1)[-1]


def candidate_prefixes(key: str) -> list[str]:
    """The prefixes ``key`` may be under, shortest first: the chunks before each ``plant``
    or ``tune`` chunk (for a recording that does not say its prefix)."""
    parts = key.split("/")
    return ["/".join(parts[:i]) for i in range(1, len(parts)) if parts[i] in ("plant", "tune")]


def reprefix(key: str, old: str, new: str) -> str:
    """``key`` under the prefix ``new`` instead of ``old`` (a replay under another prefix);
    ValueError if ``key`` is not under ``old``."""
    if not key.startswith(old + "/"):
        raise ValueError(f"key {key!r} is not under the prefix {old!r}")
    return new + key[len(old) :]


def service_node(prefix: str, service: str, key: str) -> str | None:
    """The node of ``<prefix>/<service>/<node>/...``; None if ``key`` is not one."""
    head = f"{prefix}/{service}/"
    if not key.startswith(head):
        return None
    node = key[len(head) :].split("/", 1)[0]
    return node or None


def tuner_request(prefix: str, node: str) -> str:
    return f"{prefix}/tuner/{node}/tune"


def tuner_alive(prefix: str, node: str) -> str:
    return f"{prefix}/tuner/{node}/alive"


def tune_root(prefix: str, loop: str) -> str:
    return f"{prefix}/tune/{loop}"


def tune_progress(prefix: str, loop: str) -> str:
    return f"{tune_root(prefix, loop)}/progress"


def tune_event(prefix: str, loop: str) -> str:
    return f"{tune_root(prefix, loop)}/event"


def tune_result(prefix: str, loop: str) -> str:
    return f"{tune_root(prefix, loop)}/result"


def tune_cancel(prefix: str, loop: str) -> str:
    return f"{tune_root(prefix, loop)}/cancel"


def tune_running(prefix: str, loop: str) -> str:
    return f"{tune_root(prefix, loop)}/running"


def tune_run_record(prefix: str, loop: str) -> str:
    """The channel of a run file's RunRecord (its metadata as a message); not a bus key."""
    return f"{tune_root(prefix, loop)}/run"


def logger_status(prefix: str, node: str) -> str:
    return f"{prefix}/logger/{node}/status"


def logger_alive(prefix: str, node: str) -> str:
    return f"{prefix}/logger/{node}/alive"


def monitor(prefix: str, loop: str) -> str:
    """Where the tuner publishes its assessment of a loop it tuned (``LoopMonitor``)."""
    return f"{prefix}/monitor/{loop}"


def parse_monitor_key(prefix: str, key: str) -> str | None:
    """The loop of ``<prefix>/monitor/<loop>``; None if ``key`` is not one."""
    head = f"{prefix}/monitor/"
    if not key.startswith(head):
        return None
    loop = key[len(head) :]
    return loop if loop and "/" not in loop else None
