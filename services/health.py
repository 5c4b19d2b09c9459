"""``autotune health plant|tuner|logger``: is the service up? (compose's healthcheck)

Exits 0 when the service's liveliness token is on the bus within ``--timeout`` seconds,
1 otherwise, a bus it cannot reach included (a client whose router is down: it exited 2,
which Docker reserves, and said nothing on stdout: helper review); 2 only for bad input. A
liveliness query answers in a few milliseconds. The answer is the command's output, on
stdout (``autotune health plant | grep up``); errors go to stderr. Without ``--node`` any
process of the service counts (plant processes sharding a plant file run under their own
nodes, and ``health plant`` said DOWN with both up), and the nodes seen are named.
"""

from __future__ import annotations

import argparse

from services.autotuner.loop_client import wait_for_token
from shared import keys
from shared.cli import add_common_arguments, check_ids
from shared.errors import ConfigError
from shared.session import open_session, settings_from_args

HELP = "check that a service is up (exit 0) through its liveliness token"
TOKENS = {
    "plant": lambda p, n: keys.service_alive(p, "plant_sim", n),
    "tuner": keys.tuner_alive,
    "logger": keys.logger_alive,
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("service", choices=sorted(TOKENS))
    parser.add_argument("--node", help="the service's node id (default: any node of the service)")
    parser.add_argument("--timeout", type=float, default=3.0)
    add_common_arguments(parser)


def run(args: argparse.Namespace) -> int:
    if args.node is not None:
        check_ids(args.prefix, node=args.node)
    else:
        check_ids(args.prefix)
    key = TOKENS[args.service](args.prefix, args.node or keys.ANY)
    settings = settings_from_args(args)
    try:
        session = open_session(settings, args.timeout)
    except ConfigError as err:
        if "Unable to connect" not in str(err):
            raise  # bad input (an endpoint, a config): exit 2
        print(f"{args.service}: DOWN (no session on the bus: {err})")
        return 1
    with session:
        up = wait_for_token(session, key, args.timeout)
        nodes = _nodes(session, args.prefix, args.service, key) if up and not args.node else []
    seen = f"; node {', '.join(nodes)}" if nodes else ""
    print(f"{args.service}: {'up' if up else 'DOWN'} ({key}{seen})")
    return 0 if up else 1


def _nodes(session, prefix: str, service: str, key: str) -> list[str]:
    """The nodes of ``service`` whose tokens match ``key`` (sorted; a liveliness query)."""
    name = {"plant": "plant_sim"}.get(service, service)
    found = set()
    for reply in session.liveliness().get(key, timeout=2.0):
        if reply.ok is not None:
            node = keys.service_node(prefix, name, str(reply.ok.key_expr))
            if node:
                found.add(node)
    return sorted(found)
