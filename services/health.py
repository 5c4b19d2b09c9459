"""``autotune health plant|tuner|logger``: is the service up? (compose's healthcheck)

Exits 0 when the service's liveliness token is on the bus within ``--timeout`` seconds,
1 otherwise: a liveliness query answers in a few milliseconds. The answer is the command's
output, on stdout (``autotune health plant | grep up``); errors go to stderr.
"""

from __future__ import annotations

import argparse

from services.autotuner.loop_client import wait_for_token
from shared import keys
from shared.cli import add_common_arguments, check_ids
from shared.session import open_session, settings_from_args

HELP = "check that a service is up (exit 0) through its liveliness token"
TOKENS = {
    "plant": lambda p, n: keys.service_alive(p, "plant_sim", n),
    "tuner": keys.tuner_alive,
    "logger": keys.logger_alive,
}
DEFAULT_NODES = {"plant": "plant", "tuner": "tuner", "logger": "logger"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("service", choices=sorted(TOKENS))
    parser.add_argument("--node", help="the service's node id (default: its default)")
    parser.add_argument("--timeout", type=float, default=3.0)
    add_common_arguments(parser)


def run(args: argparse.Namespace) -> int:
    node = args.node or DEFAULT_NODES[args.service]
    check_ids(args.prefix, node=node)
    key = TOKENS[args.service](args.prefix, node)
    with open_session(settings_from_args(args), args.timeout) as session:
        up = wait_for_token(session, key, args.timeout)
    print(f"{args.service}: {'up' if up else 'DOWN'} ({key})")
    return 0 if up else 1
