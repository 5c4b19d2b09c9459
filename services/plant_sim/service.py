"""plant_sim over Zenoh: serves many loops, each announced by a liveliness token.

Every command to every loop arrives on one subscriber (``<prefix>/plant/*/cmd/*``) whose FIFO
channel keeps the senders' order, so a lockstep run is deterministic. Commands are decoded
and validated; a bad one is refused with a logged reason and counted, and changes nothing.

Clocks: *lockstep* advances a loop only on an ``advance`` command (the samples of an advance
of several periods go out as ``ProcessSamples`` on ``pv_batch``, a message per part as it is
stepped, a lone sample on ``pv``); *realtime* advances every
loop on the wall clock (times ``speed``), holding the last output between samples: the loops
of one sample time together, the linear ones as arrays (``realtime.py``).

A process may serve part of a plant file (``--loops``, ``--shard K/N``: ``shards.py``); it
refuses to start when another plant process under its prefix serves one of its loops.
"""

from __future__ import annotations

import argparse
import heapq
import logging
import math
import secrets
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import zenoh

from services.plant_sim.load_bound import LOAD_TIMEOUT, check_load_timeout, load_bound
from services.plant_sim.plant_file import default_plant_path, load_plant_file
from services.plant_sim.publishers import Publishers
from services.plant_sim.realtime import Group, RealtimeSteppers
from services.plant_sim.shards import CLAIM_TIMEOUT, check_not_served, select_loops
from services.plant_sim.simulation.loop import CommandRejected, LoopSnapshot, SimLoop
from shared import keys, wire
from shared.cli import (
    OneLineParser,
    add_common_arguments,
    check_flags,
    check_ids,
    setup_logging,
)
from shared.control.beyond import beyond
from shared.errors import AutotuneError, ConfigError, DecodeError
from shared.messages import (
    COMMANDS,
    MAX_BATCH,
    AdvanceCommand,
    ClockMode,
    LeaseCommand,
    LoopInfo,
    LoopStatus,
    Message,
    ProcessSample,
    ProcessSamples,
    ReleaseCommand,
    ServiceStatus,
    SyncCommand,
)
from shared.reject_log import RejectLog
from shared.service_shell import ServiceShell, run_until_stopped
from shared.session import settings_from_args

log = logging.getLogger("plant_sim")

SERVICE = "plant_sim"
# s between the questions to a plant process that did not answer what it serves
CLAIM_RETRY = 2.0
# s of wall time the realtime clock may fall behind before it says so, and then at most
# once in BEHIND_EVERY s
BEHIND = 1.0
BEHIND_EVERY = 30.0
CHANNEL_CAPACITY = 65536
MODEL_STALL = 10.0  # s of wall time in one model step() before the plant says it hangs


@dataclass(frozen=True)
class Encoded:
    """A message already encoded as ``model``'s JSON (a lockstep batch: ``wire.encode_samples``)."""

    model: type[Message]
    payload: bytes


Outbox = list[tuple[str, Message | Encoded]]  # what one command publishes, in order
# the rest of a long lockstep advance: steps its next part into the outbox, and returns what
# is left of it after that (None: the advance is over)
Rest = Callable[[Outbox], "Rest | None"]
# samples a lockstep advance steps before it publishes them: the asker (and the logger) read
# one part while the plant steps the next, rather than all of them after it; the first part is
# FIRST_CHUNK, each next twice the last, up to STREAM_CHUNK (the asker starts sooner)
FIRST_CHUNK = 64
STREAM_CHUNK = 256
assert STREAM_CHUNK <= MAX_BATCH  # a part is one ProcessSamples


# s of stepping in one part of an advance, once a part took twice as long (a slow user model;
# a part of a fast one is never so long): parts then keep well inside the 5 s within which the
# asker must hear from the plant
PART_SECONDS = 1.0


def _part_size(size: int, per_sample: float) -> int:
    """``size`` samples, or fewer where the loop's ``per_sample`` cost (s), measured on a part
    that took over twice PART_SECONDS, would make a part take longer than PART_SECONDS (one
    sample at least)."""
    if per_sample > 0.0:
        return max(1, min(size, int(PART_SECONDS / per_sample)))
    return size


@dataclass(frozen=True)
class ServiceOptions:
    prefix: str = keys.DEFAULT_PREFIX
    node: str = "plant"
    clock: ClockMode = "lockstep"
    speed: float = 1.0


MAX_LAPSED = 64  # lapsed supervisors remembered per loop
PAUSE_GAP = 1.0  # s between watchdog ticks (0.05 s apart) that means the plant itself paused
HELD_UP = 0.2  # s a publication has lasted that means the plant is held up behind a subscriber


@dataclass
class Lease:
    """A supervisor's hold on a loop during an experiment (the plant-side watchdog)."""

    source: str
    timeout: float  # s of wall time without a command from ``source``
    deadline: float  # time.monotonic() by which the next command must come
    snapshot: LoopSnapshot
    user: str | None = None  # the Zenoh user its commands' keys name (verified under ACL)
    pv_limits: tuple[float, float] | None = None  # realtime: restored at a PV outside them


def _sender(source: str, user: str | None) -> str:
    """Who sent a command, as refusals are counted: its source, and its user when named."""
    return source if user is None else f"{source}@{user}"


def _holder(source: str, user: str | None) -> str:
    """How refusals and logs name a supervisor: its source, and its user when known."""
    return repr(source) if user is None else f"{source!r} (user {user!r})"


class PlantService:
    """The Zenoh shell around a set of SimLoops."""

    def __init__(self, session: zenoh.Session, loops: dict[str, SimLoop], options: ServiceOptions):
        self.session = session
        self.loops = loops
        self.opt = options
        self.lock = threading.Lock()
        self.rejected_by_reason: Counter[str] = Counter()
        self._per_sample: dict[str, float] = {}  # s a lockstep sample of each loop last took
        self.accepted = 0
        self.overruns = 0
        self._remote_loops: set[str] = set()
        self._log_reject = RejectLog(log)
        self.leases: dict[str, Lease] = {}
        self._stalled: set[str] = set()  # loops whose model step() hangs, said once each
        # loop → {source: why}: supervisors whose lease the plant ended (it restored the loop);
        # their commands are refused until they lease again, so a tuner that missed the news
        # (paused, cut off) cannot drive a loop it no longer holds
        self.lapsed: dict[str, dict[str, str]] = {}
        # this process's identity among plant instances (LoopInfo.instance)
        self.instance = secrets.token_hex(6)
        self.started = time.time()  # wall clock: of two processes on one loop, the later stops
        # why this process stops (another, started before it, serves one of its loops)
        self.yielded: str | None = None
        self._stop: threading.Event | None = None
        # the start's check is over (``_claim_ok``: passed); the watch waits for it, so that
        # a process the check refuses says it once, in the check's words
        self._claimed = threading.Event()
        self._claim_ok = False
        self._gone_instances: set[str] = set()  # other plant runs whose token went
        self.publishers = Publishers(session)
        # realtime: the loops stepped by sample time, linear ones as arrays; a loop is read or
        # changed only checked out of them (``_fresh``), and taken back by ``_settle``
        self.steppers = RealtimeSteppers(loops) if options.clock == "realtime" else None
        self._pv_keys = {lid: keys.pv(options.prefix, lid) for lid in loops}

    def _fresh(self, loop_id: str) -> SimLoop:
        """The loop, exact (realtime: checked out of its batch until ``_settle``)."""
        if self.steppers is not None:
            return self.steppers.check_out(loop_id)
        return self.loops[loop_id]

    def _settle(self) -> None:
        """Take what commands changed in the loops checked out back into the batches."""
        if self.steppers is not None:
            self.steppers.check_in()

    # --- messages -------------------------------------------------------------------------

    def loop_status(
        self,
        loop: SimLoop,
        reason: str,
        token: int | None = None,
        source: str | None = None,
        by: tuple[str, str | None] | None = None,
    ) -> LoopStatus:
        """The loop's status; ``by``: the (source, key user) of the command that caused it."""
        lease = self.leases.get(loop.settings.loop_id)
        status = loop.status(
            self.opt.node, self.opt.clock, reason, token, source, lease.source if lease else None
        )
        update = {}
        if lease is not None and lease.user is not None:
            update["lease_user"] = lease.user
        if by is not None:
            update["by_source"], update["by_user"] = by
        return status.model_copy(update=update) if update else status

    def loop_info(self, loop: SimLoop) -> LoopInfo:
        info = loop.info(self.opt.node, self.opt.clock, self.opt.speed)
        return info.model_copy(update={"instance": self.instance})

    def service_status(self) -> ServiceStatus:
        return ServiceStatus(
            node=self.opt.node,
            clock=self.opt.clock,
            speed=self.opt.speed,
            loops=(
                self.steppers.times()
                if self.steppers is not None
                else {lid: lp.t for lid, lp in self.loops.items()}
            ),
            accepted=self.accepted,
            rejected=sum(self.rejected_by_reason.values()),
            rejected_by_reason=dict(self.rejected_by_reason),
            overruns=self.overruns,
            instance=self.instance,
            started=self.started,
        )

    def _publish(self, out: Outbox) -> None:
        for key, msg in out:
            if isinstance(msg, Encoded):
                self.publishers.put_json(key, msg.model, msg.payload)
            else:
                self.publishers.put(key, msg)

    # --- commands -------------------------------------------------------------------------

    def _reject(
        self,
        loop: SimLoop | None,
        category: str,
        reason: str,
        out: Outbox,
        source: str | None = None,
    ) -> None:
        self.rejected_by_reason[category] += 1
        where = f"loop {loop.settings.loop_id}: " if loop else ""
        self._log_reject(category, where + reason)
        if loop is not None:
            loop.rejected += 1
            loop.last_reject = reason
            if source is not None:
                loop.refused(source, reason)
            out.append(
                (
                    keys.status(self.opt.prefix, loop.settings.loop_id),
                    self.loop_status(loop, "reject"),
                )
            )

    def handle_command(self, key: str, payload: bytes, encoding: str | None) -> None:
        """Validate and apply one command, then publish what it caused; a long lockstep
        advance part by part (``_advance``), each published before the next is stepped."""
        out: Outbox = []
        with self.lock:
            try:
                rest = self._handle(key, payload, encoding, out)
            finally:
                self._settle()
        self._publish(out)
        while rest is not None:
            out = []
            with self.lock:
                rest = rest(out)
            self._publish(out)

    def _handle(self, key: str, payload: bytes, encoding: str | None, out: Outbox) -> Rest | None:
        prefix = self.opt.prefix
        parsed = keys.parse_command(prefix, key)
        if parsed is None:
            self._reject(None, "key", f"unexpected key {key!r}", out)
            return
        loop_id, kind, user = parsed  # user: verified by the router's ACL when deployed secure
        loop = self._fresh(loop_id) if loop_id in self.loops else None
        if loop is None:
            if loop_id not in self._remote_loops:
                self._reject(
                    None,
                    "unknown_loop",
                    f"unknown loop {loop_id!r} (this plant serves {', '.join(self.loops)})",
                    out,
                )
            return
        model = COMMANDS.get(kind)
        if model is None:
            self._reject(
                loop,
                "kind",
                f"unknown command {kind!r}; expected one of {', '.join(COMMANDS)}",
                out,
            )
            return
        try:
            cmd = wire.decode(model, payload, encoding)
        except DecodeError as err:
            self._reject(loop, "malformed", f"{kind}: {err}", out)
            return
        sender = _sender(cmd.source, user)  # refusals and lapses are counted by it
        if cmd.loop != loop_id:
            self._reject(
                loop,
                "loop_mismatch",
                f"{kind}: payload names loop {cmd.loop!r} but was sent to {loop_id!r}",
                out,
                sender,
            )
            return
        lease = self.leases.get(loop_id)
        holder = lease is not None and (cmd.source, user) == (lease.source, lease.user)
        if lease is not None and holder:
            lease.deadline = time.monotonic() + lease.timeout
        if lease is not None and not holder and not isinstance(cmd, SyncCommand):
            # exclusive: one supervisor at a time drives a leased loop, and only it lets go
            # (two tuners on one loop snapshotted each other's test as the state to restore);
            # the holder is its source *and* the user its key names, so that under access
            # control a session cannot pass for another by writing its source
            self._reject(
                loop,
                "leased",
                f"{kind} refused: the loop is leased by {_holder(lease.source, lease.user)}",
                out,
                sender,
            )
            return
        lapsed = self.lapsed.get(loop_id, {})
        lease_kinds = LeaseCommand | ReleaseCommand | SyncCommand
        if sender in lapsed and not isinstance(cmd, lease_kinds):
            self._reject(
                loop,
                "lapsed",
                f"{kind} refused: {cmd.source!r} no longer holds the loop ({lapsed[sender]}; "
                "the plant restored it to its state before the test)",
                out,
                sender,
            )
            return
        if isinstance(cmd, LeaseCommand):
            lapsed.pop(sender, None)
            if lease is None:  # a holder renewing keeps the snapshot of before its test
                self.leases[loop_id] = Lease(
                    cmd.source,
                    cmd.timeout,
                    time.monotonic() + cmd.timeout,
                    loop.snapshot(),
                    user,
                    cmd.pv_limits,
                )
                log.info("loop %s leased by %s", loop_id, _holder(cmd.source, user))
            else:  # its limits as the holder names them now
                lease.pv_limits = cmd.pv_limits
            out.append(
                (
                    keys.status(prefix, loop_id),
                    self.loop_status(loop, "lease", by=(cmd.source, user)),
                )
            )
        elif isinstance(cmd, ReleaseCommand):
            lapsed.pop(sender, None)
            held = self.leases.pop(loop_id, None)
            if held is not None and cmd.restore:  # its holder could not confirm its restore
                loop.restore(held.snapshot)
                if loop.fault is not None:  # as ``_end_lease`` says it: not its state before
                    log.warning(
                        "loop %s released by %s, its restore unconfirmed: its setpoint and "
                        "gains restored, but it is faulted (%s) and stays in manual at op %.4g "
                        "%% (it was %s at op %.4g %% before the experiment)",
                        loop_id,
                        _holder(cmd.source, user),
                        loop.fault,
                        loop.op,
                        held.snapshot.mode,
                        held.snapshot.op,
                    )
                else:
                    log.warning(
                        "loop %s released by %s, its restore unconfirmed: restored to its "
                        "state before the experiment (%s, op %.4g %%)",
                        loop_id,
                        _holder(cmd.source, user),
                        held.snapshot.mode,
                        held.snapshot.op,
                    )
            elif held is not None:
                log.info("loop %s released by %s", loop_id, _holder(cmd.source, user))
            status = self.loop_status(loop, "release", by=(cmd.source, user))
            out.append((keys.status(prefix, loop_id), status))
        elif isinstance(cmd, AdvanceCommand):
            if self.opt.clock != "lockstep":
                self._reject(
                    loop, "clock", "advance refused: the plant runs in realtime", out, sender
                )
                return
            rest = self._advance(loop, cmd, lease, out)
            loop.accepted += 1
            self.accepted += 1
            return rest
        elif isinstance(cmd, SyncCommand):
            out.append(
                (
                    keys.status(prefix, loop_id),
                    self.loop_status(loop, "sync", cmd.token, sender),
                )
            )
            return
        else:
            try:
                loop.apply(cmd)
            except CommandRejected as err:
                self._reject(loop, err.category, f"{kind}: {err.reason}", out, sender)
                return
            status = self.loop_status(loop, kind, by=(cmd.source, user))
            out.append((keys.status(prefix, loop_id), status))
        loop.accepted += 1
        self.accepted += 1

    def _advance(
        self, loop: SimLoop, cmd: AdvanceCommand, lease: Lease | None, out: Outbox
    ) -> Rest | None:
        """Step a lockstep advance's first part (``FIRST_CHUNK`` samples) into ``out``; the rest
        of it (None: it is over). It ends early with the sample its stops name (a relay's next
        decision, a verification record's end). Between parts the lock is let go, and the
        advance goes on only while the loop is held as it was when it began (a lease that
        expired or changed hands meanwhile ends it: the loop is no longer its asker's). While
        the plant steps for the lease's holder, the holder is not silent but waiting: each
        part renews its lease's deadline (a record of 100,000 samples of a slow model can
        outlast the lease's timeout; its commands queue behind the advance meanwhile)."""
        prefix, loop_id = self.opt.prefix, loop.settings.loop_id
        test = cmd.stop_test() if cmd.banded else None
        stopped = False

        def ends(pv: float, op: float) -> bool:
            nonlocal stopped
            stopped = test(pv, op)
            return stopped

        left = cmd.steps
        # a part takes PART_SECONDS of stepping at most, by the loop's last cost per sample: a
        # model whose step() takes 20 ms stepped 256 samples (5.1 s) between two messages, and
        # its tuner, silent-plant bound 5 s, aborted a healthy run (helper trial F)
        per = self._per_sample.get(loop_id, 0.0)
        size = _part_size(FIRST_CHUNK, per)

        def part(out: Outbox) -> Rest | None:
            nonlocal left, size
            if self.leases.get(loop_id) is not lease:
                return None
            if lease is not None:  # its holder asked for this advance (others are refused)
                lease.deadline = max(lease.deadline, time.monotonic() + lease.timeout)
            had = loop.fault
            first = left == cmd.steps
            began = time.monotonic()
            # (and a slow model's part ends PART_SECONDS into it, however slow its first)
            rows = loop.advance_rows(min(left, size), ends if test else None, began + PART_SECONDS)
            took = time.monotonic() - began
            if rows and took > 2.0 * PART_SECONDS:  # a slow model (not a fast one's hiccup)
                self._per_sample[loop_id] = took / len(rows)
            left -= len(rows)
            size = _part_size(min(2 * size, STREAM_CHUNK), self._per_sample.get(loop_id, 0.0))
            if first and len(rows) == 1 and (stopped or not left):
                out.append((keys.pv(prefix, loop_id), ProcessSample(**rows[0])))
            elif rows:  # one message per part: a message's cost on the bus is per message
                payload = wire.encode_samples(loop_id, rows)
                out.append((keys.pv_batch(prefix, loop_id), Encoded(ProcessSamples, payload)))
            if loop.fault and not had:  # the model failed: say so once, on the status
                out.append((keys.status(prefix, loop_id), self.loop_status(loop, "fault")))
            return part if rows and left > 0 and not stopped else None

        return part(out)

    # --- threads --------------------------------------------------------------------------

    def _on_command(self, sample: zenoh.Sample) -> None:
        mark = sample.attachment
        source = wire.replay_source(mark.to_bytes()) if mark is not None else None
        if source is not None:  # `autotune replay --with-commands`: a recording, no operator
            # (a replay on the live prefix leased flow1 under the recorded run's id, stepped
            # its valve to 55 % and left that run's gains on it, filed in the change history
            # as the run's: helper trial)
            with self.lock:
                # counted against its loop too (`autotune loops LOOP --json`: rejected,
                # last_reject), which said 0 refusals after a replay's 200 commands; its
                # status not published (a replay's commands answered on the live bus)
                parsed = keys.parse_command(self.opt.prefix, str(sample.key_expr))
                loop = self._fresh(parsed[0]) if parsed and parsed[0] in self.loops else None
                try:
                    self._reject(
                        loop,
                        "replay",
                        f"{sample.key_expr}: a command replayed from {source} (autotune "
                        "replay): never applied",
                        [],
                    )
                finally:
                    self._settle()
            return
        try:
            self.handle_command(
                str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding)
            )
        except Exception:  # a broken user model must not take the service down
            log.exception("command on %s failed", sample.key_expr)
            with self.lock:
                self.rejected_by_reason["internal"] += 1

    def _on_query(self, query: zenoh.Query, what: str) -> None:
        try:
            with self.lock:
                try:
                    replies = self._answer(query.key_expr, what)
                finally:
                    if self.steppers is not None:  # read only: nothing to take back
                        self.steppers.release()
            for key, msg in replies:
                wire.reply(query, key, msg)
        except Exception:
            log.exception("query %s failed", query.selector)

    def _answer(self, asked: zenoh.KeyExpr, what: str) -> Outbox:
        prefix = self.opt.prefix
        if what == "service":
            return [(keys.service_status(prefix, SERVICE, self.opt.node), self.service_status())]
        replies: Outbox = []
        for loop_id, loop in self.loops.items():
            key = keys.status(prefix, loop_id) if what == "status" else keys.info(prefix, loop_id)
            if asked.intersects(zenoh.KeyExpr(key)):
                loop = self._fresh(loop_id)
                msg = self.loop_status(loop, "query") if what == "status" else self.loop_info(loop)
                replies.append((key, msg))
        return replies

    def _on_peer(self, sample: zenoh.Sample) -> None:
        """Track loops served by other plant_sim processes, so their commands are not ours."""
        parsed = keys.parse_loop_key(self.opt.prefix, str(sample.key_expr))
        if parsed is None or parsed[0] in self.loops:
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._remote_loops.add(parsed[0])
            else:
                self._remote_loops.discard(parsed[0])

    def expire_lease(self, loop_id: str, why: str) -> None:
        """Restore a leased loop to its pre-experiment state (the supervisor is gone)."""
        out: Outbox = []
        with self.lock:
            self._end_lease(loop_id, why, out)
        self._publish(out)

    def _end_lease(self, loop_id: str, why: str, out: Outbox) -> None:
        """``expire_lease`` under the lock, its status added to ``out`` to publish: ended in
        the same hold of the lock as the look that found it due (a lease released and taken
        by another between the two was ended in the newcomer's name, review)."""
        lease = self.leases.pop(loop_id, None)
        if lease is None:
            return
        loop = self._fresh(loop_id)
        loop.restore(lease.snapshot)
        lapsed = self.lapsed.setdefault(loop_id, {})
        lapsed[_sender(lease.source, lease.user)] = f"its lease ended at t = {loop.t:.6g} s: {why}"
        while len(lapsed) > MAX_LAPSED:  # bounded: the oldest are forgotten first
            lapsed.pop(next(iter(lapsed)))
        status = self.loop_status(loop, "watchdog").model_copy(update={"ended": why[:400]})
        out.append((keys.status(self.opt.prefix, loop_id), status))
        self._settle()
        if loop.fault is not None:  # restore leaves a faulted loop in manual at its output
            log.warning(
                "loop %s: %s; its setpoint and gains restored, but it is faulted (%s) and "
                "stays in manual at op %.4g %% (it was %s at op %.4g %% before the experiment)",
                loop_id,
                why,
                loop.fault,
                loop.op,
                lease.snapshot.mode,
                lease.snapshot.op,
            )
            return
        log.warning(
            "loop %s: %s; restored to its state before the experiment (%s, op %.4g %%)",
            loop_id,
            why,
            lease.snapshot.mode,
            lease.snapshot.op,
        )

    def _watchdog(self, stop: threading.Event) -> None:
        """Expire leases whose holder fell silent. A plant that was itself paused (SIGSTOP, a
        suspended VM), or held up publishing behind a subscriber that stopped reading (a
        paused logger: a lockstep advance's samples block, and the commands queued behind
        them wait), heard nobody meanwhile: that time is added to every deadline rather than
        blamed on the supervisors."""
        last = time.monotonic()
        while not stop.wait(0.05):
            now = time.monotonic()
            paused, last = now - last, now
            self._check_leases(now, paused)

    def _model_watch(self, stop: threading.Event) -> None:
        """``_watch_models`` every second, on a thread of its own (the lease watchdog waits
        on the lock a hung model holds), and the count of refusals left unlogged."""
        while not stop.wait(1.0):
            self._watch_models(time.monotonic())
            self._log_reject.flush(time.monotonic())

    def _watch_models(self, now: float) -> None:
        """Say (once a hang) which loop's model has not returned from its step() for
        MODEL_STALL s: it holds the plant's lock, so every loop of this process waits on it
        (the watchdog below too), and no other line would tell why. Read without the lock."""
        for lid, loop in self.loops.items():
            since = loop.stepping_since
            if since is None or now - since < MODEL_STALL:
                self._stalled.discard(lid)
            elif lid not in self._stalled:
                self._stalled.add(lid)
                log.error(
                    "loop %s: its model's step() has not returned for %.0f s: every loop of "
                    "this plant process waits on it (a model that may block is best served by "
                    "a plant process of its own: --loops)",
                    lid,
                    now - since,
                )

    def _check_leases(self, now: float, paused: float) -> None:
        """One watchdog tick at monotonic time ``now``, ``paused`` s after the last: expire
        the leases past their deadline, after adding a pause of the plant (or a hold-up
        behind a subscriber) to every deadline."""
        held = self.publishers.held_since()
        held_up = held is not None and now - held > HELD_UP
        out: Outbox = []
        with self.lock:
            if paused > PAUSE_GAP or held_up:
                for ls in self.leases.values():
                    ls.deadline += paused
            late = [lid for lid, ls in self.leases.items() if now > ls.deadline]
            for lid in late:
                self._end_lease(lid, "no command from its supervisor within the lease timeout", out)
        self._publish(out)

    def _on_run_token(self, sample: zenoh.Sample) -> None:
        """A supervisor's run token vanishing (killed, disconnected) expires its lease."""
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        parsed = keys.parse_tune_key(self.opt.prefix, str(sample.key_expr))
        if parsed is not None and parsed[1] == "running" and parsed[0] in self.loops:
            self.expire_lease(parsed[0], "its supervisor's run token disappeared")

    def _pace(self, stop: threading.Event) -> None:
        """Realtime clock: advance the loops of each sample time together when their next
        sample is due on the wall clock (k·T/speed after the start, never accumulated)."""
        steppers = self.steppers
        assert steppers is not None
        groups = steppers.groups
        period = [g.sample_time / self.opt.speed for g in groups]
        start = time.monotonic()
        due = [(period[i], 1, i) for i in range(len(groups))]  # (time, sample k, group)
        heapq.heapify(due)
        said = -math.inf  # wall time of the last word that the clock falls behind
        while not stop.is_set():
            at, k, i = due[0]
            wait = start + at - time.monotonic()
            if wait > 0 and stop.wait(wait):
                break
            if -wait > BEHIND and time.monotonic() - said > BEHIND_EVERY:
                # a model slower than its period: sim time runs slower than asked, and
                # nothing said so (a 20 ms step at ×20 kept ×10: helper trial)
                said = time.monotonic()
                log.warning(
                    "the realtime clock is %.3g s of wall time behind at ×%g: the loops' "
                    "steps take longer than their periods allow (or this process did not run), "
                    "so sim time runs slower than asked (%d sample(s) late so far)",
                    -wait,
                    self.opt.speed,
                    self.overruns,
                )
            self.tick(groups[i], late=-wait > period[i])
            heapq.heapreplace(due, ((k + 1) * period[i], k + 1, i))

    def tick(self, group: Group, late: bool = False) -> None:
        """Realtime: one period of ``group``'s loops (``late``: past its due time, counted as
        overruns), their samples published, then any model failure on its status, then the
        leases ended at a PV outside their limits (after the sample that crossed them, as
        their holders read them)."""
        steppers = self.steppers
        assert steppers is not None
        prefix = self.opt.prefix
        ended: Outbox = []
        with self.lock:
            self.overruns += group.size * int(late)
            tick = steppers.tick(group)
            faulted = [(lp.settings.loop_id, self.loop_status(lp, "fault")) for lp in tick.faulted]
            if self.leases:
                for lid, why in self._outside_limits():
                    self._end_lease(lid, why, ended)
        for lid, payload in tick.samples:
            self.publishers.put_json(self._pv_keys[lid], ProcessSample, payload)
        for lid, status in faulted:  # the model failed: say so once, on the status
            self.publishers.put(keys.status(prefix, lid), status)
        self._publish(ended)

    def _outside_limits(self) -> list[tuple[str, str]]:
        """Realtime, under the lock after a tick: the leased loops whose PV is outside their
        lease's limits, each with why its lease ends (the plant restores them at once: their
        supervisor would abort there, but may be paused or stalled)."""
        assert self.steppers is not None
        out = []
        for lid, lease in self.leases.items():
            if lease.pv_limits is None:
                continue
            lo, hi = lease.pv_limits
            pv = self.steppers.latest(lid)
            if not lo <= pv <= hi:
                out.append(
                    (
                        lid,
                        f"the PV {beyond(pv, lo, hi)} left the experiment's limits "
                        f"[{lo:g}, {hi:g}]",
                    )
                )
                continue
            # the transmitter clips the PV at its range's ends: limits at or past an end (the
            # default, the range itself) are left where the PV sits at that end
            r_lo, r_hi = self.loops[lid].settings.pv_range
            if (pv <= r_lo and lo <= r_lo) or (pv >= r_hi and hi >= r_hi):
                out.append(
                    (
                        lid,
                        f"the PV {pv:g} reached an end of its range [{r_lo:g}, {r_hi:g}]: "
                        f"clipped there, it may be past the experiment's limits "
                        f"[{lo:g}, {hi:g}] unseen",
                    )
                )
        return out

    def run(self, stop: threading.Event) -> None:
        """Serve until ``stop`` is set; undeclare everything on the way out."""
        prefix, shell = self.opt.prefix, ServiceShell(self.session, log)
        # first the claim: what this process serves, answered before any command is taken;
        # another process serving one of its loops makes it refuse to start
        self._stop = stop
        service_key = keys.service_status(prefix, SERVICE, self.opt.node)
        shell.queryable(service_key, partial(self._on_query, what="service"), 1024)
        # and watched for as long as it serves: a process whose claim this one's check did
        # not yet see (two started within milliseconds: both served a loop, 3 tries in 10)
        # is found when its instance token reaches this one (``_on_plant``)
        shell.subscribe(
            keys.service_instance(prefix, SERVICE, keys.ANY, keys.ANY),
            self._on_plant,
            64,
            liveliness=True,
            history=True,
        )
        try:
            check_not_served(self.session, prefix, set(self.loops))
            self._claim_ok = True
            # announced once the check passed: a process it refuses never claimed (the others
            # logged that one "also serves" their loops and "stops": review)
            shell.announce(keys.service_instance(prefix, SERVICE, self.opt.node, self.instance))
        except ConfigError:
            self._claimed.set()
            shell.withdraw()
            shell.undeclare()
            shell.join(2.0)
            raise
        self._claimed.set()
        # the declarations below cost time in proportion to those made before (Zenoh's
        # routing tables): the one-off start statuses go first, while there are few
        for lid, lp in self.loops.items():
            wire.put(self.session, keys.status(prefix, lid), self.loop_status(lp, "start"))
        if self.opt.clock == "realtime":
            self.publishers.declare([keys.pv(prefix, lid) for lid in self.loops], ProcessSample)
        # on Zenoh's receiving thread: a lockstep round trip's command wakes no thread of ours
        shell.subscribe(keys.all_commands(prefix), self._on_command, CHANNEL_CAPACITY, direct=True)
        shell.subscribe(
            keys.loop_alive(prefix, keys.ANY), self._on_peer, 1024, liveliness=True, history=True
        )
        for what, key in (
            ("status", keys.status(prefix, keys.ANY)),
            ("info", keys.info(prefix, keys.ANY)),
        ):
            shell.queryable(key, partial(self._on_query, what=what), 1024)
        shell.subscribe(
            keys.tune_running(prefix, keys.ANY), self._on_run_token, 1024, liveliness=True
        )
        shell.thread(lambda: self._watchdog(stop), name="watchdog")
        shell.thread(lambda: self._model_watch(stop), name="model-watch")
        if self.opt.clock == "realtime":
            shell.thread(lambda: self._pace(stop), name="clock")
        for lid in self.loops:
            shell.announce(keys.loop_alive(prefix, lid))
        shell.announce(keys.service_alive(prefix, SERVICE, self.opt.node))
        log.info(
            "serving %s (%s clock%s) under %s/plant/",
            _some(list(self.loops)),
            self.opt.clock,
            f", ×{self.opt.speed:g}" if self.opt.clock == "realtime" else "",
            prefix,
        )
        try:
            shell.wait(stop, 0.5)
        finally:
            shell.withdraw()
            shell.undeclare()
            shell.join(2.0)
            self.publishers.close()
            log.info(
                "stopped: %d commands applied, %d refused",
                self.accepted,
                sum(self.rejected_by_reason.values()),
            )
        if self.yielded is not None:
            raise ConfigError(self.yielded)

    def _on_plant(self, sample: zenoh.Sample) -> None:
        """Another plant process's run appeared: if it serves one of this process's loops,
        the later started of the two stops (exit 2, naming the other), and the other says so
        in its log. Why not both: each loop stays served; a tie on the start time goes by
        the instance ids, which both compare the same way."""
        prefix = self.opt.prefix
        parsed = keys.parse_service_instance(prefix, SERVICE, str(sample.key_expr))
        if parsed is None or parsed[1] == self.instance:
            return
        if sample.kind != zenoh.SampleKind.PUT:
            self._gone_instances.add(parsed[1])
            return
        if not self._claimed.wait(2.0 * CLAIM_TIMEOUT) or not self._claim_ok:
            return  # refused at the start, in the check's words
        if not self._judge_claim(*parsed):
            # no answer (a process paused, or starved): asked again while its token lives,
            # so that one paused through this one's start is judged once it runs (both had
            # served its loops when it resumed: review)
            threading.Thread(
                target=self._ask_again, args=parsed, name="plant-claim", daemon=True
            ).start()

    def _ask_again(self, node: str, instance: str) -> None:
        """``_judge_claim`` every ``CLAIM_RETRY`` s until the process answers, its token goes
        or this one stops."""
        stop = self._stop
        while stop is not None and not stop.wait(CLAIM_RETRY):
            if instance in self._gone_instances or self._judge_claim(node, instance):
                return

    def _judge_claim(self, node: str, instance: str) -> bool:
        """Ask plant process ``node``'s run ``instance`` what it serves and act on it (the
        later started of two on one loop stops); False where it did not answer."""
        key = keys.service_status(self.opt.prefix, SERVICE, node)
        answers = wire.query_all(self.session, key, ServiceStatus, CLAIM_TIMEOUT)
        other = next((st for st in answers if st.instance == instance), None)
        if other is None:
            return False
        both = sorted(set(other.loops) & set(self.loops))
        if not both:
            return True
        theirs = (other.started if other.started is not None else 0.0, instance)
        if theirs < (self.started, self.instance):
            self.yielded = (
                f"loop(s) {_some(both)} also served by plant process {node!r} (instance "
                f"{instance}), started {self.started - theirs[0]:.3g} s before this one: this "
                "process stops (each loop must be served by one process: split the plant "
                "file with --loops or --shard K/N)"
            )
            log.error("%s", self.yielded)
            if self._stop is not None:
                self._stop.set()
        else:
            log.warning(
                "plant process %r (instance %s), started after this one, also serves loop(s) "
                "%s: it stops",
                node,
                instance,
                _some(both),
            )
        return True


def _some(ids: list[str], limit: int = 20) -> str:
    """The ids, the first ``limit`` of them and the count when there are more."""
    if len(ids) <= limit:
        return ", ".join(ids)
    return f"{len(ids)} loops ({', '.join(ids[:limit])}, …)"


# --- command line ---------------------------------------------------------------------------

HELP = "run the plant simulator service (plant_sim)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--plant",
        metavar="FILE",
        help="plant file (TOML) defining the loops (default: one loop of every "
        "preset: hx1, hx2, lvl1, lvl2, flow1)",
    )
    parser.add_argument(
        "--seed", type=int, help="seed for every loop's noise (overrides the plant file's)"
    )
    parser.add_argument(
        "--load-timeout",
        type=float,
        default=LOAD_TIMEOUT,
        metavar="S",
        help="wall s the plant file's models may take to load; a model that blocks longer is "
        "refused, one line, exit 2 (default: %(default)s)",
    )
    parser.add_argument(
        "--noise-std",
        type=float,
        metavar="SIGMA",
        help="measurement noise of every loop, PV units (overrides the plant file)",
    )
    parser.add_argument(
        "--clock",
        choices=("lockstep", "realtime"),
        default="lockstep",
        help="lockstep: loops advance only when their driver says so; realtime: "
        "paced by the wall clock (default: %(default)s)",
    )
    parser.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="realtime speed-up of the wall clock (default: %(default)s)",
    )
    parser.add_argument(
        "--node", default="plant", help="this process's id on the bus (default: %(default)s)"
    )
    parser.add_argument(
        "--loops",
        metavar="ID,...",
        help="serve only these loops of the plant file (the others: another plant process)",
    )
    parser.add_argument(
        "--shard",
        metavar="K/N",
        help="serve the K-th of N shares of the plant file's loops, dealt round-robin in "
        "file order (run N processes, K = 1 … N)",
    )
    add_common_arguments(parser)


def options_from_args(args: argparse.Namespace) -> ServiceOptions:
    if not args.speed > 0 or args.speed != args.speed or args.speed == float("inf"):
        raise ConfigError(f"--speed {args.speed}: must be a finite number > 0")
    check_ids(args.prefix, node=args.node)
    return ServiceOptions(prefix=args.prefix, node=args.node, clock=args.clock, speed=args.speed)


def run(args: argparse.Namespace) -> int:
    check_flags("plant", args)
    setup_logging(args.verbose + 1, SERVICE)
    options = options_from_args(args)
    if args.noise_std is not None and not 0 <= args.noise_std < float("inf"):
        raise ConfigError(f"--noise-std {args.noise_std}: must be a finite number ≥ 0")
    check_load_timeout(args.load_timeout)
    path = args.plant or default_plant_path()
    with load_bound(args.load_timeout, f"plant file {path}"):
        loops = load_plant_file(
            path,
            seed=args.seed,
            noise_std=args.noise_std,
            select=lambda ids: select_loops(ids, args.loops, args.shard),
        )
    run_until_stopped(
        settings_from_args(args), lambda session: PlantService(session, loops, options)
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m services.plant_sim", description=__doc__)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except AutotuneError as err:
        print(f"plant_sim: error: {err}", flush=True, file=sys.stderr)
        return 2
