"""Turn the tuning traffic into one MCAP file per run (no Zenoh in here).

A run starts with its first TuneProgress (phase ``start``) and ends with its TuneResult, or
when the plant's watchdog reports it restored the loop (the tuner was lost). Everything on
the loop's keys in between goes into the file: process samples, status, every command, the
tuner's progress, events and result. Messages are validated against their model first; one
that is not valid is counted and left out. Recent messages are kept per loop, so a sample
that overtakes the run's first progress message on another link is not lost.
"""

from __future__ import annotations

import json
import logging
from collections import Counter, deque
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import pydantic

from services.logger.mcap_io import RunWriter
from shared.messages import (
    COMMANDS,
    LoopStatus,
    Message,
    ProcessSample,
    TuneProgress,
    TuneResult,
    TunerEvent,
)

log = logging.getLogger("logger")

BUFFER = 4096  # recent messages kept per loop


@dataclass
class Item:
    key: str
    model: type[Message]
    payload: bytes
    msg: Message
    t: float


@dataclass
class OpenRun:
    run_id: str
    loop: str
    method: str
    rule: str
    writer: RunWriter
    t_start: float
    started: str
    request: str = ""
    info: str = ""
    samples: int = 0
    first_seq: int | None = None
    last_seq: int | None = None
    gaps: int = 0


@dataclass
class Loop:
    recent: deque[Item] = field(default_factory=lambda: deque(maxlen=BUFFER))
    run: OpenRun | None = None
    t: float = 0.0


def model_for(prefix: str, key: str) -> tuple[str, type[Message]] | None:
    """(loop, model) of a key the logger records, or None."""
    head = key[len(prefix) + 1 :].split("/") if key.startswith(prefix + "/") else []
    if len(head) == 3 and head[0] == "plant":
        return {"pv": (head[1], ProcessSample), "status": (head[1], LoopStatus)}.get(head[2])
    if len(head) == 4 and head[0] == "plant" and head[2] == "cmd" and head[3] in COMMANDS:
        return head[1], COMMANDS[head[3]]
    if len(head) == 3 and head[0] == "tune":
        models = {"progress": TuneProgress, "event": TunerEvent, "result": TuneResult}
        return (head[1], models[head[2]]) if head[2] in models else None
    return None


class Recorder:
    def __init__(self, runs_dir: Path, prefix: str, flush_interval: float = 1.0):
        self.runs_dir = Path(runs_dir)
        self.runs_dir.mkdir(parents=True, exist_ok=True)
        self.prefix = prefix
        self.flush_interval = flush_interval
        self.loops: dict[str, Loop] = {}
        self.counts: Counter[str] = Counter()
        self.finished: list[Path] = []

    def handle(self, key: str, payload: bytes) -> None:
        """Take one message from the bus."""
        self.counts["received"] += 1
        found = model_for(self.prefix, key)
        if found is None:
            self.counts["ignored"] += 1
            return
        loop_id, model = found
        try:
            msg = model.model_validate_json(payload)
        except pydantic.ValidationError:
            self.counts["invalid"] += 1
            return
        loop = self.loops.setdefault(loop_id, Loop())
        t = getattr(msg, "t", None)
        loop.t = t if t is not None else loop.t
        item = Item(key, model, payload, msg, loop.t)
        loop.recent.append(item)
        if loop.run is None and isinstance(msg, TuneProgress) and msg.phase == "start":
            self._open(loop_id, loop, msg)
            return
        run = loop.run
        if run is None:
            return
        self._write(run, item)
        if isinstance(msg, TuneResult) and msg.run_id == run.run_id:
            self._close(loop, status=msg.status, result=msg)
        elif isinstance(msg, LoopStatus) and msg.reason == "watchdog":
            self._close(loop, status="tuner lost", result=None)

    def _open(self, loop_id: str, loop: Loop, start: TuneProgress) -> None:
        now = datetime.now(UTC)
        method = start.message.split(" ")[0] if start.message else "run"
        path = self.runs_dir / f"{now:%Y%m%dT%H%M%SZ}_{loop_id}_{method}_{start.run_id}.mcap"
        run = OpenRun(
            start.run_id,
            loop_id,
            method,
            "",
            RunWriter(path, self.flush_interval),
            start.t,
            now.isoformat(),
        )
        loop.run = run
        self.counts["runs"] += 1
        log.info("run %s on %s: recording to %s", start.run_id, loop_id, path)
        for item in loop.recent:  # what came just before, the start message included
            if item.t >= start.t and not (
                isinstance(item.msg, TuneProgress | TunerEvent | TuneResult)
                and item.msg.run_id != start.run_id
            ):
                self._write(run, item)

    def _write(self, run: OpenRun, item: Item) -> None:
        msg = item.msg
        if isinstance(msg, ProcessSample):
            if run.last_seq is not None and msg.seq != run.last_seq + 1:
                run.gaps += max(0, msg.seq - run.last_seq - 1)
            run.first_seq = msg.seq if run.first_seq is None else run.first_seq
            run.last_seq = msg.seq
            run.samples += 1
        elif isinstance(msg, TunerEvent) and msg.kind == "request":
            run.request = str(msg.data.get("request", ""))
            run.info = str(msg.data.get("info", ""))
            try:
                run.rule = json.loads(run.request).get("rule", "")
                run.method = json.loads(run.request).get("method", run.method)
            except json.JSONDecodeError:
                pass
        run.writer.write(item.key, item.model, item.payload, item.t)
        self.counts["written"] += 1

    def _close(self, loop: Loop, status: str, result: TuneResult | None) -> None:
        run = loop.run
        loop.run = None
        meta = {
            "run_id": run.run_id,
            "loop": run.loop,
            "method": run.method,
            "rule": run.rule,
            "status": status,
            "started": run.started,
            "finished": datetime.now(UTC).isoformat(),
            "prefix": self.prefix,
            "samples": str(run.samples),
            "first_seq": str(run.first_seq),
            "last_seq": str(run.last_seq),
            "dropped": str(run.gaps),
            "messages": str(run.writer.messages),
            "request": run.request,
            "info": run.info,
            "result": result.model_dump_json() if result else "",
            "ku": "" if result is None or result.ku is None else repr(result.ku),
            "pu": "" if result is None or result.pu is None else repr(result.pu),
        }
        run.writer.finish(meta)
        self.finished.append(run.writer.path)
        self.counts["dropped"] += run.gaps
        log.info(
            "run %s on %s: %s, %d messages, %d samples, %d dropped → %s",
            run.run_id,
            run.loop,
            status,
            run.writer.messages,
            run.samples,
            run.gaps,
            run.writer.path,
        )

    def flush_due(self) -> None:
        for loop in self.loops.values():
            if loop.run is not None:
                loop.run.writer.flush_if_due()

    def close_all(self, status: str = "incomplete") -> None:
        """Finish every open file (on SIGTERM or Ctrl-C): nothing received is lost."""
        for loop in self.loops.values():
            if loop.run is not None:
                self._close(loop, status=status, result=None)

    def open_runs(self) -> list[str]:
        return [lp.run.run_id for lp in self.loops.values() if lp.run is not None]
