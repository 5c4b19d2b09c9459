"""Drive a plant_sim loop in the same process: the LoopClient interface without the bus.

The live tuner drives a loop over Zenoh (``loop_client.LoopClient``); this drives a ``SimLoop``
object directly, with the plant service's own rules for commands (validated by the loop,
refused with its reason, counted), in lockstep. A ``TuningRun`` over it is the whole live run
— experiment, selection, apply and verify, restore — on the real plant models, thousands of
times faster than over a bus: what property tests and batch studies need.
"""

from __future__ import annotations

from services.autotuner.loop_client import CommandRefused
from services.plant_sim.simulation.loop import CommandRejected, SimLoop
from shared.messages import (
    AdvanceCommand,
    Command,
    LeaseCommand,
    LoopInfo,
    LoopStatus,
    ProcessSample,
    ReleaseCommand,
    SyncCommand,
)

NODE = "local"


class LocalLoopClient:
    """One driver's view of an in-process loop (lockstep clock)."""

    def __init__(self, loop: SimLoop, *, source: str = "autotune-local"):
        self.sim = loop
        self.loop = loop.settings.loop_id
        self.source = source
        self.info: LoopInfo = loop.info(NODE, "lockstep", 1.0)
        self.last_sample: ProcessSample | None = None
        self.last_status: LoopStatus = self.sync()
        self.lease: LeaseCommand | None = None
        self.gone = False  # an in-process loop never goes away
        self.lease_timeout = 10.0  # s; asked for, never expires in process
        self.commands: list[Command] = []  # every accepted command, in order

    @property
    def holding(self) -> bool:
        """This client holds the loop's lease (in process, nobody can take it back)."""
        return self.lease is not None

    def __enter__(self) -> LocalLoopClient:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def sync(self) -> LoopStatus:
        self.last_status = self.sim.status(NODE, "lockstep", "sync", 0)
        return self.last_status

    def query_status(self, timeout: float) -> LoopStatus:
        """The loop's status, read without a command (as a query over the bus would)."""
        return self.sim.status(NODE, "lockstep", "query")

    def send(self, cmd: Command) -> None:
        self._apply(cmd)

    def _apply(self, cmd: Command) -> None:
        sim = self.sim
        if isinstance(cmd, LeaseCommand):
            self.lease = cmd
        elif isinstance(cmd, ReleaseCommand):
            self.lease = None
        elif isinstance(cmd, AdvanceCommand):
            for _ in range(cmd.steps):
                self.last_sample = sim.advance()
        elif isinstance(cmd, SyncCommand):
            return
        else:
            try:
                sim.apply(cmd)
            except CommandRejected as err:
                sim.rejected += 1
                sim.last_reject = f"{cmd.kind}: {err.reason}"
                return
        sim.accepted += 1
        self.commands.append(cmd)

    def command(self, cmd: Command) -> LoopStatus:
        before = self.sim.rejected
        self._apply(cmd)
        status = self.sync()
        if status.rejected > before:
            raise CommandRefused(f"loop {self.loop}: {status.last_reject}")
        return status

    def advance(self, steps: int) -> list[ProcessSample]:
        out = [self.sim.advance() for _ in range(steps)]
        if out:
            self.last_sample = out[-1]
        return out

    def samples(self, steps: int) -> list[ProcessSample]:
        return self.advance(steps)

    def next_sample(self) -> ProcessSample:
        return self.advance(1)[0]
