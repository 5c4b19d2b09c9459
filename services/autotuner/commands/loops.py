"""``autotune loops [LOOP] [--json]``: every loop on the bus, as its faceplate shows it.

Each loop's ``LoopStatus`` and ``LoopInfo`` are read by a query of every loop's status and
info keys (``<prefix>/plant/*/status``, ``<prefix>/plant/*/info``), validated on receipt. A
process that has just joined the bus is still meeting its peers, so the queries are repeated
until the set of loops has stayed the same for a quarter of a second (at most ``--timeout``
s); with LOOP, until that loop has answered.

Per loop: description, model, mode, setpoint, PV, output, the gains in engineering units
(Kc in % of output per PV unit, Ti and Td in s) and in % of the PV's span (Kc in % per %,
the proportional band PB = 100/Kc in % of span), the clock, the sample time, sim time, who
holds its lease (a tuning run or a step test) and why its model failed, if it did.

JSON (``--json``: a list of objects; with LOOP, one object), keys: loop, node, description,
model, mode, action, sp, pv, op (%), pv_units, pv_range [lo, hi], op_limits [lo, hi] (%),
gains {kc, ti, td, n, beta} (ti null: no integral action), gains_percent {kc, ti, td, pb}
(null without a usable PV range), disturbances {name: value}, clock, sample_time (s), t
(sim s), leased_by, lease_user, fault, accepted and rejected (the commands the plant applied
to the loop and refused since it started) and last_reject (the last refusal's reason). A
loop that answered its status but not its info within the wait has null description, model
and sample_time.

Exit 0; 2 with one line when LOOP is not on the bus, or no loop is, or LOOP's plant
announces it (its liveliness token is up) but it did not answer (a paused or overloaded
plant); 1 when such loops are left out of the listing of every loop: the others are listed,
and one line on stderr names those.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Any

import zenoh

from services.autotuner.loop_client import listed, live_loops
from shared import json_text, keys, wire
from shared.cli import MAX_SECONDS, add_common_arguments, check_ids
from shared.control.forms import IsaGains, pv_span, to_percent
from shared.errors import AutotuneError, ConfigError, DecodeError
from shared.messages import LoopInfo, LoopStatus, Message
from shared.session import open_session, settings_from_args, unreached

HELP = "every loop on the bus: mode, SP, PV, OP, gains, clock, lease (--json for scripts)"

DEFAULT_TIMEOUT = 2.0  # s of wall time to wait for the loops' answers
SETTLE = 0.25  # s: the set of loops must stay the same this long before the answer is taken
ROUND_PAUSE = 0.05  # s between two rounds of queries
QUERY_TIMEOUT = 1.0  # s: one round's queries at most (a plant answers in milliseconds)


def seconds(text: str) -> float:
    """``--timeout``: a finite number of seconds > 0 (argparse type: the flag is named)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: not a number of seconds") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text}: must be a finite number of seconds")
    if not 0 < value <= MAX_SECONDS:
        raise argparse.ArgumentTypeError(f"{text}: must be > 0 and at most {MAX_SECONDS:g} s")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("loop", nargs="?", metavar="LOOP", help="one loop only, e.g. hx1")
    parser.add_argument(
        "--json",
        action="store_true",
        help="a JSON list of loop objects (with LOOP, one object); keys in the description",
    )
    parser.add_argument(
        "--timeout",
        type=seconds,
        default=DEFAULT_TIMEOUT,
        metavar="S",
        help="seconds to wait for the loops to answer (default: %(default)s)",
    )
    add_common_arguments(parser)


# --- reading the bus --------------------------------------------------------------------------


def _collect(
    session: zenoh.Session,
    key: str,
    model: type[Message],
    prefix: str,
    timeout: float,
    into: dict[str, Any],
) -> None:
    """One query of ``key``: every valid reply into ``into`` by loop id. A reply whose key is
    not a loop's, or whose payload names another loop, or fails validation, is left out."""
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            continue
        parsed = keys.parse_loop_key(prefix, str(reply.ok.key_expr))
        if parsed is None:
            continue
        try:
            msg = wire.decode_sample(model, reply.ok)
        except DecodeError:
            continue
        if msg.loop == parsed[0]:
            into[parsed[0]] = msg


def read_loops(
    session: zenoh.Session, prefix: str, timeout: float, want: str | None = None
) -> dict[str, tuple[LoopStatus, LoopInfo | None]]:
    """Every loop on the bus: (status, info) by loop id, sorted. Queries are repeated until
    the set of loops that answered has not changed for SETTLE s and each has given its info;
    with ``want``, until that loop has answered both, or the set has settled without it. At
    most ``timeout`` s of wall time."""
    deadline = time.monotonic() + timeout
    statuses: dict[str, LoopStatus] = {}
    infos: dict[str, LoopInfo] = {}
    seen: set[str] = set()
    since = time.monotonic()
    while True:
        left = max(0.05, min(deadline - time.monotonic(), QUERY_TIMEOUT))
        _collect(session, keys.status(prefix, keys.ANY), LoopStatus, prefix, left, statuses)
        _collect(session, keys.info(prefix, keys.ANY), LoopInfo, prefix, left, infos)
        now = time.monotonic()
        if set(statuses) != seen:
            seen, since = set(statuses), now
        if want is not None and want in statuses and want in infos:
            break
        settled = bool(seen) and now - since >= SETTLE
        if settled and (seen <= set(infos) if want is None else want not in seen):
            break
        if now >= deadline:
            break
        time.sleep(min(ROUND_PAUSE, max(0.0, deadline - now)))
    return {lid: (statuses[lid], infos.get(lid)) for lid in sorted(statuses)}


def read_loop(
    session: zenoh.Session, prefix: str, loop: str, timeout: float
) -> tuple[LoopStatus, LoopInfo | None]:
    """One loop's (status, info); ConfigError naming the loops that are there if it is not."""
    found = read_loops(session, prefix, timeout, want=loop)
    if loop not in found:
        raise ConfigError(not_found(loop, prefix, sorted(found), timeout))
    return found[loop]


def not_found(loop: str, prefix: str, present: list[str], timeout: float) -> str:
    """The one line for a loop that did not answer: the loops that did, or the key asked."""
    if present:
        return f"loop {loop!r} not found: the loops on the bus are {listed(present)}"
    return (
        f"loop {loop!r} not found: nothing answered {keys.status(prefix, loop)} within "
        f"{timeout:g} s (is `autotune plant` running and reachable, with this --prefix?)"
    )


# --- the loop object --------------------------------------------------------------------------


def gains_percent(status: LoopStatus) -> dict[str, float | None] | None:
    """The loop's gains in % of its PV's span (Kc % per %, PB % of span, Ti and Td s); None
    when its PV range has no usable span."""
    try:
        span = pv_span(status.pv_range)
    except ValueError:
        return None
    g = status.gains
    return to_percent(IsaGains(g.kc, g.ti, g.td), span).to_dict()


def loop_object(status: LoopStatus, info: LoopInfo | None) -> dict[str, Any]:
    """The loop as ``loops --json`` gives it (the keys are a contract: see the module doc)."""
    return {
        "loop": status.loop,
        "node": status.node,
        "description": info.description if info else None,
        "model": info.model if info else None,
        "mode": status.mode,
        "action": status.action,
        "sp": status.sp,
        "pv": status.pv,
        "op": status.op,
        "pv_units": info.pv_units if info else None,
        "pv_range": list(status.pv_range),
        "op_limits": list(status.op_limits),
        "gains": status.gains.model_dump(mode="json"),
        "gains_percent": gains_percent(status),
        "disturbances": dict(status.disturbances),
        "clock": status.clock,
        "sample_time": info.sample_time if info else None,
        "t": status.t,
        "leased_by": status.leased_by,
        "lease_user": status.lease_user,
        "fault": status.fault,
        # the commands the plant applied to the loop and refused (bad payloads, a loop held
        # by a run, values out of range), and the last refusal's reason: the counters the
        # plant keeps, which no command showed (only its log, or a query by hand)
        "accepted": status.accepted,
        "rejected": status.rejected,
        "last_reject": status.last_reject,
    }


# --- text -------------------------------------------------------------------------------------


def num(value: float | None, fmt: str = ".4g") -> str:
    """A number for a table cell; ``—`` for none."""
    return "—" if value is None else format(value, fmt)


def holder(obj: dict[str, Any]) -> str:
    """Who holds the loop's lease: its source, and its Zenoh user when known; ``—`` if none."""
    if obj["leased_by"] is None:
        return "—"
    user = obj["lease_user"]
    return obj["leased_by"] if user is None else f"{obj['leased_by']} (user {user})"


COLUMNS = (  # heading, aligned left?, cell
    ("loop", True, lambda o: o["loop"]),
    ("mode", True, lambda o: o["mode"] + ("!" if o["fault"] else "")),
    ("SP", False, lambda o: num(o["sp"])),
    ("PV", False, lambda o: num(o["pv"])),
    ("units", True, lambda o: o["pv_units"] or ""),
    ("OP %", False, lambda o: num(o["op"])),
    ("Kc", False, lambda o: num(o["gains"]["kc"])),
    ("Ti s", False, lambda o: num(o["gains"]["ti"])),
    ("Td s", False, lambda o: num(o["gains"]["td"])),
    ("β", False, lambda o: num(o["gains"]["beta"], "g")),
    ("Kc %/%", False, lambda o: num((o["gains_percent"] or {}).get("kc"))),
    ("PB %", False, lambda o: num((o["gains_percent"] or {}).get("pb"))),
    ("T s", False, lambda o: num(o["sample_time"], "g")),
    ("clock", True, lambda o: o["clock"]),
    ("t s", False, lambda o: num(o["t"], ".6g")),
    ("lease", True, holder),
    ("description", True, lambda o: o["description"] or ""),
)


def format_table(objs: list[dict[str, Any]]) -> str:
    """The loops as a table, one row each: Kc in % of output per PV unit, Kc %/% and PB in %
    of the PV's span, T the sample time; a faulted loop's mode is marked ``!`` and its fault
    spelt out below the table."""
    cells = [[cell(o) for _, _, cell in COLUMNS] for o in objs]
    heads = [h for h, _, _ in COLUMNS]
    widths = [max(len(c) for c in col) for col in zip(heads, *cells, strict=True)]

    def line(row: list[str]) -> str:
        return "  ".join(
            f"{c:<{w}}" if left else f"{c:>{w}}"
            for c, w, (_, left, _) in zip(row, widths, COLUMNS, strict=True)
        ).rstrip()

    notes = [f"{o['loop']}: FAULT: {o['fault']}" for o in objs if o["fault"]]
    return "\n".join([line(heads), *(line(r) for r in cells), *notes])


SILENT = 1  # exit status: loops whose plant announces them did not answer


def silent_line(loops: list[str], timeout: float) -> str:
    """The loops whose liveliness tokens are up but that did not answer: their plant is
    paused or overloaded (it left them out of the table without a word)."""
    return (
        f"{listed(loops)}: announced on the bus (liveliness token up) but did not answer "
        f"within {timeout:g} s: their plant is paused or overloaded"
    )


def run(args: argparse.Namespace) -> int:
    if args.loop is not None:
        check_ids(args.prefix, loop=args.loop)
    else:
        check_ids(args.prefix)
    with open_session(settings_from_args(args), args.timeout) as session:
        if args.loop is not None:
            try:
                objs = [loop_object(*read_loop(session, args.prefix, args.loop, args.timeout))]
            except ConfigError:
                if args.loop in live_loops(session, args.prefix):
                    raise AutotuneError(silent_line([args.loop], args.timeout)) from None
                raise
            silent: list[str] = []
        else:
            found = read_loops(session, args.prefix, args.timeout)
            objs = [loop_object(st, info) for st, info in found.values()]
            silent = [lp for lp in live_loops(session, args.prefix) if lp not in found]
        if not objs and not silent:
            raise ConfigError(
                f"no loop answered {keys.status(args.prefix, keys.ANY)} within "
                f"{args.timeout:g} s (is `autotune plant` running and reachable, with this "
                f"--prefix?){unreached(session)}"
            )
    if args.json:
        print(json_text.dumps(objs[0] if args.loop is not None else objs, indent=2))
    elif objs:
        print(format_table(objs))
    if silent:
        print(f"autotune loops: {silent_line(silent, args.timeout)}", file=sys.stderr)
        return SILENT
    return 0
