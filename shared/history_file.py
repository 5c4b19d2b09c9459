"""The change history's file: ``history.jsonl`` in the logger's runs directory, one JSON object
per line, append-only (written by ``services.logger.history``; read by ``autotune history``,
``revert`` and ``apply``). Record kinds: ``change`` (a loop's gains changed: ``before``,
``after``, who and why) and ``tune`` (a run's result: what it recommended, chose and verified).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from shared import json_text
from shared.errors import ConfigError

log = logging.getLogger(__name__)

HISTORY_FILE = "history.jsonl"
RUN_SOURCE = "tuner:"  # a tuning run's command source: tuner:<run id>


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


def read_history(path: Path, skipped: list[int] | None = None) -> Iterator[dict[str, Any]]:
    """The records of a history file, oldest first; a line that is not a JSON object (a
    line cut short by a crash, an edit) is skipped, its number (from 1) added to ``skipped``
    when given. Nothing if there is no file; ConfigError if it is not a regular file (a
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
            if isinstance(rec, dict):
                yield rec
            elif line.strip() and skipped is not None:
                skipped.append(n)


def of_loop(rec: dict[str, Any], loop: str, prefix: str | None) -> bool:
    """Is ``rec`` of ``loop`` on the bus ``prefix`` (None: any; a record written before
    records named their prefix counts as any)?"""
    return rec.get("loop") == loop and (prefix is None or rec.get("prefix", prefix) == prefix)


def loop_changes(path: Path, loop: str, prefix: str | None = None) -> list[dict[str, Any]]:
    """The ``change`` records of ``loop`` (on the bus ``prefix``; None: any), oldest first."""
    return [
        r for r in read_history(path) if r.get("record") == "change" and of_loop(r, loop, prefix)
    ]
