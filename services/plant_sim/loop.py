"""One simulated loop: the process, its measurement and its PID block, advanced per sample.

Timing at each period [t_k, t_{k+1}): the output u_k is held (ZOH); at t_{k+1} the PV is
measured (true PV + seeded Gaussian noise, limited to the transmitter's range), then the PID
block executes (in auto) or tracks (in manual), giving u_{k+1}. A sample therefore reports
the PV measured at t and the output held from t on.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

from services.plant_sim.models import ProcessModel
from services.plant_sim.pid import PidBlock
from shared.messages import (
    Action,
    ClockMode,
    Command,
    DisturbanceCommand,
    GainsCommand,
    LoopInfo,
    LoopStatus,
    Mode,
    ModeCommand,
    OutputCommand,
    PidGains,
    ProcessSample,
    SetpointCommand,
)

MAX_SOURCES = 256  # senders whose refusals a loop keeps count of


class CommandRejected(Exception):
    """A command the loop refuses; ``category`` is the counter it goes to."""

    def __init__(self, category: str, reason: str):
        self.category = category
        self.reason = reason
        super().__init__(reason)


@dataclass(frozen=True)
class LoopSettings:
    """Everything about a loop that is not the process model itself."""

    loop_id: str
    model_name: str
    model_params: dict
    sample_time: float
    noise_std: float
    seed: int
    mode: Mode
    setpoint: float | None
    action: Action
    op_limits: tuple[float, float]
    pv_range: tuple[float, float]
    pv_units: str
    gains: PidGains
    sp_track: bool
    description: str


@dataclass(frozen=True)
class LoopSnapshot:
    """What a supervisor must put back: mode, output, setpoint, gains, disturbances."""

    mode: Mode
    op: float
    sp: float
    gains: PidGains
    disturbances: dict[str, float]


class SimLoop:
    """A loop as a DCS holds it: PV, SP, OP, mode, gains, limits and its process."""

    def __init__(self, settings: LoopSettings, process: ProcessModel):
        self.settings = settings
        self.process = process
        self.sample_time = settings.sample_time
        self.seq = 0
        self._rng = np.random.default_rng([settings.seed, _stable_hash(settings.loop_id)])
        pv_rest = process.reset()
        self.pv = self._measure(pv_rest)
        self.sp = settings.setpoint if settings.setpoint is not None else pv_rest
        self.pid = PidBlock(
            settings.gains,
            settings.sample_time,
            settings.op_limits,
            settings.action,
            "manual",
            op=process.op0,
        )
        self.pid.track(self.pv, self.pid.op)
        if settings.mode == "auto":
            self.pid.set_mode("auto", self.sp, self.pv)
        self.accepted = 0
        self.rejected = 0
        self.last_reject: str | None = None
        self.fault: str | None = None  # why the model failed mid-run (loop held in manual)
        self._refusals: dict[str, tuple[int, str]] = {}  # by sender: count, last reason

    @property
    def t(self) -> float:
        """Sim time of the current sample, s (seq·T, never accumulated)."""
        return self.seq * self.sample_time

    @property
    def op(self) -> float:
        return self.pid.op

    @property
    def mode(self) -> Mode:
        return self.pid.mode

    def _measure(self, pv_true: float) -> float:
        pv = pv_true
        if self.settings.noise_std > 0:
            pv += self.settings.noise_std * float(self._rng.standard_normal())
        lo, hi = self.settings.pv_range
        return min(max(pv, lo), hi)

    def sample(self) -> ProcessSample:
        return ProcessSample(
            loop=self.settings.loop_id,
            seq=self.seq,
            t=self.t,
            pv=self.pv,
            sp=self.sp,
            op=self.op,
            mode=self.mode,
        )

    def advance(self, held_op: float | None = None) -> ProcessSample:
        """Hold the output for one period, measure, execute the PID block; return the sample.

        ``held_op`` is the output latched at the start of the period (realtime clock: a
        command that arrives mid-period takes effect at the next sample); None holds the
        present output (lockstep: the clock stands still between samples).
        """
        pv_true = self.process.step(self.pid.op if held_op is None else held_op)
        if not math.isfinite(pv_true):
            raise RuntimeError(f"loop {self.settings.loop_id}: the model returned PV {pv_true}")
        self.seq += 1
        self.pv = self._measure(pv_true)
        if self.pid.mode == "auto":
            self.pid.update(self.sp, self.pv)
        else:
            if self.settings.sp_track:
                self.sp = self.pv
            self.pid.track(self.pv, self.pid.op)
        return self.sample()

    def refused(self, source: str, reason: str) -> None:
        """Count a refusal against the command's sender (the last MAX_SOURCES senders)."""
        count, _ = self._refusals.pop(source, (0, ""))
        self._refusals[source] = (count + 1, reason)
        while len(self._refusals) > MAX_SOURCES:
            del self._refusals[next(iter(self._refusals))]

    def status(
        self,
        node: str,
        clock: ClockMode,
        reason: str,
        token: int | None = None,
        source: str | None = None,
        leased_by: str | None = None,
    ) -> LoopStatus:
        """The loop's ``LoopStatus`` as the plant publishes it (``reason``: what changed); a
        sync's answer also carries its sender's own refusals, so that a client never takes
        another's refused command for its own."""
        s = self.settings
        mine = self._refusals.get(source, (0, None)) if source is not None else (None, None)
        return LoopStatus(
            loop=s.loop_id,
            node=node,
            seq=self.seq,
            t=self.t,
            pv=self.pv,
            sp=self.sp,
            op=self.op,
            mode=self.mode,
            action=s.action,
            gains=self.pid.gains,
            op_limits=s.op_limits,
            pv_range=s.pv_range,
            disturbances=self.disturbances(),
            clock=clock,
            accepted=self.accepted,
            rejected=self.rejected,
            last_reject=self.last_reject,
            sync_token=token,
            sync_rejected=mine[0],
            sync_last_reject=mine[1],
            reason=reason,
            leased_by=leased_by,
            fault=self.fault,
        )

    def info(self, node: str, clock: ClockMode, speed: float) -> LoopInfo:
        """The loop's ``LoopInfo``: model, parameters, units, ranges, sample time, clock."""
        s = self.settings
        return LoopInfo(
            loop=s.loop_id,
            node=node,
            t=self.t,
            model=s.model_name,
            description=s.description,
            model_params=s.model_params,
            sample_time=s.sample_time,
            pv_units=s.pv_units,
            pv_range=s.pv_range,
            op_limits=s.op_limits,
            disturbances=list(self.process.disturbance_names()),
            noise_std=s.noise_std,
            clock=clock,
            speed=speed,
        )

    def disturbances(self) -> dict[str, float]:
        names = self.process.disturbance_names()
        values = getattr(self.process, "disturbances", None)
        if isinstance(values, dict):
            return {n: float(values[n]) for n in names}
        return {n: float(getattr(self.process, n, math.nan)) for n in names}

    def snapshot(self) -> LoopSnapshot:
        return LoopSnapshot(self.mode, self.op, self.sp, self.pid.gains, self.disturbances())

    def restore(self, snap: LoopSnapshot) -> None:
        """Put the loop back as it was (into auto bumplessly, at the old setpoint)."""
        for name, value in snap.disturbances.items():
            self.process.set_disturbance(name, value)
        self.pid.set_gains(snap.gains, self.sp, self.pv)
        self.pid.set_mode("manual", self.sp, self.pv)
        self.sp = snap.sp
        if snap.mode == "manual":
            self.pid.set_output(snap.op)
        else:
            self.pid.set_mode("auto", self.sp, self.pv)

    def apply(self, cmd: Command) -> None:
        """Apply a validated command; raise CommandRejected (nothing changed) if refused."""
        match cmd:
            case ModeCommand(mode=mode):
                self.pid.set_mode(mode, self.sp, self.pv)
            case OutputCommand(op=op):
                if self.mode != "manual":
                    raise CommandRejected(
                        "mode", "output refused: the loop is in auto (switch it to manual first)"
                    )
                lo, hi = self.settings.op_limits
                if not lo <= op <= hi:
                    raise CommandRejected(
                        "range", f"op {op} is outside the output limits [{lo}, {hi}] %"
                    )
                self.pid.set_output(op)
            case SetpointCommand(sp=sp):
                lo, hi = self.settings.pv_range
                if not lo <= sp <= hi:
                    raise CommandRejected(
                        "range",
                        f"sp {sp} is outside the PV range [{lo}, {hi}] {self.settings.pv_units}",
                    )
                self.sp = sp
            case GainsCommand(gains=gains):
                self.pid.set_gains(gains, self.sp, self.pv)
            case DisturbanceCommand(name=name, value=value):
                names = self.process.disturbance_names()
                if name not in names:
                    raise CommandRejected(
                        "disturbance",
                        f"unknown disturbance {name!r}; this "
                        f"loop has: {', '.join(names) or 'none'}",
                    )
                try:
                    self.process.set_disturbance(name, value)
                except (KeyError, ValueError) as err:
                    raise CommandRejected("range", f"disturbance {name}: {err}") from None
            case _:
                raise CommandRejected("kind", f"{type(cmd).__name__} is not a loop setting")


def _stable_hash(text: str) -> int:
    """A hash that is the same in every process (Python's hash() is salted)."""
    return zlib.crc32(text.encode())
