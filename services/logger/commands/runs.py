"""``autotune runs [DIR]``: list the recorded runs (time, loop, method, K_u, P_u, rule, gains,
status), newest last; ``--compare RUN RUN``: two runs' figures side by side (``compare``).

A file that cannot be read — not MCAP, truncated, corrupt, a newer format, metadata that is
not what the logger writes — is listed too, its status ``unreadable: <reason>`` (with
``--json``: ``"status": "unreadable"`` and ``"reason"``); the others are listed as usual and
the exit code stays 0. A file a logger is still writing (no MCAP footer yet, and open in a
process on this machine) is a run in progress, status ``recording``, not a broken file."""

from __future__ import annotations

import argparse
import contextlib
from datetime import UTC, datetime
from pathlib import Path

from services.logger.compare import compare, format_compare
from services.logger.mcap_io import being_written, read_run
from shared import json_text
from shared.errors import AutotuneError, one_line, printable
from shared.messages import APPLIED_STATUSES

HELP = "list the recorded tuning runs"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "runs",
        nargs="?",
        default="runs",
        metavar="DIR",
        help="the logger's runs directory (default: %(default)s)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON object per run, a list")
    parser.add_argument(
        "--compare",
        nargs=2,
        metavar="RUN",
        help="two runs' figures side by side: each a file, a file name in DIR or a run id",
    )


def resolve_run(folder: Path, run: str) -> Path:
    """A run named on the command line: a file, a file name in ``folder``, or a run id (the
    file in ``folder`` whose name ends with ``_<id>.mcap``)."""
    for candidate in (Path(run), folder / run):
        if candidate.is_file():
            return candidate
        if candidate.is_dir():  # as `autotune analyze` says of one
            raise AutotuneError(f"--compare {run}: {candidate} is a directory, not a run file")
    hits = sorted(folder.glob(f"*_{run}.mcap")) if folder.is_dir() and "/" not in run else []
    if len(hits) == 1:
        return hits[0]
    if len(hits) > 1:
        raise AutotuneError(f"--compare {run}: several files in {folder} have that run id")
    raise AutotuneError(f"--compare {run}: no such file, nor a run of that id in {folder}")


def summarize(path: Path) -> dict:
    """The run's row; for a file that cannot be read, a row that says why."""
    try:
        meta, _ = read_run(path)
        return _row(path, meta)
    except AutotuneError as err:
        if being_written(path):
            return _named_row(path, "recording", "in progress: a logger is writing it")
        # what its name tells, beside why it is not read (its row was blank but for that)
        return _named_row(path, "unreadable", _reason(path, err))


def _named_row(path: Path, status: str, reason: str) -> dict:
    """A row from what the file's name tells (``<UTC>_<loop>_<method>_<id>.mcap``, as the
    logger names it): a run in progress, or a file that cannot be read."""
    parts = path.stem.removesuffix("_replay").split("_")
    named = len(parts) >= 4
    started = parts[0] if named else None
    with contextlib.suppress(ValueError):  # ISO, as a readable row's, where it is a stamp
        stamp = datetime.strptime(started or "", "%Y%m%dT%H%M%SZ")
        started = stamp.replace(tzinfo=UTC).isoformat()
    return {
        "file": path.name,
        "started": started,
        "loop": "_".join(parts[1:-2]) if named else None,
        "method": parts[-2] if named else None,
        "status": status,
        "reason": reason,
    }


def _reason(path: Path, err: AutotuneError) -> str:
    """The error without the file's name (the row has it) nor the recover hint."""
    # whole: the hint goes, not the reason (cut to 300 characters first, a CRC's reason
    # ended "…; `autot…": helper)
    text = one_line(err, limit=2000).removeprefix(f"{path}: ")
    return text.split("; if a logger was killed")[0].split("; `autotune recover")[0]


def _count(meta: dict[str, str], key: str) -> int:
    raw = meta.get(key) or "0"
    try:
        n = int(raw)
    except ValueError:
        n = -1
    if n < 0:
        raise AutotuneError(f"metadata 'run', field {key}: not a count: {one_line(repr(raw))}")
    return n


def _row(path: Path, meta: dict[str, str]) -> dict:
    if not meta:
        raise AutotuneError("no 'run' metadata record (not a run file the logger finished)")
    if not meta.get("run_id") and not meta.get("loop"):  # a record of someone else's
        raise AutotuneError(
            "not an autotune run file: its 'run' metadata record has no run_id nor loop"
        )
    result: dict = {}
    if meta.get("result"):  # read leniently: a result from an older autotune still lists
        try:
            result = json_text.loads(meta["result"])
        except ValueError as err:
            raise AutotuneError(
                f"metadata 'run', field result: not JSON ({one_line(err)})"
            ) from None
        if not isinstance(result, dict):
            raise AutotuneError("metadata 'run', field result: not a JSON object")
    for key in ("ku", "pu"):
        v = result.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int | float)):
            raise AutotuneError(
                f"metadata 'run', field result.{key}: not a number: {one_line(repr(v))}"
            )
    chosen = result.get("chosen") if isinstance(result.get("chosen"), dict) else {}
    isa = chosen.get("isa") if isinstance(chosen.get("isa"), dict) else None
    if isa is None:  # refused before any was chosen (the safety envelope): the rule's own
        every = result.get("gains") if isinstance(result.get("gains"), dict) else {}
        ruled = every.get(result.get("rule")) if isinstance(result.get("rule"), str) else None
        isa = (
            ruled.get("isa")
            if isinstance(ruled, dict) and isinstance(ruled.get("isa"), dict)
            else None
        )
    return {
        "file": path.name,
        "started": meta.get("started"),
        "loop": meta.get("loop"),
        "method": meta.get("method"),
        # the rule whose gains these are (the run's result); the one asked for beside it: a
        # run asked for "auto" listed "auto" beside tl-pi's gains
        "rule": result.get("rule") or meta.get("rule"),
        "requested_rule": meta.get("rule"),
        "ku": result.get("ku"),
        "pu": result.get("pu"),
        "gains": isa,
        # whether those gains were left on the loop (the table puts the others in ( ))
        "gains_on_loop": bool(isa) and meta.get("status") in APPLIED_STATUSES,
        "status": meta.get("status"),
        # an `autotune apply` run: the recorded run whose gains it applied (its method is that
        # run's; listed as "apply", not as a second test of that method)
        "applied_from": result.get("applied_from"),
        # a replay recorded by a logger with --record-replays: the file replayed (None: a
        # live run; `runs` listed replays as live runs of the day they were replayed)
        "replay": meta.get("replay") or None,
        # a file `autotune recover` wrote: what it read, and what it knows it lost
        "recovered": meta.get("recovered"),
        "lost": meta.get("lost"),
        # a file whose metadata record failed its CRC, rebuilt from its run record
        "rebuilt": meta.get("rebuilt"),
        "samples": _count(meta, "samples"),
        "dropped": _count(meta, "dropped"),
    }


def _num(v, fmt: str = ".4g") -> str:
    if v is None:
        return "—"
    if isinstance(v, bool) or not isinstance(v, int | float):
        return "?"
    return format(v, fmt)


def run(args: argparse.Namespace) -> int:
    folder = Path(args.runs)
    if args.compare:
        a, b = (resolve_run(folder, r) for r in args.compare)
        c = compare(a, b)
        print(json_text.dumps(c, indent=2) if args.json else format_compare(c))
        return 0
    if not folder.is_dir():
        what = "not a directory" if folder.exists() else "no such directory"
        raise AutotuneError(f"{folder}: {what} (the logger's --runs)")
    rows = [summarize(p) for p in sorted(folder.glob("*.mcap"))]
    if args.json:
        print(json_text.dumps(rows, indent=2))
        return 0
    if not rows:
        print(f"no runs in {folder}")
        return 0
    print(
        f"{'started (UTC)':<20} {'loop':<8} {'method':<6} {'K_u':>9} {'P_u (s)':>9} "
        f"{'rule':<14} {'Kc':>8} {'Ti':>8} {'Td':>8} status"
    )
    unapplied = False
    for r in rows:
        g = r.get("gains") or {}
        # a run that did not leave its gains on the loop (refused, aborted, proposed): they
        # are in ( ), not to be read as the loop's (helper trial E misread them so)
        held = r.get("status") in APPLIED_STATUSES or not g
        unapplied = unapplied or not held

        def cell(v, held: bool = held) -> str:
            return _num(v) if held or v is None else f"({_num(v)})"

        print(
            f"{printable((r.get('started') or '')[:19]):<20} {printable(r.get('loop') or ''):<8} "
            f"{'apply' if r.get('applied_from') else printable(r.get('method') or ''):<6} "
            f"{_num(r.get('ku')):>9} {_num(r.get('pu')):>9} "
            f"{printable(r.get('rule') or ''):<14} {cell(g.get('kc')):>8} {cell(g.get('ti')):>8} "
            f"{cell(g.get('td')):>8} {printable(_status(r))}  {printable(r['file'])}"
        )
    if unapplied:
        print("gains in ( ): computed by the run, not left on the loop (see its status)")
    if any("not a readable MCAP file" in (r.get("reason") or "") for r in rows):
        print(
            "a file not readable as MCAP, if a logger was killed while writing it: "
            f"autotune recover {folder}/FILE -o FIXED.mcap salvages its messages"
        )
    return 0


def _status(row: dict) -> str:
    if row.get("status") == "unreadable":
        return f"unreadable: {row.get('reason')}"
    status = str(row.get("status") or "—")
    if row.get("replay"):
        status += " (replay)"
    if row.get("lost"):
        status += " (recovered, data lost)"
    elif row.get("rebuilt"):
        status += " (recovered, metadata rebuilt)"
    dropped = row.get("dropped")
    if isinstance(dropped, int) and dropped > 0:  # holes in its record: said where it is
        # listed (a logger paused 25 s in a relay run listed plain "ok", 344 samples gone
        # and `analyze` then "DIFFERENT": helper trial)
        status += f" ({dropped} samples dropped)"
    return status
