"""Drive one plant_sim loop over Zenoh: read it, command it, step its clock.

Samples and status arrive on one FIFO subscriber (order kept) that a reader thread moves onto
a queue, so every wait is bounded: a silent plant becomes ``PlantLost``, never a hang. The
loop's liveliness token is watched too: a plant that dies or is cut off is ``PlantLost`` at
once. While the client holds the loop's lease, every status the plant publishes says who holds
it: one that no longer names this client (the plant's watchdog restored the loop, the plant
restarted) is ``LeaseLost`` at once, and so is a refusal because the lease lapsed.
"""

from __future__ import annotations

import itertools
import queue
import secrets
import threading
import time

import zenoh

from shared import keys, wire
from shared.errors import AutotuneError
from shared.messages import (
    AdvanceCommand,
    Command,
    LeaseCommand,
    LoopInfo,
    LoopStatus,
    Message,
    ProcessSample,
    ReleaseCommand,
    SyncCommand,
)

LEASE_TIMEOUT = 10.0  # s of wall time without a command before the plant restores the loop
RENEW_EVERY = 2.0  # s of wall time between lease-keeping syncs in realtime, at most
RESEND_EVERY = 1.0  # s: a sync whose answer is late is sent again (lost while reconnecting)
_GONE = "<gone>"  # inbox marker: the loop's liveliness token vanished


class PlantLost(AutotuneError):
    """The plant stopped answering."""


class CommandRefused(AutotuneError):
    """The loop refused a command; the message is the plant's reason."""


class LeaseLost(AutotuneError):
    """The plant no longer lets this client hold the loop (it restored it, or restarted)."""


def wait_for_token(session: zenoh.Session, key_expr: str, timeout: float) -> bool:
    """Block until a liveliness token matching ``key_expr`` is seen; False after ``timeout``."""
    events: queue.Queue[zenoh.Sample] = queue.Queue()
    sub = session.liveliness().declare_subscriber(
        key_expr, zenoh.handlers.FifoChannel(16), history=True
    )
    reader = threading.Thread(target=lambda: [events.put(s) for s in sub], daemon=True)
    reader.start()
    deadline = time.monotonic() + timeout
    try:
        while True:
            try:
                sample = events.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return False
            if sample.kind == zenoh.SampleKind.PUT:
                return True
    finally:
        sub.undeclare()


def wait_for_loop(session: zenoh.Session, prefix: str, loop: str, timeout: float) -> None:
    """Block until the loop's liveliness token is seen, or raise PlantLost after ``timeout``."""
    if not wait_for_token(session, keys.loop_alive(prefix, loop), timeout):
        raise PlantLost(
            f"loop {loop!r} not found: nothing announces {keys.loop_alive(prefix, loop)} "
            f"after {timeout:g} s (is `autotune plant` running, reachable and serving "
            "that loop?)"
        )


class LoopClient:
    """One driver's view of a loop. Use as a context manager."""

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        loop: str,
        *,
        source: str = "autotune",
        timeout: float = 5.0,
        lease_timeout: float = LEASE_TIMEOUT,
        user: str | None = None,
    ):
        self.session = session
        self.prefix = prefix
        self.loop = loop
        self.source = source
        self.timeout = timeout
        self.lease_timeout = lease_timeout  # what this client asks for when it leases
        self.user = user  # its authenticated Zenoh user, named in its command keys
        self._renew_every = min(RENEW_EVERY, lease_timeout / 4)
        # a silence this long (this process paused, its link re-forming) may have cost the
        # lease: it is confirmed before anything is written
        self._suspect_after = 0.4 * lease_timeout
        # every client on the bus sees every loop status: tokens start at random so that no
        # client takes another's barrier for its own (0 is the lease keeper's, never awaited)
        self._tokens = itertools.count(secrets.randbits(40) + 1)
        self._last_sent = time.monotonic()
        self._refused = 0  # our commands the plant refused so far (from its sync answers)
        self._loop_refused = 0
        self.holding = False  # this client holds the loop's lease (confirmed by the plant)
        self.gone = False  # the plant's liveliness token vanished since this client began
        self._inbox: queue.Queue[tuple[str, bytes, str]] = queue.Queue()
        self._sub = session.declare_subscriber(
            keys.loop_feed(prefix, loop), zenoh.handlers.FifoChannel(65536)
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self._alive = session.liveliness().declare_subscriber(
            keys.loop_alive(prefix, loop), zenoh.handlers.FifoChannel(64)
        )
        threading.Thread(target=self._watch_alive, daemon=True).start()
        self._pv_key = keys.pv(prefix, loop)
        self._status_key = keys.status(prefix, loop)
        self.info = self._query_info()
        self.last_sample: ProcessSample | None = None
        self.last_status: LoopStatus = self.sync()

    def _read(self) -> None:
        for s in self._sub:
            mark = s.attachment
            if mark is not None and wire.replay_source(mark.to_bytes()) is not None:
                continue  # `autotune replay` of a recorded run: not this loop's present
            self._inbox.put((str(s.key_expr), s.payload.to_bytes(), str(s.encoding)))

    def _watch_alive(self) -> None:
        """The plant's token vanishing (killed, or this client cut off from it) ends the wait
        at once: Zenoh tells in milliseconds what a timeout would in seconds."""
        for s in self._alive:
            if s.kind == zenoh.SampleKind.DELETE:
                self.gone = True
                self._inbox.put((_GONE, b"", ""))

    def close(self) -> None:
        self._sub.undeclare()
        self._alive.undeclare()

    def __enter__(self) -> LoopClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def query_status(self, timeout: float) -> LoopStatus | None:
        """The loop's status by a query: reads, sends no command (what a client that lost
        the plant may still do, to say how the loop was left once it is back in reach)."""
        return wire.query_one(
            self.session, keys.status(self.prefix, self.loop), LoopStatus, timeout
        )

    def _query_info(self) -> LoopInfo:
        info = wire.query_one(
            self.session, keys.info(self.prefix, self.loop), LoopInfo, self.timeout
        )
        if info is None:
            raise PlantLost(
                f"loop {self.loop!r}: no plant answered "
                f"{keys.info(self.prefix, self.loop)} within {self.timeout:g} s"
            )
        return info

    def _next(self, wait: float | None = None) -> Message | None:
        """The next sample or status on the loop's feed (others' too). With ``wait``, None
        when nothing comes within it; else PlantLost after ``timeout`` s of silence."""
        while True:
            try:
                key, payload, enc = self._inbox.get(timeout=self.timeout if wait is None else wait)
            except queue.Empty:
                if wait is not None:
                    return None
                raise PlantLost(
                    f"loop {self.loop!r}: no message from the plant for {self.timeout:g} s"
                ) from None
            if key == _GONE:
                self.holding = False
                self.gone = True
                raise PlantLost(
                    f"loop {self.loop!r}: lost the plant (its liveliness token "
                    f"{keys.loop_alive(self.prefix, self.loop)} vanished: the plant stopped, "
                    "or this tuner was cut off from it)"
                )
            if key == self._pv_key:
                self.last_sample = wire.decode(ProcessSample, payload, enc)
                return self.last_sample
            if key == self._status_key:
                self.last_status = status = wire.decode(LoopStatus, payload, enc)
                if self.holding and status.leased_by != self.source:
                    self.holding = False
                    raise LeaseLost(self._lost_why(status))
                return status

    def _lost_why(self, status: LoopStatus) -> str:
        if status.reason == "watchdog":
            why = "the plant's watchdog restored the loop to its state before the test"
        elif status.leased_by is not None:
            why = f"the plant says {status.leased_by!r} holds it"
        elif status.reason == "start":
            why = "the plant restarted"
        else:
            why = "the plant no longer holds it for this run"
        return f"loop {self.loop}: lease lost at t = {status.t:.6g} s: {why}"

    def send(self, cmd: Command) -> None:
        """Put ``cmd`` on the loop's command key, in this client's name (its ``source``: the
        plant renews a lease and counts refusals by it). Holding the lease after a silence
        of 40 % of its timeout (this process paused, its link re-forming), the lease is
        confirmed first: LeaseLost rather than a write to a loop the plant took back. Once
        the plant's token has vanished nothing more is sent: a plant that comes back is a new
        instance that never granted this client anything."""
        if self.gone:
            raise PlantLost(
                f"loop {self.loop!r}: the plant was lost (its liveliness token vanished); "
                f"{cmd.kind} not sent"
            )
        if (
            self.holding
            and not isinstance(cmd, SyncCommand)
            and time.monotonic() - self._last_sent > self._suspect_after
        ):
            self.sync()
        if cmd.source != self.source:
            cmd = cmd.model_copy(update={"source": self.source})
        wire.put(self.session, keys.command(self.prefix, self.loop, cmd.kind, self.user), cmd)
        self._last_sent = time.monotonic()

    def _keep_lease(self) -> None:
        """In realtime a run may send nothing for minutes (a relay half-cycle, a verification
        step): a sync every few seconds of wall time keeps the plant's lease on the loop
        alive (any command from the holder renews it), and asks for no answer."""
        if time.monotonic() - self._last_sent > self._renew_every:
            self.send(SyncCommand(loop=self.loop, token=0, source=self.source))

    def sync(self) -> LoopStatus:
        """Barrier: return the loop's status once every command sent so far is applied.

        Bounded by ``timeout`` s of wall time whatever else arrives (samples keep coming in
        realtime); a sync lost on the way (a link re-forming) is sent again every
        RESEND_EVERY s, and any of its answers will do."""
        tokens: set[int] = set()
        deadline = time.monotonic() + self.timeout
        resend = 0.0
        while True:
            now = time.monotonic()
            if now > deadline:
                raise PlantLost(
                    f"loop {self.loop!r}: no answer to a sync within {self.timeout:g} s"
                )
            if now >= resend:
                token = next(self._tokens)
                tokens.add(token)
                self.send(SyncCommand(loop=self.loop, token=token, source=self.source))
                resend = now + RESEND_EVERY
            msg = self._next(wait=max(0.0, min(resend, deadline) - time.monotonic()))
            if isinstance(msg, LoopStatus) and msg.sync_token in tokens:
                self._refused = msg.sync_rejected or 0
                self._loop_refused = msg.rejected
                return msg

    def command(self, cmd: Command) -> LoopStatus:
        """Send ``cmd`` and confirm it was applied; CommandRefused carries the plant's reason.
        The plant counts refusals per sender (a sync's answer carries ours), so another
        client's refused commands are never taken for ours."""
        before = self._refused
        if isinstance(cmd, ReleaseCommand):
            self.holding = False  # its own release's status must not read as a lost lease
        self.send(cmd)
        status = self.sync()
        mine = status.sync_rejected
        if mine is None:  # a plant that does not count by sender: the loop's counter
            if status.rejected > self._loop_refused:
                raise CommandRefused(f"loop {self.loop}: {status.last_reject}")
        elif mine > before:
            raise CommandRefused(f"loop {self.loop}: {status.sync_last_reject}")
        if isinstance(cmd, LeaseCommand):
            self.holding = status.leased_by == self.source
            if not self.holding:
                raise CommandRefused(f"loop {self.loop}: lease not granted")
        return status

    def advance(self, steps: int) -> list[ProcessSample]:
        """Lockstep: advance ``steps`` periods in one round trip; return their samples."""
        last = self.last_sample.t if self.last_sample is not None else self.last_status.t
        self.send(AdvanceCommand(loop=self.loop, steps=steps, source=self.source, t=last))
        out: list[ProcessSample] = []
        while len(out) < steps:
            msg = self._next()
            if isinstance(msg, ProcessSample):
                out.append(msg)
        return out

    def samples(self, steps: int) -> list[ProcessSample]:
        """The next ``steps`` samples, advancing the clock in lockstep, waiting in realtime."""
        if self.info.clock == "lockstep":
            return self.advance(steps)
        return [self.next_sample() for _ in range(steps)]

    def next_sample(self) -> ProcessSample:
        """The next sample: in lockstep, advance the loop one period first."""
        if self.info.clock == "lockstep":
            self.send(
                AdvanceCommand(
                    loop=self.loop,
                    steps=1,
                    source=self.source,
                    t=self.last_status.t if self.last_sample is None else self.last_sample.t,
                )
            )
        while True:
            if self.info.clock != "lockstep":
                self._keep_lease()
            msg = self._next()
            if isinstance(msg, ProcessSample):
                return msg
