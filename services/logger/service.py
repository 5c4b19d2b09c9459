"""logger over Zenoh: records every tuning run to MCAP (``autotune logger``).

One subscriber on ``<prefix>/**`` with a large FIFO channel keeps each publisher's order and
never drops a sample (a full channel holds the network back instead); gaps in a loop's
sample numbers are counted as dropped and reported in each file's metadata and the status.
Two liveliness subscribers tell the recorder when a loop's plant (``<prefix>/plant/*/alive``)
or a run's tuner (``<prefix>/tune/*/running``) comes and goes: evidence of a restarted plant
and of a lost tuner. Traffic marked as a replay (``autotune replay``) is left out unless
``--record-replays``. Files are flushed at least every second; SIGTERM and Ctrl-C finish
every open file. ``--runs DIR`` is created if missing; a file there, or a directory that
cannot be written, is refused before anything starts.
"""

from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path

import zenoh

from services.logger.recorder import Recorder, prepare_runs_dir
from shared import keys, wire
from shared.cli import add_common_arguments, check_ids, install_stop_handlers, setup_logging
from shared.messages import LoggerStatus
from shared.session import open_session, settings_from_args
from shared.wire import replay_source

log = logging.getLogger("logger")

HELP = "run the logger service: every tuning run to an MCAP file"
CHANNEL_CAPACITY = 1 << 20


class LoggerService:
    def __init__(self, session: zenoh.Session, recorder: Recorder, node: str):
        self.session = session
        self.recorder = recorder
        self.node = node
        self.lock = threading.Lock()

    def status(self) -> LoggerStatus:
        c = self.recorder.counts
        return LoggerStatus(
            node=self.node,
            runs_dir=str(self.recorder.runs_dir),
            open_runs=self.recorder.open_runs(),
            finished_runs=len(self.recorder.finished),
            received=c["received"],
            written=c["written"],
            invalid=c["invalid"],
            dropped=c["dropped"],
        )

    def _receive(self, sub: zenoh.Subscriber) -> None:
        for sample in sub:
            attachment = sample.attachment
            replay = replay_source(attachment.to_bytes() if attachment is not None else None)
            with self.lock:
                try:
                    self.recorder.handle(str(sample.key_expr), sample.payload.to_bytes(), replay)
                except Exception:  # a write error must not stop the recording of others
                    log.exception("recording %s failed", sample.key_expr)

    def _watch_tokens(self, sub: zenoh.Subscriber, kind: str) -> None:
        """Liveliness of loops (``kind`` "plant") or of runs ("tune"), to the recorder."""
        prefix = self.recorder.prefix
        for sample in sub:
            key = str(sample.key_expr)
            chunks = key[len(prefix) + 1 :].split("/") if key.startswith(prefix + "/") else []
            if len(chunks) != 3 or chunks[0] != kind:
                continue
            alive = sample.kind == zenoh.SampleKind.PUT
            with self.lock:
                try:
                    if kind == "plant":
                        self.recorder.plant_token(chunks[1], alive)
                    else:
                        self.recorder.run_token(chunks[1], alive)
                except Exception:
                    log.exception("liveliness %s failed", key)

    def _answer(self, queryable: zenoh.Queryable) -> None:
        key = keys.logger_status(self.recorder.prefix, self.node)
        for query in queryable:
            with query, self.lock:
                wire.reply(query, key, self.status())

    def run(self, stop: threading.Event) -> None:
        s, prefix = self.session, self.recorder.prefix
        fifo = zenoh.handlers.FifoChannel
        sub = s.declare_subscriber(f"{prefix}/**", fifo(CHANNEL_CAPACITY))
        queryable = s.declare_queryable(keys.logger_status(prefix, self.node), fifo(64))
        watchers = {
            kind: s.liveliness().declare_subscriber(pattern, fifo(1024), history=True)
            for kind, pattern in (
                ("plant", keys.loop_alive(prefix, keys.ANY)),
                ("tune", keys.tune_running(prefix, keys.ANY)),
            )
        }
        threads = [
            threading.Thread(target=self._receive, args=(sub,), daemon=True),
            threading.Thread(target=self._answer, args=(queryable,), daemon=True),
            *(
                threading.Thread(target=self._watch_tokens, args=(w, kind), daemon=True)
                for kind, w in watchers.items()
            ),
        ]
        for th in threads:
            th.start()
        token = s.liveliness().declare_token(keys.logger_alive(prefix, self.node))
        log.info("logger %s recording %s/** into %s", self.node, prefix, self.recorder.runs_dir)
        try:
            while not stop.wait(0.25):
                with self.lock:
                    self.recorder.tick()
        finally:
            sub.undeclare()
            queryable.undeclare()
            for w in watchers.values():
                w.undeclare()
            for th in threads:
                th.join(timeout=5.0)
            with self.lock:
                self.recorder.close_all()
            token.undeclare()
            st = self.status()
            log.info(
                "stopped: %d runs, %d messages written, %d invalid, %d dropped",
                st.finished_runs,
                st.written,
                st.invalid,
                st.dropped,
            )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--runs",
        default="runs",
        metavar="DIR",
        help="directory for the run files, created if missing (default: %(default)s)",
    )
    parser.add_argument(
        "--node", default="logger", help="this process's id on the bus (default: %(default)s)"
    )
    parser.add_argument(
        "--record-replays",
        action="store_true",
        help="also record what `autotune replay` publishes, each replay to its own file "
        "marked as a replay (default: replays are not recorded)",
    )
    add_common_arguments(parser)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.verbose + 1, "logger")
    check_ids(args.prefix, node=args.node)
    runs = prepare_runs_dir(Path(args.runs))  # before anything starts: one line if it is bad
    recorder = Recorder(runs, args.prefix, record_replays=args.record_replays)
    stop = threading.Event()
    install_stop_handlers(stop)
    with open_session(settings_from_args(args)) as session:
        LoggerService(session, recorder, args.node).run(stop)
    return 0
