"""``autotune history LOOP [--runs DIR] [--json]``: the loop's gains changes, oldest first.

Read from the logger's ``history.jsonl`` in its runs directory (``services.logger.history``):
every change of the loop's gains with its UTC and sim time, who made it (the command's source
and the Zenoh user its key named), the gains before and after, and, for a tuning run, the
run's rule and its verification. Runs that recommended gains without applying them
(``tune --no-apply``, or rejected) are listed too: ``autotune apply RUN_ID`` applies them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from shared import json_text
from shared.cli import check_ids
from shared.errors import ConfigError, one_line, printable
from shared.history_file import (
    HISTORY_FILE,
    applicable_rule,
    of_loop,
    proposed_rule,
    read_history,
    same_gains,
)
from shared.keys import DEFAULT_PREFIX
from shared.messages import APPLICABLE_STATUSES

HELP = "the change history of a loop's gains (kept by the logger)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("loop", metavar="LOOP", help="loop id, e.g. hx1")
    parser.add_argument(
        "--runs",
        default="runs",
        metavar="DIR",
        help="the logger's runs directory, where history.jsonl is (default: %(default)s)",
    )
    parser.add_argument("--json", action="store_true", help="the entries as one JSON list")
    parser.add_argument(
        "--prefix",
        default=DEFAULT_PREFIX,
        help="the bus the loop is on, the root of its key expressions (default: %(default)s)",
    )


def entries(
    runs: Path,
    loop: str,
    prefix: str | None = None,
    skipped: list[tuple[int, str]] | None = None,
) -> list[dict[str, Any]]:
    """The loop's changes (on the bus ``prefix``; None: any), each with its run's ``tune``
    record (None for changes not made by a run), and the runs that changed nothing
    (``record`` ``tune``), in file order; the unreadable lines (number, why) into ``skipped``."""
    history = read_history(runs / HISTORY_FILE, skipped)
    records = [r for r in history if of_loop(r, loop, prefix)]
    tunes = {r.get("run_id"): r for r in records if r.get("record") == "tune"}
    changed = {r.get("run_id") for r in records if r.get("record") == "change"}
    out = []
    for r in records:
        if r.get("record") == "change":
            out.append({**r, "tune": tunes.get(r.get("run_id")) if r.get("run_id") else None})
        elif r.get("record") == "tune" and r.get("run_id") not in changed:
            out.append(r)
    return out


def _proposed(tune: dict[str, Any]) -> str:
    """What a run that did not apply its gains proposed: its rule, and the recommended one
    where the tune asked for another (``autotune apply`` applies the proposed one)."""
    rule, recommended = proposed_rule(tune), tune.get("recommended")
    if recommended and rule != recommended:
        return f"proposed {rule} (recommended {recommended})"
    return f"recommended {rule}"


def _apply_hint(tune: dict[str, Any]) -> str:
    """What a run that did not apply its gains proposed, and the ``autotune apply`` command
    that applies gains of it within its safety envelope (a refused ``--rule``'s are not)."""
    run_id, rule, usable = tune.get("run_id"), proposed_rule(tune), applicable_rule(tune)
    if usable is None:
        return f"{_proposed(tune)}, none within the safety envelope: nothing to apply"
    if usable == rule:
        return f"{_proposed(tune)}: `autotune apply {run_id}`"
    return (
        f"proposed {rule}, outside the safety envelope; recommended {usable}: "
        f"`autotune apply {run_id} --rule {usable}`"
    )


def _held_already(tune: dict[str, Any]) -> bool:
    """Did the run apply gains the loop held already (its chosen gains its previous ones,
    ``same_gains``), with the setpoint weight it verified and applied them with (the chosen
    ISA gains carry none: a β-only change is a change)?"""
    chosen, before = tune.get("chosen") or {}, tune.get("previous_gains") or {}
    if not chosen or not before:
        return False
    verified = ((tune.get("verification_after") or {}).get("gains") or {}).get("beta")
    beta = chosen.get("beta", verified)
    return same_gains({**chosen, "beta": before.get("beta", 1.0) if beta is None else beta}, before)


def _num(x: Any, unit: str = "") -> str:
    if x is None:
        return "—"
    return f"{x:.4g}{unit}" if isinstance(x, int | float) else str(x)


def _gains_line(before: dict | None, after: dict | None) -> str:
    before, after = before or {}, after or {}
    parts = []
    for name, unit in (("kc", ""), ("ti", " s"), ("td", " s"), ("beta", "")):
        b, a = before.get(name), after.get(name)
        if b != a:
            parts.append(f"{name.capitalize()} {_num(b)} → {_num(a)}{unit}")
    for name in ("n",):
        if before.get(name) != after.get(name):
            parts.append(f"N {_num(before.get(name))} → {_num(after.get(name))}")
    return "  ".join(parts) or "no change"


def _who(r: dict) -> str:
    src, user = r.get("by_source"), r.get("by_user")
    if src is None and user is None:
        return {
            "start": "the plant (re)started with its configured gains",
            "another plant": "another plant node now serves the loop",
            "unseen": "changed where the logger did not see it (not running, paused or its "
            "messages lost)"
            + (
                f": the gains run {r['run_id']} applied, by its result"
                if r.get("run_id")
                else "; who is not known"
            ),
        }.get(r.get("cause"), "not known")
    return f"{src or '?'}" + (f" (user {user})" if user else "")


def _verification(v: dict | None, units: str | None = None) -> str:
    """The verification's figures in a phrase; ``units``: the PV's (older records: none)."""
    if not v:
        return ""
    iae_unit = f" {units or 'PV units'}·s"
    band = v.get("settling_band")
    # the band where the noise widened it past 2 % of the step (a level's: 37.5 %)
    within = (
        f" (within ±{band:.3g} %)" if isinstance(band, int | float) and band > 2.0 + 1e-9 else ""
    )
    # a measured step with no crest after its largest: none, as `tune` says it ("—" read as
    # not measured, beside the table's "none": walkthrough)
    dr = v.get("decay_ratio")
    decay = "none" if dr is None and v.get("overshoot") is not None else _num(dr)
    return (
        f"overshoot {_num(v.get('overshoot'), ' %')}, decay ratio {decay}, "
        f"settling {_num(v.get('settling_time'), ' s')}{within}, "
        f"IAE {_num(v.get('iae_sp'), iae_unit)}"
    )


def format_entries(
    loop: str, path: Path, items: list[dict], prefix: str | None = None, elsewhere: tuple = ()
) -> str:
    """The entries as text; with none, which bus (``prefix``) was looked at, and the other
    buses whose records of ``loop`` the file holds (``elsewhere``: --prefix picks one)."""
    if not items:
        on = f" under prefix {prefix!r}" if prefix is not None else ""
        other = (
            f" (it holds {loop}'s under {', '.join(repr(p) for p in elsewhere)}: --prefix "
            "picks the bus)"
            if elsewhere
            else ""
        )
        return f"No change of {loop}'s gains on record in {path}{on}{other}."
    lines = [f"Gains of {loop} ({path}), oldest first:"]
    for r in items:
        when = f"{r.get('utc', '?')}  t = {_num(r.get('t'), ' s')}"
        if r.get("record") == "tune":
            rule = proposed_rule(r)
            source = r.get("applied_from")  # an `autotune apply` run: another run's gains
            kind = f"apply of run {source}" if source else r.get("method")
            head = f"  {when}  run {r.get('run_id')} ({kind}): {r.get('status')}, "
            of = f"the gains of run {source}, {rule}" if source else rule
            if r.get("applied") and _held_already(r):  # applied, and nothing changed: a
                # second `apply` of a run said "ok, not applied" while the CLI said "applied"
                lines.append(f"{head}gains unchanged ({of}: the loop held them already)")
            elif r.get("applied"):  # its release not heard, nor its change filed from it
                lines.append(f"{head}applied ({of}); no change of the gains on record for it")
            elif source:  # tried on the loop and not kept: apply would try them again
                lines.append(f"{head}not applied (the gains of run {source}, {rule})")
            elif r.get("status") == "rejected" and r.get("verification_after"):
                # tried on the loop and refused by its verification: applying them again
                # would run the same test (it was suggested: helper 52)
                why = r.get("reason") or "its verification failed"
                lines.append(f"{head}tried on the loop and rejected ({why})")
            elif r.get("status") in APPLICABLE_STATUSES and r.get("gains"):
                lines.append(f"{head}not applied; {_apply_hint(r)}")
            else:  # an aborted or failed run: nothing `autotune apply` would take; why it
                # ended (a run refused the loop held by another never ran: no record of it)
                why = f" ({one_line(r['reason'], 200)})" if r.get("reason") else ""
                lines.append(f"{head.rstrip(', ')}{why}, no gains to apply")
            continue
        tune = r.get("tune")
        what = f"run {r['run_id']}" if r.get("run_id") else r.get("cause", "")
        if tune:
            what += f" ({tune.get('method')}, {tune.get('rule')}"
            what += f", from run {tune['applied_from']})" if tune.get("applied_from") else ")"
        said = f": {what}" if r.get("by_source") or r.get("run_id") else ""
        lines.append(f"  {when}  {_who(r)}{said}")
        lines.append(f"      {_gains_line(r.get('before'), r.get('after'))}")
        if tune and tune.get("verification_after"):
            lines.append(
                "      verified: " + _verification(tune["verification_after"], tune.get("pv_units"))
            )
        elif tune and tune.get("status") == "unverified":  # `apply --no-verify`: nothing said
            lines.append("      unverified (--no-verify): the gains were not tried on the loop")
        if tune and tune.get("status") == "forced":
            lines.append("      forced (--force): applied outside the safety envelope")
    return "\n".join(printable(line) for line in lines)  # a file's text shown, not obeyed


def run(args: argparse.Namespace) -> int:
    check_ids(args.prefix, loop=args.loop)
    runs = Path(args.runs)
    if not runs.is_dir():
        raise ConfigError(f"--runs {runs}: not a directory (the logger's runs directory)")
    skipped: list[tuple[int, str]] = []
    items = entries(runs, args.loop, args.prefix, skipped)
    if skipped:  # a line cut short by a crash, or edited: said, not silently passed over
        shown = ", ".join(str(n) for n, _ in skipped[:5]) + (", …" if len(skipped) > 5 else "")
        first, why = skipped[0]
        print(
            f"autotune history: warning: {runs / HISTORY_FILE}: {len(skipped)} line(s) not "
            f"readable as a record (line {shown}): skipped; line {first}: "
            f"{printable(one_line(why, 160))}",
            file=sys.stderr,
        )
    if args.json:
        print(json_text.dumps(items, indent=2))
    else:
        elsewhere: tuple = ()
        if not items:  # the loop's records under another bus's prefix, if any
            found = {r.get("prefix") for r in entries(runs, args.loop, None)}
            elsewhere = tuple(sorted(p for p in found if p and p != args.prefix))
        print(format_entries(args.loop, runs / HISTORY_FILE, items, args.prefix, elsewhere))
    return 0
