"""Open-loop step test (process reaction curve), as a state machine fed one sample at a time.

In manual at the present output: a quiet baseline (noise and rest value), a step of ``size``
% in the output, samples until the PV is at rest again (``reaction_curve.settled``), then the
reaction-curve figures. It stops, and the driver restores the output, when:

* the PV sits at (or within noise of) an end of the transmitter's range ``pv_range`` before
  the step: a clipped measurement is flat and noise-free, so it cannot show rest;
* after the step, the PV reaches an end of that range, or would within twice the time it took
  to start moving plus four samples (about what it keeps moving for once the output is
  restored);
* the PV would leave the band of ``max_move`` × its range about its rest before the step
  (the test's allowance: an integrating loop never stops moving, a self-regulating one with a
  large gain may go far);
* the PV would leave ``pv_limits`` within that time (the experiment stops before the PV
  passes them, not once it has), leaves them, or no rest comes within ``timeout`` seconds
  of the step.

An integrating process (a level) never comes to rest: the PV ramps
(``reaction_curve.steady_ramp``). That is Ziegler and Nichols' original reaction curve: the
test goes on until the ramp's slope R is known to ``rate_precision`` (two standard errors) or
the PV would leave its allowance, then holds an equal and opposite pulse of the same area
(the step's size for as long as the step was held, or a smaller pulse for longer where the
output's limits leave less room), which gives the integrator back its level, and ends with an
``IntegratingCurve``: K' = R and the dead time L where the ramp's line meets the baseline.

``services.autotuner.step_run.run_step_test`` drives a live loop with it, always restores the
loop's mode and output, and then waits (bounded) for the PV to return to rest, so that what
runs next starts from rest. Samples are any object with ``t``, ``pv`` and ``op`` (the bus's
``ProcessSample`` among them): no I/O here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from services.autotuner.identify import inverse_response
from services.autotuner.identify.experiments import (
    Band,
    Demand,
    Event,
    Identification,
    Progress,
    Settings,
    Setup,
    action_question,
    as_controlled,
    samples_until,
)
from services.autotuner.identify.model_fit import (
    ProcessFit,
    StepModel,
    choose_on_record,
    delay_spread,
    model_of,
    refine_on_record,
)
from services.autotuner.identify.reaction_curve import (
    LOOSE_BAND,
    MIN_CHANGE_SIGMAS,
    RAMP_STEADY_FLOOR,
    RAMP_STEADY_FLOOR_BEFORE,
    REST_BAND,
    IntegratingCurve,
    ReactionCurve,
    SteadyRamp,
    analyze_step,
    band_reachable,
    fit_integrator,
    settled,
    steady_ramp,
)
from services.autotuner.identify.step_frequency import response_point
from shared.control.beyond import beyond
from shared.control.forms import MIN_STEP
from shared.control.signals import Sample, at_rest, line_fit, noise_level, range_end
from shared.errors import AutotuneError

HOLD_EVENTS = ("step_started", "pulse_started", "output_held")  # the driver's hold times
SETTLE_CHECK_EVERY = 8  # samples between rest checks (each is a regression over a window)
# ... up to a record of this many times 2·SETTLE_CHECK_EVERY samples; doubled each time the
# record doubles past it: about this many checks per doubling (``check_spacing``)
CHECKS_PER_DOUBLING = 128
# standard errors of a fitted dead time (``model_fit.delay_spread``) within which it is not
# told from none, and by which a design on an unresolved one exceeds it: three, as the fitted
# figure scatters more than the linearised error says (1.4-1.9x over 12 noisy seeds)
SPREADS = 3.0
CLEAR_RUN = 5  # samples running clear of the noise that say the response has begun
# a PV's steps that shrink by this ratio a sample or faster are a lag's approach, judged on
# where they lead (``_geometric_left``): a first-order lag of T under 4.5 samples (e^{−1/4.5})
GEOMETRIC_RATIO = 0.8
# where the PV is about to leave its allowance: a ramp steady (its slope's change lost in the
# noise and resolved to 10 %) over this many apparent dead times is taken as integrating (the
# usual 10 need the PV to travel 20 dead times' worth of ramp, more than an integrator with a
# long dead time has room for: such steps were aborted, their R and L left unread)
RAMP_WINDOWS_AT_THE_EDGE = 3.0
# the words that open the step test's dead-time warning, and those that say what the design
# took instead (repeated steps and ``autotune analyze`` find the warning by them)
UNRESOLVED = "dead time not resolved by the record"
DESIGN_TAKES = "the model and the rules that rest on L take"
RETURN_WAIT_FACTOR = 3.0  # the return to rest may take this many times the step's own settling


class StepTestAborted(AutotuneError):
    """The step test stopped before a result; the loop has been restored."""


@dataclass(frozen=True)
class StepTestConfig:
    size: float = 5.0  # % of output; negative steps down
    baseline: float | None = None  # s of quiet before the step; None: 40 samples
    timeout: float = 7200.0  # s after the step to wait for rest (and, at most, to return)
    # the trend that stops a step short of a limit is taken at 2 standard errors less
    # (``_heading_out``); False: a run recorded before, the fitted trend as it was
    trend_error: bool = True  # (a run's set-up: ``Setup.step_trend_error``)
    # the time the PV keeps moving once the output is restored is also read off the trend's
    # line, where it crosses the rest before the step (``_coast``: an integrator behind a lag
    # coasts its dead time and lag); False: a run recorded before, twice the time the PV
    # took to start moving alone
    coast: bool = True  # (a run's set-up: ``Setup.step_coast``)
    # the trend toward the engineer's limits (``pv_limits``) is extended over the samples to
    # the next check too, and where the baseline drifted against it, it is the fitted one
    # without that drift (``_heading_out``); False: a run recorded before, as the allowance's
    drift_guard: bool = True  # (a run's set-up: ``Setup.step_drift_guard``)
    # a PV that began to move fewer than twelve samples ago (too few for ``_approach_left``'s
    # thirds) and whose sample-to-sample steps shrink as a lag's do goes as far as they lead
    # (``_geometric_left``); False: a run recorded before, the straight line alone
    early_approach: bool = True  # (a run's set-up: ``Setup.step_early_approach``)
    # the flag that sets ``timeout``, as the advice names it: `autotune step`'s --timeout,
    # a tune's --max-time (`step` advised "--max-time", which it does not have: helper trial)
    timeout_flag: str = "--max-time"
    pv_limits: tuple[float, float] | None = None  # abort outside; None: the loop's PV range
    # the PV may move this fraction of its range either way from its rest (the allowance)
    max_move: float = 0.25
    # integrating: the ramp's slope R is known to this, relative, at two standard errors
    rate_precision: float = 0.02
    # rest also asks the PV's scatter about its trend to be noise (``reaction_curve.settled``
    # ``swing``); False: a run recorded before, whose rest was its trend's alone
    swing_check: bool = False
    # PV units the transmitter does not resolve (``Setup.resolution_floor``; 0: none, a run
    # recorded before or no range known): a response within it is none, and the test aborts
    # (a valve stuck in its deadband read as a gain of 4e-8); a baseline may drift within it
    # and be rest (a noise-free PV's creep after a test was told "keeps drifting" where the
    # tuner's own rest check had just found rest)
    resolution: float = 0.0
    # a dead time the record does not resolve is designed with the most the record allows
    # (``StepTest._design_delay``); False: a run recorded before, designed with the fit's, or
    # the floor of half a sample
    bound_delay: bool = False
    # an integrating read fits its ramps' slowing with L (``fit_integrator``'s ``slowing``);
    # False: a run recorded before, straight ramps
    leak: bool = False
    # the check for a PV heading out reads the trend since the PV began to move where that is
    # the slower one, and a PV that moved then stopped goes no further (``_heading_out``);
    # False: a run recorded before, the window's straight line alone
    trend_since_move: bool = True
    # a ramp's slope changing by under ``RAMP_STEADY_FLOOR`` across its window is steady,
    # and a ramp within the noise and the resolution is no response (``_after_step``);
    # False: a run recorded before, a change of 1e-6 the floor and no such guard
    steady_floor: bool = True


@dataclass(frozen=True)
class StepFindings:
    """The run's ``experiment`` object for a step test."""

    step_size: float  # % of output
    method: str  # how the reaction curve was read (``ReactionCurve.method``)
    model: ProcessFit | None  # refined on the record (None: the tangent's model stands)

    def to_dict(self) -> dict[str, Any]:
        return {
            "step_size": self.step_size,
            "method": self.method,
            **(self.model.to_dict() if self.model else {}),
        }


@dataclass
class StepTest:
    """The experiment; ``feed`` each sample, hold the output it returns.

    ``pv_range`` is the transmitter's range, which clips the measured PV (None: ``pv_limits``
    stand for it); ``pv_units`` only words the reasons.
    """

    config: StepTestConfig
    op_start: float
    op_limits: tuple[float, float]
    pv_limits: tuple[float, float]
    sample_time: float
    pv_range: tuple[float, float] | None = None
    pv_units: str = ""
    # PV units the baseline may drift over its window and still be rest: a repeated test's
    # return's exponential tail, which a noise-free PV shows (0: the noise alone decides)
    rest_drift: float = 0.0
    # baseline → step → done | aborted; integrating: step → return (the pulse) → settle → done
    phase: str = "baseline"
    reason: str = ""
    t_step: float | None = None
    result: ReactionCurve | IntegratingCurve | None = None
    ramp: SteadyRamp | None = None  # set when the test stopped on an integrating response
    _pulse_op: float = math.nan  # integrating: the return pulse's output, %
    _pulse_for: float = 0.0  # s it is held (equal area: step size × time held / its size)
    _pulse_start: float | None = None  # sim time from which it is held
    _stopped: tuple[float, float, str] = (math.nan, math.nan, "")  # t, PV, and why the step ended
    _settle: tuple[float, float] = (math.inf, math.inf)  # integrating: rest window from, until
    _restore_at: float | None = None  # integrating: sim time the output is back at its start
    _pulse_end_seen: float = math.nan  # integrating: the sample at which the pulse ended
    # +1 reverse-acting loop, −1 direct: its findings are given as its controller acts
    # (``as_controlled``); the curve itself is kept as measured
    direction: float = 1.0
    t: list[float] = field(default_factory=list)
    pv: list[float] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    _baseline_samples: int = 0
    _pv_before: float = math.nan
    _noise: float = 0.0
    # PV units/s: the baseline's drift at the step, the part of its straight line clear of
    # 2 standard errors (0: none, or within them)
    _drift: float = 0.0
    _t_moved: float | None = None  # s from the step until the PV first cleared its noise
    _op: float = math.nan  # the output it wants held now

    # the reaction curve is timed from when the stepped output is held
    needs_hold_time: ClassVar[bool] = True

    def __post_init__(self) -> None:
        cfg = self.config
        if not math.isfinite(cfg.size) or abs(cfg.size) < MIN_STEP:
            raise ValueError(
                f"size {cfg.size:g}: must be a number of % at least {MIN_STEP:g} in size"
            )
        target = self.op_start + cfg.size
        lo, hi = self.op_limits
        if not lo <= target <= hi:
            raise ValueError(
                f"size {cfg.size:+g} %: the output would go from {self.op_start:g} "
                f"to {target:g} %, outside the loop's limits [{lo:g}, {hi:g}] %"
            )
        if not 0 < cfg.max_move <= 1:
            raise ValueError(f"max_move {cfg.max_move}: must be a fraction of the range, 0–1")
        if not 0 < cfg.rate_precision < 1:
            raise ValueError(f"rate_precision {cfg.rate_precision}: must be between 0 and 1")
        base = cfg.baseline if cfg.baseline is not None else 40 * self.sample_time
        if not base >= 0:
            raise ValueError(f"baseline {base}: must be ≥ 0 s")
        self._baseline_samples = max(10, math.ceil(base / self.sample_time))
        self._op = self.op_start

    @property
    def finished(self) -> bool:
        return self.phase in ("done", "aborted")

    @property
    def op_target(self) -> float:
        return self.op_start + self.config.size

    @property
    def ends(self) -> tuple[float, float]:
        """The PV values where the measurement clips: the transmitter's range."""
        return tuple(self.pv_range) if self.pv_range is not None else tuple(self.pv_limits)

    @property
    def allowance(self) -> tuple[float, float]:
        """The PV values the test may take it to: ``max_move`` × the range either way from the
        rest before the step, within the range."""
        lo, hi = self.ends
        reach = self.config.max_move * (hi - lo)
        return max(lo, self._pv_before - reach), min(hi, self._pv_before + reach)

    def _end_words(self, end: str) -> str:
        lo, hi = self.ends
        value = f"{hi if end == 'top' else lo:g}{' ' + self.pv_units if self.pv_units else ''}"
        if self.pv_range is None:
            return f"its {'upper' if end == 'top' else 'lower'} limit ({value})"
        return f"the {end} of its range ({value})"

    def _rate_units(self) -> str:
        return f"{self.pv_units or 'PV units'}/s per %"

    # --- the experiment protocol ---------------------------------------------------------

    @property
    def closing(self) -> Demand | None:
        """Finished: the output back at rest."""
        return Demand(op=self.op_start) if self.finished else None

    @property
    def demand(self) -> Demand:
        return Demand(op=self._op)

    def feed(self, s: Sample) -> Demand:
        """Take the sample at ``s.t``; return the output to hold from ``s.t`` on."""
        self._op = self._feed(s)
        return Demand(op=self._op)

    def held(self, t: float) -> None:
        """The driver reports the sim time from which the changed output is held (event
        ``step_started``; an integrating loop's return pulse ``pulse_started``, its output
        back at the start ``output_held``: ``HOLD_EVENTS``, which a replay reads back in
        order)."""
        kind = (
            "step_started"
            if self.t_step is None
            else "pulse_started"
            if self.phase == "return"
            else "output_held"
        )
        self.step_started(t)
        self.events.append(Event(self.t[-1] if self.t else t, kind, {"t": t}))

    def horizon(self, cap: int) -> int:
        """How many samples (≤ ``cap``, ≥ 1) may pass up to the next one at which the test
        may decide anything — step, end, abort — as long as the PV stays inside ``band()``:
        so a batch of that many, fed one by one, leaves the test exactly where feeding them
        one at a time would (each count a lower bound). The baseline's rest is checked once
        its window is full, then at every sample; after the step, the rest and the trend
        at every check (``check_spacing``), and the timeout; an integrating loop's pulse
        and rest window end at their times. (A round trip a sample took a level's lockstep
        step test 3.4 s of wall time.)"""
        if not self.t or self.finished:
            return 1
        length, t = len(self.pv), self.t[-1]
        if self.phase == "baseline":
            return max(1, min(cap, self._baseline_samples - length))
        if self.phase == "step":
            if self.t_step is None:  # the step not yet held
                return 1
            checks = samples_to_check(length)
            timeout = self._until(self.t_step + self.config.timeout - t)
            return max(1, min(cap, checks, timeout))
        if self.phase == "return" and self._pulse_start is not None:
            return max(1, min(cap, self._until(self._pulse_start + self._pulse_for - t)))
        if self.phase == "settle":
            return max(1, min(cap, self._until(self._settle[1] - t)))
        return 1

    def _until(self, seconds: float) -> int:
        return samples_until(seconds, self.sample_time, self.t[-1])

    def band(self) -> Band:
        """The PV limits (the test aborts outside them) and, once the step is held, the ends
        of the transmitter's range less the tolerance at which it aborts there: a batch ends
        with the first sample at or past either."""
        lo, hi = self.pv_limits
        if self.phase == "step" and self.t_step is not None:
            e_lo, e_hi = self.ends
            tol = 1e-9 * max(1.0, abs(e_lo), abs(e_hi), e_hi - e_lo)
            lo, hi = max(lo, e_lo + tol), min(hi, e_hi - tol)
        return Band(lo, hi)

    def progress(self) -> Progress:
        if self.t_step is None:
            return Progress("step", 0)
        return Progress("step", 1, message=f"output stepped to {self.op_target:g} %")

    def identification(self) -> Identification | None:
        found = self._identification()
        if found is None:
            return None
        against = self._against_action()
        if against:
            raise StepTestAborted(against)
        return as_controlled(found, self.direction)

    def _against_action(self) -> str:
        """Why the step's answer says the loop's action is the wrong one for its process (a
        gain of the other sign than the action's), empty if it does not. Why: a reverse
        loop on a process of gain −2 was refused with its model ("gain -2: must be > 0")
        and sent to the relay, which cannot tune it either (helper trial); the relay and the
        ramp ask about the action."""
        rc = self.result
        if rc is None:
            return ""
        ramps = isinstance(rc, IntegratingCurve)
        slope = rc.reaction_rate if ramps else rc.gain
        if not math.isfinite(slope) or slope * self.direction >= 0:
            return ""
        what, per = ("its rate of change", " per s") if ramps else ("its gain", "")
        return (
            f"step test: the output stepped {'up' if rc.step_size > 0 else 'down'} by "
            f"{abs(rc.step_size):g} % and the PV {'rose' if slope * rc.step_size > 0 else 'fell'}"
            f" ({what} {slope:.4g} PV units{per} per %): the process answers against the "
            f"loop's action — {action_question(self.direction)}"
        )

    def _identification(self) -> Identification | None:
        rc = self.result
        if rc is None:
            return None
        if isinstance(rc, IntegratingCurve):
            step_model = StepModel.integrating(rc.reaction_rate, rc.dead_time)
            fitted = None
            if rc.read_by == "fit" and rc.fit_rms is not None:  # least squares on the record
                spread = float(np.std(self.pv)) or 1.0
                fitted = ProcessFit(
                    "ipdt",
                    rc.reaction_rate,
                    (),
                    rc.dead_time,
                    rc.fit_rms / spread,
                    noise_rms=rc.noise_std / spread,
                )
            model = fitted or model_of(step_model)
            inverse = self.inverse_response(model.kind.upper())
            # the kink's standard error, where the ramps' lines were fitted (``fit_integrator``)
            se = rc.dead_time_se if rc.read_by == "fit" else None
            spread = se if se is not None and math.isfinite(se) and se >= 0.0 else None
            at = self._cleared()
            design = self._design_delay(model, spread, at)
            unresolved = self._unresolved_delay(model, rc, spread, design, at)
            model, step_model = self._with_delay(model, step_model, design)
            slowing = None
            if rc.slowing_lag is not None:
                slowing = (
                    f"the ramps slowed as a lag of about {_about(rc.slowing_lag)} s does, "
                    f"{rc.slowing_lag / max(rc.dead_time, 1e-9):.3g} dead times: read as "
                    "integrating (SIMC takes a lag past 8 dead times so), R its first slope "
                    "and L read with the slowing"
                )
            return Identification(
                step=rc,
                step_model=step_model,
                model=model,
                notes=[n for n in (inverse, unresolved, slowing) if n],
                inverse_response=inverse is not None,
                integrating=True,
                # the model as the design takes it (``_design_delay``)
                experiment=StepFindings(
                    rc.step_size, rc.method, model if fitted is not None else None
                ),
                # the closed loop's time scale: SIMC's integral time for a level, 8 L
                timescale=8.0 * step_model.dead_time,
                noise=rc.noise_std,
                rest_pv=rc.pv_after,
            )
        step_model = StepModel(rc.gain, rc.dead_time, rc.time_constant_tangent)
        fitted, spread = self._record_fit()
        model = fitted or model_of(step_model)
        inverse = self.inverse_response(model.kind.upper())
        at = self._cleared()
        design = self._design_delay(model, spread, at)
        unresolved = self._unresolved_delay(model, rc, spread, design, at)
        model, step_model = self._with_delay(model, step_model, design)
        return Identification(
            record_point=self.record_point(),
            step=rc,
            step_model=step_model,
            model=model,
            integrating=False,  # it settled
            experiment=StepFindings(rc.step_size, rc.method, model if fitted is not None else None),
            timescale=4 * step_model.dead_time + rc.time_constant_63,
            noise=rc.noise_std,
            rest_pv=rc.pv_before,
            notes=[n for n in (inverse, unresolved, self._loose_rest(rc)) if n],
            inverse_response=inverse is not None,
        )

    def _loose_rest(self, rc: ReactionCurve) -> str | None:
        """A note where the noise left the rest value known to ``LOOSE_BAND``/2 of the change
        rather than ``settled``'s own band (``band_reachable`` within the timeout)."""
        change = rc.pv_after - rc.pv_before
        if band_reachable(rc.noise_std, change, self.sample_time, self.config.timeout, REST_BAND):
            return None
        se = rc.noise_std / abs(change) if change else math.inf
        return (
            f"the step's change ({abs(change):.3g}) is {1 / se:.3g} σ of the noise: its rest "
            f"value is known to ±{100 * LOOSE_BAND / 2:g} % of it (one standard error), not "
            f"the {100 * REST_BAND / 2:g} % a step test reads, which needed more than the "
            f"{self.config.timeout:g} s allowed; the gain K is as uncertain — a larger step "
            "(--size) reads it closer"
        )

    def _unresolved_delay(
        self,
        model: ProcessFit,
        rc: ReactionCurve | IntegratingCurve,
        spread: float | None,
        design: tuple[float, str] | None,
        at: float | None,
    ) -> str | None:
        """A warning where the model's dead time is not a figure the record resolved: the
        floor of half a sample (a slow lag in noise: lvl1's 1 s dead time under a 640 s lag
        read as 0.5 s, said as if measured, and the rules that rest on L took it), and what
        the design takes instead (``design``: ``_design_delay``; ``at``: ``_cleared``). A
        first-order model's only lag past its time constant is L, so its rules' gains scale
        with 1/L; a second-order model's second lag carries the phase, and its L says
        little."""
        floor = 0.5 * self.sample_time
        tangent = rc.dead_time_tangent
        gave = (
            f" (the tangent gave {tangent:.3g} s)"
            if tangent is not None and tangent < floor * (1.0 - 1e-9)
            else ""
        )
        if design is None:
            if not self._floored(model):
                return None
            return (
                f"{UNRESOLVED}{gave}: L is floored at half a sample, "
                f"{floor:.3g} s (the hold's effective delay); the rules that rest on L take "
                "that floor for it, and only the verification tells how their gains suit the "
                "loop"
            )
        taken, why = design
        u = f" {self.pv_units}" if self.pv_units else ""
        cleared = (
            f"the PV cleared its noise ({self._moved_level():.3g}{u} from its rest, "
            f"{CLEAR_RUN} samples running) {at:.4g} s after the step"
            if at is not None
            else "the PV never cleared its noise for long"
        )
        if self._floored(model):
            tangent_too = f"; the tangent {tangent:.3g} s" if gave else ""
            fit = f"none (L floored at half a sample, {floor:.3g} s{tangent_too})"
        else:
            fit = f"{model.delay:.3g} s"
        found = f"the fit gave {fit}"
        if spread is not None:
            found += f", within three of its standard errors ({SPREADS * spread:.3g} s) of none"
        if why == "cleared":
            took = (
                f"{cleared}, so the response began before: {DESIGN_TAKES} {taken:.4g} s, the "
                "most dead time the record allows"
            )
        elif why == "fit-stands":
            took = (
                f"{cleared}, before three standard errors: {DESIGN_TAKES} the fit's {taken:.4g} s"
            )
        else:
            took = (
                f"{DESIGN_TAKES} {taken:.4g} s, three standard errors, the most the record "
                f"cannot tell from none ({cleared})"
            )
        return (
            f"{UNRESOLVED}: {found}; {took}: their gains are as "
            "cautious as the record is uncertain; a larger step, or less noise, resolves L"
        )

    def _floored(self, model: ProcessFit) -> bool:
        """A first-order or integrating model whose dead time is the floor of half a sample."""
        floor = 0.5 * self.sample_time
        return model.kind in ("fopdt", "ipdt") and model.delay <= floor * (1.0 + 1e-9)

    def _design_delay(
        self, model: ProcessFit, spread: float | None, at: float | None
    ) -> tuple[float, str] | None:
        """The dead time (s) the design takes where the record does not resolve the model's,
        and what sets it ("fit", "cleared" or "fit-stands"); None: the model's stands. Asked
        by the set-up only (``StepTestConfig.bound_delay``), for a first-order or integrating
        model (a second-order model's second lag carries the phase).

        Not resolved: a fitted L within ``SPREADS`` of its standard errors (``spread``, s:
        ``model_fit.delay_spread``) of none, or the floor of half a sample where no error is
        known. The design then takes ``SPREADS``·spread, the most the record cannot tell from
        none (so an L that the fit resolves just clear of it is designed on as fitted: no
        jump in the gains at the threshold), but no more than the record allows without any
        model: the time from the step to the sample from which the PV stayed clear of its
        noise (``at``: ``_cleared``), before which the response began; the floor with no error known
        takes that time. A fitted L past that time stands as fitted ("fit-stands": said).

        Why: a rule that rests on L scales its gain by 1/L, and a lag's response in noise
        fits any dead time up to its noise's worth about as well: the gravity-drain tank (1 s
        under a 190-640 s lag) read 0 (the floor), 0.025, 0.16 or 0.23 s, and AMIGO PI
        designed on those saturated its output or rang in the verification (rejected); on
        3 standard errors (0.35-0.65 s) all were verified. A resolved L stands as fitted (a
        1 s dead time under a 20 s lag reads to 0.03 s)."""
        if not self.config.bound_delay or model.kind not in ("fopdt", "ipdt"):
            return None
        cleared = at if at is not None else math.inf
        if spread is not None:
            if model.delay >= SPREADS * spread and not self._floored(model):
                return None
            most, why = SPREADS * spread, "fit"
            if cleared < most:
                most, why = cleared, "cleared"
        elif self._floored(model) and math.isfinite(cleared):
            most, why = cleared, "cleared"
        else:
            return None
        if most > model.delay * (1.0 + 1e-9):
            return most, why
        if why == "cleared" and not self._floored(model):  # unresolved, yet past the record's
            return model.delay, "fit-stands"
        return None

    def _cleared(self) -> float | None:
        """s from the step to the first of ``CLEAR_RUN`` samples running at which the PV is
        clear of its noise (``_moved_level``: 5σ) on the side it went to (None: never): the
        response began before it. A run, not one sample: a spike of the noise (5.5σ once, a
        tenth of a second after the step) took a design's dead time from 2 s to 0.3 s."""
        if self.t_step is None or not math.isfinite(self._pv_before) or not self.pv:
            return None
        t = np.asarray(self.t)
        keep = t >= self.t_step
        y = np.asarray(self.pv)[keep] - self._pv_before
        if y.size < CLEAR_RUN:
            return None
        side = math.copysign(1.0, float(y[int(np.argmax(np.abs(y)))]))  # where it went most
        clear = (side * y > self._moved_level()).astype(int)
        runs = np.convolve(clear, np.ones(CLEAR_RUN, dtype=int), mode="valid")
        first = np.nonzero(runs == CLEAR_RUN)[0]
        return float(t[keep][first[0]] - self.t_step) if first.size else None

    def _with_delay(
        self, model: ProcessFit, step_model: StepModel, design: tuple[float, str] | None
    ) -> tuple[ProcessFit, StepModel]:
        """The model and the reaction curve's model with the dead time the design takes
        (``_design_delay``); as they are where the model's stands."""
        if design is None:
            return model, step_model
        taken = design[0]
        return (
            dataclasses.replace(model, delay=taken),
            dataclasses.replace(step_model, dead_time=max(step_model.dead_time, taken)),
        )

    def inverse_response(self, model: str) -> str | None:
        """A warning if the PV first went the other way after the step (by more than 6σ of
        the noise and 2 % of its change, ``inverse_response.dip``): a right-half-plane zero
        (a drum level's swell, a column's inverse response) that the fitted models have no
        term for, so the robustness they predict for every rule is optimistic on this
        process (seen: Ms 1.45 predicted, about 2.2 on the plant). The record up to the
        return pulse, if any."""
        if self.t_step is None or not math.isfinite(self._pv_before):
            return None
        t, y = np.asarray(self.t), np.asarray(self.pv) - self._pv_before
        keep = (t >= self.t_step) & (t < (self._pulse_start or math.inf))
        t, y = t[keep], y[keep]
        if y.size < 10:
            return None
        change = float(np.mean(y[-max(1, y.size // 10) :]))  # where it went: the end's mean
        if change == 0.0:
            return None
        along = y * math.copysign(1.0, change)  # > 0: the way of its change
        # 2 % of the change: the shared test's 4 % of half of it
        away = inverse_response.dip(along, self._noise, 0.5 * abs(change))
        if away is None:
            return None
        worst = int(np.argmin(along))
        u = f" {self.pv_units}" if self.pv_units else ""
        return (
            f"inverse response: after the step the PV first went {away:.3g}{u} the "
            f"other way (most at t = {t[worst]:.4g} s) before its change of {change:+.3g}{u}: "
            f"a right-half-plane zero, which the {model} model has no term for, so the "
            "robustness it predicts for the rules (Ms, margins) is optimistic on this "
            "process: derivative action is offered, not recommended; prefer the most "
            "cautious rule, or detune"
        )

    # --- the state machine ---------------------------------------------------------------

    def _abort(self, reason: str) -> float:
        """Every abort: the phase, the reason and an ``aborted`` event; the output at rest."""
        self.phase, self.reason = "aborted", reason
        self.events.append(Event(self.t[-1] if self.t else 0.0, "aborted", {"reason": reason}))
        return self.op_start

    def _feed(self, s: Sample) -> float:
        if self.finished:
            return self.op_start
        self.t.append(s.t)
        self.pv.append(s.pv)
        lo, hi = self.pv_limits
        if not lo <= s.pv <= hi:
            return self._abort(
                f"PV {beyond(s.pv, lo, hi)} left its limits [{lo:g}, {hi:g}] at t = {s.t:g} s"
            )
        if self.phase == "baseline":  # at rest first: no trend beyond the noise
            return self._baseline(s)
        if self.phase == "return":
            return self._return_pulse(s)
        if self.phase == "settle":
            return self._settled(s)
        if self.t_step is None:
            return self.op_target
        return self._after_step(s)

    @property
    def pv_before_step(self) -> float:
        """PV units: the rest before the step (NaN before the baseline was measured)."""
        return self._pv_before

    @property
    def noise_std(self) -> float:
        """PV units: the noise σ measured at rest before the step."""
        return self._noise

    def _baseline(self, s: Sample) -> float:
        n = self._baseline_samples
        if len(self.pv) < n:
            return self.op_start
        base = np.asarray(self.pv[-n:])
        end = range_end(base, self.ends)
        if end is not None:
            return self._abort(
                f"the PV sits at {self._end_words(end)}: a measurement clipped by the "
                "transmitter is flat and noise-free whatever the process does, so it cannot "
                "show rest; bring the PV inside its range first"
            )
        if not at_rest(base, allowance=max(self.rest_drift, self.config.resolution)):
            if len(self.pv) >= 20 * n:
                return self._abort("the PV is not at rest before the step (it keeps drifting)")
            return self.op_start
        self._pv_before = float(base.mean())
        self._noise = noise_level(base)
        if self.config.drift_guard:
            tb = np.asarray(self.t[-n:], dtype=float)
            slope, _, err = line_fit(tb - tb[-1], base)
            self._drift = math.copysign(max(abs(slope) - 2.0 * err, 0.0), slope)
        self.phase = "step"
        self.events.append(
            Event(
                s.t,
                "step",
                {"op": self.op_target, "pv_before": self._pv_before, "noise_std": self._noise},
            )
        )
        return self.op_target

    def _after_step(self, s: Sample) -> float:
        elapsed = s.t - self.t_step
        if elapsed > self.config.timeout:
            if self._t_moved is None and self.config.resolution > 0:
                return self._abort(
                    f"the PV did not respond to the step within {self.config.timeout:g} s: it "
                    f"stayed within {self._moved_level():.3g} of its rest {self._pv_before:.6g} "
                    "(its noise and the transmitter's resolution): a valve that does not move, "
                    f"or a process slower than the time allowed ({self.config.timeout_flag})"
                )
            return self._abort(
                f"no steady state within {self.config.timeout:g} s of the step"
                + (self._too_noisy() or self._still_settling())
            )
        lo, hi = self.ends
        tol = 1e-9 * max(1.0, abs(lo), abs(hi), hi - lo)
        if s.pv >= hi - tol or s.pv <= lo + tol:
            end = "top" if s.pv >= hi - tol else "bottom"
            return self._abort(
                f"the PV reached {self._end_words(end)} at t = {s.t:g} s: the measurement is "
                "clipped there and shows nothing of the response; use a smaller step"
            )
        if self._t_moved is None and abs(s.pv - self._pv_before) > self._moved_level():
            self._t_moved = elapsed
        if not check_due(len(self.pv)):
            return self.op_target
        t, y = np.asarray(self.t), np.asarray(self.pv)
        # (a ramp within the noise and the transmitter's resolution is no response: a 1e6 s
        # lag's 5e-4 in 100 s, noise-free, is as steady as any)
        cfg = self.config
        moved = self._t_moved is not None or cfg.resolution <= 0 or not cfg.steady_floor
        floor = RAMP_STEADY_FLOOR if cfg.steady_floor else RAMP_STEADY_FLOOR_BEFORE
        ramp = (
            steady_ramp(t, y, self.t_step, self._pv_before, self._noise, floor=floor)
            if moved
            else None
        )
        if ramp is not None and ramp.precision <= self.config.rate_precision:
            return self._integrating(s, ramp, "precision")
        if reason := self._heading_out(t, y, elapsed):
            # the last look before giving up: a steady ramp over fewer dead times
            ramp = ramp or (
                steady_ramp(
                    t,
                    y,
                    self.t_step,
                    self._pv_before,
                    self._noise,
                    RAMP_WINDOWS_AT_THE_EDGE,
                    floor,
                )
                if moved
                else None
            )
            if ramp is not None:  # R is known, if less precisely than asked: say so
                return self._integrating(s, ramp, "range")
            return self._abort(reason)
        done, rest = settled(
            t,
            y,
            self.t_step,
            self._pv_before,
            self._noise,
            pv_range=self.ends,
            swing=self.config.swing_check,
            horizon=self.config.timeout,
        )
        if done:
            try:
                self.result = analyze_step(
                    t,
                    y,
                    self.t_step,
                    self.config.size,
                    self._pv_before,
                    rest,
                    self._noise,
                    self.sample_time,
                    self.config.resolution,
                )
            except ValueError as err:
                return self._abort(str(err))
            self.phase = "done"
            self.events.append(
                Event(s.t, "done", {"gain": self.result.gain, "dead_time": self.result.dead_time})
            )
            return self.op_start
        return self.op_target

    def _too_noisy(self) -> str:
        """Why no rest came, where the noise says it: the PV's change over the last quarter
        of the record is too few σ for its mean to know the rest value to ``LOOSE_BAND``/2 of
        it in the time allowed (``band_reachable``); empty otherwise."""
        m = max(20, len(self.pv) // 4)
        change = float(np.mean(self.pv[-m:])) - self._pv_before
        if 0 < abs(change) <= MIN_CHANGE_SIGMAS * self._noise:
            # ``settled`` reads no rest of a change within 5σ, however long the record: a
            # step of 2σ (0.02·e^{−s}/(10s + 1), σ 0.05, 5 %) waited 7,200 s and ended "no
            # steady state" without a word of why (helper trial)
            size = abs(self.config.size) * 2.0 * MIN_CHANGE_SIGMAS * self._noise / abs(change)
            said = (
                f": the PV moved by {abs(change):.3g}, {abs(change) / self._noise:.3g} σ of its "
                f"noise, and a rest is read only from a change of {MIN_CHANGE_SIGMAS:g} σ or "
                "more — "
            )
            lo, hi = self.op_limits
            room = max(hi - self.op_start, self.op_start - lo)
            if size > room:  # a gain of 0 asked for --size 740 % (helper trial)
                return said + (
                    f"a step of about {size:.2g} % for 10 σ, more than the output's room "
                    f"({room:.3g} % from {self.op_start:.4g} % within [{lo:g}, {hi:g}] %): the "
                    "PV hardly answers the output (a valve that does not act, a process gain "
                    "near zero, or the wrong loop)"
                )
            return said + f"a larger step (--size about {size:.2g} %, for 10 σ)"
        if band_reachable(self._noise, change, self.sample_time, self.config.timeout, LOOSE_BAND):
            return ""
        sigmas = abs(change) / self._noise if self._noise > 0 else math.inf
        return (
            f": the PV moved by {abs(change):.3g}, {sigmas:.3g} σ of its noise, too little "
            f"for its rest value to be read to {100 * LOOSE_BAND / 2:g} % of the change in "
            f"that time — a larger step (--size), or a longer {self.config.timeout_flag}"
        )

    def _still_settling(self) -> str:
        """Why no rest came, where the PV is still settling as a lag does: its time constant
        read from the record's last three sixths (their means' differences fall by e^{−w/τ}
        from one to the next), and the time to ask for; empty where they do not fall so.
        A clean e^{−10s}/(1000s + 1) has no rest within 7,200 s; with the --max-time named
        (8100) its step test ends with the FOPDT exact."""
        t, y = np.asarray(self.t), np.asarray(self.pv)
        after = t > self.t_step
        t, y = t[after], y[after]
        m = t.size // 6
        if m < 3:
            return ""
        first, mid, last = (float(np.mean(y[-(k + 1) * m : y.size - k * m])) for k in (2, 1, 0))
        ratio = (last - mid) / (mid - first) if mid != first else math.nan
        if not 0.0 < ratio < 1.0:
            return ""
        tau = -(t[-1] - t[-1 - m]) / math.log(ratio)
        need = self.t_step - float(self.t[0]) + 8.0 * tau  # 8 τ: within 0.03 % of its change
        return (
            f": the PV is still settling as a lag of about {_about(tau)} s does (by the record's "
            f"last third), which comes to rest in 5 to 8 of them — a longer "
            f"{self.config.timeout_flag} (about "
            f"{math.ceil(need / 100.0) * 100:.0f}), or the relay test, which needs no rest"
        )

    def _moved_level(self) -> float:
        """PV units from the rest before the step that tell a response: 5σ of the noise, and
        at least the transmitter's resolution (``StepTestConfig.resolution``)."""
        lo, hi = self.ends
        tol = 1e-9 * max(1.0, abs(lo), abs(hi), hi - lo)
        return max(5.0 * self._noise + tol, self.config.resolution)

    def _coast(self, slope: float, level: float, err: float, now: float) -> float | None:
        """s the PV keeps moving once the output is restored, read off its trend (``slope``
        ± ``err`` PV units/s, at ``level`` at sim time ``now``): from the step to where the
        trend's line crosses the rest before it. A response that speeds up (an integrator
        behind a lag) coasts for that long, its dead time and lag, which the time it took to
        start moving does not show: 0.2·e^{−s}/(s(5s + 1)) stepped 5 % was stopped 2.8 s
        short of its allowance, moving 1 %/s, and went on 6 s to 78.7 % (helper trial). A
        response that slows down (a lag's approach) crosses before its dead time is over,
        and adds nothing. None where the trend is not clearly away from the rest."""
        away = level - self._pv_before
        if not (abs(slope) > 3.0 * err and away * slope > 0 and abs(away) > 4.0 * self._noise):
            return None
        cross = now - away / slope  # sim time s at which the trend's line meets the rest
        return cross - self.t_step if cross > self.t_step else None

    def _heading_out(self, t: np.ndarray, y: np.ndarray, elapsed: float) -> str | None:
        """Why to stop now if the PV, on its present trend, nears an end of its range, its
        limits (``pv_limits``) or the test's allowance (``max_move``).

        After the output is restored the PV keeps moving for about its dead time (and lags):
        the horizon is twice the time it took to start moving (an upper bound on the dead
        time) plus four samples; stop if the trend's line, extended by it, comes within 4σ.
        """
        keep = t >= self.t_step
        tw, yw = t[keep], y[keep]
        m = max(20, tw.size // 4)
        if tw.size < m:
            return None
        tw, yw = tw[-m:], yw[-m:]
        slope, level, err = line_fit(tw - tw[-1], yw)
        moved = self._t_moved if self._t_moved is not None else elapsed
        began = tw >= self.t_step + moved
        since_move = self.config.trend_since_move
        if since_move and self._t_moved is not None and 4 <= int(began.sum()) < m:
            # the PV began to move within the window: where its trend since is the slower one,
            # it is that one (a line through the flat dead time and the move read a pure
            # delay's jump, 50 to 55 in a sample and flat since, as heading past 75 at 3.8 %/s,
            # and aborted it; a lag's onset is steepest at its start, and keeps the window's)
            after = line_fit(tw[began] - tw[-1], yw[began])
            if abs(after[0]) < abs(slope):
                slope, level, err = after
        horizon = 2.0 * moved + 4.0 * self.sample_time
        if self.config.coast and (coast := self._coast(slope, level, err, float(tw[-1]))):
            horizon = max(horizon, coast + 4.0 * self.sample_time)
        # extended by its least trend the noise allows (2 standard errors toward none): σ 2 on
        # a 5 % step of e^{−3s}/(10s + 1) read 1.24 %/s over 20 samples, extended it 29.6 s
        # to 91 and aborted "would leave the allowance" a response that ends at 55 (helper
        # trial); the PV's own crossing still stops it (``level``)
        fitted = slope
        if self.config.trend_error:
            slope = math.copysign(max(abs(slope) - 2.0 * err, 0.0), slope)
        reach = float(level + slope * horizon)
        # toward the engineer's limits: over the horizon and the samples to the next check
        # (the stop comes that late), and where the baseline drifted against the trend
        # (still settling from an earlier change, rest passed on a short window: the drift
        # fades, and the step's own answer is steeper) the fitted trend without that drift,
        # not 2 standard errors less. Back-to-back steps of e^{−4s}/(30s + 1), σ 0.05,
        # limits ±1.5, each begun with the PV ~0.45 up on its way down to rest, went past a
        # limit in 14 runs of 60, up to 0.475 (helper trial); now 2, up to 0.325. The fitted
        # trend from rest as well stopped 9 of 24 steps whose answer ends inside the limits
        # (a small step's slow start read with its noise over a long horizon), so from rest
        # the lenient reading stands
        hard_slope, hard_horizon = slope, horizon
        # (limits that are the transmitter's range, or stand for it, are its ends: read as
        # before)
        asked = self.pv_range is not None and tuple(self.pv_limits) != tuple(self.pv_range)
        if self.config.drift_guard and asked:
            hard_slope = fitted - self._drift if self._drift * fitted < 0 else slope
            hard_horizon = horizon + samples_to_check(len(self.pv)) * self.sample_time
        hard = float(level + hard_slope * hard_horizon)
        # the approach judged on the samples since the PV started moving: a window that also
        # holds the flat dead time before it reads a lag's onset as speeding up (the straight
        # line took e^{−10s}/(2s+1)'s 5 % step, at 53.2 and slowing, past 75: helper trial F)
        since = y[keep][t[keep] >= self.t_step + moved] if self._t_moved is not None else yw
        left = _approach_left(since if since.size >= 12 else yw, stopped=since_move)
        if left is not None and abs(left) < abs(hard - level):
            hard = float(level + left)
        if self.config.early_approach and 4 <= since.size < 12:
            # a dead time's flat stretch in the window hides a fast lag's slowing from the
            # thirds: 2e^{−20s}/(s + 1)'s 5 % step, at 59.3 and slowing by 0.61 a sample, was
            # extended 43 s on its straight line to past 75 and aborted (it ends at 60). Not
            # toward the engineer's limits (``hard``): a fast lag beside a slow one shrinks its
            # steps as well, and the tail misses the slow mode's ramp (e^{−20s}(31s + 2)/((s +
            # 1)(30s + 1)) went past limits at 58.5 that the straight line held: review)
            early = _geometric_left(since, self._noise)
            if early is not None and (left is None or abs(early) < abs(left)):
                left = early
        if left is not None and abs(left) < abs(reach - level):
            # slowing down as a lag's approach does: it goes no further than its end (a
            # straight line over 2 L took e^{−10s}/(2s+1)'s 5 % step past 75 %: it ends at 55)
            reach = float(level + left)
        lo, hi = self.ends
        margin = 4.0 * self._noise
        u = f" {self.pv_units}" if self.pv_units else ""
        for end, near in (
            ("top", max(level, reach) >= hi - margin),
            ("bottom", min(level, reach) <= lo + margin),
        ):
            if near:
                return (
                    f"the PV would reach {self._end_words(end)} within {horizon:.3g} s (now "
                    f"{level:.4g}{u}, moving {slope:.3g}{u}/s): stopped before the measurement "
                    "clips; use a smaller step"
                )
        p_lo, p_hi = self.pv_limits
        a_lo, a_hi = self.allowance
        for (b_lo, b_hi), to, (rate, within), what, advice in (
            (
                (p_lo, p_hi),
                hard,
                (hard_slope, hard_horizon),
                f"its limits [{p_lo:g}, {p_hi:g}]{u}",
                ": stopped before it does, as it keeps moving for about its dead time once the "
                "output is restored; use a smaller step",
            ),
            (
                (a_lo, a_hi),
                reach,
                (slope, horizon),
                f"the test's allowance, {a_lo:.4g}–{a_hi:.4g}{u} ("
                f"{100 * self.config.max_move:.3g} % of its range either way from its rest),",
                "; use a smaller step or a larger allowance",
            ),
        ):
            if max(level, to) >= b_hi or min(level, to) <= b_lo:
                trend = f"within {within:.3g} s (now {level:.4g}{u}, moving {rate:.3g}{u}/s)"
                return f"the PV would leave {what} {trend}{advice}"
        return None

    def _integrating(self, s: Sample, ramp: SteadyRamp, stopped_by: str) -> float:
        """End the step on a steady ramp (R known, or the allowance reached) and hold the
        equal and opposite pulse that gives the integrator back its level (exactly, for a
        linear integrator, whatever its dead time)."""
        self.ramp = ramp
        rate = ramp.slope / self.config.size
        self.events.append(
            Event(
                s.t,
                "integrating",
                {
                    "slope": ramp.slope,
                    "reaction_rate": rate,
                    "dead_time": ramp.dead_time,
                    "precision": ramp.precision,
                    "stopped_by": stopped_by,
                },
            )
        )
        size, lo, hi = self.config.size, *self.op_limits
        room = self.op_start - lo if size > 0 else hi - self.op_start
        amplitude = min(abs(size), room)
        if self.t_step is None or amplitude < 0.2 * abs(size):
            return self._abort(
                f"integrating process (R = {rate:.3g} {self._rate_units()}, L ≈ "
                f"{ramp.dead_time:.3g} s), but the output has no room below its start for "
                "the return pulse: the PV stays where the step took it"
            )
        self._pulse_op = self.op_start - math.copysign(amplitude, size)
        self._pulse_for = (s.t - self.t_step) * abs(size) / amplitude  # refined when held
        self._stopped = (s.t, s.pv, stopped_by)
        self.phase = "return"
        self.events.append(
            Event(s.t, "return_pulse", {"op": self._pulse_op, "for": self._pulse_for})
        )
        return self._pulse_op

    def _return_pulse(self, s: Sample) -> float:
        """Hold the pulse its length; then the output at its start again, and the PV watched
        for its dead time (the pulse's end reaches it that much later) and 20 samples more,
        over which its rest is measured."""
        start = self._pulse_start
        if start is None or s.t < start + self._pulse_for - 1e-9 * max(1.0, abs(s.t)):
            return self._pulse_op
        after = s.t + max(self.ramp.dead_time, 0.0) + 2.0 * self.sample_time
        self._settle = (after, after + 20.0 * self.sample_time)
        self._restore_at = None  # told by the driver (held), else this sample's time
        self._pulse_end_seen = s.t
        self.phase = "settle"
        self.events.append(Event(s.t, "pulse_end", {"op": self.op_start}))
        return self.op_start

    def _settled(self, s: Sample) -> float:
        if s.t < self._settle[1] - 1e-9 * max(1.0, abs(s.t)):
            return self.op_start
        t = np.asarray(self.t)
        rest = np.asarray(self.pv)[t >= self._settle[0] - 1e-9 * max(1.0, abs(s.t))]
        self.result = self._integrating_curve(float(rest.mean()), at_rest(rest, self.ends))
        self.phase = "done"
        self.events.append(
            Event(
                s.t,
                "done",
                {"reaction_rate": self.result.reaction_rate, "dead_time": self.result.dead_time},
            )
        )
        return self.op_start

    def _integrating_curve(self, pv_after: float, returned: bool) -> IntegratingCurve:
        """R and L fitted to the whole record (``fit_integrator``: the step's kink and the
        pulse's both inform L); the trailing ramp's own figures if the fit fails."""
        ramp, size = self.ramp, self.config.size
        t_stop, pv_peak, stopped_by = self._stopped
        pulse_start = self._pulse_start if self._pulse_start is not None else t_stop
        restore = self._restore_at if self._restore_at is not None else self._pulse_end_seen
        changes = [
            (self.t_step, size),
            (pulse_start, self._pulse_op - (self.op_start + size)),
            (restore, self.op_start - self._pulse_op),
        ]
        fit = fit_integrator(
            np.asarray(self.t),
            np.asarray(self.pv),
            changes,
            pulse_start - self.t_step,
            slowing=self.config.leak,
        )
        if fit is not None:
            rate, lag, lag_se = fit.rate, fit.dead_time, fit.dead_time_se
            precision, how, rms = 2.0 * fit.rate_se / abs(fit.rate), "fit", fit.rms
            drift = fit.drift
            slowing = 1.0 / fit.leak if fit.leak > 0.0 else None
        else:
            # the baseline's mean is known to σ/√n, which shifts where the ramp meets it
            base_se = self._noise / math.sqrt(self._baseline_samples) / abs(ramp.slope)
            rate, lag, lag_se = (
                ramp.slope / size,
                ramp.dead_time,
                math.hypot(ramp.dead_time_se, base_se),
            )
            precision, how, rms, drift, slowing = ramp.precision, "ramp", None, 0.0, None
        floor = 0.5 * self.sample_time
        dead_time = max(lag, floor)
        return IntegratingCurve(
            step_size=size,
            pv_before=self._pv_before,
            slope=ramp.slope,
            reaction_rate=rate,
            reaction_rate_precision=precision,
            dead_time=dead_time,
            dead_time_se=lag_se,
            a=rate * dead_time,
            held=(self._pulse_start or t_stop) - self.t_step,
            pv_peak=pv_peak,
            pv_after=pv_after,
            returned=returned,
            pulse_op=self._pulse_op,
            pulse_held=self._pulse_for,
            noise_std=self._noise,
            window=ramp.window,
            dead_time_tangent=lag,
            dead_time_floor=floor,
            stopped_by=stopped_by,
            read_by=how,
            fit_rms=rms,
            drift=drift,
            slowing_lag=slowing,
        )

    def _settled_curve(self) -> tuple[ReactionCurve, float] | None:
        """The settled step's reaction curve and the sign that turns its gain positive (a
        process whose PV falls as the output rises, a direct-acting loop's, is read turned
        over); None without one, or with no gain to read."""
        rc = self.result
        if not isinstance(rc, ReactionCurve) or self.t_step is None:
            return None
        if not (math.isfinite(rc.gain) and rc.gain != 0):
            return None
        return rc, (1.0 if rc.gain > 0 else -1.0)

    def record_point(self) -> tuple[float, float, float] | None:
        """(K_u, P_u, their relative uncertainty) the record implies by itself, from the step
        on (``step_frequency``)."""
        settled = self._settled_curve()
        if settled is None:
            return None
        rc, sign = settled
        t = np.asarray(self.t) - self.t_step
        after = t > 1e-9 * max(1.0, abs(self.t_step))
        y = sign * (np.asarray(self.pv)[after] - self._pv_before)
        return response_point(t[after], y, rc.step_size, self.sample_time, self._noise)

    def process_model(self) -> ProcessFit | None:
        """The process model for the rules and the robustness figures: FOPDT and SOPDT
        refined on the whole record (output error, from the rest of the baseline), the best
        by its information criterion. The tangent construction's first order is only the
        start: it ignores the response's shape, and a PID judged on it can be far less
        robust on the plant than predicted (seen: Ms 2.6 predicted 1.5, on a plant with an
        inverse response)."""
        return self._record_fit()[0]

    def _record_fit(self) -> tuple[ProcessFit | None, float | None]:
        """``process_model`` and the standard error of its dead time (s; None: not asked by
        the set-up, ``StepTestConfig.bound_delay``, or no figure: ``model_fit.delay_spread``)."""
        settled = self._settled_curve()
        if settled is None:
            return None, None
        rc, sign = settled
        t, y = np.asarray(self.t), sign * (np.asarray(self.pv) - self._pv_before)
        u = np.where(t >= self.t_step - 1e-9 * max(1.0, abs(self.t_step)), rc.step_size, 0.0)
        lag = max(rc.time_constant_63, self.sample_time)
        delay = max(rc.dead_time, 0.0)
        gain = sign * rc.gain
        starts = (
            ProcessFit("fopdt", gain, (lag,), delay, math.inf),
            ProcessFit("sopdt", gain, (0.7 * lag, 0.3 * lag), 0.5 * delay, math.inf),
        )
        fits = [
            f
            for start in starts
            if (f := refine_on_record(start, self.sample_time, u, y)) is not None
        ]
        best = choose_on_record(fits, y.size)
        if best is None:
            return None, None
        spread = None
        if self.config.bound_delay and best.kind == "fopdt":
            spread = delay_spread(best, self.sample_time, u, y)
        # a dead time below half a sample is not resolved by the record (as for the tangent)
        model = dataclasses.replace(
            best,
            gain=sign * best.gain,
            delay=max(best.delay, 0.5 * self.sample_time),
            noise_rms=self._noise / (float(np.std(y)) or 1.0),
        )
        return model, spread

    def step_started(self, t: float) -> None:
        """The driver reports the sim time from which the changed output is held: the step's,
        then (integrating) the return pulse's, whose length then gives back the step's area
        exactly (the step size × the time it was held, at the pulse's amplitude)."""
        if self.t_step is None:
            self.t_step = t
        elif self.phase == "return" and self._pulse_start is None:
            self._pulse_start = t
            amplitude = abs(self._pulse_op - self.op_start)
            self._pulse_for = (t - self.t_step) * abs(self.config.size) / amplitude
        elif self.phase == "settle" and self._restore_at is None:
            self._restore_at = t


def check_spacing(n: int) -> int:
    """Samples between rest checks in a record of ``n`` samples: ``SETTLE_CHECK_EVERY``, and
    twice that each time the record doubles past ``2·SETTLE_CHECK_EVERY·CHECKS_PER_DOUBLING``
    (2,048) samples. Why: each check is a regression over a window of the whole record, and
    one every 8 samples made a long record's checks grow as its square (a step test of
    1.43·e^{−0.056s}/(866s² + 348s + 1) sampled every 0.02 s ran 65,000 samples and took 490
    s of wall time). A check comes at most 1/128 of the record late."""
    spacing = SETTLE_CHECK_EVERY
    while n >= 2 * spacing * CHECKS_PER_DOUBLING:
        spacing *= 2
    return spacing


def check_due(n: int) -> bool:
    """Whether a record of ``n`` samples is checked now (``check_spacing``)."""
    return n % check_spacing(n) == 0


def samples_to_check(n: int) -> int:
    """Samples from a record of ``n`` to its next check (≥ 1): the next multiple of the
    spacing there, which is a check whatever spacing it falls in (the spacings double at
    multiples of every smaller spacing)."""
    spacing = check_spacing(n + 1)
    return (n // spacing + 1) * spacing - n


def _geometric_left(y: np.ndarray, noise: float) -> float | None:
    """How much further a PV goes whose last three sample-to-sample steps shrink as a lag's
    approach does, by a ratio q at most GEOMETRIC_RATIO a sample (PV units, signed): the
    last step's geometric tail d·q/(1 − q) at the slower of the two ratios, taken twice
    over. None unless the three steps go one way, each clear of the noise (6σ: a step's
    noise is σ√2), and each shrinks by that ratio: a response still speeding up, or steady
    (an integrator), keeps the straight line."""
    steps = np.diff(np.asarray(y, dtype=float)[-4:])
    if steps.size < 3 or not np.all(np.isfinite(steps)):
        return None
    if not (np.all(steps > 0) or np.all(steps < 0)) or np.min(np.abs(steps)) <= 6.0 * noise:
        return None
    q = max(steps[1] / steps[0], steps[2] / steps[1])
    if not 0.0 < q <= GEOMETRIC_RATIO:
        return None
    return float(2.0 * steps[2] * q / (1.0 - q))


def _approach_left(y: np.ndarray, stopped: bool = True) -> float | None:
    """How much further a PV slowing down as a lag's exponential approach would go (PV
    units, signed), from the means of the record's three thirds (m₁, m₂, m₃): their steps
    shrink by r = (m₂ − m₁)/(m₃ − m₂) a third, so what is left after the last third's middle
    is (m₃ − m₂)/(r − 1), taken twice over (the noise in the means, a lag not quite
    exponential) and from the last sample. None unless the PV clearly slows (r > 1.2) in one
    direction: a response still speeding up (an S-curve before its inflection) keeps the
    straight line. ``stopped``: a PV that moved over the first third and not beyond the
    noise since goes no further (False: a run recorded before)."""
    n = y.size // 3
    if n < 4:
        return None
    m1, m2, m3 = (float(np.mean(y[i * n : (i + 1) * n])) for i in range(3))
    d1, d2 = m2 - m1, m3 - m2
    # stopped: a clear move over the first third, none beyond the noise of the means over
    # the last two (a dead time with next to no lag: e^{−3s}/(0.01s + 1)'s 5 % step, flat at
    # 55 a sample after its jump, read on the straight line through the jump as heading past
    # 75, and aborted; so was every step of a pure delay)
    se = 3.0 * float(np.std(y[n : 3 * n])) * math.sqrt(2.0 / n)  # 3 σ of a difference of means
    if stopped and abs(d1) > se and abs(d2) <= se:
        return 2.0 * d2 + (m3 - float(y[-1]))
    if d1 == 0.0 or d2 == 0.0 or (d1 > 0) != (d2 > 0):
        return None
    r = d1 / d2
    if r <= 1.2:
        return None
    return 2.0 * d2 / (r - 1.0) + (m3 - float(y[-1]))


@dataclass
class ReturnWatch:
    """After the output is restored: is the PV back at rest? ``feed`` each sample.

    The restore is a step back from ``pv_from`` (the rest after the step), so the same test
    as after the step applies (``settled``, which also refuses a PV clipped at an end of
    ``pv_range``). Given ``pv_back`` (the rest before the step), the PV must also have come
    half of the way back to it: a noise-free PV still in its dead time, flat bar the last
    of the step's creep, was taken for at rest where the step had left it (52 for 50), and
    an aborted step's PV, carried on past where it stopped, at its crest (62.8 for 60). It
    gives up ``timeout`` seconds after ``t_restore``.
    """

    t_restore: float  # s, sim time from which the restored output is held
    pv_from: float  # PV units, the rest value before the restore
    noise_std: float  # PV units
    timeout: float  # s
    pv_range: tuple[float, float] | None = None
    pv_back: float | None = None  # PV units, the rest before the step the restore undoes
    # the scatter about the window's line must be noise too (``settled``'s ``swing``): an
    # underdamped return (1/(100s² + 6s + 1), ζ 0.3) was "back at rest" mid-swing, 0.43 off
    # and falling, and the next step read K 1.052 for 1 from it (helper trial)
    swing: bool = True
    # a PV at rest short of half of the way back, at two checks running, ends the watch (not
    # at rest where it was: ``rest_off``). For an aborted step's return: an integrating
    # process held at a constant output stays where the test took it, and the watch waited
    # the whole --timeout (7,200 s; two hours at ×1) for a return it cannot make (helper
    # trial). False: the watch waits for the return or its timeout
    settle_off: bool = False
    rest_off: float = field(default=math.nan, init=False)  # PV units: at rest short of it
    _off_checks: int = field(default=0, init=False)  # checks running that found it so
    t: list[float] = field(default_factory=list)
    pv: list[float] = field(default_factory=list)
    done: bool = False
    at_rest: bool = False
    rest: float = math.nan  # PV units, where it came to rest (NaN: it did not)

    @property
    def pv_end(self) -> float:
        """The rest value if at rest, else the last PV seen (NaN before any)."""
        if self.at_rest:
            return self.rest
        return self.pv[-1] if self.pv else math.nan

    def horizon(self, cap: int, sample_time: float) -> int:
        """Samples (≤ ``cap``, ≥ 1) up to the next at which the watch may end: its next rest
        check (``check_spacing``) or its timeout (samples ``sample_time``
        s apart), whichever may come first; 1 before any sample."""
        if self.done or not self.t:
            return 1
        checks = samples_to_check(len(self.pv))
        last = self.t[-1]
        timeout = samples_until(self.t_restore + self.timeout - last, sample_time, last)
        return max(1, min(cap, checks, timeout))

    def feed(self, t: float, pv: float) -> bool:
        """Take one sample; True once done (at rest, or out of time)."""
        if self.done:
            return True
        self.t.append(t)
        self.pv.append(pv)
        if check_due(len(self.pv)):
            ok, rest = settled(
                np.asarray(self.t),
                np.asarray(self.pv),
                self.t_restore,
                self.pv_from,
                self.noise_std,
                pv_range=self.pv_range,
                swing=self.swing,
                horizon=self.timeout,
            )
            # half of the way toward it, not away: an aborted step's PV, carried on by its
            # lags past where the test stopped, was taken for back at its crest (62.8 for 60)
            way = self.pv_back - self.pv_from if self.pv_back is not None else 0.0
            back = (rest - self.pv_from) * way >= 0.5 * way * way
            if ok and back:
                self.done, self.at_rest, self.rest = True, True, rest
                return True
            self._off_checks = self._off_checks + 1 if ok and self.settle_off else 0
            if self._off_checks >= 2:
                self.done, self.rest_off = True, rest
                return True
        if t - self.t_restore >= self.timeout:
            self.done = True
        return self.done


def return_timeout(config: StepTestConfig, t_step: float, t_end: float) -> float:
    """Seconds to wait for the return to rest: a few times the step's own settling time (the
    way back has the same dynamics), capped by the test's timeout."""
    return min(config.timeout, RETURN_WAIT_FACTOR * max(t_end - t_step, 0.0))


def build(settings: Settings, setup: Setup) -> StepTest:
    """The step test a request and a loop's set-up ask for; ValueError naming the setting
    that cannot work. Its wait for rest after the step is the request's ``max_time``, else
    200 of the loop's time scales (and 400 samples at least) when one is known."""
    if setup.op_start is None:
        raise ValueError("op_start: required for a step test")
    ts, scale = setup.sample_time, setup.time_scale
    if settings.max_time:
        timeout = {"timeout": settings.max_time}
    elif scale:
        timeout = {"timeout": min(StepTestConfig.timeout, max(200 * scale, 400 * ts))}
    else:
        timeout = {}
    cfg = StepTestConfig(
        size=settings.step_size,
        pv_limits=setup.pv_limits,
        swing_check=bool(setup.step_swing),
        bound_delay=bool(setup.step_delay_bound),
        leak=bool(setup.step_leak),
        trend_since_move=bool(setup.step_trend_since_move),
        steady_floor=bool(setup.step_steady_floor),
        trend_error=bool(setup.step_trend_error),
        coast=bool(setup.step_coast),
        drift_guard=bool(setup.step_drift_guard),
        early_approach=bool(setup.step_early_approach),
        resolution=setup.resolution_floor(),
        **timeout,
    )
    return StepTest(
        cfg,
        setup.op_start,
        setup.op_limits,
        setup.pv_limits,
        ts,
        pv_range=setup.pv_range,
        pv_units=setup.pv_units or "",
        direction=setup.direction or 1.0,
    )


def _about(x: float) -> str:
    """A rough figure in s: whole seconds from 100 on (not 1e+03), three digits below."""
    return f"{x:.0f}" if x >= 100.0 else f"{x:.3g}"
