"""``autotune replay RUN.mcap``: republish a recorded run over Zenoh.

As ``ros2 bag play``: ``--rate`` scales the pace (sim time of the recording → wall time),
``--loop`` keeps one loop, ``--topics`` only the given topics, ``--start-offset`` skips the
first seconds. Messages go out in the order they were recorded, on their recorded keys, or
with ``--prefix X`` under X instead of the recorded prefix. Every message carries the
attachment ``{"replay": "<file name>"}``, so a logger does not take a replay for a new run
(``autotune logger --record-replays`` records it, marked as a replay). Commands to the loop
are left out unless ``--with-commands`` (for a viewer of the bus); a plant refuses every
command marked as a replay, so none moves a valve. The whole file is checked before anything
is sent: a missing, truncated or altered file (a payload that is not JSON, a missing or extra
field, a topic autotune does not record) gets one line naming the record and the reason,
exit 2.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pydantic
import zenoh

from services.logger.mcap_io import Record, read_run
from services.logger.recorder import model_for
from shared import keys, wire
from shared.errors import AutotuneError, ConfigError
from shared.messages import Command
from shared.session import add_zenoh_arguments, open_session, settings_from_args
from shared.wire import replay_attachment

HELP = "republish a recorded run over Zenoh (like ros2 bag play)"


# the pace's bounds: a day of recording in a tenth of a second at most, and no slower than a
# minute of it in a week (--rate 1e-308 overflowed the wall clock's arithmetic: exit 70)
MIN_RATE, MAX_RATE = 1e-4, 1e6


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
        help="also republish commands to the loop, for a viewer (a plant refuses them)",
    )
    parser.add_argument(
        "--prefix",
        help="publish under this prefix instead of the recorded one (default: the recorded "
        "prefix, from the file's metadata)",
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)"
    )
    add_zenoh_arguments(parser)


@dataclass(frozen=True)
class Outgoing:
    """One record to republish: where it was recorded, and the key it goes out on."""

    record: Record
    loop: str
    command: bool
    key: str


def recorded_prefix(path: Path | str, meta: dict[str, str], records: list[Record]) -> str:
    """The prefix the run was recorded under: the metadata's, else the one every key fits."""
    if meta.get("prefix"):
        return meta["prefix"]
    candidates: set[str] | None = None
    for r in records:
        mine = {p for p in keys.candidate_prefixes(r.key) if model_for(p, r.key)}
        candidates = mine if candidates is None else candidates & mine
        if not candidates:
            break
    if not candidates:
        raise AutotuneError(
            f"{path}: no 'prefix' in the run's metadata, and the topics share none that "
            "autotune records under"
        )
    return min(candidates, key=len)


def check_records(path: Path | str, prefix: str, records: list[Record]) -> list[tuple[str, bool]]:
    """(loop, is a command) of every record, each validated as the logger validates it live;
    AutotuneError naming the first bad record (number, topic, sim time) and why."""
    out = []
    t0 = min((r.log_time for r in records), default=0)
    for i, r in enumerate(records):
        # its time into the recording (the log time itself is ns since 1970: "1.79e+09 s")
        where = f"{path}: {r.topic} message {i} ({(r.log_time - t0) / 1e9:.6g} s in)"
        found = model_for(prefix, r.key)
        if found is None:
            raise AutotuneError(f"{where}: not a topic autotune records under {prefix!r}")
        loop, model = found
        try:
            keys.check_id(loop)
        except ValueError as err:
            raise AutotuneError(f"{where}: {err}") from None
        if r.schema and r.schema != model.__name__:
            raise AutotuneError(f"{where}: schema {r.schema!r}, expected {model.__name__!r}")
        try:
            model.model_validate_json(r.data)
        except pydantic.ValidationError as err:
            raise AutotuneError(f"{where}: {wire.describe_validation_error(err)}") from None
        out.append((loop, issubclass(model, Command)))
    return out


def select(
    records: list[Record],
    checked: list[tuple[str, bool]],
    recorded: str,
    prefix: str,
    loop: str | None,
    topics: list[str] | None,
    start_offset: float,
    with_commands: bool,
) -> list[Outgoing]:
    """The records to republish, on their new keys (``recorded`` prefix → ``prefix``).
    ``--topics`` names recorded or republished topics (or keys)."""
    if not records:
        return []
    t0 = min(r.log_time for r in records)
    keep = []
    for r, (lp, command) in zip(records, checked, strict=True):
        key = keys.reprefix(r.key, recorded, prefix)  # every record is under it: checked
        if command and not with_commands:
            continue
        if loop is not None and lp != loop:
            continue
        if topics and not {r.topic, r.key, "/" + key, key} & set(topics):
            continue
        if (r.log_time - t0) / 1e9 < start_offset:
            continue
        keep.append(Outgoing(r, lp, command, key))
    return keep


# a pause in the recording this many times its usual spacing (and over HOLE_MIN s) is a hole,
# samples the logger missed: replayed as one usual spacing, not as silence (a 70 s hole went
# silent for 70 s at --rate 1, and a logger recording the replay ended its file incomplete:
# review). Sim times inside the messages keep the hole.
HOLE_FACTOR = 20.0
HOLE_MIN = 1.0  # s of the recording


def paced(log_times: list[int]) -> tuple[list[float], float]:
    """The replay's schedule: each record's offset in s of the recording from the earliest
    (records in file order, whose log times need not be: a lockstep advance's command is
    filed before its samples), the holes of the recording's timeline shortened to its usual
    spacing (the median gap between its distinct log times); and the s taken out.
    ``log_times`` in ns."""
    times = sorted(set(log_times))
    if not times:
        return [], 0.0
    gaps = [(b - a) / 1e9 for a, b in itertools.pairwise(times)]
    usual = statistics.median(gaps) if gaps else 0.0
    at = {times[0]: 0.0}
    offset, cut = 0.0, 0.0
    for t, g in zip(times[1:], gaps, strict=True):
        if usual > 0 and g > max(HOLE_FACTOR * usual, HOLE_MIN):
            cut += g - usual
            g = usual
        offset += g
        at[t] = offset
    return [at[t] for t in log_times], cut


def _starts(records: list[Record]) -> bool:
    """Whether ``records`` hold a run's start (its ``start`` progress message)."""
    for r in records:
        if r.topic.endswith("/progress"):
            try:
                if json.loads(r.data).get("phase") == "start":
                    return True
            except (ValueError, AttributeError):
                continue
    return False


def _held(records: list[Record], checked: list[tuple[str, bool]], commands: bool) -> str:
    """What the file holds, for a selection that kept nothing: its loops, topics and length,
    so that the filter that missed can be set right."""
    if not records:
        return "the file holds no messages"
    loops = sorted({lp for lp, _ in checked})
    # the topics as --topics takes them (their leaves, "pv, result", were not: `--topics
    # result` matched nothing, and said so again: helper trial)
    leaves = sorted(
        {r.topic for r, (_, c) in zip(records, checked, strict=True) if commands or not c}
    )
    span = (max(r.log_time for r in records) - min(r.log_time for r in records)) / 1e9
    without = "" if commands else " (commands only with --with-commands)"
    return (
        f"no message passes the filters; the file holds loop(s) {', '.join(loops)}, topics "
        f"{', '.join(leaves)}{without}, {span:.4g} s long (--start-offset within it)"
    )


def wait_for_subscriber(session: zenoh.Session, key: str | list[str], seconds: float) -> bool:
    """Give a newly joined session's subscribers time to be known, so that the first
    messages are not published to nobody: a subscriber for every one of the keys (one key:
    that one), within ``seconds``; False if one had none by then. The first subscriber known
    is not every one: with ``--with-commands`` the plant's, on the first key (a command),
    ended the wait before the logger's (met through the plant a moment later) was known, and
    the logger missed the run's start and recorded nothing of the replay (helper trial)."""
    publishers = [
        session.declare_publisher(k) for k in dict.fromkeys([key] if isinstance(key, str) else key)
    ]
    try:
        deadline = time.monotonic() + seconds
        while not all(p.matching_status.matching for p in publishers):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True
    finally:
        for p in publishers:
            p.undeclare()


def read_checked(path: str) -> tuple[str, list[Record], list[tuple[str, bool]]]:
    """(recorded prefix, records, their checks): the whole file, before anything is sent."""
    try:
        meta, records = read_run(path)
    except AutotuneError:
        raise
    except Exception as err:  # the reader's own failure on a damaged file: one line
        raise AutotuneError(
            f"{path}: not a readable MCAP file ({type(err).__name__}: {err})"
        ) from None
    recorded = recorded_prefix(path, meta, records)
    try:
        keys.check_prefix(recorded)
    except ValueError as err:
        raise AutotuneError(f"{path}: metadata 'prefix': {err}") from None
    return recorded, records, check_records(path, recorded, records)


def run(args: argparse.Namespace) -> int:
    if not MIN_RATE <= args.rate <= MAX_RATE:
        raise ConfigError(
            f"--rate {args.rate}: must be from {MIN_RATE:g} to {MAX_RATE:g} (the pace against "
            "the recording's sim time)"
        )
    if not args.start_offset >= 0:
        raise ConfigError(f"--start-offset {args.start_offset}: must be ≥ 0 s")
    if not args.wait >= 0:
        raise ConfigError(f"--wait {args.wait}: must be ≥ 0 s")
    if args.prefix is not None:
        try:
            keys.check_prefix(args.prefix)
        except ValueError as err:
            raise ConfigError(f"--prefix: {err}") from None
    recorded, records, checked = read_checked(args.file)
    prefix = recorded if args.prefix is None else args.prefix
    chosen = select(
        records,
        checked,
        recorded,
        prefix,
        args.loop,
        args.topics,
        args.start_offset,
        args.with_commands,
    )
    if not chosen:
        held = _held(records, checked, args.with_commands)
        given = [
            flag
            for flag, value in (
                ("--loop", args.loop),
                ("--topics", args.topics),
                ("--start-offset", args.start_offset > 0),
            )
            if value
        ]
        if records and given:  # a filter that fits nothing in the file: bad input, exit 2
            raise ConfigError(f"{', '.join(given)}: nothing to replay: {held}")
        print(f"nothing to replay: {held}")
        return 0
    if args.start_offset > 0 and _starts(records) and not _starts([o.record for o in chosen]):
        # (a logger records a replay's run from its start: helper trial, nothing recorded and
        # nothing said)
        print(
            f"note: --start-offset {args.start_offset:g} skips the run's start: a logger that "
            "records replays (--record-replays) opens no file for what follows",
            file=sys.stderr,
        )
    attachment = replay_attachment(Path(args.file).name)
    with open_session(settings_from_args(args)) as session:
        wait_for_subscriber(session, [out.key for out in chosen], args.wait)
        schedule, cut = paced([out.record.log_time for out in chosen])
        if cut > 0:
            print(
                f"note: {cut:.4g} s of holes in the recording (samples its logger missed) are "
                "replayed as one sample's spacing each",
                file=sys.stderr,
            )
        wall0, first = time.monotonic(), schedule[0] if schedule else 0.0
        for out, offset in zip(chosen, schedule, strict=True):
            r = out.record
            due = wall0 + max(0.0, offset - first) / args.rate
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            session.put(
                out.key,
                r.data,
                encoding=wire.JSON + (f";{r.schema}" if r.schema else ""),
                congestion_control=zenoh.CongestionControl.BLOCK,
                attachment=attachment,
            )
    under = "" if prefix == recorded else f" under {prefix} (recorded under {recorded})"
    print(f"replayed {len(chosen)} messages from {args.file}{under}")
    return 0
