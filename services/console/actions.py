"""What the page's buttons do, through the same paths as the CLI's commands.

Tune and cancel are ``autotune tune``'s (``submit``, ``follow``, the cancel key); apply is
``autotune apply``'s (the run's record in the change history, the rule's envelope checked, the
loop checked to be the one identified, then a run of its own through the autotuner, verified);
revert is ``autotune revert``'s (the change history, a lease-respecting gains command through
``LoopClient``, confirmed by the plant). The console never writes to a loop by itself: only
the autotuner's runs and the plant's own command path do, as for any other client.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from services.autotuner.commands.apply import (
    choose,
    recorded_request,
    recorded_run,
    same_loop,
)
from services.autotuner.commands.revert import CATCH_UP, reverted_gains, target
from services.autotuner.commands.tune import follow, submit
from services.autotuner.loop_client import (
    CommandRefused,
    LoopClient,
    wait_for_loop,
    wait_for_token,
)
from shared import keys, wire
from shared.errors import AutotuneError, ConfigError
from shared.history_file import HISTORY_FILE, loop_changes, of_loop
from shared.messages import GainsCommand, LoopInfo, PidGains, TuneAccepted, TuneRequest, TuneResult

SOURCE = "autotune-console"
RESULT_WAIT = 3600.0  # s of wall time a run may take before the console stops waiting
RECORD_WAIT = 5.0  # s the logger may take to write a finished run into the change history
LOOP_WAIT = 5.0  # s to wait for a loop's plant to be seen
TOKEN_WAIT = 1.0  # s to wait for a run's liveliness token to be seen

log = logging.getLogger("console")


def run_tune(
    session: zenoh.Session,
    prefix: str,
    req: TuneRequest,
    on_accepted: Callable[[TuneAccepted], None],
) -> TuneResult:
    """Submit ``req`` to any autotuner and follow the run to its result (``tune``'s path:
    the tuner gone, or the bus lost, end the wait with the reason)."""

    def start() -> TuneAccepted:
        accepted = submit(session, prefix, "*", req, say=log.warning)
        on_accepted(accepted)
        return accepted

    return follow(session, prefix, req.loop, start, RESULT_WAIT)


def cancel(session: zenoh.Session, prefix: str, loop: str, run_id: str | None) -> None:
    """Ask the loop's run to stop (the tuner restores the loop before it answers);
    AutotuneError, nothing sent, when no run is going on the loop (its tuner's token
    ``tune/<loop>/running`` not on the bus): a cancel of nothing was answered "cancel sent
    to flow1's run: the tuner restores the loop" (helper trial)."""
    keys.check_id(loop)
    if not wait_for_token(session, keys.tune_running(prefix, loop), TOKEN_WAIT):
        raise AutotuneError(f"no run going on {loop}: nothing to cancel")
    session.put(keys.tune_cancel(prefix, loop), (run_id or "").encode())


def check_run_of(runs: Path, prefix: str, loop: str, run_id: str) -> None:
    """ConfigError naming the loop and the run unless run ``run_id`` of ``loop`` is among
    the recorded runs (its ``tune`` record in the change history, as ``autotune apply``
    looks it up): the page's Reject of a run id that does not exist was answered "run zzz
    rejected: its gains were not applied, flow1 unchanged" (helper trial)."""
    try:
        rec = recorded_run(runs, run_id)
    except ConfigError as err:
        raise ConfigError(f"reject run {run_id} of {loop}: {err}; nothing rejected") from None
    if not of_loop(rec, loop, prefix):
        where = str(rec.get("loop"))
        if rec.get("prefix", prefix) != prefix:
            where += f" under prefix {rec.get('prefix')}"
        raise ConfigError(
            f"reject run {run_id} of {loop}: run {run_id} tuned {where}, not {loop}; "
            "nothing rejected"
        )


def _record(runs: Path, run_id: str) -> dict[str, Any]:
    """The run's record in the change history, waiting for the logger to write it."""
    deadline = time.monotonic() + RECORD_WAIT
    while True:
        try:
            return recorded_run(runs, run_id)
        except ConfigError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def apply_request(
    session: zenoh.Session, prefix: str, runs: Path, run_id: str, rule: str | None
) -> TuneRequest:
    """``autotune apply RUN_ID [--rule RULE]``'s request, after its checks (the record, the
    rule's envelope, the loop still the one identified); ConfigError or AutotuneError with
    the reason otherwise."""
    rec = _record(runs, run_id)
    loop = str(rec.get("loop"))
    req = recorded_request(rec, run_id, choose(rec, rule), True, SOURCE)
    info = wire.query_one(session, keys.info(prefix, loop), LoopInfo, LOOP_WAIT)
    if info is None:
        raise AutotuneError(f"loop {loop}: no plant answers for it")
    if (why := same_loop(rec.get("identified_on"), info)) is not None:
        raise AutotuneError(f"loop {loop} is not the loop run {run_id} identified: {why}")
    return req


def revert(
    session: zenoh.Session,
    prefix: str,
    runs: Path,
    loop: str,
    to: str | None = None,
    user: str | None = None,
    last_only: bool = False,
    shown: PidGains | None = None,
) -> dict[str, Any]:
    """``autotune revert LOOP [--to RUN_ID]``: the gains before the loop's last change (or
    before run ``to``'s), written bumplessly by one gains command and confirmed by the plant;
    refused when the loop's gains are not the last on record (a change the history missed),
    and, ``last_only`` (the page's Reject of run ``to``), when run ``to``'s change is not the
    last; with ``shown`` (the gains the page showed as the loop's when Revert was pressed),
    when the loop's gains are no longer those: two Reverts pressed at once undid the last
    change and then the revert itself, the tuned gains back on the loop. Returns what was
    done: loop, the change undone, before and after gains."""
    keys.check_id(loop)
    path = runs / HISTORY_FILE
    wait_for_loop(session, prefix, loop, LOOP_WAIT)
    with LoopClient(session, prefix, loop, source=SOURCE, user=user) as client:
        now = client.sync()
        if shown is not None and now.gains != shown:
            raise AutotuneError(
                f"loop {loop}: its gains changed since the page showed them (now "
                f"{_gains_line(now.gains)}, shown {_gains_line(shown)}): nothing written; "
                "Revert again to undo the change now last"
            )
        deadline = time.monotonic() + CATCH_UP
        while True:  # the logger writes a change down as it sees it: let it catch up
            changes = loop_changes(path, loop, prefix)
            last = changes[-1] if changes else None
            current = last is not None and _gains(last["after"]) == now.gains
            if current or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        if not changes:
            raise ConfigError(f"{path}: no change of {loop}'s gains on record")
        undo = target(changes, to, 1)
        if last_only and undo is not changes[-1]:
            # the page's Reject of a run: its gains are no longer the loop's, and writing back
            # the gains before it would undo the later change unsaid (an operator's Kc 3 was
            # put back to 2 by a Reject pressed again after a reload: helper trial)
            later = changes[-1]
            raise AutotuneError(
                f"loop {loop}: its gains changed after run {to}'s ({later.get('cause')} by "
                f"{later.get('by_source') or 'an unknown sender'} at {later.get('utc')}): "
                "rejecting the run would write over that change; nothing written (Revert "
                "undoes the last change)"
            )
        if not current:
            raise AutotuneError(
                f"loop {loop}: its gains are not the last on record (a change the history "
                "did not see; is the logger running on this runs directory?): not reverted"
            )
        back = reverted_gains(undo, now, client.info.pv_units, path)
        try:
            status = client.command(GainsCommand(loop=loop, gains=back, source=SOURCE, t=now.t))
        except CommandRefused as err:
            raise AutotuneError(f"revert refused by the plant: {err}") from None
    if status.gains != back:
        raise AutotuneError(f"loop {loop}: the plant shows other gains than those written")
    return {
        "loop": loop,
        "reverted": {k: undo.get(k) for k in ("utc", "run_id", "cause", "by_source")},
        "before": now.gains.model_dump(),
        "after": status.gains.model_dump(),
    }


def _gains_line(g: PidGains) -> str:
    return f"Kc {g.kc:.4g}, Ti {'off' if g.ti is None else f'{g.ti:.4g} s'}, Td {g.td:.4g} s"


def _gains(d: dict[str, Any]) -> PidGains:
    try:
        return PidGains.model_validate(d)
    except Exception:
        raise AutotuneError(f"the change history holds gains that are not valid: {d!r}") from None
