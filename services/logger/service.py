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
import json
import logging
import queue
import threading
from collections.abc import Callable
from pathlib import Path

import zenoh

from services.logger.history import ChangeHistory
from services.logger.mcap_io import bus_name
from services.logger.monitor_log import MonitorLog
from services.logger.recorder import Recorder, prepare_runs_dir
from shared import keys, wire
from shared.cli import add_common_arguments, check_ids, setup_logging
from shared.messages import LoggerStatus, TuneResult
from shared.service_shell import ServiceShell, run_until_stopped
from shared.session import settings_from_args, zenoh_config
from shared.wire import DecodeError, replay_source

log = logging.getLogger("logger")

HELP = "run the logger service: every tuning run to an MCAP file"
CHANNEL_CAPACITY = 1 << 20
# a run closed "tuner lost" has its tuner asked for its result every LATE_ASK s, this many
# times (about a minute: a logger cut off reconnects within seconds once it runs again)
LATE_ASK, LATE_TRIES = 2.0, 30
# a restarted plant's loop has its status asked this many times, RESTART_ASK s apart, until
# one is heard (its queryable may be declared a moment after its first samples come)
RESTART_ASK, RESTART_TRIES = 1.0, 5


class LoggerService:
    def __init__(
        self,
        session: zenoh.Session,
        recorder: Recorder,
        node: str,
        history: ChangeHistory | None = None,
    ):
        self.session = session
        self.recorder = recorder
        self.node = node
        # said absolute in its status: a client in another directory (or on another machine)
        # is told where the runs are (``revert``, ``apply``)
        self.runs_dir = str(recorder.runs_dir.resolve())
        self.lock = threading.Lock()
        # every loop's gains changes, kept beside the run files (``history.jsonl``)
        self.history = history or ChangeHistory(
            recorder.runs_dir, recorder.prefix, bus=bus_name(recorder.namespace, recorder.prefix)
        )
        # the tuner's assessments of the loops it tuned (``monitor.jsonl``)
        self.monitor_log = MonitorLog(recorder.runs_dir, recorder.prefix)
        # loops whose plant restarted (the recorder's evidence): their status to ask
        self._restarts: queue.Queue[str] = queue.Queue()
        recorder.on_new_instance = self._plant_restarted

    def status(self) -> LoggerStatus:
        c = self.recorder.counts
        return LoggerStatus(
            node=self.node,
            runs_dir=self.runs_dir,
            open_runs=self.recorder.open_runs(),
            finished_runs=len(self.recorder.finished),
            received=c["received"],
            written=c["written"],
            invalid=c["invalid"],
            dropped=c["dropped"],
            incomplete_runs=self.recorder.incomplete_runs(),
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        attachment = sample.attachment
        replay = replay_source(attachment.to_bytes() if attachment is not None else None)
        with self.lock:
            try:
                self.recorder.handle(str(sample.key_expr), sample.payload.to_bytes(), replay)
            except Exception:  # a write error must not stop the recording of others
                log.exception("recording %s failed", sample.key_expr)
            if replay is None:  # a replay changes no loop's settings
                try:
                    self.history.handle(str(sample.key_expr), sample.payload.to_bytes())
                except OSError as err:  # a full disk: one line, not a traceback a message
                    log.error(
                        "the change history of %s not written: %s",
                        sample.key_expr,
                        err.strerror or err,
                    )
                except Exception:
                    log.exception("the change history of %s failed", sample.key_expr)

    def _on_token(self, sample: zenoh.Sample) -> None:
        """A loop's token (``<prefix>/plant/<loop>/alive``) or a run's
        (``<prefix>/tune/<loop>/running``) appeared or vanished: to the recorder."""
        prefix, key = self.recorder.prefix, str(sample.key_expr)
        plant, tune = keys.parse_loop_key(prefix, key), keys.parse_tune_key(prefix, key)
        alive = sample.kind == zenoh.SampleKind.PUT
        with self.lock:
            try:
                if plant is not None and plant[1] == "alive":
                    self.recorder.plant_token(plant[0], alive)
                elif tune is not None and tune[1] == "running":
                    self.recorder.run_token(tune[0], alive)
            except Exception:
                log.exception("liveliness %s failed", key)

    def _plant_restarted(self, loop: str) -> None:
        """A new plant instance of ``loop`` (on Zenoh's thread, the lock held): the history
        takes its next status as the start, asked for at once (``_ask_restarted``)."""
        self.history.plant_restarted(loop)
        if self.history.awaits_restart_status(loop):
            self._restarts.put(loop)

    def _ask_restarted(self, stop: threading.Event) -> None:
        """Ask the status of each loop whose plant restarted: its ``start`` status is put as
        the plant's session opens, lost where this logger is not yet reached (it connects
        again a moment later to a plant that held the rendezvous port), and in realtime no other
        comes until a command; the answer files the restart's change of gains at once."""
        prefix = self.recorder.prefix
        while not stop.is_set():
            try:
                loop = self._restarts.get(timeout=0.25)
            except queue.Empty:
                continue
            with self.lock:
                if not self.history.awaits_restart_status(loop):
                    continue  # its status heard live already (its own ``start``)
            for _ in range(RESTART_TRIES):
                try:
                    replies = list(self.session.get(keys.status(prefix, loop), timeout=2.0))
                except zenoh.ZError:  # the session closing as the logger stops
                    return
                self._file_statuses(replies, self.history.restart_status)
                with self.lock:
                    if not self.history.awaits_restart_status(loop):
                        break  # answered, or a live status heard meanwhile
                if stop.wait(RESTART_ASK):
                    return

    def _on_monitor(self, sample: zenoh.Sample) -> None:
        """A LoopMonitor (``<prefix>/monitor/<loop>``): appended, or counted invalid."""
        try:
            self.monitor_log.handle(str(sample.key_expr), sample.payload.to_bytes())
        except OSError as err:  # a full disk: one line, not a traceback a message
            log.error("monitor.jsonl: %s not written: %s", sample.key_expr, err.strerror or err)

    def _learn_loops(self, timeout: float = 5.0) -> None:
        """Every loop's status, asked once at start: a change of gains made while this logger
        was not running is recorded now (``unseen``), not at the loop's next status (in
        lockstep a status comes only with a command: a user's ``revert`` was refused as "no
        change on record" until one came). Statuses heard meanwhile on the bus come in order
        on the subscriber; these only teach the history what it has not seen yet."""
        try:
            replies = list(
                self.session.get(keys.status(self.recorder.prefix, keys.ANY), timeout=timeout)
            )
        except zenoh.ZError as err:  # the session closing as the logger stops
            log.warning("loops' statuses not asked at start: %s", err)
            return
        self._file_statuses(replies, self.history.learn)

    def _file_statuses(self, replies: list, take: Callable[[str, bytes], None]) -> None:
        """Each status a query was answered with, given to the change history's ``take``
        under the lock; one that fails is logged, the others taken."""
        for reply in replies:
            if reply.ok is None:
                continue
            with self.lock:
                try:
                    take(str(reply.ok.key_expr), reply.ok.payload.to_bytes())
                except Exception:
                    log.exception("the change history of %s failed", reply.ok.key_expr)

    def _ask_late_results(self, stop: threading.Event) -> None:
        """Ask the tuners for the results of runs closed "tuner lost" (``<prefix>/tune/<loop>/
        result``: the tuner answers with each loop's last): a logger paused past Zenoh's
        lease, or cut off, as a run ended never hears its result published, and recorded an
        ok run as lost. A result found goes in as if it had come late on the bus."""
        tries: dict[str, int] = {}
        prefix = self.recorder.prefix
        while not stop.wait(LATE_ASK):
            with self.lock:
                open_ = self.recorder.lost_runs()
            tries = {r: n for r, n in tries.items() if any(r == o for o, _ in open_)}  # bounded
            lost = [(r, loop) for r, loop in open_ if tries.get(r, 0) < LATE_TRIES]
            for run_id, loop in lost:
                tries[run_id] = tries.get(run_id, 0) + 1
                try:
                    replies = list(  # every tuner's, each kept (not the latest on the key)
                        self.session.get(
                            keys.tune_result(prefix, loop),
                            target=zenoh.QueryTarget.ALL,
                            consolidation=zenoh.ConsolidationMode.NONE,
                            timeout=LATE_ASK,
                        )
                    )
                except zenoh.ZError:  # the session closing as the logger stops
                    return
                for reply in replies:
                    if reply.ok is None:
                        continue
                    payload = reply.ok.payload.to_bytes()
                    try:
                        found = wire.decode(TuneResult, payload).run_id == run_id
                    except DecodeError:
                        continue
                    if found:
                        with self.lock:
                            self.recorder.handle(str(reply.ok.key_expr), payload, None)
                            try:
                                self.history.late_result(payload)
                            except Exception:
                                log.exception("the change history of run %s failed", run_id)
                        break

    def _on_query(self, query: zenoh.Query) -> None:
        with self.lock:
            wire.reply(query, keys.logger_status(self.recorder.prefix, self.node), self.status())

    def run(self, stop: threading.Event) -> None:
        prefix, shell = self.recorder.prefix, ServiceShell(self.session, log)
        # on Zenoh's receiving thread (in order, no thread woken per message): the hot path
        shell.subscribe(keys.everything(prefix), self._on_sample, CHANNEL_CAPACITY, direct=True)
        shell.queryable(keys.logger_status(prefix, self.node), self._on_query, 64)
        shell.subscribe(keys.monitor(prefix, keys.ANY), self._on_monitor, 1024)
        for pattern in (keys.loop_alive(prefix, keys.ANY), keys.tune_running(prefix, keys.ANY)):
            shell.subscribe(pattern, self._on_token, 1024, liveliness=True, history=True)
        shell.announce(keys.logger_alive(prefix, self.node))
        log.info("logger %s recording %s/** into %s", self.node, prefix, self.recorder.runs_dir)
        # a thread of the shell's, joined before the session closes: Zenoh refuses to close
        # a session a query is still using ("Already borrowed", seen in CI for the tuner's
        # like question); the question is bounded by its own timeout (5 s)
        shell.thread(self._learn_loops, name="learn-loops")
        shell.thread(lambda: self._ask_late_results(stop), name="late-results")
        shell.thread(lambda: self._ask_restarted(stop), name="restarted-plants")

        def tick() -> None:
            with self.lock:
                self.recorder.tick()

        try:
            shell.wait(stop, 0.25, tick)
        finally:
            shell.undeclare()
            shell.join(5.0)
            with self.lock:
                self.recorder.close_all()
            shell.withdraw()  # after the files are finished: up until then
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
    settings = settings_from_args(args)
    namespace = json.loads(zenoh_config(settings).get_json("namespace")) or ""
    recorder = Recorder(
        runs, args.prefix, record_replays=args.record_replays, namespace=str(namespace)
    )
    run_until_stopped(settings, lambda session: LoggerService(session, recorder, args.node))
    return 0
