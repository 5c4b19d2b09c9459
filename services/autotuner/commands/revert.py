"""``autotune revert LOOP [--to RUN_ID | --steps N]``: write back the gains in force before the
last change of the loop's gains (seed 001: "leave the previous controller settings with the
operator in case he/she wants to revert back to them").

The changes come from the logger's change history (``history.jsonl`` in its runs directory,
``--runs``). Default: the gains before the last change; ``--steps N``: before the N-th last;
``--to RUN_ID``: before that run's change. The loop's present gains must be the last on
record (else a change the history did not see came in between: refused, unless ``--force``).
The write is one gains command, which the plant applies bumplessly; it refuses it while a
tuning run holds the loop. The logger records the revert as a change like any other (source
``autotune-revert``). Exit 0 once the plant confirms the gains; 1 when the plant refuses them;
2 on bad input or nothing to revert to.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from services.autotuner.commands.logger_dirs import elsewhere
from services.autotuner.commands.set_loop import check_kc
from services.autotuner.loop_client import CommandRefused, LoopClient, wait_for_loop
from services.autotuner.recorder_watch import unrecorded_change
from shared import json_text
from shared.cli import add_common_arguments, check_ids
from shared.errors import AutotuneError, ConfigError
from shared.history_file import HISTORY_FILE, loop_changes
from shared.identity import auth_user
from shared.messages import GainsCommand, LoopStatus, PidGains
from shared.session import open_session, settings_from_args

HELP = "write back a loop's gains from before its last change (or a given run's)"
SOURCE = "autotune-revert"
CATCH_UP = 3.0  # s the logger may take to write the latest change down


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("loop", metavar="LOOP", help="loop id, e.g. hx1")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--to", metavar="RUN_ID", help="the gains in force before this run")
    # default None, 1 said in run(): argparse takes a value equal to the default for the
    # flag's absence, and let `--to RUN --steps 1` through while it refused `--steps 3`
    which.add_argument(
        "--steps", type=int, default=None, metavar="N", help="N changes back (default: 1)"
    )
    parser.add_argument(
        "--runs",
        default="runs",
        metavar="DIR",
        help="the logger's runs directory, where history.jsonl is (default: %(default)s)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="write even if the loop's gains are not the last on record",
    )
    parser.add_argument("--json", action="store_true", help="print what was done as JSON")
    parser.add_argument(
        "--wait",
        type=float,
        default=10.0,
        help="seconds to wait for the loop to appear on the bus (default: %(default)s)",
    )
    add_common_arguments(parser)


def target(changes: list[dict[str, Any]], to: str | None, steps: int) -> dict[str, Any]:
    """The change to undo: the last of run ``to`` (the run that wrote the gains, or the run
    whose gains ``autotune apply`` wrote: the history names it "from run"), else the
    ``steps``-th last; ConfigError naming the flag when there is none."""
    if to is not None:
        mine = [c for c in changes if to in (c.get("run_id"), c.get("applied_from"))]
        if not mine:
            raise ConfigError(f"--to {to}: no change of the loop's gains by that run on record")
        return mine[-1]
    if steps < 1:
        raise ConfigError(f"--steps {steps}: must be ≥ 1")
    if steps > len(changes):
        raise ConfigError(f"--steps {steps}: only {len(changes)} change(s) on record")
    return changes[-steps]


def _gains(d: dict[str, Any], what: str) -> PidGains:
    try:
        return PidGains.model_validate(d)
    except Exception:
        raise AutotuneError(f"the history's {what} gains are not valid gains: {d!r}") from None


def reverted_gains(undo: dict[str, Any], now: LoopStatus, units: str, path: Path) -> PidGains:
    """The gains before the change ``undo`` (a record of ``path``), as a revert writes them:
    valid gains, and none that `set` would refuse, whatever the file says (a Kc of 1e+250
    written into it by hand was put on a loop in auto, exit 0: helper review); ConfigError
    names the file and the bound."""
    back = _gains(undo["before"], "earlier")
    check_kc(
        back.kc,
        now.pv_range,
        f" {units}" if units else "",
        f"{path}: the gains on record before that change have Kc",
    )
    return back


def _line(g: PidGains) -> str:
    ti = "off" if g.ti is None else f"{g.ti:.4g} s"
    return f"Kc {g.kc:.4g}, Ti {ti}, Td {g.td:.4g} s, N {g.n:g}, β {g.beta:g}"


def run(args: argparse.Namespace) -> int:
    check_ids(args.prefix, loop=args.loop)
    steps = 1 if args.steps is None else args.steps
    if steps < 1:  # before anything waits on the bus
        raise ConfigError(f"--steps {steps}: must be ≥ 1")
    runs = Path(args.runs)
    if not runs.is_dir():
        raise ConfigError(f"--runs {runs}: not a directory (the logger's runs directory)")
    path = runs / HISTORY_FILE
    settings = settings_from_args(args)
    with open_session(settings, args.wait) as session:
        wait_for_loop(session, args.prefix, args.loop, args.wait)
        with LoopClient(
            session, args.prefix, args.loop, source=SOURCE, user=auth_user(settings)
        ) as client:
            now = client.sync()
            deadline = time.monotonic() + CATCH_UP
            while True:  # the logger writes a change down as it sees it: let it catch up
                changes = loop_changes(path, args.loop, args.prefix)
                last = changes[-1] if changes else None
                current = last is not None and _gains(last["after"], "last") == now.gains
                if current or time.monotonic() > deadline:
                    break
                time.sleep(0.1)
            if not changes:
                raise ConfigError(
                    f"{path}: no change of {args.loop}'s gains on record"
                    f"{elsewhere(session, args.prefix, runs)}"
                )
            undo = target(changes, args.to, steps)
            if not current and not args.force:
                raise AutotuneError(
                    f"loop {args.loop}: its gains ({_line(now.gains)}) are not the last on "
                    f"record ({_line(_gains(last['after'], 'last'))}): a change the history "
                    f"did not see (is the logger running on this runs directory?"
                    f"{elsewhere(session, args.prefix, runs)}); --force reverts anyway"
                )
            back = reverted_gains(undo, now, client.info.pv_units, path)
            # the loop has them already (--steps 2 right after a revert names the change the
            # revert undid): nothing is sent, and it is said so (it read "Reverted … was Kc 5
            # … now Kc 5")
            status = now
            unrecorded = None
            if back != now.gains:
                try:
                    status = client.command(
                        GainsCommand(loop=args.loop, gains=back, source=SOURCE, t=now.t)
                    )
                except CommandRefused as err:
                    print(f"autotune revert: refused: {err}", file=sys.stderr)
                    return 1
                unrecorded = unrecorded_change(session, args.prefix, args.loop)
    if status.gains != back:  # the plant said yes: it must show them
        raise AutotuneError(f"loop {args.loop}: the plant shows {_line(status.gains)}")
    what = (
        f"run {undo['run_id']}"
        if undo.get("run_id")
        else "the plant's restart with its configured gains (start)"
        if undo.get("cause") == "start"
        else f"the change by {undo.get('by_source') or 'someone unseen'} ({undo.get('cause')})"
    )
    changed = status is not now
    report = {
        "loop": args.loop,
        "reverted": {k: undo.get(k) for k in ("utc", "t", "run_id", "cause", "by_source")},
        "before": now.gains.model_dump(),
        "after": status.gains.model_dump(),
        "t": status.t,
        "changed": changed,
    }
    if args.json:
        print(json_text.dumps(report, indent=2))
    elif not changed:
        print(
            f"Nothing to revert: {args.loop} has the gains before {what} "
            f"({undo.get('utc')}) already: {_line(now.gains)}"
        )
    else:
        print(
            f"Reverted {args.loop} to the gains before {what} ({undo.get('utc')}):\n"
            f"  was {_line(now.gains)}\n  now {_line(status.gains)} (confirmed by the plant)"
        )
    if unrecorded:
        print(unrecorded, file=sys.stderr)
    return 0
