"""Pydantic models for every message on the bus. JSON on the wire; the model name is the schema.

Units: time in seconds of *sim time* (``t``), outputs in % of span (0–100), PV and setpoint in
the loop's engineering units (``LoopInfo.pv_units``), controller gain Kc in % of output per PV
unit. Messages are strict: wrong types, NaN/inf and unknown fields are rejected on receipt.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.control.pid import Action, Mode, PidSettings
from shared.control.record_stops import MAX_WINDOW, CalmCheck, Guard, record_test
from shared.control.signals import end_test

ClockMode = Literal["lockstep", "realtime"]

LoopId = Annotated[
    str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
]
Percent = Annotated[float, Field(ge=0.0, le=100.0)]
# a run's id: the tuner's are 12 hex digits; any client's goes into file names and log lines
RunId = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")]
SimTime = Annotated[float, Field(ge=0.0)]


class Message(BaseModel):
    """Base of every bus message: strict, finite numbers, no unknown fields, immutable."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)


class PidGains(Message):
    """Gains of the loop's PID block in ideal (ISA) form.

    u = Kc·(β·sp − pv) + (Kc/Ti)·∫e dt − Kc·Td·d(pv_f)/dt, derivative filtered with Tf = Td/n.
    ``ti`` None means no integral action (P or PD with a manual reset).
    """

    kc: float = Field(ge=0.0, description="controller gain, % of output per PV unit")
    ti: float | None = Field(default=None, gt=0.0, description="integral time, s; None = off")
    td: float = Field(default=0.0, ge=0.0, description="derivative time, s")
    n: float = Field(default=10.0, ge=1.0, le=1000.0, description="derivative filter: Tf = Td/n")
    beta: float = Field(default=1.0, ge=0.0, le=1.0, description="setpoint weight on P action")

    def to_core(self) -> PidSettings:
        """The PID block's own settings (``shared.control.pid``), the same numbers."""
        return PidSettings(self.kc, self.ti, self.td, self.n, self.beta)

    @classmethod
    def from_core(cls, settings: PidSettings) -> PidGains:
        """The message for a PID block's settings, the same numbers."""
        return cls(kc=settings.kc, ti=settings.ti, td=settings.td, n=settings.n, beta=settings.beta)


class ProcessSample(Message):
    """One sample of a loop at sim time ``t``: PV measured at ``t``, the output held from ``t``."""

    loop: LoopId
    seq: int = Field(ge=0, description="sample index; t = seq·sample_time")
    t: SimTime
    pv: float
    sp: float
    op: Percent
    mode: Mode


MAX_BATCH = 1024  # samples in one ProcessSamples at most (an advance of more: several)
MAX_ADVANCE = 100_000  # samples one AdvanceCommand may ask for


class ProcessSamples(Message):
    """Lockstep: the samples of one advance of several periods, in order, as one message
    (``<prefix>/plant/<loop>/pv_batch``); each is what ``pv`` would have carried, and every
    consumer takes it as that many ProcessSamples. Why: a message's cost on the bus (a wake
    of every subscriber's thread) is paid once per batch, not once per sample."""

    loop: LoopId
    samples: list[ProcessSample] = Field(min_length=1, max_length=MAX_BATCH)

    @model_validator(mode="after")
    def _one_loop_in_order(self) -> ProcessSamples:
        """Every sample is this loop's, numbered one after the other: a batch with a hole
        or out of order inside is refused whole (a missing batch shows as a gap in seq)."""
        first = self.samples[0].seq
        for i, s in enumerate(self.samples):
            if s.loop != self.loop:
                raise ValueError(f"samples.{i}.loop: {s.loop!r} in a batch of loop {self.loop!r}")
            if s.seq != first + i:
                raise ValueError(
                    f"samples.{i}.seq: {s.seq}, expected {first + i} (one after the other)"
                )
        return self


class LoopStatus(Message):
    """Everything an operator sees on the loop's faceplate, plus the command counters."""

    loop: LoopId
    node: str
    seq: int = Field(ge=0)
    t: SimTime
    pv: float
    sp: float
    op: Percent
    mode: Mode
    action: Action
    gains: PidGains
    op_limits: tuple[float, float]
    pv_range: tuple[float, float]
    disturbances: dict[str, float]
    clock: ClockMode
    accepted: int = Field(ge=0, description="commands applied to this loop")
    rejected: int = Field(ge=0, description="commands to this loop refused")
    last_reject: str | None = None
    sync_token: int | None = Field(default=None, description="echo of the SyncCommand answered")
    sync_rejected: int | None = Field(
        default=None, description="in a sync's answer: commands of its sender refused so far"
    )
    sync_last_reject: str | None = Field(
        default=None, description="in a sync's answer: why its sender was last refused"
    )
    reason: str = Field(description="what caused this status: start, a command kind, or query")
    leased_by: str | None = Field(
        default=None, description="the supervisor holding the loop's lease (an experiment), if any"
    )
    lease_user: str | None = Field(
        default=None,
        description="the holder's Zenoh user, named by its command keys (verified by the "
        "router's access control in a secure deployment)",
    )
    fault: str | None = Field(
        default=None,
        description="why the loop's model failed (the loop is then held in manual), if it did",
    )
    by_source: str | None = Field(
        default=None,
        max_length=64,
        description="the source label of the command that caused this status (a lease, a "
        "release or an applied command), if one did",
    )
    by_user: str | None = Field(
        default=None,
        description="that command's sender as the bus knows it: the Zenoh user its key names "
        "(verified by the router's access control in a secure deployment), if any",
    )
    ended: str | None = Field(
        default=None,
        max_length=400,
        exclude_if=lambda v: v is None,
        description="in the status of a lease the plant ended (reason watchdog): why it ended "
        "it and restored the loop",
    )


class LoopInfo(Message):
    """Static description of a loop: its model, units, ranges and clock."""

    loop: LoopId
    node: str
    t: SimTime
    model: str
    description: str
    model_params: dict[str, Any]
    sample_time: float = Field(gt=0.0)
    pv_units: str
    pv_range: tuple[float, float]
    op_limits: tuple[float, float]
    disturbances: list[str]
    noise_std: float = Field(ge=0.0)
    clock: ClockMode
    speed: float = Field(gt=0.0, description="realtime speed-up of the wall clock")
    instance: str | None = Field(
        default=None,
        description="drawn at random when the plant process starts: a restarted plant, or "
        "another serving the same loop id, has another",
    )


class ServiceStatus(Message):
    """Health and counters of one plant_sim process."""

    node: str
    clock: ClockMode
    speed: float
    loops: dict[str, SimTime] = Field(description="sim time of each served loop")
    accepted: int = Field(ge=0)
    rejected: int = Field(ge=0, description="every command refused, unknown loops included")
    rejected_by_reason: dict[str, int]
    overruns: int = Field(ge=0, description="realtime periods started late")
    # this process's run among plant processes (``LoopInfo.instance``), and when it started
    # (wall clock, s since the epoch): of two processes found serving one loop, the later
    # started stops (``shards``); None: a plant that does not say
    instance: str | None = Field(default=None, max_length=64)
    started: float | None = None


class Command(Message):
    """Base of every command to a loop; its kind is the last chunk of the key."""

    kind: ClassVar[str]
    loop: LoopId
    t: SimTime | None = Field(default=None, description="sim time of the sender's last sample")
    source: str = Field(default="operator", max_length=64)


class ModeCommand(Command):
    kind: ClassVar[str] = "mode"
    mode: Mode


class OutputCommand(Command):
    """Manual output; refused in auto and outside the loop's output limits."""

    kind: ClassVar[str] = "output"
    op: Percent


class SetpointCommand(Command):
    """Setpoint in PV units; refused outside the loop's PV range."""

    kind: ClassVar[str] = "setpoint"
    sp: float


class GainsCommand(Command):
    """New PID gains, applied bumplessly."""

    kind: ClassVar[str] = "gains"
    gains: PidGains


class DisturbanceCommand(Command):
    """Set one of the model's disturbance inputs (``LoopInfo.disturbances``) to ``value``."""

    kind: ClassVar[str] = "disturbance"
    name: str = Field(min_length=1, max_length=64)
    value: float


class SettleStop(Message):
    """A record's end on settling (``record_stops.settled``): the last ``k`` samples' mean
    within ``band`` of ``target``, their spread within ``flat`` (None: not asked), asked from
    ``min_samples`` samples on."""

    k: int = Field(ge=1, le=1_000_000)
    target: float
    band: float = Field(ge=0.0, description="PV units")
    flat: float | None = Field(default=None, ge=0.0, description="PV units")
    min_samples: int = Field(default=1, ge=1, le=1_000_000)


class GuardStop(Message):
    """A record's end on running away (``record_stops.Guard``): its output at a limit, or its
    deviation from ``target`` growing, over whole ``window``-sample windows."""

    window: int = Field(ge=8, le=1_000_000, description="samples")
    target: float = Field(description="PV units: the setpoint the deviations are from")
    op_low: float = Field(description="%: the output's low limit")
    op_high: float = Field(description="%: the output's high limit")


class RecordStops(Message):
    """The judging of a verification record, for a lockstep advance that is the whole record
    from its first sample: at every ``judge``-th sample the guard (once a new window is in)
    and, at multiples of 8·judge, the settling (``record_stops.record_test``)."""

    judge: int = Field(ge=1, le=1_000_000, description="samples between judging points")
    settle: SettleStop | None = None
    guard: GuardStop | None = None

    def stop_test(
        self, steps: int, band_ends: Callable[[float, float | None], bool]
    ) -> Callable[[float, float | None], bool]:
        """The end test of an advance of ``steps`` samples that is this record from its first
        sample, past ``band_ends`` too (``record_stops.record_test``; stateful: one per
        advance, asked of every sample in turn)."""
        s, g = self.settle, self.guard
        settle = (s.k, s.target, s.band, s.flat, s.min_samples) if s is not None else None
        guard = (Guard((g.op_low, g.op_high), g.window), g.target) if g is not None else None
        return record_test(steps, self.judge, settle, guard, band_ends)


class CalmStop(Message):
    """A P-gain ramp's calming check (``record_stops.calm_test``), for a lockstep advance that
    ends where it passes: the ramp had been fed ``fed`` samples (the last of them
    ``history``, at most ``window``); from count ``start`` on, at each multiple of ``every``,
    calm when the means of ten stretches of the last ``window`` PVs agree within ``limit``."""

    fed: int = Field(ge=0)
    start: int = Field(ge=0)
    every: int = Field(default=8, ge=1, le=MAX_WINDOW)
    window: int = Field(ge=10, le=MAX_WINDOW, description="samples")
    limit: float = Field(ge=0.0, description="PV units")
    history: list[float] = Field(default_factory=list, max_length=MAX_WINDOW)

    @model_validator(mode="after")
    def _history_fits(self) -> CalmStop:
        if len(self.history) > self.window:
            raise ValueError(f"history: {len(self.history)} PVs, more than the window")
        return self

    @classmethod
    def of(cls, check: CalmCheck) -> CalmStop:
        """The message of a ramp's calming checks (ValueError: numbers it cannot carry)."""
        return cls(
            fed=check.fed,
            start=check.start,
            every=check.every,
            window=check.window,
            limit=check.limit,
            history=list(check.history),
        )

    def check(self) -> CalmCheck:
        """The calming checks this message carries."""
        h = tuple(self.history)
        return CalmCheck(self.fed, self.start, self.every, self.window, self.limit, h)

    def stop_test(
        self, band_ends: Callable[[float, float | None], bool]
    ) -> Callable[[float, float | None], bool]:
        """The end test of an advance that ends at this check's pass, past ``band_ends`` too
        (stateful: one per advance)."""
        return self.check().end_test(band_ends)


class AdvanceCommand(Command):
    """Lockstep clock: advance the loop by ``steps`` sample periods, publishing each sample;
    with ``stop_below``/``stop_above``, stop early after the first sample whose PV is at or
    below/above them, with ``stop_op_below``/``stop_op_above`` likewise for its output
    (``stops_at``); with ``calm``, also at a P-gain ramp's first calming check that passes
    (``CalmStop``); with ``record``, where a verification record's judging would stop it
    (``RecordStops``). Why: a relay decides nothing while the PV stays between its levels, so it
    asks for a half-cycle in one round trip and the plant stops at the sample where the next
    decision falls, which the asker then knows without being told; a ramp trial also decides
    where the output first sits at a limit; a verification record only where it settles or
    runs away, which the plant asks of the samples as it steps them (one round trip a
    record)."""

    kind: ClassVar[str] = "advance"
    steps: int = Field(default=1, ge=1, le=MAX_ADVANCE)
    stop_below: float | None = Field(
        default=None, description="PV units: the advance ends with a sample at or below this"
    )
    stop_above: float | None = Field(
        default=None, description="PV units: the advance ends with a sample at or above this"
    )
    stop_op_below: float | None = Field(
        default=None, description="%: the advance ends with a sample whose output is at or below"
    )
    stop_op_above: float | None = Field(
        default=None, description="%: the advance ends with a sample whose output is at or above"
    )
    calm: CalmStop | None = Field(
        default=None,
        description="the advance also ends at the first of a P-gain ramp's calming checks "
        "that passes",
    )
    record: RecordStops | None = Field(
        default=None,
        description="the advance is a verification record from its first sample: it also ends "
        "where the record's judging would stop it (settled, or running away)",
    )

    @property
    def banded(self) -> bool:
        """Whether any stop is set (else the advance runs its ``steps``)."""
        stops = (self.stop_below, self.stop_above, self.stop_op_below, self.stop_op_above)
        judged = self.record is not None or self.calm is not None
        return judged or any(x is not None for x in stops)

    def stops_at(self, pv: float, op: float | None = None) -> bool:
        """True when a sample of PV ``pv`` (and output ``op``, %) ends this advance
        (``ends_batch``: the PV, or the output, at or past a stop)."""
        return self.stop_test()(pv, op)

    def stop_test(self) -> Callable[[float, float | None], bool]:
        """``stops_at`` as a function of the sample, the stops read once (``end_test``): for
        a test asked of every sample of the advance."""
        pv_stops = (self.stop_below, self.stop_above)
        test = end_test(pv_stops, (self.stop_op_below, self.stop_op_above))
        if self.calm is not None:
            test = self.calm.stop_test(test)
        return test if self.record is None else self.record.stop_test(self.steps, test)


class SyncCommand(Command):
    """Barrier: the loop answers with a LoopStatus carrying ``token`` once all earlier commands
    are applied."""

    kind: ClassVar[str] = "sync"
    token: int


class LeaseCommand(Command):
    """A supervisor takes the loop for an experiment. The plant snapshots the loop (mode,
    output, setpoint, gains, disturbances) and restores it by itself if the supervisor's
    run token (``<prefix>/tune/<loop>/running``) disappears or no command from ``source``
    arrives for ``timeout`` seconds of wall time."""

    kind: ClassVar[str] = "lease"
    timeout: float = Field(default=10.0, gt=0.0, le=3600.0)
    # the experiment's PV limits (PV units): on the realtime clock the plant restores the
    # loop, as its watchdog does, at the first sample whose PV is outside them. Why: the loop
    # runs on between the supervisor's commands, and a supervisor paused or stalled mid-test
    # (SIGSTOP, a swapping machine) held a relay's output while the PV ran on past its limits
    # until the lease timed out (80 s outside them). Left off the wire when None: a plant of
    # an earlier version refuses a field it does not know, and the lease with it.
    pv_limits: tuple[float, float] | None = Field(default=None, exclude_if=lambda v: v is None)

    @model_validator(mode="after")
    def _limits_in_order(self) -> LeaseCommand:
        if self.pv_limits is not None and not self.pv_limits[0] < self.pv_limits[1]:
            raise ValueError(f"pv_limits: low {self.pv_limits[0]:g} is not below high")
        return self


class ReleaseCommand(Command):
    """The supervisor hands the loop back (it has restored or re-tuned it itself).

    ``restore``: the supervisor could not confirm that it put the loop back (its plant fell
    silent, or refused a write, mid-restore): the plant restores its snapshot of the loop from
    the lease, as its watchdog would, then lets go. Why: a release queued behind a paused
    plant reached it before the run token's disappearance, and a plain release let go of a
    loop left in manual at the relay's output."""

    kind: ClassVar[str] = "release"
    # left off the wire when false: a plant of an earlier version (no such field, extra ones
    # refused) took the tuner's every release for malformed, and an ok run's gains were
    # undone by its watchdog (helper trial E, a plant and a tuner of two versions)
    restore: bool = Field(default=False, exclude_if=lambda v: not v)


COMMANDS: dict[str, type[Command]] = {
    cls.kind: cls
    for cls in (
        ModeCommand,
        OutputCommand,
        SetpointCommand,
        GainsCommand,
        DisturbanceCommand,
        AdvanceCommand,
        SyncCommand,
        LeaseCommand,
        ReleaseCommand,
    )
}

Method = Literal["relay", "ramp", "step"]
# ``ok``: the gains were verified on the loop and passed, within the safety envelope;
# ``forced``: verified and passed, but applied outside the envelope (a predicted Ms above the
# bound, a contradicted ultimate point) because ``force`` asked (not known to be safe);
# ``unverified``: applied without verification, as ``verify = false`` asks (not known to be
# safe); ``proposed``: identified and computed, not applied, as ``apply = false`` asks
# (`autotune apply` applies and verifies them); the rest: nothing applied
RunStatus = Literal["ok", "forced", "unverified", "proposed", "rejected", "aborted", "failed"]
# the statuses of a run whose gains ``autotune apply`` takes later (all but aborted, failed)
APPLICABLE_STATUSES: tuple[RunStatus, ...] = ("ok", "forced", "unverified", "proposed", "rejected")
# the statuses of a run that did what it was asked (the CLI's exit 0)
DONE_STATUSES: tuple[RunStatus, ...] = ("ok", "forced", "unverified", "proposed")
# the statuses of a run that may have left its gains in the loop (``applied`` says whether)
APPLIED_STATUSES: tuple[RunStatus, ...] = ("ok", "forced", "unverified")


class TuneRequest(Message):
    """Ask the autotuner to tune a loop (the queryable ``<prefix>/tuner/<node>/tune``).

    Optional settings left out take the defaults the README lists."""

    loop: LoopId
    method: Method = "relay"
    rule: str = Field(
        default="auto", min_length=1, max_length=32, description="auto: the recommended rule"
    )
    amplitude: float | None = Field(default=None, gt=0.0, le=50.0, description="relay d, %")
    hysteresis: float | None = Field(default=None, ge=0.0, description="relay ε, PV units")
    cycles: int = Field(default=3, ge=2, le=20, description="relay cycles that must agree")
    relay_bias: float | None = Field(
        default=None,
        ge=0.0,
        le=0.8,
        description="relay stage 2's asymmetry: low output b − (1 − relay_bias)·d (static gain)",
    )
    tolerance: float = Field(default=0.02, gt=0.0, lt=0.5)
    bump: float | None = Field(default=None, gt=0.0, description="ramp setpoint bump, PV units")
    kc_start: float | None = Field(default=None, gt=0.0, description="ramp first gain")
    step_size: float | None = Field(default=None, description="step test output step, %")
    repeat: int | Literal["auto"] | None = Field(
        default=None,
        description="step tests, up and down in turn (None: one); auto: until their mean is "
        "known to ± 5 %, at most 6",
    )
    pv_limits: tuple[float, float] | None = None
    max_time: float | None = Field(
        default=None, gt=0.0, le=1e7, description="experiment budget, sim s (as the CLI bounds it)"
    )
    verify: bool = True
    apply: bool = True
    force: bool = Field(
        default=False, description="apply gains even if predicted unstable or above ms_bound"
    )
    ms_bound: float = Field(
        default=2.0, gt=1.0, le=10.0, description="refuse gains whose predicted Ms exceeds it"
    )
    lambda_s: float | None = Field(
        default=None,
        gt=0.0,
        le=1e7,
        description="lambda rules: the closed-loop time constant λ, s (None: the larger of the "
        "model's lag and 3 × its dead time; integrating: 3 × the dead time)",
    )
    aim: Literal["balanced", "robust", "fast"] = Field(
        default="balanced", description="what the recommended rule favours (README)"
    )
    apply_from: RunId | None = Field(
        default=None,
        description="autotune apply: no experiment; apply_gains (a recorded run's) are applied "
        "and verified as a tune's would be",
    )
    apply_gains: PidGains | None = None
    apply_predicted_overshoot: float | None = Field(
        default=None, description="%: the recorded run's prediction for apply_gains"
    )
    apply_predicted_ms: float | None = Field(
        default=None,
        gt=0.0,
        # left out unset: a tuner before it refused every request ("Extra inputs are not
        # permitted"), a plain tune's too (autotune perf --source b961985)
        exclude_if=lambda v: v is None,
        description="the recorded run's Ms for apply_gains on its model (None: not judged); "
        "a setpoint weight against an overshoot over the limit is tried only where it is "
        "within ms_bound",
    )
    apply_timescale: float | None = Field(default=None, gt=0.0, le=1e7)
    apply_noise: float | None = Field(default=None, ge=0.0)
    rest_window: float | None = Field(
        default=None,
        gt=0.0,
        le=86400.0,
        description="drift check before the test, sim s (None: the loop's Ti, 40 samples "
        "at least, 900 s at most)",
    )
    max_overshoot: float = Field(
        default=35.0, ge=0.0, le=1000.0, description="verification: overshoot limit, %"
    )
    max_decay_ratio: float = Field(
        default=0.35, gt=0.0, le=1.0, description="verification: decay ratio limit"
    )
    overshoot_miss: float = Field(
        default=20.0,
        gt=0.0,
        le=1000.0,
        description="verification: how far (percentage points) the measured overshoot may "
        "exceed the predicted one before the model is judged wrong",
    )
    max_op_noise: float | None = Field(
        default=None,
        gt=0.0,
        le=100.0,
        allow_inf_nan=False,
        # left out unset, as apply_predicted_ms: a tuner before it refuses unknown fields
        exclude_if=lambda v: v is None,
        description="verification: output noise limit, % of output (σ of the sample-to-sample "
        "change over √2, at rest); the recommendation keeps within it where a rule can "
        "(None: 10 %)",
    )
    source: str = Field(default="operator", max_length=64)
    # wall clock (Unix s) until which the client waits for the tuner's answer: a tuner that
    # reads the request later refuses it, as its client has given up (a tuner paused for 55 s
    # started a run both its clients had reported failed, and tuned hx1 with no one watching:
    # helper trial). Left off the wire when None: a tuner of an earlier version refuses a
    # field it does not know, and the client then asks again without it (``submit``)
    answer_by: float | None = Field(
        default=None, allow_inf_nan=False, exclude_if=lambda v: v is None
    )


# how a tuner's refusal of a request it read past its ``answer_by`` says so: its client, still
# waiting the second it keeps for the answer's way back, takes it for no answer (``submit``)
ANSWERED_LATE = "after its client stopped waiting for an answer"


class TuneAccepted(Message):
    run_id: RunId
    loop: LoopId
    t: SimTime
    method: Method
    rule: str


class TuneProgress(Message):
    """Published on ``<prefix>/tune/<loop>/progress`` while a run goes on."""

    run_id: RunId
    loop: LoopId
    t: SimTime
    phase: str
    cycles: int = 0
    ku: float | None = None
    pu: float | None = None
    message: str = ""


def verify_message(gains: PidGains) -> str:
    """A ``verify`` progress's ``message``: the gains that verification verifies (the report
    tells a run's two verifications apart by it where the run ended in one)."""
    ti = "off" if gains.ti is None else f"{gains.ti:.4g} s"
    weight = "" if gains.beta == 1.0 else f", β {gains.beta:g}"
    return f"Kc {gains.kc:.4g}, Ti {ti}, Td {gains.td:.4g}{weight}"


class TunerEvent(Message):
    """An experiment's event (relay switch, cycle, trial, phase change) with its sim time."""

    run_id: RunId
    loop: LoopId
    t: SimTime
    kind: str
    data: dict[str, float | int | str | None]


class Verification(Message):
    """A setpoint step and a load step on the loop with a set of gains."""

    gains: PidGains
    sp_step: float
    overshoot: float | None = Field(description="% of the setpoint step")
    decay_ratio: float | None = Field(description="second peak over first (ZN aim: 0.25)")
    rise_time: float | None
    settling_time: float | None = Field(
        description="s to stay within settling_band of the step (the noise averaged)"
    )
    settling_band: float | None = Field(
        default=None,
        description="% of the setpoint step: the band settling_time is read within, 2 % or "
        "3σ of the PV's noise where that is wider (37.5 % on a step 8σ tall)",
    )
    iae_sp: float | None = Field(description="PV units·s; None: no setpoint step was measured")
    load_step: float | None = Field(description="% of output, None when the model has no load")
    iae_load: float | None
    max_deviation_load: float | None
    recovery_time: float | None
    stable: bool
    saturated: bool = Field(description="the output sat at a limit for a third of the time")
    score: float = Field(
        description="IAE per unit step, setpoint and load together, s (the load's IAE in % "
        "of the PV's span per % of output)"
    )
    stopped: str | None = Field(
        default=None, description="why the verification was cut short (runaway), if it was"
    )
    op_noise: float | None = Field(
        default=None, description="σ of the output at rest with these gains, % of output"
    )
    op_limited: float | None = Field(
        default=None,
        description="s of the setpoint step's response the output spent at a limit (then the "
        "response is not the linear loop's); None: no step measured",
    )
    op_rest: float | None = Field(default=None, description="% of output at rest before the test")
    kick: float | None = Field(
        default=None, description="% of output: the setpoint step's proportional kick, |Kc·step|"
    )
    ringing: float | None = Field(
        default=None,
        description="the loop's oscillatory mode, fitted on the setpoint and load responses: "
        "its amplitude ratio over one period (the larger of the two); None: no mode stands out "
        "of the noise",
    )
    ringing_period: float | None = Field(default=None, description="s: that mode's period")
    unmodelled_ringing: float | None = Field(
        default=None,
        description="a fast oscillatory mode of the setpoint step's response that the process "
        "model's response to it does not have: its amplitude ratio over one period; None: "
        "none stands out of the noise (or no model)",
    )
    unmodelled_period: float | None = Field(default=None, description="s: that mode's period")
    margin_factor: float | None = Field(
        default=None,
        description="the gain-margin check of gains with a derivative: Kc × this (Ti and Td "
        "kept) after they passed, a setpoint step of half the verification's; None: not made",
    )
    margin_swing: float | None = Field(
        default=None,
        description="the check's RMS swing over its last time scale, about that time scale's "
        "straight line (a slow approach is no swing), the noise taken off, as a fraction of "
        "its step",
    )
    margin_growth: float | None = Field(
        default=None,
        description="that swing over the least of the time scales before it (the first, the "
        "step's own response, left out); None: not read",
    )
    margin_stopped: str | None = Field(
        default=None, description="why the check was cut short (failed), if it was"
    )
    margin_ringing: float | None = Field(
        default=None,
        description="where the gains rang with a fast mode the model lacks past the decay "
        "ratio limit (the check is then made for a PI too): a fast mode's amplitude ratio over "
        "one period in the check (1 or more: it grows at that gain); None: none read",
    )
    margin_ringing_period: float | None = Field(
        default=None, description="s: that mode's period in the check"
    )


class TuneResult(Message):
    """Published on ``<prefix>/tune/<loop>/result`` when a run ends, whatever the outcome."""

    run_id: RunId
    loop: LoopId
    t: SimTime
    method: Method
    rule: str
    pv_units: str = ""
    pv_range: tuple[float, float] | None = Field(
        default=None,
        description="the loop's transmitter range (lo, hi), PV units: the span hi − lo the "
        "% of span figures are of (None: not known, no % figures)",
    )
    status: RunStatus
    reason: str | None = None
    ku: float | None = Field(default=None, description="% of output per PV unit")
    ku_percent: float | None = Field(
        default=None, description="K_u in % of output per % of span: ku·span/100"
    )
    pu: float | None = Field(default=None, description="s")
    ku_spread: float | None = None
    pu_spread: float | None = None
    l_over_t: float | None = None
    requested_rule: str | None = None  # "auto" or the rule asked for
    ms_bound: float | None = Field(
        default=None,
        # left off the wire at the default bound: a reader of a version before it refuses
        # the field (as ``lease_user`` and ``answer_by`` are left off)
        exclude_if=lambda v: v is None,
        description="the --ms-bound the gains were judged within, where not the default "
        "(an apply of them later verifies them within the same, its gain-margin check at "
        "the same factor)",
    )
    max_op_noise: float | None = Field(
        default=None,
        # left off the wire where not asked, as ``ms_bound``: a reader before it refuses it
        exclude_if=lambda v: v is None,
        description="the --max-op-noise (% of output) the recommendation and the "
        "verification held the gains to, where asked (None: the default, 10 %); an apply of "
        "them later holds them to the same",
    )
    # the verification's other limits asked for where not the default (left off the wire
    # otherwise, as ``ms_bound``): an apply of the gains later verifies them within the same
    max_overshoot: float | None = Field(
        default=None, exclude_if=lambda v: v is None, description="%: --max-overshoot asked"
    )
    max_decay_ratio: float | None = Field(
        default=None, exclude_if=lambda v: v is None, description="--max-decay-ratio asked"
    )
    overshoot_miss: float | None = Field(
        default=None, exclude_if=lambda v: v is None, description="--overshoot-miss asked"
    )
    recommended: dict[str, Any] | None = Field(
        default=None, description="rule, reason, predicted ms"
    )
    robustness: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="per rule on the identified model"
    )
    warnings: list[str] = Field(default_factory=list)
    contradiction: str | None = Field(
        default=None,
        description="why no gains of this run may be applied: its identification contradicts "
        "itself (a ramp's bracketed ultimate point and its record's model's own twice apart); "
        "`autotune apply` refuses the run for it",
    )
    step: dict[str, bool | float | int | str | None] | None = Field(
        default=None, description="reaction-curve figures"
    )
    repeats: list[dict[str, bool | float | int | str | None]] | None = Field(
        default=None, description="repeated step tests: every test's figures (step: the mean)"
    )
    step_percent: dict[str, float | None] | None = Field(
        default=None,
        description="the step's process gains in % of span: gain (% of span per %), "
        "reaction_rate (% of span per s per %), a (% of span per %); ×100/span",
    )
    experiment: dict[str, bool | float | int | str | None] = Field(default_factory=dict)
    model_gain_percent: float | None = Field(
        default=None,
        description="the identified model's gain (experiment's model_gain) in % of span per % "
        "(integrating: % of span per s per %): model_gain·100/span",
    )
    gains: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="every rule, every form; isa_percent: kc (% per % of span), ti, td (s), "
        "pb (100/kc, % of span), where pv_range is known",
    )
    chosen: dict[str, Any] | None = None
    previous_gains: PidGains | None = None
    applied: bool = False
    before: Verification | None = None
    after: Verification | None = None
    restored: bool = False
    untouched: bool = Field(
        default=False,
        description="nothing was sent to the loop: the run ended before its first write "
        "(refused, or not started)",
    )
    rest: dict[str, float | int | str | bool | None] | None = Field(
        default=None, description="the drift check before the test: window, waited, drift"
    )
    acceptance: dict[str, float | bool | str | None] | None = Field(
        default=None, description="the verification's limits and whether they were met"
    )
    left: dict[str, Any] | None = Field(
        default=None,
        description="the loop as the run left it: mode, sp, op, gains, pv (its last sample), "
        "pv_rest (the mean at rest it was judged by; None when not waited for or not at rest), "
        "pv_target, band (how far from the target counts as back), returned, waited",
    )
    pv_outside: dict[str, float | int | None] | None = Field(
        default=None,
        description="where the PV went past the run's PV limits, over every sample it read "
        "(the wait for its return included): peak (PV units), samples, seconds, first_t, "
        "last_t (s); None: it stayed within them",
    )
    applied_from: str | None = Field(
        default=None,
        description="autotune apply: the run whose recorded gains this run applied and verified",
    )
    identified_on: dict[str, Any] | None = Field(
        default=None,
        description="the loop the run identified: node, instance, model, model_params, "
        "sample_time (autotune apply checks it is still the same)",
    )
    timescale: float | None = Field(
        default=None, description="s: the identified loop's time scale (verification windows)"
    )
    noise: float | None = Field(default=None, description="the PV's noise σ seen, PV units")
    sim_duration: float = 0.0
    wall_time: float = 0.0


__all__ = [
    "ANSWERED_LATE",
    "COMMANDS",
    "Action",
    "AdvanceCommand",
    "ClockMode",
    "Command",
    "DisturbanceCommand",
    "GainsCommand",
    "LoopInfo",
    "LoopStatus",
    "Message",
    "Mode",
    "ModeCommand",
    "OutputCommand",
    "PidGains",
    "ProcessSample",
    "ServiceStatus",
    "SetpointCommand",
    "SyncCommand",
]


MAX_INCOMPLETE = 1000  # runs a LoggerStatus lists as incomplete at most


class IncompleteRun(Message):
    """A live run whose file a logger could not write whole (a full disk, at any write up to
    its last, as the run ends): the file, and why. ``on_disk``: what reached the disk is kept
    (``autotune recover`` salvages it); False: nothing did, no file is left."""

    run_id: RunId
    loop: LoopId
    path: str = Field(description="the run's file, absolute, where the logger writes it")
    reason: str = Field(description="why it could not be written, e.g. No space left on device")
    on_disk: bool


class LoggerStatus(Message):
    """Health and counters of one logger process (queryable ``<prefix>/logger/<node>/status``)."""

    node: str
    runs_dir: str
    open_runs: list[str]
    finished_runs: int = Field(ge=0)
    received: int = Field(ge=0)
    written: int = Field(ge=0)
    invalid: int = Field(ge=0, description="payloads that failed validation, left out")
    dropped: int = Field(ge=0, description="process samples missing (gaps in seq)")
    incomplete_runs: list[IncompleteRun] = Field(
        default_factory=list,
        max_length=MAX_INCOMPLETE,
        # left off the wire when empty: a client before it refuses a status with a field it
        # does not know, and a logger with nothing to say would have been unreadable to it
        exclude_if=lambda v: not v,
        description="the latest runs whose file could not be written whole, open or finished: "
        "a client that ran one says so rather than take its file for the run's record",
    )


MonitorFlag = Literal["oscillating", "sluggish", "saturated", "degraded"]


class LoopMonitor(Message):
    """A loop watched in normal operation, no test signal: one window's figures and flags.

    Published by the tuner on ``<prefix>/monitor/<loop>`` every window for each loop it tuned
    (``node`` the tuner; ``autotune watch --json`` prints the same object, ``node`` "watch").
    Errors are e = sp − pv in PV units, over the samples in auto; Hägglund's detector (IAE
    between zero crossings of the error against ``iae_limit`` = a·T_u/π) counts ``detections``
    within 50 T_u and flags an oscillation beyond ``detection_limit``; ``idle_index`` (−1…1)
    reads the load disturbances (near +1: sluggish). ``flags`` maps each flag to its reason;
    ``baseline`` holds the last tune's figures compared with (``run_id``).
    """

    loop: LoopId
    node: str
    t: SimTime = Field(description="the window's last sample, s")
    t_start: SimTime = Field(description="the window's first sample, s")
    samples: int = Field(ge=0)
    auto_fraction: float = Field(ge=0.0, le=1.0, description="of the samples, in auto")
    pv_units: str = ""
    period: float = Field(gt=0.0, description="T_u the detector used, s")
    period_source: str = Field(description="where T_u came from")
    iae_rate: float | None = Field(ge=0.0, description="IAE per unit time: mean |e|, PV units")
    error_std: float | None = Field(ge=0.0, description="s.d. of the error, PV units")
    saturation: float | None = Field(ge=0.0, le=100.0, description="% of time at an op limit")
    travel: float | None = Field(ge=0.0, description="Σ|Δop| over the window, % of output")
    travel_rate: float | None = Field(ge=0.0, description="output travel, % per hour in auto")
    reversals: int | None = Field(ge=0, description="output reversals over the window")
    oscillating: bool
    oscillation_period: float | None = Field(gt=0.0, description="s, when oscillating")
    detections: int = Field(ge=0, description="most detections within 50 T_u in the window")
    detection_limit: int = Field(ge=0, description="n_lim: more is an oscillation")
    iae_limit: float = Field(ge=0.0, description="IAE_lim, PV units·s")
    idle_index: float | None = Field(ge=-1.0, le=1.0)
    flags: dict[MonitorFlag, str]
    run_id: RunId | None = Field(description="the tune compared with, if any")
    figures: dict[str, float | int | None] = Field(
        default_factory=dict,
        description="more figures: error_mean, reversal_rate, reversal_deadband, op_noise, "
        "pv_noise, duration, supervision, amplitude, pv_noise_estimate, idle_seconds",
    )
    baseline: dict[str, Any] | None = Field(
        default=None, description="the last tune's figures compared with"
    )
    notes: list[str] = Field(default_factory=list)
