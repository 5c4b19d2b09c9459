"""One simulated loop: the process, its measurement and its PID block, advanced per sample.

Timing at each period [t_k, t_{k+1}): the output u_k is held (ZOH); at t_{k+1} the PV is
measured (true PV + seeded Gaussian noise, limited to the transmitter's range), then the PID
block executes (in auto) or tracks (in manual), giving u_{k+1}. A sample therefore reports
the PV measured at t and the output held from t on.

A model that fails mid-run (its ``step`` raises, or returns something that is not a finite
number) faults the loop: it is put in manual at the output it last held, its PV is held at the
last measurement, ``fault`` says why (in every LoopStatus), the failure is logged once, and
the model is never called again. Samples keep coming (time goes on) so that whoever drives the
loop is never left waiting; commands that would move the dead process — auto, an output, a
disturbance — are refused with the fault as the reason. No method of a SimLoop raises for a
failure of the model: one broken loop never takes its service, or the other loops, down.
"""

from __future__ import annotations

import logging
import math
import numbers
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.plant_sim.load_bound import models_own
from services.plant_sim.simulation import linear_steps
from services.plant_sim.simulation.models import ProcessModel
from shared.control.forms import kc_problem
from shared.control.pid import PidBlock, PidSettings
from shared.errors import one_line as brief
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

log = logging.getLogger("plant_sim")


class ModelFailure(Exception):
    """The process model failed: raised, or gave a value that is not a finite number."""

    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(reason)


def call_model(what: str, fn: Callable[..., Any], *args: Any) -> Any:
    """Call the model's ``fn``; ModelFailure naming ``what`` and the model's own message."""
    try:
        with np.errstate(all="ignore"):  # overflow is judged from the value, not printed
            return fn(*args)
    except BaseException as err:  # a user's sys.exit() must not end the plant
        if not models_own(err):
            raise
        raise ModelFailure(_raised(what, err)) from None


def _raised(what: str, err: BaseException) -> str:
    msg = brief(err)
    return f"the model's {what} raised {type(err).__name__}{': ' + msg if msg else ''}"


def model_pv(what: str, fn: Callable[..., Any], *args: Any) -> float:
    """A PV from the model: a finite real number, else ModelFailure."""
    return _pv_of(what, call_model(what, fn, *args))


def _pv_of(what: str, value: Any) -> float:
    """``value`` as a PV: a finite real number, else ModelFailure naming ``what``."""
    if value.__class__ is not float:  # the usual answer, told from the rest at once
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ModelFailure(f"the model's {what} returned {brief(repr(value))}, not a number")
        try:  # an int past a float's range (10**400) overflows: no PV either
            value = float(value)
        except (OverflowError, ValueError, TypeError):
            raise ModelFailure(
                f"the model's {what} returned {brief(repr(value))}, not a finite number"
            ) from None
    if not math.isfinite(value):
        raise ModelFailure(f"the model's {what} returned PV {value}")
    return value


class CommandRejected(Exception):
    """A command the loop refuses; ``category`` is the counter it goes to."""

    def __init__(self, category: str, reason: str):
        self.category = category
        self.reason = reason
        super().__init__(reason)


def gains_problem(gains: PidGains, sample_time: float, pv_range: tuple[float, float]) -> str | None:
    """Why ``gains`` are no control at all on this loop (Kc 0, or a Kc whose proportional band
    is not a number: ``kc_problem``; `autotune set` refuses them in the same words), or would
    overflow the PID block's arithmetic (its terms reach Kc·span·(1 + Td/T + T/Ti) % of
    output), else None."""
    span = pv_range[1] - pv_range[0]
    none = kc_problem(gains.kc, span)
    if none:
        return f"kc {gains.kc + 0.0:g}: {none}"  # -0 is 0
    reach = 1.0 + gains.td / sample_time + (sample_time / gains.ti if gains.ti else 0.0)
    if gains.kc * span * reach < 1e300:
        return None
    return (
        f"Kc {gains.kc:g}, Ti {gains.ti}, Td {gains.td:g} s are beyond floating-point range "
        f"for a PV span of {span:g} at {sample_time:g} s samples"
    )


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
    gains: PidSettings
    disturbances: dict[str, float]


class SimLoop:
    """A loop as a DCS holds it: PV, SP, OP, mode, gains, limits and its process."""

    def __init__(self, settings: LoopSettings, process: ProcessModel):
        self.settings = settings
        self.process = process
        self.sample_time = settings.sample_time
        self.seq = 0
        self._rng = np.random.default_rng([settings.seed, _stable_hash(settings.loop_id)])
        pv_rest = model_pv("reset()", process.reset)  # ModelFailure: the loop cannot start
        self.pv = self._measure(pv_rest)
        # no setpoint given: the rest, as the transmitter reads it (a process resting beyond
        # its range runs clipped at the limit, and a setpoint outside the range means nothing)
        lo, hi = settings.pv_range
        self.sp = settings.setpoint if settings.setpoint is not None else min(max(pv_rest, lo), hi)
        self.pid = PidBlock(
            settings.gains.to_core(),
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
        # monotonic s at which the model's step() was called, until it returns (None: idle)
        self.stepping_since: float | None = None
        self.fault_t: float | None = None  # sim time of the failure
        self._refusals: dict[str, tuple[int, str]] = {}  # by sender: count, last reason
        self._disturbances: dict[str, float] = {}
        self._disturbances = self.disturbances()
        self.plain_linear = linear_steps.plain_linear(process)  # its class never changes

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
        present output (lockstep: the clock stands still between samples). Never raises: a
        model that fails faults the loop (see the module's doc) and the sample holds.
        """
        with np.errstate(all="ignore"):  # overflow is judged from the value, not printed
            return self._advance(held_op)

    def advance_many(
        self, steps: int, stops_at: Callable[[float, float], bool] | None = None
    ) -> list[ProcessSample]:
        """Lockstep: ``steps`` periods as ``advance`` does each, ending early after the first
        sample whose PV and output ``stops_at`` names (an advance's stops). A plain linear
        loop is stepped by ``linear_steps`` (the same samples to the bit, a fraction of the
        cost)."""
        if linear_steps.steppable(self):
            return [ProcessSample(**row) for row in self.advance_rows(steps, stops_at)]
        return self.advance_slowly(steps, stops_at)

    def advance_rows(
        self,
        steps: int,
        stops_at: Callable[[float, float], bool] | None = None,
        until: float | None = None,
    ) -> list[dict]:
        """``advance_many``'s samples as the dicts of their fields (what the plant encodes for
        the bus at once: building ProcessSamples would cost more than the stepping).
        ``until``: a ``time.monotonic()`` deadline past which a model stepped one sample at a
        time stops early, fewer samples than asked for (see ``advance_slowly``)."""
        if linear_steps.steppable(self):
            with np.errstate(all="ignore"):
                return linear_steps.advance(self, steps, stops_at)
        return [s.model_dump() for s in self.advance_slowly(steps, stops_at, until)]

    def advance_slowly(
        self,
        steps: int,
        stops_at: Callable[[float, float], bool] | None = None,
        until: float | None = None,
    ) -> list[ProcessSample]:
        """``advance_many`` one ``advance`` at a time: any model, a faulted loop. Past
        ``until`` (``time.monotonic()``, after one sample at least) it returns what it has:
        the plant publishes a slow model's samples before its asker's silence bound, however
        slow the model is from its first sample on. It ends at the sample where the loop
        faults: its status says so at once, not at the end of the advance (a 16,384-sample
        record ran on 25 s of sim time past a fault before its holder heard of it)."""
        out: list[ProcessSample] = []
        healthy = self.fault is None
        with np.errstate(all="ignore"):
            for _ in range(steps):
                s = self._advance(None)
                out.append(s)
                if healthy and self.fault is not None:
                    break
                if stops_at is not None and stops_at(s.pv, s.op):
                    break
                if until is not None and time.monotonic() >= until:
                    break
        return out

    def _advance(self, held_op: float | None) -> ProcessSample:
        op = self.pid.op if held_op is None else held_op
        if self.fault is None:
            self.stepping_since = time.monotonic()  # for the plant's watch on a model that hangs
            try:
                pv_true = _pv_of("step()", self.process.step(op))
            except ModelFailure as err:
                self._set_fault(err.reason, op, self.t + self.sample_time)
            except BaseException as err:  # a user's sys.exit() faults its loop
                if not models_own(err):
                    raise
                self._set_fault(_raised("step()", err), op, self.t + self.sample_time)
            finally:
                self.stepping_since = None
        self.seq += 1
        if self.fault is not None:
            return self.sample()
        self.pv = self._measure(pv_true)
        if self.pid.mode == "auto":
            self.pid.update(self.sp, self.pv)
            if not math.isfinite(self.pid.op):
                g = self.pid.gains
                self._set_fault(
                    f"the PID block's output became {self.pid.op} (Kc {g.kc:g}, Ti {g.ti}, "
                    f"Td {g.td:g}: gains out of all proportion to the PV range)",
                    op,
                    self.t,
                )
        else:
            if self.settings.sp_track:
                self.sp = self.pv
            self.pid.track(self.pv, self.pid.op)
        return self.sample()

    def _set_fault(self, reason: str, op: float, t: float) -> None:
        """Fault the loop at sim time ``t``: manual at ``op`` (the output it last held), PV
        held, logged once."""
        self.fault = f"{reason} (at t = {t:g} s)"
        self.fault_t = t
        self.pid.set_mode("manual", self.sp, self.pv)
        self.pid.set_output(op)
        log.error(
            "loop %s: model %s failed: %s; the loop is held in manual at OP %.4g %%, "
            "PV %.6g (the other loops go on)",
            self.settings.loop_id,
            self.settings.model_name,
            self.fault,
            self.pid.op,
            self.pv,
        )

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
            gains=PidGains.from_core(self.pid.gains),
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
            disturbances=list(self.disturbances()),
            noise_std=s.noise_std,
            clock=clock,
            speed=speed,
        )

    def disturbances(self) -> dict[str, float]:
        """The disturbance inputs' present values (those the model lets us read as finite
        numbers); the last ones read once the loop is faulted or the model fails to say."""
        if self.fault is not None:
            return dict(self._disturbances)
        try:
            with np.errstate(all="ignore"):
                names = [n for n in self.process.disturbance_names() if isinstance(n, str)]
                values = getattr(self.process, "disturbances", None)
                if isinstance(values, dict):
                    read = {n: values.get(n, math.nan) for n in names}
                else:
                    read = {n: getattr(self.process, n, math.nan) for n in names}
                out = {
                    n: float(v)
                    for n, v in read.items()
                    if isinstance(v, numbers.Real) and math.isfinite(float(v))
                }
        except BaseException as err:  # a user's model: its status is read, never trusted
            if not models_own(err):
                raise
            return dict(self._disturbances)
        self._disturbances = out
        return dict(out)

    def snapshot(self) -> LoopSnapshot:
        return LoopSnapshot(self.mode, self.op, self.sp, self.pid.gains, self.disturbances())

    def restore(self, snap: LoopSnapshot) -> None:
        """Put the loop back as it was: its output first, then (a loop that was in auto) into
        auto bumplessly from there, at the old setpoint. The output the test left (a relay's
        low level) is not where the loop was: auto from there would upset the process for
        an integral time before it got back. A faulted loop gets its setpoint and gains back
        but stays in manual at its held output."""
        if self.fault is None:
            for name, value in snap.disturbances.items():
                try:
                    what = f"set_disturbance({name!r})"
                    call_model(what, self.process.set_disturbance, name, value)
                except ModelFailure as err:
                    log.warning("loop %s: restore: %s", self.settings.loop_id, err.reason)
        self.pid.set_gains(snap.gains, self.sp, self.pv)
        self.pid.set_mode("manual", self.sp, self.pv)
        self.sp = snap.sp
        if self.fault is not None:
            return
        self.pid.set_output(snap.op)
        if snap.mode == "auto":
            self.pid.set_mode("auto", self.sp, self.pv)

    def apply(self, cmd: Command) -> None:
        """Apply a validated command; raise CommandRejected (nothing changed) if refused."""
        if self.fault is not None and (
            isinstance(cmd, OutputCommand | DisturbanceCommand)
            or (isinstance(cmd, ModeCommand) and cmd.mode == "auto")
        ):
            raise CommandRejected(
                "fault",
                f"{cmd.kind} refused: the loop is faulted and held in manual ({self.fault})",
            )
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
                problem = gains_problem(gains, self.sample_time, self.settings.pv_range)
                if problem:
                    raise CommandRejected("range", f"gains refused: {problem}")
                self.pid.set_gains(gains.to_core(), self.sp, self.pv)
            case DisturbanceCommand(name=name, value=value):
                try:
                    names = tuple(call_model("disturbance_names()", self.process.disturbance_names))
                except (ModelFailure, TypeError) as err:
                    raise CommandRejected("model", f"disturbance {name}: {brief(err)}") from None
                if name not in names:
                    raise CommandRejected(
                        "disturbance",
                        f"unknown disturbance {name!r}; this "
                        f"loop has: {', '.join(names) or 'none'}",
                    )
                try:
                    with np.errstate(all="ignore"):
                        self.process.set_disturbance(name, value)
                except (KeyError, ValueError) as err:
                    raise CommandRejected("range", f"disturbance {name}: {brief(err)}") from None
                except BaseException as err:  # a user's model: refused, its own words
                    if not models_own(err):
                        raise
                    raise CommandRejected(
                        "model",
                        f"disturbance {name}: the model raised {type(err).__name__}: {brief(err)}",
                    ) from None
            case _:
                raise CommandRejected("kind", f"{type(cmd).__name__} is not a loop setting")


def _stable_hash(text: str) -> int:
    """A hash that is the same in every process (Python's hash() is salted)."""
    return zlib.crc32(text.encode())
