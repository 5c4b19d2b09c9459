"""Ziegler–Nichols' ultimate-sensitivity method (seeds 000, 002, 003) as a state machine.

The loop runs P-only in auto. After a quiet period (rest PV r, noise σ), each trial sets a
gain Kc and bumps the setpoint to r ± bump (alternating); the response is watched for a few
periods and a growing/decaying sinusoid is fitted to it (``oscillation.fit_oscillation``),
giving its growth rate g and period. Gains rise geometrically until the oscillation stops
decaying (g ≥ 0), then the bracket [last decaying, first growing] is narrowed by regula falsi
on g (Illinois), and K_u is where g crosses zero, interpolated linearly in Kc between the
final bracket; P_u likewise from the two trials' periods. A trial whose swing passes
``swing_limit``·bump is cut short as growing, and the loop is calmed at a lower gain before
the next. The PV leaving its limits aborts the test.

Only a linear loop tells its ultimate point, so the output (``op_limits``) is watched too. A
trial's bump is sized so that its kick Kc·bump takes at most ``headroom`` of the output's room
to its nearer limit. A trial whose output then sits at a limit (a few samples in a row) is cut
there: judged growing if the record before shows a growing oscillation, otherwise repeated at
the same gain with half the bump (event ``bump``), until the bump would drown in the noise
(< 6σ) — then the gain backs off (while no decaying gain is known) or the test aborts. A start
gain that saturates the output at rest backs off tenfold (event ``back_off``); a loop that
will not calm between trials, or saturates while calming, gets half the calming gain (event
``calm``), a few times at most. A fitted oscillation counts only if it swings out of the
noise (its envelope ≥ 2σ for half a period, ``oscillation.stands_out``): a sinusoid fitted to
noise alone gives a period that means nothing, and a trial closes early only on one that
counts. A test that cannot go on between trials (no room for the next bump) puts the setpoint
back where it began and calms the loop there before it aborts (``_hand_back``).

Every phase has a budget in sim time, from what the test has seen: the quiet period 20 quiet
windows (per back-off); before any period is known, each trial ``first_trial_time`` and 1000
quiet windows at most, and the search 40 trial lengths (the longest so far) after the first
trial; once a period P is known (the first one measured), each trial (``trial_periods`` + ½)·P,
each calming ``settle_periods``·P before its gain is halved, and the whole test
``total_periods``·P after that first oscillation. ``max_time`` caps it all. Running out aborts
the test with the budget named in ``reason``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from services.autotuner.identify import inverse_response
from services.autotuner.identify.experiments import (
    DIRECT_NOTE,
    Band,
    Demand,
    Event,
    Identification,
    Progress,
    Settings,
    Setup,
    abort_band,
    action_question,
    clipped,
    range_allowance,
    samples_until,
)
from services.autotuner.identify.hold_correction import (
    agree,
    contradicts,
    slope_error,
    through_model,
    uncertainty,
    unmeasured,
)
from services.autotuner.identify.model_fit import (
    ProcessFit,
    choose_on_record,
    refine_on_record,
    second_order_starts,
    through_ultimate_point,
)
from services.autotuner.identify.oscillation import (
    Oscillation,
    fit_oscillation,
    stands_out,
    swings,
)
from services.autotuner.parts import Parts, in_turn
from shared.control.beyond import beyond
from shared.control.record_stops import MAX_WINDOW, CalmCheck, calm_spread
from shared.control.signals import Sample, at_rest, noise_level

CALM_EVERY = 8  # samples between a calming's checks


@dataclass(frozen=True)
class RampConfig:
    kc_start: float  # first trial gain, % per PV unit
    bump: float  # setpoint bump, PV units
    factor: float = 1.5  # geometric gain increase while searching
    tolerance: float = 0.01  # stop when (Kc_hi − Kc_lo)/Kc_lo is below this
    trial_periods: float = 4.0  # periods watched per trial
    quiet: float | None = None  # s; None: 40 samples
    first_trial_time: float = 3600.0  # s to watch a trial before any period is known
    swing_limit: float = 8.0  # × bump: a trial swinging wider is stopped (and judged by its fit)
    max_trials: int = 40
    max_time: float = 86400.0  # s: a cap; the budgets below are usually far shorter
    total_periods: float = 200.0  # periods of the oscillation the test may run once it has one
    settle_periods: float = 20.0  # periods a calming may take before its gain is halved
    headroom: float = 0.5  # of the output's room to its nearer limit, a trial's kick may take
    # --- thresholds and factors ---
    # tenfold (at rest) or factor³ (after a trial) cuts of a start gain too high, at most
    max_backoffs: int = 8
    # halvings of the calming gain in one calming before giving up
    max_calm_cuts: int = 4
    # trial lengths the search may take after the first, while no period is known
    search_lengths: float = 40.0
    # the quiet period without ``quiet``: enough samples for a trend and a noise level
    quiet_samples: int = 40
    # never fewer samples in the quiet period: a regression on fewer says nothing
    min_quiet_samples: int = 10
    # quiet periods to wait for the PV to come to rest before giving up
    quiet_periods: int = 20
    # a start gain that saturates the output at rest is divided by this
    rest_backoff: float = 10.0
    # an output at a limit this fraction of a window is stuck there (at rest, or calming)
    stuck_fraction: float = 0.5
    # the smallest bump worth a trial, in σ of the noise: a smaller one drowns in it
    min_bump_sigmas: float = 6.0
    # the output's noise taken into a trial's kick, in σ of the PV noise (times Kc)
    kick_sigmas: float = 3.0
    # a trial before any period is known is watched at most this many quiet periods
    trial_cap_quiet: int = 1000
    # the calming gain: this fraction of the last decaying one (comfortably below K_u)
    calm_gain: float = 0.7
    # the next gain stays this fraction of the bracket away from its ends (Illinois)
    bracket_margin: float = 0.05
    # the PV has moved (the trial's response began) this fraction of the bump away…
    moving_fraction: float = 0.02
    # … or this many σ of the noise, whichever is more
    moving_sigmas: float = 6.0
    # a fitted oscillation counts only if its largest amplitude is this many σ of the noise
    fit_sigmas: float = 2.0
    # trials within this range of K_u (as fractions of it) give the ZOH correction's slope
    near_ku: tuple[float, float] = (0.7, 1.3)
    # their slope is used only within this relative standard error (three trials or more)
    max_slope_error: float = 0.15
    # abort as soon as the trials say the feedback is positive (``_wrong_way``) and none has
    # oscillated; False: a run recorded before, which ran on to its trial limit or budget
    stop_wrong_way: bool = False
    # a trial closes early, and its fit counts, only on an oscillation that swings out of
    # the noise for half a period (``oscillation.stands_out``). False: a run recorded before,
    # whose trials closed early on any fit with enough turning points, and whose fits were
    # judged by their period against the window and their largest amplitude
    seen_fits: bool = True
    # a test that cannot go on between trials (no room for the next bump) first puts the
    # setpoint back where it began and calms the loop there (``_hand_back``). False: a run
    # recorded before, aborted at once, its PV left a bump off (a level stays there)
    hand_back: bool = True
    # a trial's response has died out only once flat against how far it has moved, where
    # that is less than the bump (``_died_out``). False: a run recorded before, flat against
    # the bump alone
    settled_by_move: bool = True
    # the process model's fits also start from lags far apart and from an integrator behind
    # a lag (``model_fit.second_order_starts``), and the integrators fit the output's offset
    # from its balance. False: a run recorded before, without either
    more_starts: bool = True
    # a trial's period shorter than the dead time the first trial showed is not taken as the
    # loop's time scale (``_close_trial``). False: a run recorded before, every period taken
    period_floor: bool = True
    # PV units a calming between trials may take the PV from the trial's rest, or twice the
    # trial's swing limit where that is more, while the trials say the loop's feedback is
    # positive (``_calm_bound``): a calming at a lower gain then runs off as they did, and is
    # not held on until the PV reaches the end of its range (a level whose process answered
    # against the loop's action was calmed to 0 %). None: no bound but the PV limits (a run
    # recorded before, or limits of the engineer's own)
    calm_allowance: float | None = None
    # PV units the transmitter does not resolve (``Setup.resolution_floor``): a quiet window
    # may drift within it and be rest (a noise-free PV's creep after a test); 0: the noise
    # alone decides (a run recorded before)
    resolution: float = 0.0

    def __post_init__(self) -> None:
        if not (self.kc_start > 0 and math.isfinite(self.kc_start)):
            raise ValueError(f"kc_start {self.kc_start}: must be > 0")
        if not (self.bump > 0 and math.isfinite(self.bump)):
            raise ValueError(f"bump {self.bump}: must be > 0 PV units")
        if not self.factor > 1:
            raise ValueError(f"factor {self.factor}: must be > 1")
        if not 0 < self.tolerance < 0.5:
            raise ValueError(f"tolerance {self.tolerance}: must be between 0 and 0.5")
        if not (self.max_time > 0 and self.total_periods > 0 and self.settle_periods > 0):
            raise ValueError("max_time, total_periods and settle_periods: must be > 0")
        if not 0 < self.headroom <= 1:
            raise ValueError(f"headroom {self.headroom}: must be in (0, 1]")


@dataclass(frozen=True)
class Trial:
    kc: float
    growth: float  # 1/s; −inf when the response did not oscillate
    period: float | None
    swings: int
    cut_short: bool
    # 1/s: the growth of the sinusoid fitted alone, where a slow mode fitted beside it gave
    # ``growth`` (None: no slow mode kept)
    growth_alone: float | None = None


@dataclass(frozen=True)
class RampResult:
    ku: float
    pu: float
    kc_low: float  # last decaying gain
    kc_high: float  # first growing gain
    trials: int
    noise_std: float
    rest_pv: float
    ku_loop: float = math.nan  # the sampled loop's own ultimate point (before the ZOH correction)
    pu_loop: float = math.nan
    model: ProcessFit | None = None  # fitted to the whole record (None without the outputs)
    bump: float = math.nan  # PV units: the configured setpoint bump
    bump_final: float = math.nan  # PV units: the bump after any halving (saturation)
    # how the hold's effect was taken out of the loop's point: "model" (the process model's
    # sampled and continuous crossovers), "trials" (the trials' poles), "none"
    hold_correction: str = "none"
    # the relative uncertainty (K_u, P_u) the hold's correction adds (None: none); the other
    # estimate of the plant's point, where the two disagree, and the loop's sample time
    hold_spread: tuple[float, float] | None = None
    hold_other: tuple[float, float] | None = None
    sample_time: float = math.nan
    # how far (relative) the loop's K_u moves with the trials' growth rates read from the
    # sinusoid fitted alone, where a slow mode fitted beside it was kept (``mode_gap``)
    mode_gap: float | None = None
    # how far the PV first went the other way from the first trial's bump (PV units): an
    # inverse response (``RampTest._inverse_dip``); None when it did not
    inverse_dip: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """The run's ``experiment`` object (its keys are part of the JSON interface)."""
        return {
            "trials": self.trials,
            "ku_sampled_loop": self.ku_loop,
            "pu_sampled_loop": self.pu_loop,
            "hold_correction": self.hold_correction,
            "hold_spread_ku": self.hold_spread[0] if self.hold_spread else None,
            "hold_spread_pu": self.hold_spread[1] if self.hold_spread else None,
            **(self.model.to_dict() if self.model else {}),
            "kc_low": self.kc_low,
            "kc_high": self.kc_high,
            "bump": self.bump,
            "bump_final": self.bump_final,
            "noise_std": self.noise_std,
            "rest_pv": self.rest_pv,
            **({"inverse_dip": self.inverse_dip} if self.inverse_dip is not None else {}),
        }

    @property
    def bracket(self) -> float:
        """The final bracket's width relative to K_u: the least K_u is unsure by."""
        return (self.kc_high - self.kc_low) / self.ku

    def identification(self) -> Identification:
        held = self.hold_spread
        return Identification(
            ku=self.ku,
            pu=self.pu,
            ku_spread=max(self.bracket, held[0] if held else 0.0, self.mode_gap or 0.0),
            pu_spread=None if held is None else held[1],
            ku_bracketed=True,
            experiment=self,
            timescale=self.pu,
            noise=self.noise_std,
            rest_pv=self.rest_pv,
            model=self.model,
            notes=self.hold_notes() + self.mode_notes() + self.inverse_notes(),
            inverse_response=self.inverse_dip is not None,
        )

    def inverse_notes(self) -> list[str]:
        """The inverse response the first trial showed, if it did."""
        if self.inverse_dip is None:
            return []
        where = "after the first trial's bump"
        return [inverse_response.note(where, self.inverse_dip, self.model)]

    def mode_notes(self) -> list[str]:
        """Where the slow mode fitted beside the trials' oscillations moves K_u more than the
        bracket and the hold's correction leave unsure: both readings, and the spread."""
        gap = self.mode_gap
        held = self.hold_spread[0] if self.hold_spread else 0.0
        if gap is None or gap <= max(held, self.bracket):
            return []
        return [
            f"the trials' growth rates depend on what is fitted beside their oscillation: "
            f"with a slow mode (kept, it fits better) the loop's K_u is {self.ku_loop:.4g}, "
            f"with the sinusoid alone {100 * gap:.2g} % away (a second oscillation, such as "
            f"a lightly damped plant's own, is neither); K_u ±{100 * gap:.2g} % stated"
        ]

    def hold_notes(self) -> list[str]:
        """What the engineer must know of the hold's correction: its two estimates where they
        disagree, a correction through the model, the trials' adding 2 % or more to a
        spread, or (none made) a hold that lags 1° or more at the crossover."""
        loop = f"the sampled loop's {self.ku_loop:.4g} and {self.pu_loop:.4g} s"
        held, other = self.hold_spread, self.hold_other
        spread = f"K_u ±{100 * held[0]:.2g} %, P_u ±{100 * held[1]:.2g} %" if held else ""
        ours = f"K_u {self.ku:.4g} and P_u {self.pu:.4g} s"
        if other is not None:
            theirs = f"{other[0]:.4g} and {other[1]:.4g} s"
            by_trials = self.hold_correction == "trials"
            return [
                "the zero-order hold's effect is uncertain: the trials' poles correct "
                f"{loop} to {ours if by_trials else theirs}, the process model to "
                f"{theirs if by_trials else ours}; {ours} stated, its spreads covering both "
                f"({spread})"
            ]
        lag = math.degrees(math.pi * self.sample_time / self.pu_loop)
        if self.hold_correction == "model":
            return [
                f"K_u and P_u are corrected for the zero-order hold through the process model "
                f"(the trials' growth rates too noisy to give it; {loop}); a model's class "
                f"sets its slopes, so the correction may be off by half its size, and K_u by "
                f"as much as the crossover moved ({spread})"
            ]
        if self.hold_correction == "trials" and held is not None and max(held) >= 0.02:
            per = self.pu_loop / self.sample_time
            return [
                f"K_u and P_u carry the trials' correction for the zero-order hold ({loop}, "
                f"{per:.0f} samples a period): a first-order step that sees no aliasing, good "
                f"to about half its size ({spread})"
            ]
        if self.hold_correction == "none" and lag >= 1.0:
            return [
                f"K_u and P_u are the sampled loop's, not the plant's own: the zero-order hold "
                f"lags {lag:.2g}° at the crossover (T = {self.sample_time:.4g} s), and the "
                "plant's own point lies at a higher frequency (K_u higher, P_u shorter) by an "
                "amount neither the trials (too noisy) nor a process model could give"
                + (f" ({spread})" if spread else "")
            ]
        return []


def mode_gap(trials: list[Trial], ku: float, near: tuple[float, float]) -> float | None:
    """How far (relative) the loop's K_u moves when the trials' growth rates are read from
    the sinusoid fitted alone rather than beside the slow mode kept with it: the zeros of two
    straight lines, growth against gain, through the oscillating trials within ``near`` of
    ``ku``. Why: a slow real mode beside the oscillation is what a lag chain leaves, but a
    second oscillation is not one, and the slow mode then bends the growth read: a lightly
    damped plant (ζ 0.34, its resonance near ω_u) had its loop's K_u bracketed 2.1 % low with
    a spread of 0.25 %, the sinusoid alone putting it 2.4 % higher. None where no trial near
    K_u kept a slow mode, or a line has no rising zero."""
    low, high = near
    close = [
        t for t in trials if t.period and math.isfinite(t.growth) and low * ku <= t.kc <= high * ku
    ]
    if not any(t.growth_alone is not None for t in close):
        return None
    kc = np.array([t.kc for t in close])
    if kc.size < 2 or np.ptp(kc) == 0:
        return None

    def zero(growth: list[float]) -> float | None:
        slope, at_zero = np.polyfit(kc, np.array(growth), 1)
        return float(-at_zero / slope) if slope > 0 else None

    kept = zero([t.growth for t in close])
    alone = zero([t.growth if t.growth_alone is None else t.growth_alone for t in close])
    if kept is None or alone is None or not kept > 0:
        return None
    return abs(alone / kept - 1.0)


def _white(y: np.ndarray) -> bool:
    """The scatter about the trend is white noise, not a slow swing (after a back-off the loop
    may still ring, which ``at_rest`` reads as noise): its σ matches that of the sample-to-
    sample differences (within 1.5×)."""
    scatter = noise_level(y)
    step = float(np.std(np.diff(y))) / math.sqrt(2.0)
    return scatter <= 1.5 * step or scatter <= 1e-12 * max(1.0, float(np.max(np.abs(y))))


@dataclass
class RampTest:
    config: RampConfig
    pv_limits: tuple[float, float]
    sample_time: float
    sp_start: float = math.nan  # the setpoint held during the quiet period (NaN: first PV)
    op_limits: tuple[float, float] = (0.0, 100.0)  # the loop's output limits, %
    direction: float = 1.0  # +1 reverse-acting loop, −1 direct (its model fitted as −G)
    # the transmitter's range: a PV at either end is clipped, and aborts (None: not checked)
    pv_range: tuple[float, float] | None = None

    # quiet → trial ⇄ settle → concluding → done | aborted; "concluding": finished, the loop
    # at a calming gain (``closing``), the findings computed on ``identification``
    phase: str = "quiet"
    reason: str = ""
    result: RampResult | None = None
    # how the closing refines (one model per start, a tenth of a second in all) are computed:
    # in turn here; the tuner hands each to a worker, all at once (``parts``)
    parts: Parts = field(default=in_turn, repr=False, compare=False)
    trials: list[Trial] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)

    needs_hold_time: ClassVar[bool] = False

    def __post_init__(self) -> None:
        cfg = self.config
        q = cfg.quiet if cfg.quiet is not None else cfg.quiet_samples * self.sample_time
        self._quiet_n = max(cfg.min_quiet_samples, math.ceil(q / self.sample_time))
        self._t: list[float] = []
        self._y: list[float] = []
        self._u: list[float] = []  # the loop's output, held from each sample
        self._quiet_from = 0  # where the present quiet period began (it restarts on a back-off)
        self._quiet_end = 0  # samples of the quiet period: the record's rest
        self._start = math.nan
        self._r = math.nan
        self._noise = 0.0
        self.kc = self.config.kc_start
        self.sp = self.sp_start
        self.bump = self.config.bump  # PV units; halved each time a trial saturates the output
        self._trial_bump = self.config.bump  # the present trial's (≤ bump: the kick must fit)
        self._bumps = 0  # setpoint bumps so far (their sign alternates)
        self._trial_sign = 1.0  # the present trial's bump: +1 up, −1 down
        # per trial: its PV went the other way from its bump (−1), with it (+1), unclear (0)
        self._went: list[int] = []
        self._trial_start = 0  # index into the record
        self._trial_t0 = 0.0
        self._lo: Trial | None = None
        self._hi: Trial | None = None
        self._side = 0  # Illinois: which end was kept last
        self._period: float | None = None
        self._t_period = math.nan  # s: when the first period was measured
        self._p_first = math.nan  # s: that period
        self._calm_kc = self.config.kc_start
        self._found = (math.nan, math.nan)  # concluding: K_u and P_u of the sampled loop
        self._settle_start = 0
        self._settle_t0 = 0.0
        self._calm_cuts = 0
        self._sat_run = 0  # consecutive samples with the output at a limit
        self._sat_count: list[int] = []  # samples with the output at a limit, cumulative
        self._backoffs = 0
        self._first_end = math.nan  # s: when the first trial ended
        self._trial_max = 0.0  # s: the longest trial so far (bump to verdict)
        self._last_len = 0.0  # s: the last trial's length
        self._first_dead: int | None = None  # samples: the first trial's dead time
        self._dip: float | None = None  # PV units: the first trial's inverse response
        self._trials_from_rest = True  # the trial began from the quiet period's verified rest
        self._silent = False  # the last trial's PV never moved clear of the noise
        self._handing_back = ""  # why the test ends, once it is putting the setpoint back
        self._sp0 = self.sp  # the setpoint the test began with (the first PV when not given)
        self._deadline = math.inf  # s: sim time by which the test must be over
        self._budget = ""  # which budget that is, for the abort's reason
        # the last fit of a trial's record: (trial start, end, noise, period hint), its result
        self._last_fit: tuple[tuple, Oscillation | None] | None = None

    @property
    def finished(self) -> bool:
        return self.phase in ("concluding", "done", "aborted")

    @property
    def closing(self) -> Demand | None:
        """Done: a gain known to decay, at once. The last trial's gain, which may lie above
        K_u, would otherwise be held while the findings are fitted (a quarter of a second,
        more on a busy machine) and until the tuner takes the loop to manual."""
        if self.phase not in ("concluding", "done"):
            return None
        return Demand(kc=min(self._calm_kc, self._calming_gain()), sp=self.sp)

    @property
    def demand(self) -> Demand:
        """The gain and setpoint to hold now."""
        return Demand(kc=self.demand_kc, sp=self.sp)

    def held(self, t: float) -> None:
        """Nothing to do: a new gain or setpoint is timed from the sample it follows."""

    def progress(self) -> Progress:
        n = len(self.trials)
        if not n:
            return Progress("ramp", 0)
        tr = self.trials[-1]
        if math.isfinite(tr.growth):
            message = f"Kc {tr.kc:.4g}: growth {tr.growth:.3g}/s"
        else:  # ±inf stands for "no oscillation": said in words, not as a number
            went = "ran away" if tr.growth > 0 else "did not oscillate"
            message = f"Kc {tr.kc:.4g}: {went}"
        return Progress("ramp", n, cycles=n, pu=tr.period, message=message)

    def identification(self) -> Identification | None:
        if self.phase == "concluding":
            self._conclude()
        if self.result is None:
            return None
        found = self.result.identification()
        if self.direction < 0 and found.model is not None:
            found.notes.append(DIRECT_NOTE)
        return found

    def _abort(self, reason: str) -> Demand:
        """Every abort: the phase, the reason and an ``aborted`` event. One that comes as the
        test hands the setpoint back (a limit, a budget, a loop that will not calm) says why
        the test was ending first, and then what stopped the hand-back."""
        if self._handing_back and reason != self._handing_back:
            reason = f"{self._handing_back}; putting the setpoint back where it began: {reason}"
        self.phase, self.reason = "aborted", reason
        self.events.append(Event(self._t[-1], "aborted", {"reason": reason}))
        return Demand(kc=self.kc, sp=self.sp)

    def feed(self, sample: Sample) -> Demand:
        """Take the PV sampled at ``sample.t`` (and the output the loop holds from then, %:
        for the process model and to see the output saturate); return the gain and setpoint
        to hold from ``sample.t`` on."""
        t, pv, op = sample.t, sample.pv, sample.op
        if self.finished:
            return Demand(kc=self.kc, sp=self.sp)
        self._t.append(t)
        self._y.append(pv)
        self._u.append(op)
        if math.isnan(self._start):
            self._start = t
            if math.isnan(self.sp):
                self.sp = pv
            self._sp0 = self.sp  # where the test began: the setpoint a hand-back returns to
            self._update_budget()
        lo, hi = self.pv_limits
        if not lo <= pv <= hi:
            return self._abort(
                f"PV {beyond(pv, lo, hi)} left its limits [{lo:g}, {hi:g}] at t = {t:g} s"
            )
        if why := clipped(pv, self.pv_range, t, "--bump"):
            return self._abort(why)
        if t > self._deadline:
            return self._abort(f"{self._budget} (at t = {t:g} s, in phase {self.phase})")
        self._watch_output(op)
        if self.phase == "quiet":
            self._watch_quiet(t)
        elif self.phase == "trial":
            self._watch_trial(t)
        elif self.phase == "settle":
            self._watch_settle(t)
        return Demand(kc=self.demand_kc, sp=self.sp)

    # --- budgets and the output's limits ---------------------------------------------------

    def _update_budget(self) -> None:
        """The sim time by which the test must be over: ``max_time`` from the start, and from
        what the test has seen: ``total_periods`` of the first period measured, after it;
        before that, ``search_lengths`` trial lengths (the longest so far) after the first."""
        cfg = self.config
        self._deadline = self._start + cfg.max_time
        self._budget = f"no result within max_time = {cfg.max_time:g} s"
        if self._period is not None:  # fixed by the first period: it never moves
            end = self._t_period + cfg.total_periods * self._p_first
            why = (
                f"no result within {cfg.total_periods:g} periods (P ≈ {self._p_first:.4g} s, "
                "the first measured) after the first oscillation"
            )
        elif math.isfinite(self._first_end):
            length = max(self._trial_max, self._quiet_n * self.sample_time)
            end = self._first_end + cfg.search_lengths * length
            why = (
                f"no oscillation within {cfg.search_lengths:g} trial lengths ({length:.4g} s, the "
                "longest so far) after the first trial"
            )
        else:
            return
        if end < self._deadline:
            self._deadline, self._budget = end, why

    def _watch_output(self, op: float) -> None:
        """Count the samples in a row with the output at one of its limits."""
        lo, hi = self.op_limits
        eps = 1e-6 * (hi - lo)
        at = math.isfinite(op) and (op <= lo + eps or op >= hi - eps)
        self._sat_run = self._sat_run + 1 if at else 0
        self._sat_count.append((self._sat_count[-1] if self._sat_count else 0) + at)

    def _sat_fraction(self, n: int) -> float:
        """The fraction of the last ``n`` samples with the output at a limit."""
        c = self._sat_count
        n = max(1, min(n, len(c)))
        return (c[-1] - (c[-n - 1] if n < len(c) else 0)) / n

    def _saturated(self) -> bool:
        """The output has sat at a limit for a few samples in a row (2 % of a period, once
        one is known): the loop is no longer linear."""
        return self._sat_run >= self._sat_samples()

    def _sat_samples(self) -> int:
        """Samples in a row at a limit that make a saturated output (``_saturated``)."""
        if self._period is None:
            return 3
        return max(3, math.ceil(0.02 * self._period / self.sample_time))

    def _room(self) -> float:
        """% from the present output to its nearer limit (NaN if the output is not known)."""
        lo, hi = self.op_limits
        u = self._u[-1]
        return min(u - lo, hi - u) if math.isfinite(u) else math.nan

    def _min_bump(self) -> float:
        """The smallest bump worth a trial, PV units: 6σ of the noise (a thousandth of the
        configured bump without noise), never more than the configured bump."""
        cfg = self.config
        return min(cfg.bump, max(cfg.min_bump_sigmas * self._noise, 1e-3 * cfg.bump))

    # --- quiet period ----------------------------------------------------------------------

    def _watch_quiet(self, t: float) -> None:
        """Wait for the PV to be at rest (20 quiet periods at most). An output at its limit
        half the time means the start gain drives it there on the noise alone (or into a limit
        cycle): back off tenfold, once per quiet window; at a limit at all, it is not at rest."""
        n = self._quiet_n
        seen = len(self._y) - self._quiet_from
        saturated = self._sat_fraction(n) if seen >= n else 0.0
        if saturated >= self.config.stuck_fraction:
            if self._backoffs >= self.config.max_backoffs:
                self._abort(
                    f"the output stays at its limit at rest, even at Kc = {self.kc:.4g} "
                    f"(start gain {self.config.kc_start:g} backed off {self._backoffs} times)"
                )
                return
            self._back_off(
                t, self.kc / self.config.rest_backoff, "the output sits at its limit at rest"
            )
            self._quiet_from, self._sat_run = len(self._y), 0
            return
        if seen >= n:
            base = np.asarray(self._y[-n:])
            rest = at_rest(base, allowance=self.config.resolution)
            if saturated == 0 and rest and (not self._backoffs or _white(base)):
                self._r, self._noise = float(base.mean()), noise_level(base)
                self._quiet_end = len(self._y)
                self._begin_trial(t)
            elif seen >= self.config.quiet_periods * n:
                why = "the output keeps reaching its limits" if saturated else "it keeps drifting"
                self._abort(f"the PV is not at rest before the test ({why})")

    def _back_off(self, t: float, kc: float, why: str) -> None:
        self._backoffs += 1
        self.events.append(Event(t, "back_off", {"kc": kc, "from": self.kc, "reason": why}))
        self.kc = self._calm_kc = kc

    # --- trials ----------------------------------------------------------------------------

    def _begin_trial(self, t: float) -> None:
        """Bump the setpoint at gain ``kc``; first shrink the bump (or back the gain off) so
        the kick Kc·bump and the output's noise stay within ``headroom`` of the output's room."""
        bump, room = self.bump, self._room()
        if math.isfinite(room):
            if room <= 0:
                self._hand_back(t, f"the output rests at its limit ({self._u[-1]:.4g} %): no room")
                return
            fits = self.config.headroom * room / self.kc - self.config.kick_sigmas * self._noise
            if bump > fits:
                if fits >= self._min_bump():
                    bump = fits
                    self.events.append(
                        Event(t, "bump", {"bump": bump, "kc": self.kc, "reason": "kick fitted"})
                    )
                elif self._lo is None and self._backoffs < self.config.max_backoffs:
                    kc = (
                        self.config.headroom * room / (bump + self.config.kick_sigmas * self._noise)
                    )
                    self._back_off(t, kc, "the kick Kc·bump would saturate the output")
                else:
                    cfg, least = self.config, self._min_bump()
                    kick = self.kc * (least + cfg.kick_sigmas * self._noise)
                    self._hand_back(
                        t,
                        f"no bump the noise allows (≥ {least:.4g}) fits the output's room at "
                        f"Kc = {self.kc:.4g}: its kick with the noise's, Kc·(bump + "
                        f"{cfg.kick_sigmas:g}σ) = {kick:.4g} %, is over {cfg.headroom:.0%} of "
                        f"the room to the output's limit ({room:.4g} %); the relay and the "
                        "step test need no gain on the loop (--method relay, --method step)",
                    )
                    return
        n = self._bumps
        self._bumps += 1
        self._trial_bump = bump
        # from the present setpoint, not from where the PV rests: under P-only control the PV
        # settles off the setpoint, and a bump from the PV's rest would kick by that offset too
        self._trial_sign = 1.0 if n % 2 == 0 else -1.0
        self.sp += bump * self._trial_sign
        self._trial_start, self._trial_t0 = len(self._y) - 1, t
        self._next_check = 16
        self._sat_run = 0
        self.phase = "trial"
        self.events.append(
            Event(
                t, "trial", {"n": len(self.trials) + 1, "kc": self.kc, "sp": self.sp, "bump": bump}
            )
        )

    def _hand_back(self, t: float, reason: str) -> None:
        """End a test that cannot go on (``reason``) where it began: the setpoint put back to
        where the test started it and the loop calmed there, at a gain known to decay, then
        the test aborted. The trials bump the setpoint up and back in turn, so a test stopped
        after an odd one left the PV a bump off its rest, and the loop, restored to its output
        before the test, with it: an integrating level stays there (lvl2 was left 0.010 m off
        with a band of 0.008, "not returned"), a slow one takes its lag to come back."""
        if not self.config.hand_back or self._handing_back or self.sp == self._sp0:
            self._abort(reason)
            return
        self._handing_back = reason
        self.sp = self._sp0
        self.events.append(Event(t, "hand_back", {"sp": self.sp, "reason": reason}))
        self._begin_settle(t)

    def _trial_cap(self) -> float:
        """s to watch a trial before any period is known: ``first_trial_time``, and 1000
        quiet windows. (A gain nearer K_u rings longer than a lower one did: an earlier
        response's length is no bound on the next.)"""
        cfg = self.config
        return min(cfg.first_trial_time, cfg.trial_cap_quiet * self._quiet_n * self.sample_time)

    def _watch_trial(self, t: float) -> None:
        n = len(self._y) - self._trial_start
        if self._saturated():
            self._trial_saturated(t)
        elif self._swing_limit_hit():
            self._close_trial(t, cut=True)
        elif self._period is not None:
            if t - self._trial_t0 >= (self.config.trial_periods + 0.5) * self._period:
                self._close_trial(t, cut=False)
        elif t - self._trial_t0 >= self._trial_cap():
            self._close_trial(t, cut=False, capped=True)
        elif n >= self._next_check:  # geometric spacing keeps the checks' cost near linear
            self._next_check = int(n * 1.25) + 16
            if self._died_out(n):
                self._close_trial(t, cut=False)
                return
            # enough swings seen: counted first, and the fit (which counts the same) made only
            # once there are enough to close on. It closes the trial only on an oscillation
            # the close will judge by: the noise's own turning points make up the count on a
            # finely sampled record, and a trial closed on them, a few seconds into a slow
            # response, was judged "did not oscillate" and the gain raised (to 3.8·K_u on the
            # heat exchanger sampled at 0.025 s)
            enough = 2 * self.config.trial_periods + 1
            if self._swings() >= enough:
                osc = self._fit(raw=not self.config.seen_fits)
                if osc is not None and osc.swings >= enough:
                    self._close_trial(t, cut=False)

    def _trial_saturated(self, t: float) -> None:
        """The output has sat at a limit: the loop is not linear any more. Judged growing if
        the record before the saturation shows a growing oscillation; otherwise repeated at
        the same gain with half the bump, or (no smaller bump the noise allows) with the gain
        backed off while no decaying gain is known, else aborted."""
        end = len(self._y) - self._sat_run + 1  # the PV at the first saturated sample is clean
        osc = self._fit(end)
        if osc is not None and osc.swings >= 2 and osc.growth > 0:
            self._close_trial(t, cut=True, end=end)
            return
        self._last_len = t - self._trial_t0
        self.events.append(
            Event(t, "saturated", {"kc": self.kc, "bump": self._trial_bump, "op": self._u[-1]})
        )
        half = 0.5 * self._trial_bump
        if half >= self._min_bump():
            self.bump = min(self.bump, half)
            self.events.append(
                Event(t, "bump", {"bump": self.bump, "kc": self.kc, "reason": "output saturated"})
            )
        elif self._lo is None and self._backoffs < self.config.max_backoffs:
            self._back_off(t, self.kc / self.config.factor**3, "the output saturates")
        else:
            self._abort(
                f"the output saturates at Kc = {self.kc:.4g} even with a bump of "
                f"{self._trial_bump:.4g} (the noise allows none below {self._min_bump():.4g}); "
                "the relay and the step test need no gain on the loop (--method relay, "
                "--method step)"
            )
            return
        self._begin_settle(t)

    def _inverse_dip(self, end: int | None) -> float | None:
        """How far the PV first went the other way from the first trial's bump, from its
        rest (PV units; ``inverse_response.dip``, on the scale of how far it went the bump's
        way)."""
        along = (np.asarray(self._y[self._trial_start : end]) - self._r) * self._trial_sign
        if along.size < 3 or not float(np.max(along)) > 0:
            return None
        return inverse_response.dip(along, self._noise, float(np.max(along)))

    def _died_out(self, n: int) -> bool:
        """The trial's response has come and gone: the PV moved, and it has been flat over
        the last half of the response and over twice the dead time it took to start moving (a
        delay-dominated loop's response is a staircase whose treads last one dead time: they
        are not its end)."""
        if n < 40:
            return False
        y = np.asarray(self._y[self._trial_start :])
        away = np.abs(y - self._r)
        moving = np.nonzero(away >= self._moving_level())[0]
        if moving.size == 0:
            return False
        dead = int(moving[0])
        if self._first_dead is None and self._trials_from_rest:
            self._first_dead = dead  # seen from a verified rest: the loop's own dead time
        # a later trial may start on what is left of the one before (a slow loop looks calm
        # over a few dozen samples): it has not died out before the dead time the first
        # trial showed has passed twice over
        dead = max(dead, self._first_dead or 0)
        # flat over the last half of the response so far, and over two dead times
        window = max(20, (n - dead) // 2, 2 * dead + 2)
        if n - dead < window:
            return False
        # flat: the means of ten stretches of the tail agree (the noise averaged in each),
        # within 5 % of the bump, or of how far the response has moved where that is less:
        # a low gain's response is a small part of the bump, and 5 % of the bump is most of
        # it (an inverse response, (1 − s)/(s + 1)³ at 0.15·K_u, turning 0.1 below its rest
        # and rising slowly, judged over after 2 s; three such trials ended the test as
        # "the PV went the other way: is the process one for a direct-acting PID?")
        tail = y[-(window // 10) * 10 :].reshape(10, -1)
        spread = float(np.ptp(tail.mean(axis=1)))
        scale = self._trial_bump
        if self.config.settled_by_move:
            scale = min(scale, float(np.max(away)))
        return spread < max(0.05 * scale, 6.0 * self._noise / math.sqrt(tail.shape[1]))

    def _moving_level(self) -> float:
        """PV units from the rest that tell a response from the dead time before it: at a low
        gain the PV moves by Kc·K/(1 + Kc·K) of the bump, which can be a small fraction of it."""
        cfg = self.config
        return max(cfg.moving_fraction * self._trial_bump, cfg.moving_sigmas * self._noise)

    def _swing_limit_hit(self) -> bool:
        """The PV has swung further from where it rested before the trial than allowed."""
        return abs(self._y[-1] - self._r) > self.config.swing_limit * self._trial_bump

    def _swings(self) -> int:
        """The half-cycles the fit of the trial's record so far would count (no fit made)."""
        t = np.asarray(self._t[self._trial_start :])
        y = np.asarray(self._y[self._trial_start :])
        return swings(t, y, self._noise, self._period)

    def _fit(self, end: int | None = None, raw: bool = False) -> Oscillation | None:
        """The oscillation in the trial's record (up to sample ``end``), if it is one: the
        record 1.5 of its periods long, and its envelope out of the noise for half a period
        (``stands_out``: a fit to noise alone finds a sinusoid a fraction of σ tall, or one
        on a spike of it, and a period that means nothing: adopted, it would cut the next
        trials short); ``raw``: whatever the fit found (a run recorded before closed its
        trials on it)."""
        t = np.asarray(self._t[self._trial_start : end])
        y = np.asarray(self._y[self._trial_start : end])
        # the same record fitted again (a check that closes the trial, then its close) gives
        # the same fit: the last one is kept
        stop = len(self._t) if end is None else min(end, len(self._t))
        key = (self._trial_start, stop, self._noise, self._period)
        if self._last_fit is not None and self._last_fit[0] == key:
            osc = self._last_fit[1]
        else:
            osc = fit_oscillation(t, y, self._noise, self._period, self.parts)
            self._last_fit = (key, osc)
        if raw or osc is None or t.size < 2:
            return osc
        watched, level = float(t[-1] - t[0]), self.config.fit_sigmas * self._noise
        if self.config.seen_fits:
            return osc if stands_out(osc, watched, level) else None
        if osc.period > watched / 1.5:
            return None
        # its amplitude where largest: at the start (decaying) or at the end (growing)
        seen = osc.amplitude * math.exp(min(max(osc.growth * watched, 0.0), 50.0))
        return osc if seen >= level else None

    def _close_trial(
        self, t: float, cut: bool, end: int | None = None, capped: bool = False
    ) -> None:
        """Judge the trial on its record (up to sample ``end``): ``cut`` short as growing,
        or watched to its end (``capped``: to the time limit before any period is known)."""
        osc = self._fit(end)
        watched = t - self._trial_t0
        # where the last half of the trial went, against its bump or with it (said only)
        y_trial = np.asarray(self._y[self._trial_start : end])
        away = (float(np.mean(y_trial[y_trial.size // 2 :])) - self._r) * self._trial_sign
        clear = self._moving_level()
        self._went.append(-1 if away < -clear else 1 if away > clear else 0)
        self._silent = False
        if osc is None or osc.swings < (2 if cut else 3):
            # no oscillation to fit: an overdamped response, or one that ran away at once
            trial = Trial(self.kc, math.inf if cut else -math.inf, None, 0, cut)
            if capped:  # watched to the limit, and the PV never moved clear of the noise
                y = np.asarray(self._y[self._trial_start :])
                self._silent = not np.any(np.abs(y - self._r) >= self._moving_level())
        else:
            trial = Trial(self.kc, osc.growth, osc.period, osc.swings, cut, osc.growth_alone)
            # the loop's time scale (each trial's length, the calming's window): not from a
            # period shorter than the dead time the first trial showed, which no oscillation
            # of the loop's own has (its ultimate period is over twice its dead time): a fit
            # of the noise, or of a higher mode. A pure delay's first trial fitted 0.84 s for
            # a 3 s dead time; every trial after was watched for 3.8 s, closed before its
            # response came, judged "did not oscillate" up to 1.7 K_u, and the loop, calmed at
            # 0.7 of that, ran to the end of its range
            dead = (self._first_dead or 0) * self.sample_time
            if osc.period >= dead or not self.config.period_floor:
                if self._period is None:
                    self._t_period, self._p_first = t, osc.period
                self._period = osc.period
        self._last_len = watched
        self.trials.append(trial)
        self.events.append(
            Event(
                t, "trial_result", {"kc": trial.kc, "growth": trial.growth, "period": trial.period}
            )
        )
        self._trial_max = max(self._trial_max, watched)
        if len(self.trials) == 1:
            self._first_end = t
            if self._trials_from_rest:
                self._dip = self._inverse_dip(end)
        self._update_budget()
        if self._positive_feedback():
            self._abort("the loop never oscillated" + self._wrong_way())
            return
        if trial.growth < 0:
            self._lo = trial
            if self._side == -1 and self._hi is not None:
                self._hi = Trial(
                    self._hi.kc,
                    self._hi.growth / 2,
                    self._hi.period,
                    self._hi.swings,
                    self._hi.cut_short,
                )
            self._side = -1
        else:
            self._hi = trial
            if self._side == 1 and self._lo is not None and math.isfinite(self._lo.growth):
                self._lo = Trial(
                    self._lo.kc,
                    self._lo.growth / 2,
                    self._lo.period,
                    self._lo.swings,
                    self._lo.cut_short,
                )
            self._side = 1
        if self._converged():
            return
        if len(self.trials) >= self.config.max_trials:
            self._abort(f"no bracket within {len(self.trials)} trials")
            return
        self.kc = self._next_gain()
        self._begin_settle(t)

    def _positive_feedback(self) -> bool:
        """The trials went the other way from their bumps (``_wrong_way``) and none
        oscillated: the loop's feedback is positive, and more trials only bracket the gain at
        which it runs away without a period (a wrong-sign process took 9 trials, 3,961 s of
        sim time, to say so; now 3 trials, 263 s)."""
        return (
            self.config.stop_wrong_way
            and all(t.period is None for t in self.trials)
            and bool(self._wrong_way())
        )

    def _wrong_way(self) -> str:
        """Why no trial oscillated, when the trials say it: the PV went clearly the other way
        from its setpoint bump in two trials of three or more, two at least (the loop's
        feedback positive: a process whose gain has the other sign than the loop's action;
        a trial that starts on what the one before left can go either way). An inverse
        response starts the wrong way but ends with its bump. Empty otherwise."""
        against = self._went.count(-1)
        if against < 2 or 3 * against < 2 * len(self._went):
            return ""
        return ": the trials' PV went the other way from their setpoint bumps — " + action_question(
            self.direction
        )

    def _begin_settle(self, t: float) -> None:
        """Calm the loop at a gain known to decay (or below the present one) before the next
        trial."""
        self._calm_kc = self._calming_gain()
        self.phase = "settle"
        self._settle_start, self._settle_t0 = len(self._y) - 1, t
        self._calm_cuts = 0
        self._sat_run = 0

    def _calming_gain(self) -> float:
        """``calm_gain`` × the highest gain seen to decay (else one step below this one)."""
        return self.config.calm_gain * (self._lo.kc if self._lo else self.kc / self.config.factor)

    def _next_gain(self) -> float:
        lo, hi, f = self._lo, self._hi, self.config.factor
        if hi is None:  # a trial with no response seen is far below: step up further
            return lo.kc * (f**3 if self._silent else f)
        if lo is None:  # a trial that ran away at once is far above: back off further
            return hi.kc / (f if math.isfinite(hi.growth) else f**3)
        width = hi.kc - lo.kc
        if math.isfinite(lo.growth) and math.isfinite(hi.growth) and hi.growth > lo.growth:
            k = lo.kc + width * (-lo.growth) / (hi.growth - lo.growth)
        else:
            k = math.sqrt(lo.kc * hi.kc)
        m = self.config.bracket_margin
        return min(max(k, lo.kc + m * width), hi.kc - m * width)

    def _converged(self) -> bool:
        lo, hi = self._lo, self._hi
        if lo is None or hi is None or (hi.kc - lo.kc) / lo.kc > self.config.tolerance:
            return False
        finite = math.isfinite(lo.growth) and math.isfinite(hi.growth) and hi.growth > lo.growth
        w = -lo.growth / (hi.growth - lo.growth) if finite else 0.5
        ku = lo.kc + w * (hi.kc - lo.kc)
        periods = [p for p in (lo.period, hi.period) if p]
        if len(periods) == 2:
            pu = lo.period + w * (hi.period - lo.period)
        elif periods:
            pu = periods[0]
        else:
            self._abort(self._no_period_at(lo, hi))
            return True
        ku, pu = float(ku), float(pu)  # plain floats for JSON (the fits give numpy scalars)
        self._found = (ku, pu)
        self.phase = "concluding"
        self.events.append(Event(self._t[-1], "done", {"ku": ku, "pu": pu}))
        return True

    def _no_period_at(self, lo: Trial, hi: Trial) -> str:
        """Why a bracket closed without a period: no trial oscillated, or those that did were
        not at its ends (said so: a delay-dominated loop, e^{−132s}/(4.4s + 1) in noise,
        oscillated at 1.07–1.69 K_u in a mode of P_u/3, and the bracket closed near K_u on
        trials that showed none; "the loop never oscillated" was untrue)."""
        seen = [tr for tr in self.trials if tr.period]
        if not seen:
            return "the loop never oscillated" + self._wrong_way()
        gains = sorted(tr.kc for tr in seen)
        periods = sorted(tr.period for tr in seen if tr.period)
        return (
            f"no period to report: the bracket closed at Kc {lo.kc:.4g}–{hi.kc:.4g} on trials "
            f"that showed no oscillation, while {len(seen)} trial(s) at Kc {gains[0]:.4g}–"
            f"{gains[-1]:.4g} oscillated (period {periods[0]:.4g}–{periods[-1]:.4g} s), too far "
            "from it to read P_u by; a loop that oscillates in more than one mode (a long dead "
            "time) or a noisy one is read better by a relay test"
        )

    def _conclude(self) -> None:
        """The findings from the converged bracket: the plant's ultimate point and a process
        model fitted on the whole record (a quarter of a second: computed once the loop holds
        the ``closing`` gain)."""
        ku, pu = self._found
        lo, hi = self._lo, self._hi
        assert lo is not None and hi is not None
        # two estimates of the hold's effect: the trials' poles (exact on a clean loop, but
        # a slope from a handful of growth rates: on a noisy fast loop it is judged too
        # uncertain, ``max_slope_error``, and left out) and the process model fitted on the
        # whole record (robust, but its slopes are those of its class: the effect on hx1 and
        # hx2 comes out half as large again and half as large). The trials' stands when its
        # error was judged small, or the model agrees with it; else the model's; else none.
        ku_t, pu_t, judged = self._plant_crossover(ku, pu)
        trials = (float(ku_t), float(pu_t))
        from_trials = trials != (ku, pu)
        model = self._process_model(*trials)
        held = None if model is None else through_model(ku, pu, model.transfer, self.sample_time)
        # two trials leave no residual to judge their slope by: the model's must bear it out
        if from_trials and (judged or held is None or agree(trials, held, (ku, pu))):
            (ku_plant, pu_plant), how = trials, "trials"
        elif held is not None:
            (ku_plant, pu_plant), how = held, "model"
        else:
            (ku_plant, pu_plant), how = (ku, pu), "none"
        made = trials if from_trials else None
        spread = uncertainty(how, made, held, (ku, pu))
        floor = unmeasured(how, (ku, pu), (ku_plant, pu_plant), self.sample_time)
        if floor is not None:  # not measured: at least as unsure as the hold's whole lag
            spread = floor if spread is None else tuple(map(max, spread, floor))
        apart = contradicts(made, held, (ku, pu))  # the other estimate, named in a warning
        gap = mode_gap(self.trials, ku, self.config.near_ku)
        other = (held if how == "trials" else made) if apart else None
        self.result = RampResult(
            float(ku_plant),
            float(pu_plant),
            lo.kc,
            hi.kc,
            len(self.trials),
            self._noise,
            self._r,
            ku,
            pu,
            model,
            self.config.bump,
            self.bump,
            how,
            spread,
            other,
            self.sample_time,
            gap,
            self._dip,
        )
        self.phase = "done"

    def _process_model(self, ku: float, pu: float) -> ProcessFit | None:
        """A process model for the rules and the robustness figures: models through the
        measured ultimate point, each refined on the whole record (output error: the loop's
        outputs in, the PV out, from the rest of the quiet period), the best by BIC."""
        u = np.asarray(self._u, dtype=float)
        y = np.asarray(self._y, dtype=float)
        # the record from the rest before the first trial (after any back-off at rest)
        first = max(0, self._quiet_end - self._quiet_n) if self._backoffs else 0
        u, y = u[first:], y[first:]
        rest = self._quiet_end - first
        if u.size < 20 or not np.all(np.isfinite(u)) or rest < 3:
            return None
        u0 = float(np.mean(u[:rest]))
        y0 = float(np.mean(y[:rest]))
        du = u - u0 if self.direction > 0 else u0 - u  # a direct-acting loop's, turned over:
        # the model is of the process as the controller acts on it (−G), as K_u is
        more = self.config.more_starts  # and the integrators fit the output's offset
        starts = [(s, more and s.kind == "ipdt") for s in through_ultimate_point(ku, pu)]
        if more:
            starts += second_order_starts(ku, pu)
        # the fits with an offset (a parameter more, the slowest) handed out first, so that
        # the workers end together; judged in the starts' order
        order = sorted(range(len(starts)), key=lambda i: not starts[i][1])
        refines = [
            (refine_on_record, (starts[i][0], self.sample_time, du, y - y0, starts[i][1]))
            for i in order
        ]
        done = dict(zip(order, self.parts(refines), strict=True))
        fits = [f for i in range(len(starts)) if (f := done[i]) is not None]
        best = choose_on_record(fits, y.size)
        if best is None:
            return None
        return dataclasses.replace(best, noise_rms=self._noise / (float(np.std(y)) or 1.0))

    def _plant_crossover(self, ku: float, pu: float) -> tuple[float, float, bool]:
        """The plant's own ultimate point from the sampled loop's.

        The P-only loop runs through the zero-order hold, about e^{−sT/2}: it reaches −180°
        where the plant alone is at −180° + ωT/2, so its K_u sits below the plant's (by 2 %
        on a lag-dominated plant at 400 samples per period). Each oscillating trial's
        closed-loop pole s = g + jω satisfies L(s) = −1/Kc for the loop L = G·ZOH; together
        they give dL/ds, hence the phase and log-magnitude slopes of L at the crossover, and
        the frequency where arg L + ωT/2 = −π. Unchanged if the trials lack what it needs, or
        if three or more give a slope too uncertain; the flag: three or more judged it."""
        low, high = self.config.near_ku
        near = [
            tr
            for tr in self.trials
            if tr.period and math.isfinite(tr.growth) and low * ku <= tr.kc <= high * ku
        ]
        if len(near) < 2:
            return ku, pu, False
        # L(s) = −1/Kc at each trial's pole s = g + jω; a straight line in s through them
        # (least squares over every oscillating trial near K_u) gives dL/ds at the crossover
        s_pts = np.array([complex(tr.growth, 2 * math.pi / tr.period) for tr in near])
        l_pts = np.array([-1.0 / tr.kc for tr in near])
        design = np.column_stack((np.ones_like(s_pts), s_pts - s_pts.mean()))
        (_, slope), *_ = np.linalg.lstsq(design, l_pts, rcond=None)
        if not np.isfinite(slope) or np.ptp(s_pts.imag) + np.ptp(s_pts.real) == 0:
            return ku, pu, False
        judged = len(near) > 2  # residuals to judge the slope by
        if judged and slope_error(s_pts, l_pts) > self.config.max_slope_error:
            return ku, pu, False  # the growth rates' noise swamps the slope (``_conclude``)
        q = slope * (-ku)  # (dL/ds)/L at the crossover, L = −1/K_u
        w_loop = 2 * math.pi / pu
        half = 0.5 * self.sample_time
        if q.real + half >= 0:  # the phase does not fall with frequency: no correction
            return ku, pu, False
        dw = -w_loop * half / (q.real + half)
        if abs(dw) > 0.2 * w_loop:
            return ku, pu, False
        return ku * math.exp(q.imag * dw), 2 * math.pi / (w_loop + dw), judged

    def _watch_settle(self, t: float) -> None:
        """Let the loop calm at a gain known to decay, then start the next trial from where
        the PV has come to rest. A calming whose output sat at a limit for half of the last
        period, or that outlasts ``settle_periods`` periods (before any period is known: trial
        lengths), is at a gain that does not calm: the gain is halved, ``max_calm_cuts`` times
        at most. A calming that takes the PV past ``_calm_bound`` from the trial's rest is
        at a gain that does not calm the loop at all: the test aborts there."""
        bound = self._calm_bound()
        if bound is not None and abs(self._y[-1] - self._r) > bound:
            self._abort(self._ran_off(t, bound))
            return
        scale, window = self._settle_scale()
        stuck = (
            len(self._y) - self._settle_start >= window
            and self._sat_fraction(window) >= self.config.stuck_fraction
        )
        if stuck or t - self._settle_t0 > self.config.settle_periods * scale:
            if self._calm_cuts >= self.config.max_calm_cuts:
                # at a gain cut so far the loop's own action hardly moves the PV: what keeps
                # it moving is the process (a hidden load swinging ±0.5 % every 40 s on an
                # FOPDT aborted here at Kc 0.0097, 1/16 of its first calming gain)
                cause = (
                    ""
                    if stuck
                    else "; at a gain this small the loop hardly moves the PV, so the process "
                    "does: a drift or an upset during the test, or noise beyond the calm check's "
                    "allowance — try again when the process is steady"
                )
                self._abort(
                    f"the loop does not calm between trials, even at Kc = {self._calm_kc:.4g}"
                    + cause
                )
                return
            self._calm_cuts += 1
            self._calm_kc *= 0.5
            why = "output saturated" if stuck else "not calm in time"
            self.events.append(Event(t, "calm", {"kc": self._calm_kc, "reason": why}))
            self._settle_start, self._settle_t0, self._sat_run = len(self._y) - 1, t, 0
            return
        window = self._calm_window()
        if len(self._y) - self._settle_start < window or len(self._y) % CALM_EVERY:
            return
        # calm: the means of ten stretches of the last period agree (the noise averaged)
        y = np.asarray(self._y[-window:])
        spread, per = calm_spread(y)
        if spread < self._calm_limit(per):
            if self._handing_back:  # back where the test began: it ends here
                self._abort(self._handing_back)
                return
            self._r = float(np.mean(y))
            self._trials_from_rest = False
            self._begin_trial(t)

    def _calm_bound(self) -> float | None:
        """PV units the calming may take the PV from the trial's rest, where every trial so
        far went against its setpoint bump, none oscillated and none decayed (the loop's
        feedback looks positive, and a calming at a lower gain runs off as the trials did):
        ``calm_allowance``, or twice the trial's swing limit where that is more (a trial cut
        at its swing limit swings on past it while the calming gain takes over). None: no
        bound (not asked, or a trial that says otherwise: a loop whose gain near K_u ran
        away swings past the allowance while calming, and comes back: flow1)."""
        allowance = self.config.calm_allowance
        if allowance is None or self._lo is not None or not self._went:
            return None
        if any(w != -1 for w in self._went) or any(t.period for t in self.trials):
            return None
        return max(allowance, 2.0 * self.config.swing_limit * self._trial_bump)

    def _ran_off(self, t: float, bound: float) -> str:
        """Why the test aborts at a calming that ran off (``_watch_settle``), one line."""
        pv, r = self._y[-1], self._r
        return (
            f"calming between trials at Kc = {self._calm_kc:.4g}, the PV ran to {pv:.4g} at "
            f"t = {t:g} s, {pv - r:+.3g} from the trial's rest {r:.4g}, past ±{bound:.3g}, "
            "as every trial went against its setpoint bump with none oscillating: the loop's "
            f"feedback looks positive — {action_question(self.direction)}"
        )

    def _settle_scale(self) -> tuple[float, int]:
        """(s, samples): a calming's time scale — the period, else the longest trial so far
        — over which its output must not sit at a limit half the time."""
        scale = self._period or max(
            self._trial_max, self._last_len, self._quiet_n * self.sample_time
        )
        return scale, max(1, round(scale / self.sample_time))

    def _calm_limit(self, per: int) -> float:
        """PV units the means of a calming's ten stretches (``per`` samples each) may spread:
        a tenth of the bump, or 6σ of the noise averaged over a stretch."""
        return max(0.1 * self._trial_bump, 6 * self._noise / math.sqrt(per))

    def _calm_stop(self) -> CalmCheck | None:
        """The calming's checks for the loop to make as it steps (``band``): the very test of
        ``_watch_settle``, on the same PVs (None: numbers a lockstep advance cannot carry, a
        PV or limit not a number or a window past ``MAX_WINDOW``; the calming is then checked
        a round trip at a time)."""
        window = self._calm_window()
        limit = self._calm_limit(window // 10)
        history = tuple(self._y[max(self._settle_start, len(self._y) - window) :])
        if window > MAX_WINDOW or not all(map(math.isfinite, (limit, *history))):
            return None
        start = self._settle_start + window
        return CalmCheck(len(self._y), start, CALM_EVERY, window, limit, history)

    def _calm_window(self) -> int:
        """Samples of the last period whose stretches must agree for the loop to be calm;
        handing back, a quarter of the calming's time scale at least: with no period known
        the window is 40 samples, and a level's PV, a dead time and a lag of 20 s from its
        setpoint put back, looked calm over them at once (aborted 4 s after, 0.008 m off)."""
        n = max(20, round((self._period or 40 * self.sample_time) / self.sample_time))
        if self._handing_back:
            n = max(n, round(0.25 * self._settle_scale()[0] / self.sample_time))
        return n

    def horizon(self, cap: int) -> int:
        """How many samples (≤ ``cap``, ≥ 1) may pass before the next one at which the test
        may decide anything — change the gain or setpoint, or end — as long as the PV and the
        output stay inside ``band()``: so a batch of that many, fed one by one, leaves the
        test exactly where feeding them one at a time would. Each count is a lower bound
        (a time limit is counted a sample short where rounding could put it either side)."""
        if not self._t or self.finished:
            return 1
        t, n = self._t[-1], cap
        n = min(n, self._before(self._deadline - t))
        length = len(self._y)
        if self.phase == "quiet":
            n = min(n, self._quiet_n - (length - self._quiet_from))
        elif self.phase == "trial":
            if self._sat_run:  # the output at a limit: a run long enough cuts the trial
                n = min(n, self._sat_samples() - self._sat_run)
            elapsed = t - self._trial_t0
            if self._period is not None:
                n = min(n, self._before((self.config.trial_periods + 0.5) * self._period - elapsed))
            else:
                n = min(n, self._before(self._trial_cap() - elapsed))
                n = min(n, self._next_check - (length - self._trial_start))
        elif self.phase == "settle":
            scale, window = self._settle_scale()
            fill = self._settle_start + window - length  # until the calming's window is full
            if self._sat_run:  # the output at a limit: stuck once the window is full and the
                # output has sat at a limit for enough of it
                n = min(n, max(fill, self._until_stuck(window)))
            elif fill > 0:
                n = min(n, fill)
            n = min(n, self._before(self.config.settle_periods * scale - (t - self._settle_t0)))
            if self._calm_stop() is None:  # the calm check: every 8th sample, a round trip
                first = max(length + 1, self._settle_start + self._calm_window())
                n = min(n, -(-first // CALM_EVERY) * CALM_EVERY - length)
        return max(1, min(cap, n))

    def _until_stuck(self, window: int) -> int:
        """Samples up to the first at which the output could have sat at a limit for
        ``stuck_fraction`` of the last ``window`` (``_watch_settle``), each sample adding one
        at most to the count, a sample short (the fraction's rounding); 1 while the record is
        shorter than the window. A calming sat at a limit took a round trip a sample."""
        c = self._sat_count
        if len(c) <= window:
            return 1
        have = c[-1] - c[-window - 1]
        return max(1, math.ceil(self.config.stuck_fraction * window - have) - 1)

    def band(self) -> Band:
        """The PV limits and the transmitter's range (and in a trial the swing limit about
        the rest, ±``swing_limit``·bump), and, while the output is off its limits, its
        limits: the first sample at one of them starts the count of a saturated output."""
        lo, hi = abort_band(self.pv_limits, self.pv_range)
        if self.phase == "trial":
            swing = self.config.swing_limit * self._trial_bump
            lo, hi = max(lo, self._r - swing), min(hi, self._r + swing)
        elif self.phase == "settle" and (bound := self._calm_bound()) is not None:
            lo, hi = max(lo, self._r - bound), min(hi, self._r + bound)
        # calming: the batch ends at the first calming check that passes (the loop checks)
        calm = self._calm_stop() if self.phase == "settle" else None
        if self._sat_run:
            return Band(lo, hi, calm=calm)
        op_lo, op_hi = self.op_limits
        eps = 1e-6 * (op_hi - op_lo)  # as ``_watch_output`` tells a sample at a limit
        return Band(lo, hi, op_lo + eps, op_hi - eps, calm)

    def _before(self, seconds: float) -> int:
        """Samples up to the first at which ``seconds`` more of sim time may have passed
        (``samples_until``: that sample is the batch's last). (Counted a sample short, every
        timed trial's end took a round trip of one sample.)"""
        return samples_until(seconds, self.sample_time, self._t[-1])

    @property
    def demand_kc(self) -> float:
        """The gain to hold now: the trial's, or a calming one between trials."""
        return self._calm_kc if self.phase == "settle" else self.kc


def build(settings: Settings, setup: Setup) -> RampTest:
    """The ramp a request and a loop's set-up ask for; ValueError naming the setting that
    cannot work. With the loop's ``time_scale`` (s), a trial before any period is known is
    watched 30 time scales (and 200 samples at least)."""
    if setup.kc_start is None or setup.bump is None or setup.sp_start is None:
        raise ValueError("kc_start, bump, sp_start: required for a ramp test")
    ts, scale = setup.sample_time, setup.time_scale
    first = (
        {"first_trial_time": min(RampConfig.first_trial_time, max(30 * scale, 200 * ts))}
        if scale
        else {}
    )
    budget = {"max_time": settings.max_time} if settings.max_time else {}
    cfg = RampConfig(
        kc_start=setup.kc_start,
        bump=setup.bump,
        tolerance=min(settings.tolerance, 0.02) / 2,
        stop_wrong_way=bool(setup.ramp_wrong_way),
        seen_fits=bool(setup.ramp_seen_fits),
        hand_back=bool(setup.ramp_hand_back),
        settled_by_move=bool(setup.ramp_settled),
        more_starts=bool(setup.ramp_more_starts),
        period_floor=bool(setup.ramp_period_floor),
        # the step test's share of the range, where the set-up asks (``ramp_calm_guard``)
        calm_allowance=range_allowance(setup.pv_range) if setup.ramp_calm_guard else None,
        resolution=setup.resolution_floor(),
        **first,
        **budget,
    )
    return RampTest(
        cfg,
        setup.pv_limits,
        ts,
        sp_start=setup.sp_start,
        op_limits=setup.op_limits,
        direction=setup.direction or 1.0,
        pv_range=setup.pv_range if setup.pv_clip else None,
    )
