"""The experiment protocol: what every experiment (relay, ramp, step) is, and what it gives.

An experiment is a state machine fed one sample at a time (``feed``); after each sample it
says what it wants the loop to hold (a ``Demand``), keeps a list of typed ``Event``s and,
once ``finished``, its findings (``identification``). ``driver.drive`` runs any of them over
a loop; ``methods`` maps a method's name to its builder. Given the same set-up (``Setup``,
published as the run's ``experiment`` event) and the same samples, the live tuner and the
offline analysis reach the same K_u, P_u or reaction curve, to the bit.

Units: time in s (sim time), PV in engineering units, output in % of its range.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any, NamedTuple, Protocol

from services.autotuner.identify.model_fit import ProcessFit, StepModel
from services.autotuner.identify.reaction_curve import IntegratingCurve, ReactionCurve
from shared.control.forms import MAX_KC_PERCENT, MIN_RAMP_KC_PERCENT, kc_percent
from shared.control.record_stops import CalmCheck
from shared.control.signals import Sample, end_test, ends_batch, no_response_floor


@dataclass(frozen=True)
class Demand:
    """What an experiment wants the loop to hold from the sample it was fed on.

    In manual (relay, step test): the output ``op`` (%). In auto, P-only (ramp): the gain
    ``kc`` (% per PV unit) and the setpoint ``sp`` (PV units)."""

    op: float | None = None
    kc: float | None = None
    sp: float | None = None

    @property
    def auto(self) -> bool:
        """The loop runs in auto (P-only at ``kc``) rather than in manual."""
        return self.kc is not None


class Event(NamedTuple):
    """Something the experiment did or saw, at sim time ``t`` (s): ``kind`` names it
    (``switch``, ``cycle``, ``trial``, ``aborted``…), ``data`` holds its numbers."""

    t: float
    kind: str
    data: dict[str, Any]


@dataclass(frozen=True)
class Progress:
    """What the experiment has done so far, for a progress line: reported once per new
    ``count`` (a relay cycle, a ramp trial, the step), never at 0."""

    phase: str
    count: int
    cycles: int = 0
    ku: float | None = None
    pu: float | None = None
    message: str = ""


class Findings(Protocol):
    """An experiment's figures as the run's ``experiment`` JSON object."""

    def to_dict(self) -> dict[str, Any]: ...


@dataclass
class Identification:
    """What an experiment found, in the terms the rules and the verification need."""

    ku: float | None = None
    pu: float | None = None
    ku_spread: float | None = None
    pu_spread: float | None = None
    step: ReactionCurve | IntegratingCurve | None = None  # the step test's figures
    step_model: StepModel | None = None
    model: ProcessFit | None = None  # the process model fitted to the test (relay, step)
    experiment: Findings | None = None
    timescale: float = 0.0  # s: the loop's natural period, for verification windows
    noise: float = 0.0
    rest_pv: float = math.nan
    # evidence of integration in the record: True when the PV ramps under a constant output,
    # False when it settles, None when the experiment did not tell (``model_check`` then
    # accepts an integrating model only if it reproduces the measured ultimate point)
    integrating: bool | None = None
    notes: list[str] = field(default_factory=list)  # what the engineer must know (warnings)
    # repeated step tests: every test's curve (``step`` is then their mean); empty otherwise
    repeats: list[ReactionCurve | IntegratingCurve] = field(default_factory=list)
    # False when the experiment did not pin the model's static gain (a relay without bias: its
    # mean output never moves, so K is extrapolated from points near ω_u): the rules that
    # scale with 1/K (AMIGO, SIMC) are then offered but not recommended
    static_gain_known: bool = True
    # True when K_u lies between two gains tried on the loop (a ramp's bracket): its spread
    # bounds it, and a fitted model's own K_u says nothing more (``stated_spreads``)
    ku_bracketed: bool = False
    # True when the PV first went the other way after a push (a right-half-plane zero) that
    # the fitted models have no term for: their Ms is optimistic, most of all a derivative's
    # (which acts at the high frequencies where such a zero raises the gain)
    inverse_response: bool = False
    # (K_u, P_u, their relative uncertainty) a step test's record implies by itself
    # (``step_frequency``): no rule uses it; the model is judged against it as against a
    # measured ultimate point
    record_point: tuple[float, float, float] | None = None


DIRECT_NOTE = (
    "direct-acting loop: the model and its gain are of the process as its controller acts on "
    "it, the sign of its gain turned (−G), as the PID block's direct action turns it"
)


def as_controlled(ident: Identification, direction: float) -> Identification:
    """An open-loop test's findings as the controller acts on the process: for a
    direct-acting loop (``direction`` −1, the PV falls as the output rises) the step model's
    and the model's gains (and reaction rate) with their sign turned, so that the rules, the
    model checks and the robustness see a positive gain and give gains for the block's
    action, and so the model the result states; the measured reaction curve is kept as
    measured. Unchanged for a reverse-acting loop."""
    if direction > 0:
        return ident
    sm, model = ident.step_model, ident.model
    if sm is not None:
        sm = replace(
            sm,
            gain=-sm.gain if math.isfinite(sm.gain) else sm.gain,
            rate=-sm.rate if sm.rate is not None else None,
        )
    if model is not None:
        model = replace(model, gain=-model.gain)
    found = ident.experiment  # the result's model (the record's fit), the same way
    if is_dataclass(found) and getattr(found, "model", None) is not None:
        found = replace(found, model=replace(found.model, gain=-found.model.gain))
    return replace(
        ident, step_model=sm, model=model, experiment=found, notes=[*ident.notes, DIRECT_NOTE]
    )


def action_question(direction: float) -> str:
    """What a PV moving against an experiment's push asks of a loop of ``direction`` (+1
    reverse-acting, −1 direct): a process whose gain has the other sign than its action."""
    action, other = ("reverse", "direct") if direction > 0 else ("direct", "reverse")
    return f"the loop is {action}-acting; is the process one for a {other}-acting PID?"


def snapped(op: float, limits: tuple[float, float]) -> float:
    """An experiment's output (%) at the output limit it passes by rounding alone (1e-9 of
    the limits' span): a relay's bias less its amplitude, sized to the bottom of its room,
    came to −7.1e-15 %, which the output command refused, and the run failed (lvl2, seed 2).
    Further outside, it is left to be refused."""
    lo, hi = limits
    tol = 1e-9 * max(hi - lo, 1.0)
    if lo - tol <= op < lo:
        return lo
    if hi < op <= hi + tol:
        return hi
    return op


def samples_until(seconds: float, sample_time: float, t: float) -> int:
    """Samples after the one at sim time ``t`` up to the first at which ``seconds`` more may
    have passed (≥ 1), for a batch's ``horizon``: that sample may decide, so it is the
    batch's last. The rounding of the sample times (k·T, each rounded) either side of the
    limit is allowed for, and a tolerance of 1e-9 × the time (the step test's pulse and rest
    window are read so): both grow with the time, and 1e-6 of a sample alone was a sample
    short at 5e9 samples. A limit already past (or not a number) is 1; none (+inf), no
    bound."""
    x = seconds / sample_time
    if math.isnan(x) or x <= 0:
        return 1
    if math.isinf(x):
        return 1 << 30
    slack = 1e-6 + 2e-9 * max(1.0, abs(t) + abs(seconds)) / sample_time
    return max(1, math.ceil(x - slack))


def abort_band(
    pv_limits: tuple[float, float], pv_range: tuple[float, float] | None
) -> tuple[float, float]:
    """Where a sample aborts a closed-loop test: outside the PV limits, or at an end of the
    transmitter's range (``clipped``), which limits wider than the range leave inside."""
    lo, hi = pv_limits
    if pv_range is not None:
        lo, hi = max(lo, pv_range[0]), min(hi, pv_range[1])
    return lo, hi


# the fraction of the transmitter's range a relay's PV may move either way from the test's
# rest: the step test's default allowance (``StepTestConfig.max_move``)
PV_ALLOWANCE = 0.25


def range_allowance(pv_range: tuple[float, float] | None) -> float | None:
    """``PV_ALLOWANCE`` of the transmitter's range (PV units); None without a finite one."""
    if pv_range is None:
        return None
    span = pv_range[1] - pv_range[0]
    return PV_ALLOWANCE * span if math.isfinite(span) and span > 0 else None


def allowance_of(setup: Setup) -> float | None:
    """PV units a relay's PV may move from its rest (``range_allowance``); None: not asked
    (a set-up recorded before), or no finite range."""
    return range_allowance(setup.pv_range) if setup.pv_allowance else None


def allowance_band(
    limits: tuple[float, float], rest: float, allowance: float | None
) -> tuple[float, float]:
    """``limits`` narrowed to ``rest`` ± ``allowance`` (unchanged where either is unknown)."""
    if allowance is None or not math.isfinite(rest):
        return limits
    return max(limits[0], rest - allowance), min(limits[1], rest + allowance)


def beyond_allowance(pv: float, rest: float, allowance: float, t: float) -> str:
    """Why a relay aborts at a PV past its allowance, one line."""
    return (
        f"PV {pv:.4g} at t = {t:g} s is {pv - rest:+.3g} from the test's rest {rest:.4g}, past "
        f"its allowance of ±{allowance:.3g} ({100 * PV_ALLOWANCE:g} % of the transmitter's "
        "range, as the step test's): the test does not take the process further from where "
        "it rested"
    )


def run_pv_limits(
    asked: tuple[float, float] | None, pv_range: tuple[float, float]
) -> tuple[float, float]:
    """The PV limits a run keeps to: those asked (else the transmitter's range), within that
    range where it is one (lo < hi): past its ends the PV is not measured (it clips), and
    the plant refuses a setpoint there (limits of 0-100 on a range of 49-51: the
    verification stepped the setpoint to 51.2 and the run aborted)."""
    ranged = pv_range[0] < pv_range[1]  # (a range not lo < hi clips nothing it can say)
    return abort_band(tuple(asked) if asked else pv_range, pv_range if ranged else None)


def limits_problem(
    method: str,
    hysteresis: float | None,
    pv: float,
    limits: tuple[float, float],
    units: str = "",
    bump: float | None = None,
) -> str | None:
    """Why a run cannot start within its PV ``limits`` (the field at fault first), None if
    it can: a relay ``hysteresis`` of half their width or more never switches within them
    (1e308 held the relay's first push for hours of sim time), a ramp's setpoint ``bump`` of
    half their width or more cannot be taken within them (1e308 took the lease and ran the
    drift check before the plant refused the setpoint), and a PV already outside."""
    lo, hi = limits
    u = f" {units}" if units else ""
    if method == "relay" and hysteresis is not None and hysteresis >= 0.5 * (hi - lo):
        return (
            f"hysteresis: {hysteresis:g}{u} is at least half the PV "
            f"limits' width ({hi - lo:g}): the relay could not switch within them"
        )
    if method == "ramp" and bump is not None and bump >= 0.5 * (hi - lo):
        return (
            f"bump: {bump:g}{u} is at least half the PV limits' width ({hi - lo:g}): a trial's "
            "setpoint and its swing could not stay within them"
        )
    if not lo <= pv <= hi:
        return f"pv_limits: the PV {pv:.4g} is already outside [{lo:g}, {hi:g}]"
    return None


def start_gain_problem(method: str, kc_start: float | None, span: float | None) -> str | None:
    """Why a ramp cannot start at ``kc_start`` (% per PV unit), None if it can: a gain above
    ``MAX_KC_PERCENT`` % of output per % of span (a proportional band of 0.1 %) is what no
    write of gains may ask (1e308 was sent to the plant, which refused it mid-run), and one
    below ``MIN_RAMP_KC_PERCENT`` leaves the ramp a day of doublings to go."""
    if method != "ramp" or kc_start is None or span is None:
        return None
    pct = kc_percent(kc_start, span)
    if pct is None or MIN_RAMP_KC_PERCENT <= pct <= MAX_KC_PERCENT:
        return None
    if pct < MIN_RAMP_KC_PERCENT:
        return (
            f"kc_start: {kc_start:g} ({pct:.6g} % of output per % of span): a ramp starts "
            f"from at least {MIN_RAMP_KC_PERCENT:g} % per % of span (a proportional band of "
            "100,000 %), where its output still answers the PV"
        )
    return (
        f"kc_start: {kc_start:g} ({pct:.6g} % of output per % of span): a gain must be at "
        f"most {MAX_KC_PERCENT:g} % per % of span (a proportional band of 0.1 %)"
    )


def clipped(pv: float, pv_range: tuple[float, float] | None, t: float, smaller: str) -> str:
    """Why a sample ends a test, when its PV sits at an end of the transmitter's range: the
    transmitter clips there, so the swing beyond is not measured (a relay read a cycle with
    flat tops as one 33 % above K_u, its cycles agreeing to 0.13 %); empty otherwise.
    ``smaller``: the flag that makes the swing smaller."""
    if pv_range is None or pv_range[0] < pv < pv_range[1]:
        return ""
    lo, hi = pv_range
    return (
        f"PV {pv:.4g} at an end of the transmitter's range [{lo:g}, {hi:g}] at t = {t:g} s: "
        f"clipped there, its swing is not measured (a smaller {smaller} keeps it inside)"
    )


DEFAULT_RELAY_AMPLITUDE = 5.0  # %: also the load step of the verification
DEFAULT_STEP_SIZE = 5.0  # %
DEFAULT_BUMP_FRACTION = 0.01  # of the PV range, ramp setpoint bump


@dataclass(frozen=True)
class Settings:
    """What the engineer asked of the experiment, plain (the shell converts a request)."""

    amplitude: float = 5.0  # relay d, % of output
    amplitude_given: bool = False  # d was asked for (kept), not the default (it may grow)
    hysteresis: float | None = None  # relay ε, PV units; None: from the noise
    cycles: int = 3  # relay cycles that must agree
    tolerance: float = 0.02  # relative agreement asked of the result
    relay_bias: float = 0.0  # relay stage 2: low output b − (1 − relay_bias)·d
    step_size: float = 5.0  # step test, % of output
    max_time: float | None = None  # s of sim time for the experiment; None: its own budgets
    repeat: int | None = None  # step tests to run (None: one); with repeat_auto, the most
    repeat_auto: bool = False  # step tests added until their mean is known (repeated_steps)

    @classmethod
    def of(cls, req: Any) -> Settings:
        """From a tune request (read by attribute: the bus's ``TuneRequest``, or anything with
        its fields), the defaults filled in where it leaves a field unset."""
        return cls(
            amplitude=req.amplitude or DEFAULT_RELAY_AMPLITUDE,
            amplitude_given=req.amplitude is not None,
            hysteresis=req.hysteresis,
            cycles=req.cycles,
            tolerance=req.tolerance,
            relay_bias=req.relay_bias or 0.0,
            step_size=req.step_size or DEFAULT_STEP_SIZE,
            max_time=req.max_time,
            repeat=None if req.repeat in (None, "auto") else req.repeat,
            repeat_auto=req.repeat == "auto",
        )


@dataclass(frozen=True)
class Setup:
    """What the live loop contributes to an experiment (logged as the ``experiment`` event,
    so that a replay rebuilds the same state machine). Limits in % (output) and PV units."""

    sample_time: float  # s
    op_lo: float
    op_hi: float
    pv_lo: float  # abort outside (the request's pv_limits, or the transmitter's range)
    pv_hi: float
    pv_range_lo: float | None = None  # the transmitter's range: where the PV clips
    pv_range_hi: float | None = None
    pv_units: str | None = None
    time_scale: float | None = None  # s: the loop's slowest known dynamics (the rest window)
    kc_start: float | None = None  # closed-loop tests: first gain, % per PV unit
    bump: float | None = None  # closed-loop tests: setpoint bump, PV units
    sp_start: float | None = None  # closed-loop tests: the setpoint at the start
    op_start: float | None = None  # open-loop tests: the output held at the start, %
    direction: float | None = None  # +1 reverse-acting loop, −1 direct (None: unrecorded, +1)
    # True on the realtime clock: a changed output is held from the sample after the one that
    # caused it (or later), so an output record is read from the samples, each of which
    # carries the output held from it (None: lockstep, held from the sample that caused it)
    outputs_from_samples: bool | None = None
    # True: a relay test whose stage 2 is stuck for a stage-1 period sets it again from the
    # cycle it got (``RelayConfig.stuck_periods``); None: a run recorded before, whose stage 2
    # was abandoned there instead (so its replay makes the live run's decisions)
    stage_two_rearm: bool | None = None
    # True: a relay test's stage 2 arms a switch still locked out once the PV is back past
    # the level it switched at (``RelayConfig.arm_at_turn``); None: a run recorded before,
    # whose lockout held until it was overdue by a stage-1 period (so its replay makes the
    # live run's decisions)
    stage_two_turn: bool | None = None
    # True: such a stage 2, ended on two agreeing cycles, keeps its points as measured where
    # a correction would move them by more than that (``RelayConfig.steady_second``); None:
    # recorded before, its points always corrected
    stage_two_steady: bool | None = None
    # True: a relay whose stage-1 cycle lies within its hysteresis (switching on the noise)
    # widens it and counts again (``RelayConfig.chatter_widenings``); None: recorded before,
    # such cycles counted as any other
    relay_chatter: bool | None = None
    # True: a relay whose PV comes to rest against its push before any switch aborts there
    # (``RelayConfig.wrong_way``); None: recorded before, it ran to its time budget
    relay_wrong_way: bool | None = None
    # True: that rest must hold from some time T after the relay began to 2T
    # (``RelayConfig.rest_twice``); None: recorded before, the first reading of it aborted
    relay_rest_twice: bool | None = None
    # True: a relay whose stage-1 cycles ride on their hysteresis grows its amplitude, where
    # the request left it to the default, and counts again (``RelayConfig.grow_times``);
    # None: recorded before, d kept
    relay_grow: bool | None = None
    # True: a relay's whole-record fit of an integrating model also fits the held output's
    # offset from its balance (``RelayConfig.fit_offset``); None: recorded before, it did not
    relay_offset: bool | None = None
    # True: a ramp whose trials went against their bumps, none oscillating, aborts there
    # (``RampConfig.stop_wrong_way``); None: recorded before, it ran on to its limits
    ramp_wrong_way: bool | None = None
    # True: a relay or ramp whose PV reaches an end of the transmitter's range (clipped)
    # aborts there (``experiments.clipped``); None: recorded before, it measured on
    pv_clip: bool | None = None
    # True: a relay aborts once its PV moves more than ``PV_ALLOWANCE`` of the transmitter's
    # range from the test's rest (``allowance_band``), as the step test does; None: recorded
    # before, its PV limits alone (a relay on an integrating loop whose action was the wrong
    # one drained its level to 0 %: helper trial). Not the ramp's: its trials near K_u swing
    # further on a loop of the presets (flow1), and each trial has its own swing limit
    pv_allowance: bool | None = None
    # True: a step test's rest asks the PV's scatter about its trend to be noise (an
    # underdamped response is not at rest mid-swing); None: recorded before
    step_swing: bool | None = None
    # True: a step test's dead time that the record does not resolve is designed with the
    # most the record cannot tell from none (``StepTestConfig.bound_delay``); None: recorded
    # before, with the fit's or the floor of half a sample
    step_delay_bound: bool | None = None
    # True: a step test's trend toward a limit is taken at 2 standard errors less
    # (``StepTestConfig.trend_error``); None: recorded before, the fitted trend as it was
    step_trend_error: bool | None = None
    # True: a step test's horizon for the PV's coast once the output is restored is also
    # read off the trend's line, where it crosses the rest (``StepTestConfig.coast``); None:
    # recorded before, twice the time the PV took to start moving
    step_coast: bool | None = None
    # True: a step test's PV that began to move only a few samples ago, its steps shrinking
    # as a lag's do, is judged on where those steps lead (``StepTestConfig.early_approach``);
    # None: recorded before, the straight line alone until twelve samples since the move
    step_early_approach: bool | None = None
    # True: a step test's trend toward the engineer's limits is extended over the samples to
    # the next check too, and is the fitted one without the baseline's drift where that drift
    # opposes it (``StepTestConfig.drift_guard``); None: recorded before
    step_drift_guard: bool | None = None
    # True: the transmitter's resolution (``rest_window.RESOLUTION`` of its range) floors what
    # counts as a response to the output (a relay or step test whose PV moves within it
    # aborts there) and as a drift before a test (a noise-free PV's creep within it is rest);
    # None: recorded before
    resolution: bool | None = None
    # True: a relay's stage-1 cycles that repeat a pattern of a few cycles are steady
    # (``RelayConfig.pattern_cycles``); None: recorded before, not looked for
    relay_pattern: bool | None = None
    # True: a relay's cycle closes at one crossing of r per switch up, none sooner after it
    # than a quarter of the time the last took (``RelayConfig.early_crossing``), and its
    # chatter is judged against the hysteresis the noise needs where the given one is
    # smaller (``RelayConfig.noise_chatter``); None: recorded before
    relay_noise: bool | None = None
    # True: a noise-free relay cycle (σ within the resolution and the rounding) is smoothed
    # over 3 samples, not a twentieth of it (``RelayConfig.smooth_floor``); None: recorded
    # before, a twentieth wherever σ > 0
    relay_smooth_floor: bool | None = None
    # True: a ramp trial closes early, and its fit counts, only on an oscillation that swings
    # out of the noise (``RampConfig.seen_fits``); None: recorded before
    ramp_seen_fits: bool | None = None
    # True: a ramp that cannot go on between trials puts the setpoint back where it began
    # and calms the loop there before it aborts (``RampConfig.hand_back``); None: recorded
    # before, aborted at once
    ramp_hand_back: bool | None = None
    # True: a ramp trial's response has died out only once flat against how far it moved
    # (``RampConfig.settled_by_move``); None: recorded before, flat against the bump alone
    ramp_settled: bool | None = None
    # True: the ramp's process model is also fitted from lags far apart and from an
    # integrator behind a lag (``RampConfig.more_starts``); None: recorded before, without
    ramp_more_starts: bool | None = None
    # True: a ramp trial's period shorter than the dead time the first trial showed is not the
    # loop's time scale (``RampConfig.period_floor``); None: recorded before, every period was
    ramp_period_floor: bool | None = None
    # True: a ramp's calming between trials, while every trial went against its bump with
    # none oscillating or decaying, aborts once its PV runs further from the trial's rest
    # than the step test's allowance, or twice the trial's swing limit where that is more
    # (``RampConfig.calm_allowance``); None: recorded before (or the engineer's own PV limits
    # given), its PV limits alone (a ramp on a level whose action was the wrong one calmed it
    # to 0 %: helper trial)
    ramp_calm_guard: bool | None = None
    # True: a step test read as integrating fits its ramps' slowing with its dead time (a lag
    # far slower than the test: ``reaction_curve.fit_integrator``'s leak); None: recorded
    # before, straight ramps
    step_leak: bool | None = None
    # True: a step test's check for a PV heading out reads the trend since the PV began to
    # move where that is slower (``StepTestConfig.trend_since_move``); None: recorded before
    step_trend_since_move: bool | None = None
    # True: a step test's ramp is steady once its slope changes by under 0.5 % across its
    # window, and one within the noise and the resolution is no response
    # (``StepTestConfig.steady_floor``); None: recorded before, a floor of 1e-6
    step_steady_floor: bool | None = None

    def resolution_floor(self) -> float:
        """PV units: what the transmitter does not resolve (``signals.no_response_floor``),
        where the set-up asks (``resolution``, with its range known); 0 otherwise. A move of
        the PV within it answers no output, and a drift within it over a rest window is
        rest."""
        rng = self.pv_range
        return no_response_floor(rng) if self.resolution and rng is not None else 0.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Setup:
        """From the event's data (unknown keys ignored; TypeError if a required one lacks)."""
        return cls(**{f.name: d[f.name] for f in fields(cls) if f.name in d})

    def to_dict(self) -> dict[str, Any]:
        """The event's data: the fields that are set, in this order."""
        return {f.name: v for f in fields(self) if (v := getattr(self, f.name)) is not None}

    @property
    def op_limits(self) -> tuple[float, float]:
        return (self.op_lo, self.op_hi)

    @property
    def pv_limits(self) -> tuple[float, float]:
        return (self.pv_lo, self.pv_hi)

    @property
    def pv_range(self) -> tuple[float, float] | None:
        if self.pv_range_lo is None or self.pv_range_hi is None:
            return None
        return (self.pv_range_lo, self.pv_range_hi)


# The set-up's switches each method runs with today, live and in the benchmark: every
# behaviour added since recordings began. Off (None) in a set-up recorded before one was,
# so that its replay rebuilds the state machine that ran.
_LIVE_FLAGS: dict[str, tuple[str, ...]] = {
    "relay": (
        "stage_two_rearm",
        "stage_two_turn",
        "stage_two_steady",
        "relay_chatter",
        "relay_wrong_way",
        "relay_rest_twice",
        "relay_grow",
        "relay_offset",
        "relay_pattern",
        "relay_noise",
        "relay_smooth_floor",
        "pv_clip",
        "pv_allowance",
        "resolution",
    ),
    "ramp": (
        "ramp_wrong_way",
        "ramp_seen_fits",
        "ramp_hand_back",
        "ramp_settled",
        "ramp_more_starts",
        "ramp_period_floor",
        "ramp_calm_guard",
        "pv_clip",
        "resolution",
    ),
    "step": (
        "step_swing",
        "step_delay_bound",
        "step_leak",
        "step_trend_since_move",
        "step_steady_floor",
        "step_trend_error",
        "step_coast",
        "step_early_approach",
        "step_drift_guard",
        "resolution",
    ),
}


def live_flags(method: str) -> dict[str, bool]:
    """The set-up's switches a run of ``method`` has on today (``Setup`` keywords): what the
    live tuner asks, and what the benchmark must ask to measure the same experiment. Why one
    list: the benchmark built its set-up without them and measured the ramp as recorded
    before its fits had to stand out of the noise (at 3 % noise, seeds 1-7, trials closed on
    fits of the noise put K_u 15 % high on 1/(s+1)⁴, which the live tuner reads within 1.1 %)."""
    return dict.fromkeys(_LIVE_FLAGS.get(method, ("resolution",)), True)


@dataclass(frozen=True)
class Band:
    """The PV range (PV units, open at both ends; ±inf: unbounded), and the output's (%),
    inside which the samples to come change nothing the loop must be told: a batch may run
    on while both stay inside, and must end with the first sample at or past a bound
    (``shared.control.signals.ends_batch``)."""

    below: float
    above: float
    op_below: float = -math.inf
    op_above: float = math.inf
    # a P-gain ramp calming: the batch also ends at its first calming check that passes
    calm: CalmCheck | None = None

    def ends(self, pv: float, op: float | None = None) -> bool:
        """True for the sample (PV ``pv``, output ``op``) past the band's bounds."""
        return ends_batch(pv, op, self.stops(), self.op_stops())

    def end_test(self) -> Callable[[float, float | None], bool]:
        """The test that ends a batch, asked of its every sample in turn: ``ends``, the stops
        read once (``end_test``), and the calming check (``calm``: stateful, one per batch)."""
        test = end_test(self.stops(), self.op_stops())
        return test if self.calm is None else self.calm.end_test(test)

    def stops(self) -> tuple[float | None, float | None]:
        """(stop_below, stop_above) of an AdvanceCommand: None for an unbounded side."""
        return _bound(self.below), _bound(self.above)

    def op_stops(self) -> tuple[float | None, float | None]:
        """(stop_op_below, stop_op_above) of an AdvanceCommand."""
        return _bound(self.op_below), _bound(self.op_above)


def _bound(x: float) -> float | None:
    return x if math.isfinite(x) else None


class Experiment(Protocol):
    """The interface every experiment implements (and the driver relies on)."""

    events: list[Event]
    reason: str  # why it aborted ("" otherwise)
    # True when the experiment must know the sim time from which a changed demand holds (an
    # open-loop step is timed from it); the driver then reports it through ``held``
    needs_hold_time: bool

    @property
    def finished(self) -> bool: ...

    @property
    def closing(self) -> Demand | None:
        """Once finished, what the loop must hold at once, before ``identification`` computes
        the findings (None: nothing to apply). That computation can take seconds, and on the
        realtime clock the loop runs on meanwhile: an output left at an experiment's level
        that long drives the PV to its full static response."""
        ...

    @property
    def demand(self) -> Demand:
        """What it wants held now (before any sample: what it starts from)."""
        ...

    def feed(self, sample: Sample) -> Demand:
        """Take one sample; return what to hold from ``sample.t`` on."""
        ...

    def held(self, t: float) -> None:
        """The driver reports the sim time from which the last changed demand holds."""
        ...

    def horizon(self, cap: int) -> int:
        """How many samples (≤ ``cap``, ≥ 1) may pass before its next demand matters — as
        long as the PV stays in ``band()`` when that is not None."""
        ...

    def band(self) -> Band | None:
        """The PV (and output) band within which the next ``horizon`` samples decide nothing
        (None: any sample may matter only by count, as ``horizon`` says)."""
        ...

    def progress(self) -> Progress: ...

    def identification(self) -> Identification | None:
        """Its findings once done (None if it has none)."""
        ...
