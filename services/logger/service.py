"""logger over Zenoh: records every tuning run to MCAP (``autotune logger``).

One subscriber on ``<prefix>/**`` with a large FIFO channel keeps each publisher's order and
never drops a sample (a full channel holds the network back instead); gaps in a loop's
sample numbers are counted as dropped and reported in each file's metadata and the status.
Files are flushed at least every second; SIGTERM and Ctrl-C finish every open file.
"""

from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path

import zenoh

from services.logger.recorder import Recorder
from shared import keys, wire
from shared.cli import add_common_arguments, check_ids, install_stop_handlers, setup_logging
from shared.messages import LoggerStatus
from shared.session import open_session, settings_from_args

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
            with self.lock:
                try:
                    self.recorder.handle(str(sample.key_expr), sample.payload.to_bytes())
                except Exception:  # a write error must not stop the recording of others
                    log.exception("recording %s failed", sample.key_expr)

    def _answer(self, queryable: zenoh.Queryable) -> None:
        key = keys.logger_status(self.recorder.prefix, self.node)
        for query in queryable:
            with query, self.lock:
                wire.reply(query, key, self.status())

    def run(self, stop: threading.Event) -> None:
        s, prefix = self.session, self.recorder.prefix
        sub = s.declare_subscriber(f"{prefix}/**", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        queryable = s.declare_queryable(
            keys.logger_status(prefix, self.node), zenoh.handlers.FifoChannel(64)
        )
        threads = [
            threading.Thread(target=self._receive, args=(sub,), daemon=True),
            threading.Thread(target=self._answer, args=(queryable,), daemon=True),
        ]
        for th in threads:
            th.start()
        token = s.liveliness().declare_token(keys.logger_alive(prefix, self.node))
        log.info("logger %s recording %s/** into %s", self.node, prefix, self.recorder.runs_dir)
        try:
            while not stop.wait(0.25):
                with self.lock:
                    self.recorder.flush_due()
        finally:
            sub.undeclare()
            queryable.undeclare()
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
        help="directory for the run files (default: %(default)s)",
    )
    parser.add_argument(
        "--node", default="logger", help="this process's id on the bus (default: %(default)s)"
    )
    add_common_arguments(parser)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.verbose + 1, "logger")
    check_ids(args.prefix, node=args.node)
    stop = threading.Event()
    install_stop_handlers(stop)
    recorder = Recorder(Path(args.runs), args.prefix)
    with open_session(settings_from_args(args)) as session:
        LoggerService(session, recorder, args.node).run(stop)
    return 0
