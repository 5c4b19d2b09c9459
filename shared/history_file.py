"""The change history's file: ``history.jsonl`` in the logger's runs directory, one JSON object
per line, append-only (written by ``services.logger.history``; read by ``autotune history``,
``revert`` and ``apply``). Record kinds: ``change`` (a loop's gains changed: ``before``,
``after``, who and why) and ``tune`` (a run's result: what it recommended, chose and verified).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import pydantic

from shared import json_text
from shared.errors import ConfigError

log = logging.getLogger(__name__)

HISTORY_FILE = "history.jsonl"
RUN_SOURCE = "tuner:"  # a tuning run's command source: tuner:<run id>


class _Shape(pydantic.BaseModel):
    """What a record's readers rely on, checked as the file is read: the types they format
    and compare (strict: a number is a number, a name a string), any other field as it is."""

    model_config = pydantic.ConfigDict(strict=True, extra="allow")


class _Gains(_Shape):
    kc: float | None = None
    ti: float | None = None
    td: float | None = None
    beta: float | None = None
    n: float | None = None


class _Common(_Shape):
    loop: str
    prefix: str | None = None
    utc: str | None = None
    t: float | None = None
    run_id: str | None = None


class _Change(_Common):
    record: Literal["change"]
    node: str | None = None
    mode: str | None = None
    cause: str | None = None
    by_source: str | None = None
    by_user: str | None = None
    before: _Gains  # the logger writes both: `revert` takes them as they are
    after: _Gains


class _Tune(_Common):
    record: Literal["tune"]
    status: str | None = None
    reason: str | None = None
    method: str | None = None
    rule: str | None = None
    recommended: str | None = None
    applied: bool | None = None
    applied_from: str | None = None
    previous_gains: _Gains | None = None
    chosen: _Gains | None = None
    verification_before: dict[str, Any] | None = None
    verification_after: dict[str, Any] | None = None
    gains: dict[str, _Gains | None] | None = None
    robustness: dict[str, dict[str, Any] | None] | None = None
    identified_on: dict[str, Any] | None = None
    ku: float | None = None
    timescale: float | None = None
    noise: float | None = None
    contradiction: str | None = None


_SHAPES: dict[str, type[_Shape]] = {"change": _Change, "tune": _Tune}


def malformed(rec: dict[str, Any]) -> str | None:
    """Why a ``change`` or ``tune`` record cannot be read as one (its first bad field), None
    if it can (or is of another kind, left to its readers). Why: a record edited to hold
    ``"before": "x"`` stopped `autotune history` with an internal error (review)."""
    shape = _SHAPES.get(rec.get("record"))  # type: ignore[arg-type]
    if shape is None:
        return None
    try:
        shape.model_validate(rec)
    except pydantic.ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(x) for x in first["loc"]) or "record"
        said = "not a JSON object" if first["type"] in ("model_type", "dict_type") else None
        return f"{where}: {said or first['msg']}"
    return None


def run_of(source: str | None) -> str | None:
    """The run id a command source names (``tuner:<run id>``), else None."""
    if source and source.startswith(RUN_SOURCE):
        return source[len(RUN_SOURCE) :] or None
    return None


def proposed_rule(tune: dict[str, Any]) -> str | None:
    """The rule a run's ``tune`` record proposed: the one it chose (a ``--rule`` asked for,
    else the recommended one), the rule ``autotune apply`` applies unless told another."""
    return tune.get("rule") or tune.get("recommended")


def outside_envelope(tune: dict[str, Any], rule: str | None) -> bool:
    """The run judged ``rule``'s gains outside its safety envelope (``autotune apply`` refuses
    them): a ``--rule`` the tune was asked for and refused."""
    judged = (tune.get("robustness") or {}).get(rule) if rule else None
    return judged is not None and judged.get("within_envelope") is not True


def applicable_rule(tune: dict[str, Any]) -> str | None:
    """The rule ``autotune apply`` can apply of a run: the proposed one, or the recommended
    one where the proposed is outside the safety envelope (None: neither has gains in it)."""
    for rule in (proposed_rule(tune), tune.get("recommended")):
        if rule and (tune.get("gains") or {}).get(rule) and not outside_envelope(tune, rule):
            return rule
    return None


def same_gains(applied: dict[str, Any], before: dict[str, Any]) -> bool:
    """Are the gains a run applied (Kc, Ti, Td, β) the ones the loop held before it? Each
    term the same (to 1e-9), an integral time off on both sides the same and off on one only
    a change (PI to P read "gains unchanged": review), β 1 where either gives none. Used by
    `autotune history` ("gains unchanged") and `tune`'s own words ("nothing changed")."""

    def same(a: Any, b: Any) -> bool:
        if a is None or b is None:
            return a is None and b is None
        return (
            isinstance(a, int | float)
            and isinstance(b, int | float)
            and math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
        )

    return all(same(applied.get(k), before.get(k)) for k in ("kc", "ti", "td")) and same(
        applied.get("beta", 1.0), before.get("beta", 1.0)
    )


def read_history(
    path: Path, skipped: list[tuple[int, str]] | None = None
) -> Iterator[dict[str, Any]]:
    """The records of a history file, oldest first; a line that is not a JSON object (a
    line cut short by a crash, an edit), or a ``change`` or ``tune`` record whose fields are
    not of their types (``malformed``), is skipped, its number (from 1) and why added to
    ``skipped`` when given. Nothing if there is no file; ConfigError if it is not a regular file (a
    FIFO there: `autotune history`, `apply` waited on it for ever: helper review)."""
    if path.exists() and not path.is_file():
        raise ConfigError(
            f"{path}: not a regular file (a directory, a FIFO or a device), not a change history"
        )
    try:
        f = path.open(encoding="utf-8", errors="replace")  # bad bytes: a skipped line
    except FileNotFoundError:
        return
    except OSError as err:
        log.warning("%s: cannot read the history (%s)", path, err.strerror or err)
        return
    with f:
        for n, line in enumerate(f, 1):
            try:
                rec = json_text.loads(line)
            except json.JSONDecodeError:
                rec = None
            why = malformed(rec) if isinstance(rec, dict) else "not a JSON object"
            if why is None:
                yield rec  # type: ignore[misc]
            elif line.strip() and skipped is not None:
                skipped.append((n, why))


def of_loop(rec: dict[str, Any], loop: str, prefix: str | None) -> bool:
    """Is ``rec`` of ``loop`` on the bus ``prefix`` (None: any; a record written before
    records named their prefix counts as any)?"""
    return rec.get("loop") == loop and (prefix is None or rec.get("prefix", prefix) == prefix)


def loop_changes(path: Path, loop: str, prefix: str | None = None) -> list[dict[str, Any]]:
    """The ``change`` records of ``loop`` (on the bus ``prefix``; None: any), oldest first;
    a change by an `autotune apply` run carries ``applied_from``, the approved run, from the
    run's ``tune`` record (written after it: the logger hears the release first), so that
    ``revert --to`` takes the id ``history`` shows as "from run" (it found no change by it:
    helper trial)."""
    records = list(read_history(path))
    approved = {
        r.get("run_id"): r["applied_from"]
        for r in records
        if r.get("record") == "tune" and r.get("applied_from") and of_loop(r, loop, prefix)
    }
    out = []
    for r in records:
        if r.get("record") != "change" or not of_loop(r, loop, prefix):
            continue
        source = approved.get(r.get("run_id"))
        out.append({**r, "applied_from": source} if source and not r.get("applied_from") else r)
    return out
