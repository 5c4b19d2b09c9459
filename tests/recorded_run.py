"""A real tuning run recorded in-process: the live tuner's code (TuningRun) over a plant_sim
loop (LocalLoopClient), every message it and the loop publish handed to the logger's
Recorder as the bus would. Fast (no processes), the same writer as the logger's."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from services.autotuner.identify.experiments import Band
from services.autotuner.tuning import RunHooks, TuningRun
from services.logger.recorder import Recorder
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared import keys, wire
from shared.messages import Command, ProcessSample, RecordStops, TuneRequest, TuneResult


def record_in_process(
    runs: Path,
    prefix: str,
    plant: dict[str, Any],
    loop_id: str,
    method: str,
    cancel_at: float | None = None,
    **request: Any,
) -> tuple[Path, TuneResult]:
    """(the run's MCAP file, the result the live run returned) of one run of ``method``;
    ``cancel_at``: the run cancelled (as Ctrl-C of `autotune tune` does) once a sample at or
    after that sim time (s) is stepped."""
    loop = build_plant(plant)[loop_id]
    recorder = Recorder(runs, prefix, flush_interval=3600.0)
    cancelled = threading.Event()

    def put(key: str, msg) -> None:
        recorder.handle(key, wire.encode(msg))

    class Recording(LocalLoopClient):
        def _apply(self, cmd: Command) -> None:
            super()._apply(cmd)
            if cmd.kind not in ("advance", "sync", "lease", "release"):
                put(keys.command(prefix, loop_id, cmd.kind), cmd)

        def advance(
            self, steps: int, band: Band | None = None, record: RecordStops | None = None
        ) -> list[ProcessSample]:
            out = super().advance(steps, band, record)
            for s in out:
                put(keys.pv(prefix, loop_id), s)
            if cancel_at is not None and out and out[-1].t >= cancel_at:
                cancelled.set()
            return out

    hooks = RunHooks(
        progress=lambda m: put(keys.tune_progress(prefix, loop_id), m),
        event=lambda m: put(keys.tune_event(prefix, loop_id), m),
        cancelled=cancelled,
    )
    req = TuneRequest(loop=loop_id, method=method, **request)
    live = TuningRun(Recording(loop), req, f"run{method}", hooks).run()
    put(keys.tune_result(prefix, loop_id), live)
    (path,) = recorder.finished
    return path, live


def raw_messages(path: Path) -> dict[str, list[dict]]:
    """Every message's JSON in a run file, read with the ``mcap`` library alone (as Foxglove
    would), by the topic's last chunk (commands by their kind)."""
    out: dict[str, list[dict]] = {}
    with path.open("rb") as f:
        for _, ch, m in make_reader(f).iter_messages(log_time_order=False):
            parts = ch.topic.split("/")
            name = parts[parts.index("cmd") + 1] if "cmd" in parts else parts[-1]
            out.setdefault(name, []).append(json.loads(m.data))
    return out
