"""Drive a plant_sim loop in the same process: the LoopClient interface without the bus.

The live tuner drives a loop over Zenoh (``loop_client.LoopClient``); this drives a ``SimLoop``
object directly, with the plant service's own rules for commands (validated by the loop,
refused with its reason, counted), in lockstep. A ``TuningRun`` over it is the whole live run
— experiment, selection, apply and verify, restore — on the real plant models, thousands of
times faster than over a bus: what property tests and batch studies need.

``SimLoopPort`` and ``ModelPort`` are the experiment driver's view (``identify.driver``) of a
loop in the same process: a plant_sim loop whose PID block holds what it is told, and a bare
plant model driven open loop, noise added.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.autotuner.identify.driver import until_band
from services.autotuner.identify.experiments import Band, Demand
from services.autotuner.loop_client import CommandRefused, LoopFaulted
from services.plant_sim.simulation.loop import CommandRejected, LoopSnapshot, SimLoop
from services.plant_sim.simulation.models import ProcessModel
from shared.messages import (
    AdvanceCommand,
    Command,
    GainsCommand,
    LeaseCommand,
    LoopInfo,
    LoopStatus,
    OutputCommand,
    PidGains,
    ProcessSample,
    RecordStops,
    ReleaseCommand,
    SetpointCommand,
    SyncCommand,
)

NODE = "local"


class LocalLoopClient:
    """One driver's view of an in-process loop (lockstep clock)."""

    def __init__(self, loop: SimLoop, *, source: str = "autotune-local"):
        self.sim = loop
        self.loop = loop.settings.loop_id
        self.source = source
        self.user: str | None = None  # no Zenoh user in process (``LoopClient.user``)
        self.info: LoopInfo = loop.info(NODE, "lockstep", 1.0)
        self.last_sample: ProcessSample | None = None
        self.last_status: LoopStatus = self.sync()
        self.applied_t: float | None = None  # as ``LoopClient.applied_t``
        self.lease: LeaseCommand | None = None
        self._held_from: LoopSnapshot | None = None  # the loop as the lease found it
        self.gone = False  # an in-process loop never goes away
        self.lease_timeout = 10.0  # s; asked for, never expires in process
        self.commands: list[Command] = []  # every accepted command, in order
        self._fault_note: str | None = None  # a fault the last advance ended at, to tell

    @property
    def holding(self) -> bool:
        """This client holds the loop's lease (in process, nobody can take it back)."""
        return self.lease is not None

    @property
    def fault(self) -> str | None:
        """The loop's fault, if its model failed (``LoopClient.fault``, read in process)."""
        return self.sim.fault

    def __enter__(self) -> LocalLoopClient:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def renew_lease(self) -> None:
        """Nothing to renew: a loop in this process has no watchdog."""

    def check_plant(self) -> None:
        """Nothing to lose: the loop is in this process. A fault the last advance ended at is
        told here (once), as the bus client tells it at the status after those samples."""
        note, self._fault_note = self._fault_note, None
        if note is not None:
            raise LoopFaulted(note)

    def hold_arrived(self) -> list[ProcessSample]:
        """None: the loop in this process steps only when asked, never while the run
        computes (``TuningRun._watch_limits``, asked on the realtime clock of a step that
        outlasts its first check: a test's loop that says it is realtime took the run down
        when the design took over a quarter of a second on a loaded machine)."""
        return []

    def sync(self) -> LoopStatus:
        self.last_status = self.sim.status(NODE, "lockstep", "sync", 0)
        return self.last_status

    def query_status(self, timeout: float) -> LoopStatus:
        """The loop's status, read without a command (as a query over the bus would)."""
        return self.sim.status(NODE, "lockstep", "query")

    def query_info(self, timeout: float) -> LoopInfo:
        """The loop's info (as a query over the bus would): the same plant, always."""
        return self.info

    def send(self, cmd: Command) -> None:
        self._apply(cmd)

    def _apply(self, cmd: Command) -> None:
        sim = self.sim
        if isinstance(cmd, LeaseCommand):
            if self.lease is None:  # a renewal keeps the snapshot, as the plant's does
                self._held_from = sim.snapshot()
            self.lease = cmd
        elif isinstance(cmd, ReleaseCommand):
            if cmd.restore and self._held_from is not None:  # as plant_sim does
                sim.restore(self._held_from)
            self.lease, self._held_from = None, None
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
        self.check_plant()
        before = self.sim.rejected
        self._apply(cmd)
        status = self.sync()
        self.applied_t = status.t
        if status.rejected > before:
            raise CommandRefused(f"loop {self.loop}: {status.last_reject}")
        return status

    def command_all(self, *cmds: Command) -> LoopStatus:
        """``cmds`` in order, each confirmed (the loop stands still between them)."""
        for cmd in cmds:
            status = self.command(cmd)
        return status

    def advance(
        self, steps: int, band: Band | None = None, record: RecordStops | None = None
    ) -> list[ProcessSample]:
        """Step the loop ``steps`` periods, stopping after the first sample that leaves
        ``band`` (or, with ``record``, where that record's judging stops it) as the plant does
        (``AdvanceCommand.stop_test``); their samples (what the plant would publish)."""
        self.check_plant()
        ends = band.end_test() if band is not None else None
        if record is not None:
            ends = record.stop_test(steps, ends or (lambda pv, op=None: False))
        healthy = self.sim.fault is None
        out = self.sim.advance_many(steps, ends)
        if out:
            self.last_sample = out[-1]
        if healthy and self.sim.fault is not None and self.holding:
            # the samples up to the fault are the run's (its record keeps them); the fault is
            # told at the next call, as the bus client hears it in the status after them
            self._fault_note = (
                f"loop {self.loop}: the plant faulted it ({self.sim.fault}): it holds the loop "
                "in manual at the output it last had, and the model is not called again"
            )
        return out

    def samples(
        self, steps: int, band: Band | None = None, record: RecordStops | None = None
    ) -> list[ProcessSample]:
        """The next ``steps`` samples, ending with the first that leaves ``band`` (or where
        ``record``'s judging stops it)."""
        return self.advance(steps, band, record)

    def next_sample(self) -> ProcessSample:
        return self.samples(1)[0]


@dataclass(frozen=True)
class Reading:
    """One sample: sim time t (s), PV (PV units), the output held over it (%)."""

    t: float
    pv: float
    op: float


class SimLoopPort:
    """A plant_sim loop as the experiment driver sees it, lockstep: a demand holds from the
    present sample on. With ``present_first`` the loop's present state is the first sample
    (it has been measured, not yet fed); ``limit``: no samples after this many s of sim time."""

    def __init__(self, loop: SimLoop, present_first: bool = False, limit: float = math.inf):
        self.loop = loop
        self._present = present_first
        self._t0, self._limit = loop.t, limit

    def samples(self, n: int, band: Band | None = None) -> list[Reading | ProcessSample]:
        loop = self.loop
        if self._present:
            self._present = False
            return [Reading(loop.t, loop.pv, loop.op)]
        if not loop.t - self._t0 <= self._limit:
            return []
        return until_band(loop.advance, n, band)

    def apply(self, demand: Demand, before: Demand) -> None:
        loop, name = self.loop, self.loop.settings.loop_id
        if not demand.auto:
            loop.apply(OutputCommand(loop=name, op=demand.op))
            return
        if demand.kc != before.kc:
            loop.apply(GainsCommand(loop=name, gains=PidGains(kc=demand.kc)))
        if demand.sp != before.sp:
            loop.apply(SetpointCommand(loop=name, sp=demand.sp))

    def hold_time(self) -> float:
        return self.loop.t

    def held_now(self) -> Demand:
        """What the loop holds now: its gain and setpoint in auto, its output in manual."""
        loop = self.loop
        if loop.mode == "auto":
            return Demand(kc=loop.pid.gains.kc, sp=loop.sp)
        return Demand(op=loop.op)


class ModelPort:
    """A bare plant model driven open loop, one sample per step: the PV is the model's after
    holding the output one sample time, plus seeded Gaussian noise of σ ``noise`` (drawn for
    every sample, so that a seed gives the same record at any σ)."""

    def __init__(
        self,
        model: ProcessModel,
        sample_time: float,
        op: float,
        noise: float = 0.0,
        rng: np.random.Generator | None = None,
    ):
        self.model, self.ts, self.op, self.noise = model, sample_time, op, noise
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.k = 0

    def samples(self, n: int, band: Band | None = None) -> list[Reading]:
        return until_band(self._step, n, band)

    def _step(self) -> Reading:
        self.k += 1
        pv = self.model.step(self.op) + self.noise * self.rng.standard_normal()
        return Reading(self.k * self.ts, pv, self.op)

    def apply(self, demand: Demand, before: Demand) -> None:
        self.op = demand.op

    def hold_time(self) -> float:
        return self.k * self.ts
