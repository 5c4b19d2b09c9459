"""The tuner's loop assessments kept beside the run files: ``<runs>/monitor.jsonl``.

Each ``LoopMonitor`` published on ``<prefix>/monitor/<loop>`` is validated and appended as one
JSON object on one line, the file opened for appending each time, so that it only grows and
survives restarts of the logger. A payload that is not a valid LoopMonitor, or whose loop is
not the key's, is counted and left out. A line cut short by a crash is ended before the next
one is written, so that every complete line stays one object.
"""

from __future__ import annotations

import logging
from collections import Counter
from pathlib import Path

import pydantic

from shared import keys
from shared.messages import LoopMonitor

FILE_NAME = "monitor.jsonl"

log = logging.getLogger("logger")


class MonitorLog:
    """Appends the monitor messages under ``prefix`` to ``runs_dir/monitor.jsonl``."""

    def __init__(self, runs_dir: Path, prefix: str):
        self.path = Path(runs_dir) / FILE_NAME
        self.prefix = prefix
        self.counts: Counter[str] = Counter()

    def handle(self, key: str, payload: bytes) -> LoopMonitor | None:
        """Validate and append one message; the message, or None if it was left out."""
        self.counts["received"] += 1
        loop = keys.parse_monitor_key(self.prefix, key)
        try:
            msg = LoopMonitor.model_validate_json(payload)
        except pydantic.ValidationError as err:
            msg = None
            why = f"not a LoopMonitor ({err.error_count()} errors)"
        else:
            why = f"its loop {msg.loop!r} is not the key's" if msg.loop != loop else ""
        if msg is None or why:
            self.counts["invalid"] += 1
            log.warning("monitor message on %s left out: %s", key, why)
            return None
        self.append(msg)
        return msg

    def append(self, msg: LoopMonitor) -> None:
        line = msg.model_dump_json() + "\n"
        with self.path.open("a+b") as f:
            f.seek(0, 2)
            if f.tell() > 0:
                f.seek(-1, 2)
                if f.read(1) != b"\n":  # a line cut short by a crash: end it first
                    f.write(b"\n")
            f.write(line.encode())
        self.counts["written"] += 1


def read_monitor_log(runs_dir: Path) -> list[LoopMonitor]:
    """Every whole, valid line of ``runs_dir/monitor.jsonl``, in order (none if missing)."""
    path = Path(runs_dir) / FILE_NAME
    if not path.exists():
        return []
    out = []
    for line in path.read_bytes().splitlines():
        try:
            out.append(LoopMonitor.model_validate_json(line))
        except pydantic.ValidationError:
            continue
    return out
