"""``autotune replay RUN.mcap``: republish a recorded run over Zenoh on its original keys.

As ``ros2 bag play``: ``--rate`` scales the pace (sim time of the recording → wall time),
``--loop`` keeps one loop, ``--topics`` only the given topics, ``--start-offset`` skips the
first seconds. Messages go out in the order they were recorded. Commands to the loop are left
out unless ``--with-commands``: replayed next to a live plant they would move its valve.
"""

from __future__ import annotations

import argparse
import time

import zenoh

from services.logger.mcap_io import Record, read_run
from shared import wire
from shared.cli import add_common_arguments
from shared.errors import ConfigError
from shared.session import open_session, settings_from_args

HELP = "republish a recorded run over Zenoh (like ros2 bag play)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="RUN.mcap")
    parser.add_argument(
        "-r",
        "--rate",
        type=float,
        default=1.0,
        help="pace relative to the recorded sim time (default: %(default)s)",
    )
    parser.add_argument("--loop", help="only this loop's messages")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics")
    parser.add_argument(
        "--start-offset",
        type=float,
        default=0.0,
        metavar="SEC",
        help="skip the first SEC seconds of the recording",
    )
    parser.add_argument(
        "--wait",
        type=float,
        default=3.0,
        metavar="SEC",
        help="wait up to SEC for a subscriber before the first message (default: %(default)s)",
    )
    parser.add_argument(
        "--with-commands",
        action="store_true",
        help="also republish commands to the loop (they act on a live plant)",
    )
    add_common_arguments(parser)


def select(
    records: list[Record],
    loop: str | None,
    topics: list[str] | None,
    start_offset: float,
    with_commands: bool,
) -> list[Record]:
    if not records:
        return []
    t0 = min(r.log_time for r in records)
    keep = []
    for r in records:
        parts = r.key.split("/")
        if not with_commands and "cmd" in parts:
            continue
        if loop is not None and loop not in parts:
            continue
        if topics and r.topic not in topics and r.key not in topics:
            continue
        if (r.log_time - t0) / 1e9 < start_offset:
            continue
        keep.append(r)
    return keep


def wait_for_subscriber(session: zenoh.Session, key: str, seconds: float) -> bool:
    """Give a newly joined session's subscribers time to be known, so that the first
    messages are not published to nobody; False if none appeared within ``seconds``."""
    publisher = session.declare_publisher(key)
    try:
        deadline = time.monotonic() + seconds
        while not publisher.matching_status.matching:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True
    finally:
        publisher.undeclare()


def run(args: argparse.Namespace) -> int:
    if not (args.rate > 0 and args.rate < float("inf")):
        raise ConfigError(f"--rate {args.rate}: must be a finite number > 0")
    if not args.start_offset >= 0:
        raise ConfigError(f"--start-offset {args.start_offset}: must be ≥ 0 s")
    _, records = read_run(args.file)
    chosen = select(records, args.loop, args.topics, args.start_offset, args.with_commands)
    if not chosen:
        print("nothing to replay")
        return 0
    with open_session(settings_from_args(args)) as session:
        wait_for_subscriber(session, chosen[0].key, args.wait)
        wall0, t0 = time.monotonic(), chosen[0].log_time
        for r in chosen:
            due = wall0 + max(0, r.log_time - t0) / 1e9 / args.rate
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            session.put(
                r.key,
                r.data,
                encoding=wire.JSON + (f";{r.schema}" if r.schema else ""),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
    print(f"replayed {len(chosen)} messages from {args.file}")
    return 0
