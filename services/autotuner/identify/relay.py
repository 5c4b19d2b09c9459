"""Relay feedback test (Åström & Hägglund 1984) as a state machine fed one sample at a time.

In manual at the present output u₀: a quiet period measures the PV's rest value r and noise
σ; the hysteresis ε is 3σ unless given. Then the output is a relay of amplitude d about a
bias b (initially u₀): b + d while the PV is below r − ε, b − d once it is above r + ε (signs
swapped for a direct-acting loop). The loop settles into a limit cycle. Each cycle runs
between successive upward crossings of r, found by linear interpolation between samples (so
the period is not quantised to the sample time, and noise near r does not split a cycle: a
crossing counts only after the relay has switched). Per cycle: the period, the amplitude a
(half the peak-to-peak of the PV, lightly smoothed when noisy) and the time the output spent
high. Bias adaptation moves b to the cycle's mean output when the two half-periods differ,
keeping the oscillation symmetric under a load change.

The test ends when the last N cycles agree within a tolerance (period and amplitude), giving
the describing-function estimate K_u = 4d/(π·√(a² − ε²)) and P_u, the mean period, with
their spread, and the exact G(jω) at the oscillation frequency and its 3rd and 5th
harmonics from the Fourier components of those whole cycles (``fourier``). Stage 2 (phase
``stage2``) re-aims the cycle past −180° so that the two stages' points bracket it. It aborts
(one path, ``_abort``: the reason and an ``aborted`` event) after a cycle or time budget, or
when the PV leaves its limits.

This module is the state machine; K_u and P_u from the stages' points are
``relay_estimate``'s, the process model on the record ``relay_model``'s, the result and its
JSON ``relay_result``'s. Every threshold is a field of ``RelayConfig`` (or of its
``EstimateConfig``), with its reason.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
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
    allowance_band,
    allowance_of,
    beyond_allowance,
    clipped,
)
from services.autotuner.identify.fourier import FrequencyPoint, frequency_points
from services.autotuner.identify.model_fit import ProcessFit
from services.autotuner.identify.relay_estimate import (
    Corrector,
    EstimateConfig,
    Points,
    StageOne,
    estimate,
    g_scatter,
    order_contradiction,
    refine,
    spread,
    stage_one_spreads,
)
from services.autotuner.identify.relay_model import RelayRecord, corrector, process_model
from services.autotuner.identify.relay_result import RelayResult
from shared.control.beyond import beyond
from shared.control.rest_window import RESOLUTION
from shared.control.signals import Sample, at_rest, noise_level

# the share of the room from rest to the PV limits a relay's swing is suggested to keep to,
# where one left them (``RelayTest._smaller_relay``)
SMALLER_ROOM = 0.5


@dataclass(frozen=True)
class RelayConfig:
    amplitude: float = 5.0  # d, % of output
    hysteresis: float | None = None  # ε, PV units; None: 3σ of the quiet period's noise
    quiet: float | None = None  # s; None: ``quiet_samples`` samples
    cycles: int = 3  # N: how many of the last cycles must agree
    tolerance: float = 0.02  # their relative spread (max − min)/mean, period and amplitude
    max_cycles: int = 30
    max_time: float = 14400.0  # s of relay before the first full cycle (then a cycle budget)
    bias_adaptation: bool = True
    refine: bool = True  # run the second, phase-shifted and biased stage
    low_ratio: float = 1.0  # second stage: the low output is b − low_ratio·d (the bias)
    # --- thresholds and factors ---
    # the quiet period without ``quiet``: enough samples for a trend and a noise level
    quiet_samples: int = 40
    # never fewer samples in the quiet period: a regression on fewer says nothing
    min_quiet_samples: int = 10
    # quiet periods to wait for the PV to come to rest before giving up
    quiet_periods: int = 20
    # ε = this many σ of the noise: a switch on noise alone is then a 3σ event
    hysteresis_sigmas: float = 3.0
    # a noisy cycle's PV is smoothed (over 1/``smooth_divisor`` of it, 3 samples at least)
    # before its peak-to-peak is read, once it has this many samples
    smooth_min_samples: int = 9
    smooth_divisor: int = 20
    # ... but a noise-free cycle's (σ within ``resolution`` and a rounding's 1e-9 of it) over
    # 3 samples only: the sampling's jitter in its peaks, which a coarsely sampled cycle
    # needs averaged ((s+1)⁻³ at 20 samples a period read K_u +8.6 % raw, +2.3 % so), and
    # not a twentieth of a finely sampled one, whose triangular peak that clipped: the
    # describing-function K_u read 5 % high (−14.4 % for the classic relay's −18.6 % at L/T
    # = 0.05: helper audit), and a run that falls back on it takes it. False: a run recorded
    # before, a twentieth wherever σ > 0
    smooth_floor: bool = True  # (a run's set-up: ``Setup.relay_smooth_floor``)
    # a cycle within these ratios of the one before (amplitude and period) is steady (noise
    # can split a cycle): only then may the bias move
    steady_ratios: tuple[float, float] = (0.8, 1.25)
    # the bias moves when the high part's skew exceeds this many samples of the period
    # (quantisation alone skews it by about one)
    bias_skew_samples: float = 2.5
    # a bias step is at most this fraction of d: a noisy cycle moves it less
    bias_step: float = 0.5
    # noise scatters each cycle's period and amplitude by about σ/a: the agreement asked
    # of the cycles is no tighter than this many σ/a (the Fourier points average it out)
    noise_agreement: float = 2.0
    # cycles after the first full ones before the time budget becomes a cycle budget (the
    # cycle grows from nothing at start-up, and noise can close a short first cycle)
    budget_after_cycles: int = 3
    # the cycle budget: ``max_cycles`` plus this many of the longest cycle
    budget_spare_cycles: int = 2
    # stage 2: one cycle to settle into the new cycle, one to measure
    stage_two_cycles: int = 2
    # stage 2 gets this many times its cycles' worth of stage 1's period to close them
    stage_two_patience: float = 2.0
    # stage 2 runs near stage 1's period: a crossing sooner than this fraction of it is noise
    spurious_fraction: float = 0.6
    # stage 2 aims past −180° by this fraction of stage 1's miss…
    overshoot: float = 0.5
    # … and moves the cycle's phase by at least this many degrees
    min_shift_deg: float = 2.0
    # the hysteresis level's phase is kept within ± this (asin of h/a near its flat end
    # gives no control of the phase)
    max_level_deg: float = 60.0
    # stage 2: a cycle's crossing is armed once the PV is this fraction of the way down to
    # its trough (stage 2 may switch high while still above r)
    cross_fraction: float = 0.5
    # stage 2 with a lead: the next switch is armed this fraction of the way from the level
    # to the expected peak, so that noise cannot make it chatter
    lead_fraction: float = 0.5
    # stage 2: no switch for this many of stage 1's periods (over the low output's share,
    # with a bias) means the lead shrank the cycle short of its lockout: the lockout is set
    # again from the peak the PV reached, once (None: never; stage 2 is abandoned instead)
    stuck_periods: float | None = 1.0
    # stage 2: a switch still locked out is armed once the PV is back past the level the
    # relay last switched at by the hysteresis ε (the first time by ``stuck_periods``'s
    # setting again, if set): a PV that turns short of the lockout's margin never arms it,
    # and the relay held its output while the PV ran on for a stage-1 period or more (hx1
    # realtime ×20: 2.1 °C off rest; hx1 with --relay-bias 0.5 in lockstep: 7 × stage 1's
    # swing). False: a run recorded before, whose lockout lasted until it was overdue
    arm_at_turn: bool = True
    # stage 2 set again and ended on two agreeing cycles: its points kept as measured where
    # the leakage correction would move them by more than the cycles' agreement
    steady_second: bool = True
    # ``chatter_cycles`` stage-1 cycles in a row (not the first) whose amplitude is below
    # ``chatter_fraction`` of the hysteresis are the relay switching on the noise (many
    # samples to a period give a 3σ excursion every half-cycle, before the process has
    # answered; the smoothed PV barely moves): ε is widened by ``chatter_factor`` and stage 1
    # counted again, at most this many times, then the test aborts (None: such cycles
    # counted as any other). A process's own cycle is never that far inside ε (an integrating
    # one ramps between the levels: a ≈ ε); noise splitting one makes a single small one
    chatter_widenings: int | None = 3
    chatter_cycles: int = 2
    chatter_fraction: float = 0.5
    chatter_factor: float = 2.0
    # stage 1 not yet switched, the PV at rest (over the last half of the relay so far, its
    # stretches' means agreeing) beyond twice the hysteresis against the relay's push: a
    # process whose gain has the other sign than the loop's action says; the test aborts,
    # saying so, rather than hold the output to its time budget (an inverse response turns
    # back, though on a noisy PV its turn may read at rest for a check: ``rest_twice``)
    wrong_way: bool = True
    # ``wrong_way`` only on a PV read at rest at every check from some time T after the relay
    # began to 2T at least: an inverse response's turn, on a noisy PV, reads at rest for a
    # check or two before it comes back ((1 − s)/(s + 1)³ at 1 % noise: three seeds of four
    # aborted "against the push — is the process one for a direct-acting PID?"). False: at
    # the first check that reads it (a run recorded before)
    rest_twice: bool = True
    # stage 1's relay held at one output for ``held_windows`` quiet periods (and longer: see
    # ``RelayTest._held_from``) since its last switch, the PV at rest (as ``wrong_way``
    # reads rest) short of the level that would switch it: it never will (a
    # load beyond the relay's amplitude, or the loop's action the other way); the test
    # aborts, saying so, rather than hold the loop off its rest to its time budget (a −8 %
    # load against ±5 % held e^{−2s}/((5s+1)(s+1)) 3 % below its rest for 14,400 s: helper
    # review). None: not checked
    held_windows: int | None = 10
    # stage 1's counted cycles whose hysteresis ε is over ``grow_ratio`` of their amplitude
    # ride on the hysteresis, not on the process: asin(ε/a) of their lag is the hysteresis's,
    # and an integrating process's own part of the swing (its run past ε, about k·d·θ) is
    # within the noise (lvl2 at d = 5 %: a = 1.1ε, its model's dead time read 1.5 s against
    # 2 s, the gains rejected at 46 % overshoot). d then grows toward ε/a = ``grow_target``
    # (a ∝ d), by ``grow_factor`` at most, within the output's room about the bias, and the
    # largest cycle grown with it within half the room (less 4σ) to the PV limits or the
    # transmitter's range; stage 1 counts again, ``grow_times`` at most; by less than
    # ``grow_least`` it does not (the cycles it costs buy too little). None: never, as for a
    # d the engineer gave (--amplitude) and a run recorded before
    grow_times: int | None = 2
    grow_ratio: float = 0.5
    grow_target: float = 0.25
    grow_factor: float = 4.0
    grow_least: float = 1.5
    # the whole-record fit of an integrating model also fits the held output's offset from
    # its balance (``model_fit.refine_on_record``); False: a run recorded before
    fit_offset: bool = True
    # PV units the transmitter does not resolve (``Setup.resolution_floor``; 0: none, a run
    # recorded before or no range known): counted cycles within it are no response, and the
    # test aborts (a valve that does not move read as a K_u of 2.6e8), unless d may grow (a
    # cycle rides on it as on a hysteresis); a drift within it over the quiet period is rest
    # (a noise-free PV's creep after a test)
    resolution: float = 0.0
    # stage 1's cycles repeating a pattern of 2 … this many cycles (each as the one that many
    # before it, to ``pattern_match`` relative) are steady, where they differ by more than
    # the tolerance: a noise-free loop whose switches are locked to the sample grid (a square
    # -root valve ran 7.565, 7.760, 7.776 s to 7 digits for 30 cycles, and was aborted); the
    # whole patterns are counted. None: not looked for (a run recorded before)
    pattern_cycles: int | None = 4
    pattern_match: float = 1e-3
    # a cycle's upward crossing of r counts once per switch up, and not sooner after that
    # switch than this fraction of the time the last counted one came after its own: after a
    # switch the PV goes on away from r for the dead time and must climb back from its
    # trough, so a crossing that much sooner is the noise's (a quarter: a coarsely sampled
    # loop's crossing moves by a sample either way). Sampled 1,700 times a period, the PV
    # lingers near r: its noise crossed r again after a counted crossing, and just after a
    # switch up, half a period early, and of 30 cycles none agreed. None: a run recorded
    # before (a crossing re-armed whenever the PV dipped below r)
    early_crossing: float | None = 0.25
    # chatter is judged on the counted cycles' mean amplitude against the hysteresis the
    # noise needs (``hysteresis_sigmas``·σ) where the given one is smaller (``_chattering``).
    # False: a run recorded before (judged against ε, every cycle inside it)
    noise_chatter: bool = True
    # … as long as the pattern's cycles differ by no more than this (period and amplitude):
    # a period-2 cycle whose amplitudes alternate by 30 % is not one cycle to average (review)
    pattern_spread: float = 0.1
    # the K_u/P_u estimator's thresholds (relay_estimate)
    estimate: EstimateConfig = field(default_factory=EstimateConfig)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amplitude) and self.amplitude > 0):
            raise ValueError(f"amplitude {self.amplitude}: must be > 0 % of output")
        if self.hysteresis is not None and not (
            math.isfinite(self.hysteresis) and self.hysteresis >= 0
        ):
            raise ValueError(f"hysteresis {self.hysteresis}: must be ≥ 0 PV units")
        if self.cycles < 2 or self.max_cycles < self.cycles + 1:
            raise ValueError(f"cycles {self.cycles}: need 2 ≤ cycles < max_cycles")
        if not 0 < self.tolerance < 1:
            raise ValueError(f"tolerance {self.tolerance}: must be between 0 and 1")
        if not 0.2 <= self.low_ratio <= 1.0:
            raise ValueError(f"low_ratio {self.low_ratio}: must be between 0.2 and 1")


@dataclass(frozen=True)
class Cycle:
    t_start: float
    period: float
    amplitude: float
    high_fraction: float  # of the period with the output high
    bias: float
    d: float = math.nan  # %: the relay's amplitude through it (it may grow between cycles)


@dataclass
class RelayTest:
    config: RelayConfig
    op_start: float
    op_limits: tuple[float, float]
    pv_limits: tuple[float, float]
    sample_time: float
    direction: float = 1.0  # +1 reverse-acting loop (PV rises with the output), −1 direct
    # the realtime clock: a switch takes effect at the next sample (or later), so the record
    # takes each sample's own output, not the relay's decision at it (``Setup``)
    outputs_from_samples: bool = False
    # the transmitter's range: a PV at either end is clipped, and aborts (None: not checked)
    pv_range: tuple[float, float] | None = None
    # PV units the PV may move from the rest the quiet period measured (``allowance_of``;
    # None: its limits alone)
    allowance: float | None = None

    # quiet → relay → stage2 → concluding → done | aborted; "concluding": finished, the output
    # back at rest, the findings computed on ``identification``
    phase: str = "quiet"
    reason: str = ""
    # said after the reason where the PV left its limits: the relay that would keep to them
    # (``_smaller_relay``); not part of the reason, which a replay of a run recorded before
    # it was said must find in that run's own
    advice: str = ""
    result: RelayResult | None = None
    cycles: list[Cycle] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    t: list[float] = field(default_factory=list)
    pv: list[float] = field(default_factory=list)
    op: list[float] = field(default_factory=list)

    # how the closing fits are computed: ``compute(fn, *args)`` (None: in this thread; the
    # tuner hands them to its worker processes, ``compute_pool``)
    compute: Callable[..., Any] | None = field(default=None, repr=False, compare=False)

    needs_hold_time: ClassVar[bool] = False  # each switch holds from the sample it follows

    def __post_init__(self) -> None:
        d, lo, hi = self.config.amplitude, *self.op_limits
        if not (lo <= self.op_start - d and self.op_start + d <= hi):
            raise ValueError(
                f"relay amplitude {d:g} %: the output would swing {self.op_start - d:g}–"
                f"{self.op_start + d:g} %, beyond the loop's limits [{lo:g}, {hi:g}] %"
            )
        cfg = self.config
        quiet = cfg.quiet if cfg.quiet is not None else cfg.quiet_samples * self.sample_time
        self._quiet_samples = max(cfg.min_quiet_samples, math.ceil(quiet / self.sample_time))
        self.bias = self.op_start
        self._state = 1.0  # +1: pushing the PV up
        self._r = math.nan
        self._eps = 0.0
        self._noise = 0.0
        self._relay_start = math.nan
        self._relay_index = 0  # set with the relay's start (``_quiet``)
        self._crossings: list[float] = []  # upward crossings of r (interpolated)
        self._armed = False  # an upward crossing counts only after the relay went up, below r
        self._level = 0.0  # h: switch down above r + h, up below r − h (stage 1: h = ε)
        self._switch_armed = True  # the next switch may happen (stage 2's lead needs a lockout)
        self._margin = 0.0  # how far past the opposite level the PV must go to arm a switch
        self._cross_margin = 0.0  # how far below r the PV must go to arm a cycle's crossing
        self._crossed = False  # the crossing since the last switch up was counted
        self._up_at = math.nan  # s: the last switch up
        self._up_to_cross = math.nan  # s from a switch up to the crossing counted after it
        self._switched_at = math.nan  # s: the last switch
        self._responded_at = math.nan  # s: the PV first moved ε the first push's way
        self._extreme = math.nan  # the PV's farthest since then towards arming the next switch
        self._rearmed = False  # stage 2's lockout was set again from the cycle it got
        self._aim = 0.0  # rad: stage 2 aims its level at a·sin(_aim)
        self._chatter = 0  # times ε was widened for a relay switching on the noise
        self._d = cfg.amplitude  # %: the relay's amplitude now (``grow_times``)
        self._grown = 0  # times d grew
        self._grow_checked = False  # stage 1's counted cycles were judged for a growth
        self._held: str | None = None  # what held d where the cycle still rode on ε
        self._switches = 0  # the relay's switches since it started
        # s since the relay began at which the PV was first read at rest against its push, at
        # every check since (``_rest_held``); None: not at the last check
        self._against_since: float | None = None
        self._push = (math.nan, math.nan)  # s: the relay's first push, from its start to its switch
        self._from_cycle = 0  # stage 1's cycles (and the budget's) count from this one
        self._stage_two_from = 0  # stage 2's cycles count from this many
        self._stage_two_start = math.nan  # s: its patience runs from here
        self._agreement = cfg.tolerance  # asked of the cycles (wider with noise)
        self._low = 1.0  # the low output is b − low·d (stage 2: the bias)
        self._stage1: StageOne | None = None
        self._stage_two_kept = True  # concluding: whether stage 2's cycle is used
        self._ops_kept = 0  # concluding: the outputs recorded when it decided to end
        self._demand = Demand(op=self.op_start)

    # --- the experiment protocol ---------------------------------------------------------

    @property
    def finished(self) -> bool:
        return self.phase in ("concluding", "done", "aborted")

    @property
    def closing(self) -> Demand | None:
        """Finished: the output back at rest, before the closing fits (a second on a busy
        machine, while a realtime loop runs on)."""
        return Demand(op=self.op_start) if self.finished else None

    @property
    def demand(self) -> Demand:
        return self._demand

    def feed(self, sample: Sample) -> Demand:
        """Take the PV sampled at ``sample.t``; return the output to hold from then on."""
        self._demand = Demand(op=self._feed(sample.t, sample.pv, sample.op))
        return self._demand

    def held(self, t: float) -> None:
        """Nothing to do: a switch is timed from the sample that caused it."""

    def horizon(self, cap: int) -> int:
        """While the relay runs, as many as ``cap`` (the ``band`` ends a batch where the next
        switch or crossing may fall), short of the time budgets; in the quiet period, the
        samples that fill its first window (none of them can start the relay), then 1: any
        sample may show the PV at rest."""
        if self.phase == "quiet":
            return max(1, min(cap, self._quiet_samples - len(self.pv)))
        if self.phase not in ("relay", "stage2") or not self.t:
            return 1
        t = self.t[-1]
        deadlines = [self._relay_start + self._budget()]
        s1 = self._stage1
        if self.phase == "stage2" and s1 is not None:
            deadlines.append(self._stage_two_deadline())
            stuck = self._stuck_at()
            if stuck is not None:
                deadlines.append(stuck)
        # the first sample past a deadline must be a batch's last: stop one short of it (past
        # the stuck one, each sample may show the PV turned back: one at a time)
        room = math.floor((min(deadlines) - t) / self.sample_time) - 1
        held = self._held_from()
        if held is not None and t < held:  # the held relay's check: a batch ends before it
            deadlines.append(held)
            room = math.floor((min(deadlines) - t) / self.sample_time) - 1
        if self._watching_wrong_way() or (held is not None and t >= held):
            q = self._quiet_samples  # the checks of a PV at rest: at each quiet window's end
            room = min(room, q - len(self.pv) % q)
        return max(1, min(cap, room))

    def band(self) -> Band | None:
        """Where the PV may go without a decision, from the state now (``_relay``, ``_arm``):
        the relay switches only once armed and past its level on the side it pushes towards
        (r + h while high, r − h while low), and is armed only past the opposite level by its
        margin; a cycle closes only when the PV crosses r upwards once armed (so a batch below
        r ends at r, one above it once the PV is back below), and is armed only while the relay
        is high, the PV below r by its margin; the PV limits abort. Every bound is where such a
        step may happen, so a batch ends on it, or earlier: a batch that ends without a
        decision costs a round trip, never a late switch."""
        limits = self._abort_limits()
        if self.phase == "quiet":  # the limits alone: past them the test aborts
            return Band(*limits)
        if self.phase not in ("relay", "stage2") or not self.pv:
            return None
        r, h, pv = self._r, self._level, self.pv[-1]
        below, above = limits
        # locked out in stage 2, back past the level it switched at arms it (``_turned``)
        turn = self.config.arm_at_turn and self.phase == "stage2" and not self._switch_armed
        if self._state > 0:
            if self._switch_armed:
                above = min(above, r + h)
            else:
                below = max(below, r + h - self._margin)
                if turn:
                    above = min(above, r - h + self._eps)
            if not self._armed:
                below = max(below, r - self._cross_margin)
        elif self._switch_armed:
            below = max(below, r - h)
        else:
            above = min(above, r - h + self._margin)
            if turn:
                below = max(below, r + h - self._eps)
        if self._armed:
            if pv < r:
                above = min(above, r)
            else:
                below = max(below, r)
        return Band(below, above)

    def progress(self) -> Progress:
        n = len(self.cycles)
        if not n:
            return Progress("relay", 0)
        cyc = self.cycles[-1]
        return Progress("relay", n, cycles=n, ku=self.ku_of(cyc.amplitude, cyc.d), pu=cyc.period)

    def identification(self) -> Identification | None:
        if self.phase == "concluding":
            self._compute_findings()
        if self.result is None:
            return None
        found = self.result.identification()
        if self.direction < 0:  # worked in the loop's own sense: say what the model is of
            found.notes.append(DIRECT_NOTE)
        return found

    # --- the state machine ---------------------------------------------------------------

    def _out(self) -> float:
        """The relay's output in the loop's own sense (``_actual``: the output to hold)."""
        swing = 1.0 if self._state > 0 else -self._low
        return self.bias + swing * self._d

    def _actual(self, v: float) -> float:
        """The output to hold for ``v`` in the loop's own sense: the same for a reverse-acting
        loop, mirrored about the output at rest for a direct-acting one. The relay works, and
        records, in the loop's sense (up pushes the PV up), so that its frequency points, its
        model and its bias adaptation are those of the process as its controller acts on it
        (−G for a direct-acting loop: a positive gain, K_u and gains for the block's action)."""
        return v if self.direction > 0 else 2.0 * self.op_start - v

    def _limits(self) -> tuple[float, float]:
        """The output limits in the loop's own sense (%)."""
        lo, hi = self.op_limits
        if self.direction > 0:
            return lo, hi
        return 2.0 * self.op_start - hi, 2.0 * self.op_start - lo

    def _abort(self, reason: str) -> float:
        """Every abort: the phase, the reason and an ``aborted`` event; the output at rest."""
        self.phase, self.reason = "aborted", reason
        self.events.append(Event(self.t[-1] if self.t else 0.0, "aborted", {"reason": reason}))
        return self.op_start

    def _feed(self, t: float, pv: float, held: float) -> float:
        """Take the PV at ``t``; ``held``: the output the sample says is held from ``t``.
        The record's output at ``t`` is the relay's decision there (lockstep: it holds from
        that very sample), or, with ``outputs_from_samples``, the sample's own: on the
        realtime clock a switch holds from the next sample, and a record of the decisions
        would put every switch a sample early (K_u 5–6 % low, P_u 3–4 % long on hx1 and
        flow1)."""
        if self.finished:
            return self.op_start
        self.t.append(t)
        self.pv.append(pv)
        lo, hi = self.pv_limits
        if not lo <= pv <= hi:
            self.advice = self._smaller_relay(lo, hi)
            return self._abort(
                f"PV {beyond(pv, lo, hi)} left its limits [{lo:g}, {hi:g}] at t = {t:g} s"
            )
        smaller = "--amplitude"
        if self._grown:  # not the engineer's d: the relay's own growth swung it there
            smaller = f"--amplitude than the {self._d:.3g} % the relay grew to"
        if why := clipped(pv, self.pv_range, t, smaller):
            return self._abort(why)
        a_lo, a_hi = allowance_band((-math.inf, math.inf), self._r, self.allowance)
        if not a_lo <= pv <= a_hi:
            against = self._against(pv) if not self._switched() else ""
            why = beyond_allowance(pv, self._r, self.allowance or 0.0, t)
            if against:
                return self._abort(f"{why}: {against}")
            # the relay's amplitude that keeps its cycle within it, as at the PV limits; or
            # limits of the engineer's own (--pv-limits), which replace the allowance
            self.advice = self._smaller_relay(a_lo, a_hi) + (
                "; or --pv-limits of your own, which replace the allowance"
            )
            return self._abort(why)
        out = self._quiet(t) if self.phase == "quiet" else self._relay(t, pv)
        # in the loop's sense (``_actual`` is its own inverse)
        self.op.append(self._actual(held) if self.outputs_from_samples else out)
        return self._actual(out)

    def _smaller_relay(self, lo: float, hi: float) -> str:
        """The relay's amplitude that would keep its cycle within half the room from rest to
        the PV limits (``SMALLER_ROOM``), said where the PV left them: a relay's cycle scales
        with its d (a = 4d·|G(jω_u)|/π). From the cycles measured, where there are some (each
        cycle's amplitude per % of its d, and the swing that crossed, the largest); before a
        whole cycle, the swing that crossed was still growing, so the d it gives is a bound,
        said as one (e^{−3s}/((10s+1)(2s+1)) at d 5 %: 0.81, then 1.31 on the way to a cycle
        of 1.36; limits ±0.3 were crossed on the first swing, at 0.3, where d 2.5 still swings
        1.36·2.5/5 = 0.68). Why: the abort said where the PV went, not what test would fit
        (helper trial). "" before the relay ran; where the room is under the cycle the noise
        needs, that instead."""
        if self.phase not in ("relay", "stage2") or math.isnan(self._r):
            return ""
        ys = self.pv[self._relay_index :]
        swing = max((abs(y - self._r) for y in ys), default=0.0)
        room = min(hi - self._r, self._r - lo)
        if not (swing > 0 and room > 0 and math.isfinite(room) and self._d > 0):
            return ""
        least = 1.0 / self.config.grow_ratio * max(self._eps, self.config.resolution)
        if SMALLER_ROOM * room < least:
            return (
                f"; the limits leave {room:.3g} of room from rest ({self._r:.4g}), too little "
                f"for a cycle clear of the noise's hysteresis ({self._eps:.3g}): wider "
                "--pv-limits, or a step test"
            )
        per_d = [c.amplitude / c.d for c in self.cycles if c.d > 0 and c.amplitude > 0]
        if per_d:  # a cycle measured: what it becomes at another d
            unit = max(*per_d, swing / self._d)
            d = SMALLER_ROOM * room / unit
            return (
                f"; its cycle, {unit * self._d:.3g} from rest ({self._r:.4g}) with the relay at "
                f"±{self._d:.3g} %, scales with the relay's amplitude: --amplitude {d:.2g} would "
                "keep it within about half the room to the limits"
            )
        d = self._d * SMALLER_ROOM * room / swing
        return (
            f"; it crossed them on its first swings, {swing:.3g} from rest ({self._r:.4g}) with "
            f"the relay at ±{self._d:.3g} % and still growing: a relay's cycle scales with its "
            f"amplitude, so --amplitude {d:.2g} at most, less if its cycle is larger"
        )

    def _quiet(self, t: float) -> float:
        """Wait until the last quiet period shows the PV at rest (no trend beyond its noise);
        give up after ``quiet_periods`` quiet periods."""
        cfg, n = self.config, self._quiet_samples
        if len(self.pv) < n:
            return self.op_start
        base = np.asarray(self.pv[-n:])
        if not at_rest(base, allowance=cfg.resolution):
            if len(self.pv) >= cfg.quiet_periods * n:
                return self._abort("the PV is not at rest before the test (it keeps drifting)")
            return self.op_start
        self._r = float(base.mean())
        self._noise = noise_level(base)
        h = cfg.hysteresis
        self._eps = cfg.hysteresis_sigmas * self._noise if h is None else h
        self._level = self._eps
        self._margin = self._eps
        self._cross_margin = self._eps
        self._relay_start = t
        self._relay_index = len(self.pv) - 1  # the relay's first sample in ``pv``
        self._push = (t, math.nan)
        self.phase = "relay"
        self.events.append(
            Event(
                t,
                "relay_start",
                {"rest_pv": self._r, "noise_std": self._noise, "hysteresis": self._eps},
            )
        )
        self.events.append(Event(t, "switch", {"op": self._actual(self._out())}))
        return self._out()

    def _relay(self, t: float, pv: float) -> float:
        if math.isnan(self._responded_at) and not self._switches:
            # the PV's mean over a quiet window, ε the push's way (a 3σ spike of the noise
            # alone is not an answer: it read a dead time of 100 s as a few samples), or 6σ
            # of such a mean where that is less: a hysteresis asked beyond what the push can
            # move the PV (--hysteresis 8 on 1/(s + 1)⁴ at d 5 %) was never answered, the held
            # relay never checked, and the output held 5 % off for 14,400 s (helper trial)
            recent = self.pv[-self._quiet_samples :]
            seen = 6.0 * self._noise / math.sqrt(len(recent))
            if (sum(recent) / len(recent) - self._r) * self._state > min(self._eps, seen):
                self._responded_at = t
        self._arm(pv)
        stuck = self._stuck_at()
        if self._turned(pv):  # short of arming the switch: set again once, or arm it
            if stuck is not None:
                self._rearm(t)
            else:
                self._switch_armed = True
                self.events.append(Event(t, "lockout", {"turned": self._extreme}))
        elif stuck is not None and t >= stuck and abs(pv - self._extreme) > self._margin:
            self._rearm(t)  # overdue, and the PV turned back from short of arming the switch
        if self._watching_wrong_way() and len(self.pv) % self._quiet_samples == 0:
            why = self._at_rest_against_the_push()
            if self._rest_held(t, bool(why)):
                return self._abort(f"no limit cycle: {why}")
        held = self._held_from()
        if held is not None and t >= held and len(self.pv) % self._quiet_samples == 0:
            why = self._held_short(t)
            if why:
                return self._abort(f"no limit cycle: {why}")
        cfg, r, h = self.config, self._r, self._level
        if self._switch_armed and self._state > 0 and pv > r + h:
            self._switch(t, pv, -1.0)
        elif self._switch_armed and self._state < 0 and pv < r - h:
            self._switch(t, pv, 1.0)
        self._arm(pv)
        # the PV's trough while high, its peak while low, since the last switch
        self._extreme = (min if self._state > 0 else max)(self._extreme, pv)
        once = cfg.early_crossing is not None
        if self._state > 0 and pv < r - self._cross_margin and not (once and self._crossed):
            # the next upward crossing of r closes a cycle: the relay is high and the PV has
            # been below r by the margin (stage 2 may switch high while still above r, so
            # there the PV must first be part of the way down to its trough)
            self._armed = True
        # upward crossing of r, interpolated between the last two samples
        if self._armed and len(self.pv) >= 2 and self.pv[-2] < r <= pv:
            t0, y0 = self.t[-2], self.pv[-2]
            tc = t0 + (r - y0) / (pv - y0) * (t - t0)
            self._armed = False
            s1 = self._stage1
            if once and tc - self._up_at < cfg.early_crossing * self._up_to_cross:
                # the PV is still on its way from r after the switch: the noise's crossing
                self.events.append(Event(t, "spurious_crossing", {"t": tc}))
            elif (
                self.phase == "stage2"
                and s1 is not None
                and self._crossings
                and tc - self._crossings[-1] < cfg.spurious_fraction * s1.pu
            ):
                # noise, not a cycle: stage 2 runs near stage 1's period
                self.events.append(Event(t, "spurious_crossing", {"t": tc}))
            else:
                self._crossings.append(tc)
                self._crossed, self._up_to_cross = True, tc - self._up_at
                if len(self._crossings) >= 2:
                    self._close_cycle(self._crossings[-2], tc)
                    if self.finished:
                        return self.op_start
        if self.phase == "stage2" and t - self._stage_two_deadline() > 0:
            if self._rearmed and len(self.cycles) - self._stage_two_from >= cfg.stage_two_cycles:
                # set again, its cycle is still converging: its last cycle is its closest
                self.events.append(Event(t, "stage", {"stage": 2, "unsettled": True}))
                self._conclude()
            else:
                # stage 2 never settled into its cycle: keep what stage 1 measured
                self.events.append(Event(t, "stage", {"stage": 2, "abandoned": True}))
                self._conclude(stage_two=False)
            return self.op_start if self.finished else self._out()
        budget = self._budget()
        if t - self._relay_start > budget:
            # which budget ran out: the first cycles' (--max-time: a slow process needs more;
            # lags of hours were told only "no limit cycle") or the cycles' own
            first = len(self.cycles[self._from_cycle :]) < cfg.budget_after_cycles
            why = (
                f" (the time allowed before the first {cfg.budget_after_cycles} cycles, "
                f"--max-time {cfg.max_time:g} s, ran out: a slower process needs a longer one)"
                if first
                else ""
            )
            wrong = self._wrong_way()
            unmoved = "" if wrong else self._unmoved()
            if unmoved:  # no cycle at all: said first (a dead valve was told "a slower
                # process needs a longer one": helper trial)
                return self._abort(
                    f"the PV did not respond to the relay's push in {t - self._relay_start:g} s "
                    f"({unmoved})"
                )
            return self._abort(
                f"no limit cycle that repeats within {cfg.tolerance:.0%} after "
                f"{len(self.cycles)} cycles and {t - self._relay_start:g} s" + (wrong or why)
            )
        return self._out()

    def _wrong_way(self) -> str:
        """Why no cycle came, when the PV shows it (``_against``): a suffix for the abort
        on the time budget; empty otherwise."""
        if self._switched() or len(self.pv) < 2:
            return ""
        tail = float(np.mean(self.pv[-self._quiet_samples :]))
        return f": {self._against(tail)}" if self._against(tail) else ""

    def _unmoved(self) -> str:
        """Where the relay never switched and the PV stayed within the transmitter's
        resolution of its rest since the relay began: how far (for the abort); else empty."""
        floor = self.config.resolution
        if floor <= 0 or self._switched():
            return ""
        since = np.asarray(self.pv[-round((self.t[-1] - self._relay_start) / self.sample_time) :])
        if not since.size or float(np.max(np.abs(since - self._r))) > floor:
            return ""
        return f"it stayed within {floor:.3g} of {self._r:.6g}: a valve that does not move?"

    def _inverse_dip(self, amplitude: float) -> float | None:
        """How far the PV first went the other way in the relay's first push, from its rest
        (PV units; ``inverse_response.dip``, on the scale of the cycle's amplitude): the
        relay's cycles alone do not show it. The first push is the one step from rest the
        test makes."""
        start, end = self._push
        if not (math.isfinite(start) and math.isfinite(end)):
            return None
        t, y = np.asarray(self.t), np.asarray(self.pv)
        along = y[(t > start) & (t <= end)] - self._r  # the first push raises the PV (+1)
        return inverse_response.dip(along, self._noise, amplitude)

    def _abort_limits(self) -> tuple[float, float]:
        """Where a sample aborts the test: the PV limits, the transmitter's range, and once
        the rest is known the allowance about it."""
        return allowance_band(abort_band(self.pv_limits, self.pv_range), self._r, self.allowance)

    def _switched(self) -> bool:
        """The relay has switched since it started."""
        return self._switches > 0

    def _watching_wrong_way(self) -> bool:
        return self.config.wrong_way and self.phase == "relay" and not self._switched()

    def _at_rest_against_the_push(self) -> str:
        """``_against``, for a PV at rest over the last half of the relay so far (a quiet
        period's worth at least): the means of ten stretches of it agree within 2 % of how
        far it went (and the noise averaged in each). A straight-line trend would not do: a
        window straddling an inverse response's turn has none. Empty otherwise."""
        since = round((self.t[-1] - self._relay_start) / self.sample_time)
        y = np.asarray(self.pv[-max(self._quiet_samples, since // 2) :])
        stretches = y[-(y.size // 10) * 10 :].reshape(10, -1)
        means = stretches.mean(axis=1)
        away = abs(float(np.mean(y)) - self._r)
        limit = max(0.02 * away, 6.0 * self._noise / math.sqrt(stretches.shape[1]))
        if float(np.ptp(means)) > limit:
            return ""
        return self._against(float(np.mean(y)), rest=True)

    def _rest_held(self, t: float, at_rest: bool) -> bool:
        """Whether the PV, read ``at_rest`` against the push now, has been so at every check
        from some time T after the relay began to 2T at least (``RelayConfig.rest_twice``; off:
        at once). A real wrong way stays there; an inverse response's turn does not."""
        if not at_rest:
            self._against_since = None
            return False
        if not self.config.rest_twice:
            return True
        since = t - self._relay_start
        if self._against_since is None:
            self._against_since = since
        return since >= 2.0 * self._against_since

    def _held_from(self) -> float | None:
        """When (s) stage 1's relay, held since its last switch (or its start), is checked
        for a PV at rest short of its switching level (``held_windows``); None: not now."""
        cfg = self.config
        if cfg.held_windows is None or self.phase != "relay" or math.isnan(self._relay_start):
            return None
        if math.isnan(self._responded_at):  # no push answered yet: not a held relay's case
            return None
        since = self._switched_at if self._switches else self._relay_start
        need = cfg.held_windows * self._quiet_samples * self.sample_time
        # ten times the time the PV took to answer the first push (its dead time and some):
        # a PV flat through a half-cycle's dead time is not at rest short of the level
        need = max(need, 10.0 * (self._responded_at - self._relay_start))
        if self._switches:  # and three times its first half-cycle
            need = max(need, 3.0 * (self._push[1] - self._push[0]))
        if self.cycles:
            need = max(need, 3.0 * max(c.period for c in self.cycles))
        return since + need

    def _held_short(self, t: float) -> str:
        """The PV, over the last half of the time since the relay's last switch (or its
        start), at rest (ten stretches' means agree, as ``_at_rest_against_the_push`` reads
        rest) short of the level that would switch the relay (r + h while high, r − h while
        low): why, one line. Empty otherwise (still moving, or past the level)."""
        since = self._switched_at if self._switches else self._relay_start
        n = round((t - since) / self.sample_time)
        seg = np.asarray(self.pv[-n:]) if n > 0 else np.array([])
        q = self._quiet_samples
        if seg.size < 2 * max(q, 10):
            return ""
        y = seg[-(seg.size // 2) :]
        stretches = y[-(y.size // 10) * 10 :].reshape(10, -1)
        means = stretches.mean(axis=1)
        rest = float(np.mean(y))
        level = self._r + self._state * self._level
        short = (level - rest) * self._state
        if short <= 0:
            return ""
        limit = max(0.02 * short, 6.0 * self._noise / math.sqrt(stretches.shape[1]))
        if float(np.ptp(means)) > limit:
            return ""
        output = self._actual(self._out())
        held = (
            f"the relay held the output at {output:.4g} % for {t - since:.4g} s and the PV came "
            f"to rest at {rest:.4g}, {short:.3g} short of the level that switches it "
            f"({level:.4g}): it never will — "
        )
        moved = (rest - self._r) * self._state  # toward the level, with the push
        if moved > limit:
            # the PV followed the push, too little: the process's own answer to ±d is under
            # the level (0.02·e^{−s}/(10s + 1), σ 0.05: 0.1 for 0.32), not a load against it
            # nor the wrong action, as the line said (helper trial)
            grow = 2.0 * self._d * (level - self._r) * self._state / moved
            given = self.config.hysteresis is not None
            why_level = "the --hysteresis asked" if given else "the hysteresis against the noise"
            return held + (
                f"the push moved it {moved:.3g} toward that level and no further: the "
                f"process's answer to ±{self._d:g} % is under the level's "
                f"{abs(level - self._r):.3g} from the rest ({why_level}), or a load holds it "
                f"back: a larger --amplitude (about {grow:.2g} %)"
                + (", or a smaller --hysteresis" if given else "")
            )
        return held + (
            f"a load beyond the relay's amplitude (±{self._d:g} "
            f"%) holds the PV there (a larger --amplitude, or a test once the load has passed);"
            f" if no load moved it, {action_question(self.direction)}"
        )

    def _against(self, pv: float, rest: bool = False) -> str:
        """The PV at ``pv`` went the other way from the relay's push by more than twice the
        hysteresis: what that says of the loop's action. Empty otherwise."""
        if (pv - self._r) * self._state >= -max(2.0 * self._eps, 1e-12):
            return ""
        moved = "fell" if pv < self._r else "rose"
        output = "raised" if self._state * self.direction > 0 else "lowered"
        return (
            f"the PV {moved} from {self._r:.4g} to {pv:.4g}{' and came to rest' if rest else ''}"
            f" with the output {output}, against the push — {action_question(self.direction)}"
        )

    def _switch(self, t: float, pv: float, state: float) -> None:
        self._switches += 1
        if self._switches == 1:
            self._push = (self._push[0], t)
            if math.isnan(self._responded_at):  # the switch is the answer, its mean later
                self._responded_at = t
        self._state, self._switch_armed = state, False
        if state > 0:
            self._up_at, self._crossed = t, False
        self._switched_at, self._extreme = t, pv
        self.events.append(Event(t, "switch", {"op": self._actual(self._out())}))

    def _stage_two_deadline(self) -> float:
        """Stage 2 is abandoned past this (s): its cycles' worth of stage 1's period, times
        ``stage_two_patience``, from its start (or from its lockout set again)."""
        cfg, s1 = self.config, self._stage1
        assert s1 is not None
        return self._stage_two_start + cfg.stage_two_patience * cfg.stage_two_cycles * s1.pu

    def _turned(self, pv: float) -> bool:
        """Stage 2's next switch still locked out (``arm_at_turn``), the PV at ``pv`` is back
        past the level the relay last switched at (r + h going low, r − h going high) by
        the hysteresis ε: it turned short of the lockout's margin, and holding the output on
        would drive it on. A fixed level, so that a batch (``band``) ends on it."""
        if not self.config.arm_at_turn or self.phase != "stage2" or self._switch_armed:
            return False
        if math.isnan(self._switched_at):
            return False
        return (pv - self._switched_level()) * self._state > self._eps

    def _switched_level(self) -> float:
        """The level the relay last switched at: r + h when it went low, r − h going high."""
        return self._r - self._state * self._level

    def _stuck_at(self) -> float | None:
        """When (s) stage 2's relay, still locked out of its next switch, counts as stuck: a
        lead shrinks the cycle (a higher frequency, a smaller gain), and one set from stage
        1's amplitude can then lock out a PV that turns before its margin. Once only."""
        s1 = self._stage1
        if self.phase != "stage2" or self._rearmed or self._switch_armed or s1 is None:
            return None
        if math.isnan(self._switched_at) or self.config.stuck_periods is None:
            return None
        share = max(1.0, 1.0 / self._low)  # a biased low output makes that half slower
        return self._switched_at + self.config.stuck_periods * s1.pu * share

    def _rearm(self, t: float) -> None:
        """Stage 2 got stuck (``_stuck_at``): aim again at the same phase with the amplitude
        the PV reached since the last switch (the level, the lockout and the crossing's
        margin), and arm the switch. Its cycles and its patience count from here; it ends on
        two that agree, or, out of patience, on its last (``_relay``)."""
        cfg = self.config
        reached = abs(self._extreme - self._r) if math.isfinite(self._extreme) else 0.0
        a = max(reached, self._eps)
        self._level = a * math.sin(self._aim)
        self._margin = max(self._eps, cfg.lead_fraction * (a - abs(self._level)))
        self._cross_margin = max(self._eps, cfg.cross_fraction * a)
        self._switch_armed, self._rearmed = True, True
        # the cycle under way is cut short by the forced switch: it does not count either
        self._stage_two_from, self._stage_two_start = len(self.cycles) + 1, t
        self.events.append(
            Event(t, "stage", {"stage": 2, "rearmed": True, "level": self._level, "amplitude": a})
        )

    def _moved(self, point: FrequencyPoint) -> bool:
        """Stage 2's point lies at least ``min_shift_deg`` from stage 1's: two points, not
        one measured twice (whose difference, their noise, would be read as a slope)."""
        assert self._stage1 is not None
        first = self._stage1.points[0]
        return abs(point.phase_deg - first.phase_deg) >= self.config.min_shift_deg

    def _settled(self) -> bool:
        """The last two cycles agree (period and amplitude) as stage 1's had to: after a
        forced switch (``_rearm``) stage 2's cycle takes more than one cycle to settle."""
        last, before = self.cycles[-1], self.cycles[-2]
        return spread([last.period, before.period]) <= self._agreement and (
            spread([last.amplitude, before.amplitude]) <= self._agreement
        )

    def _budget(self) -> float:
        """The relay's time budget, s from its start (or from its last widening of ε):
        ``max_time``, then, once there are a few cycles, the longest of them bounds the rest."""
        cfg = self.config
        counted = self.cycles[self._from_cycle :]
        if len(counted) >= cfg.budget_after_cycles:
            return (cfg.max_cycles + cfg.budget_spare_cycles) * max(c.period for c in counted)
        return cfg.max_time

    def _chattering(self) -> bool:
        """The last ``chatter_cycles`` cycles (not the first since stage 1's start or its
        last widening: a start-up transient) all lie below ``chatter_fraction`` of ε: the
        relay switches on the noise. One such cycle alone is noise splitting a cycle."""
        cfg = self.config
        if cfg.chatter_widenings is None:
            return False
        counted = self._chatter_cycles()
        # against the hysteresis the noise needs (``hysteresis_sigmas``·σ) where one given is
        # smaller: under a hysteresis of σ or less the noise's "cycles" are as tall as it is,
        # never far inside it, and a test that counted them ended done with K_u 10 to 14,000
        # times the process's (e^{−2s}/(3s + 1) at 1 ms, σ 0.05, --hysteresis 0.05 or 0)
        if len(counted) < cfg.chatter_cycles:
            return False
        if not cfg.noise_chatter:
            return all(c.amplitude < cfg.chatter_fraction * self._eps for c in counted)
        level = max(self._eps, cfg.hysteresis_sigmas * self._noise)
        return self._chatter_amplitude() < cfg.chatter_fraction * level

    def _chatter_cycles(self) -> list[Cycle]:
        """The last ``chatter_cycles`` counted stage-1 cycles (not the first since stage 1's
        start or its last widening)."""
        return self.cycles[self._from_cycle + 1 :][-self.config.chatter_cycles :]

    def _chatter_amplitude(self) -> float:
        """The mean amplitude of ``_chatter_cycles``."""
        counted = self._chatter_cycles()
        return sum(c.amplitude for c in counted) / len(counted)

    def _chattered(self, t: float, amplitude: float) -> None:
        """Stage-1 cycles of (mean) ``amplitude`` far inside the hysteresis ε, or the 3σ the
        noise needs where ε is smaller (``_chattering``): the relay switched on
        the noise, not on the process's answer (its "cycles" agree only within an agreement the
        noise has widened past meaning, and K_u, P_u and any model read from them are the
        noise's). ε is widened and stage 1 counted again from here, ``chatter_widenings``
        times at most; a hysteresis given by the user is not widened: the test aborts."""
        cfg = self.config
        assert cfg.chatter_widenings is not None
        if cfg.hysteresis is not None or self._chatter >= cfg.chatter_widenings:
            given = (
                "as given (--hysteresis)"
                if cfg.hysteresis is not None
                else f"after {self._chatter} widenings"
            )
            needs = cfg.hysteresis_sigmas * self._noise
            if cfg.noise_chatter and self._eps < needs:  # judged against what the noise needs
                within = (
                    f"within {cfg.hysteresis_sigmas:g}σ of the noise ({needs:.3g}; σ "
                    f"{self._noise:.3g}), the hysteresis {self._eps:.3g} {given} being under "
                    f"it; a --hysteresis of {needs:.3g} or more lets the process answer"
                )
            else:
                within = (
                    f"within the hysteresis {self._eps:.3g} {given} (noise σ "
                    f"{self._noise:.3g}); a larger --hysteresis lets the process answer"
                )
            cycles = (
                f"cycles of mean amplitude {amplitude:.3g}"
                if cfg.noise_chatter
                else f"a cycle of amplitude {amplitude:.3g}"
            )
            self._abort(f"the relay switches on the noise, not on a limit cycle: {cycles} {within}")
            return
        self._chatter += 1
        self._eps *= cfg.chatter_factor
        self._grow_checked, self._held = False, None  # judged again against the wider ε
        self._level = self._margin = self._cross_margin = self._eps
        self._from_cycle, self._relay_start = len(self.cycles), t
        self.events.append(
            Event(
                t,
                "hysteresis",
                {"hysteresis": self._eps, "amplitude": amplitude, "reason": "noise chatter"},
            )
        )

    def _arm(self, pv: float) -> None:
        """Allow the next switch once the PV has passed the opposite level by the noise margin
        since the last one. With stage 1's hysteresis that is at once; stage 2's negative
        hysteresis (a phase lead) would otherwise switch straight back."""
        if not self._switch_armed:
            r, h, margin = self._r, self._level, self._margin
            if self._state > 0:
                self._switch_armed = pv < r + h - margin
            else:
                self._switch_armed = pv > r - h + margin

    def _close_cycle(self, t0: float, t1: float) -> None:
        cfg = self.config
        t, y, u = np.asarray(self.t), np.asarray(self.pv), np.asarray([*self.op, self._out()])
        sel = (t >= t0) & (t <= t1)
        ys = y[sel]
        if self._noise > 0 and ys.size >= cfg.smooth_min_samples:
            w = max(3, ys.size // cfg.smooth_divisor) | 1
            if cfg.smooth_floor and self._noise <= max(cfg.resolution, 0.5e-9 * np.ptp(ys)):
                w = 3
            ys = np.convolve(ys, np.ones(w) / w, mode="valid")
        amplitude = 0.5 * float(ys.max() - ys.min())
        high = u[sel] > self.bias
        high_fraction = float(high.mean()) if high.size else 0.5
        cycle = Cycle(t0, t1 - t0, amplitude, high_fraction, self.bias, self._d)
        self.cycles.append(cycle)
        self.events.append(
            Event(
                t1,
                "cycle",
                {
                    "n": len(self.cycles),
                    "period": cycle.period,
                    "amplitude": amplitude,
                    "ku": self.ku_of(amplitude),
                },
            )
        )
        previous = self.cycles[-2] if len(self.cycles) >= 2 else None
        lo_ratio, hi_ratio = cfg.steady_ratios
        steady = (
            len(self.cycles) >= 3
            and previous is not None
            and lo_ratio <= amplitude / previous.amplitude <= hi_ratio
            and lo_ratio <= cycle.period / previous.period <= hi_ratio
        )
        if cfg.bias_adaptation and steady and self.phase == "relay":
            skew = 2.0 * cycle.high_fraction - 1.0
            if abs(skew) > cfg.bias_skew_samples * self.sample_time / cycle.period:
                d, (lo, hi) = self._d, self._limits()
                most = cfg.bias_step * d
                step = min(max(d * skew, -most), most)
                self.bias = min(max(self.bias + step, lo + d), hi - d)
                self.events.append(Event(t1, "bias", {"bias": self._actual(self.bias)}))
        if self.phase == "relay" and self._chattering():
            noise = self.config.noise_chatter
            self._chattered(t1, self._chatter_amplitude() if noise else amplitude)
            return
        if self.phase == "relay" and self._grows(t1):
            return
        if self.phase == "stage2":
            assert self._stage1 is not None
            if len(self.cycles) - self._stage_two_from >= cfg.stage_two_cycles and (
                not self._rearmed or self._settled()
            ):
                self._conclude()
            return
        n = cfg.cycles
        # the first cycle (after a widening too) is the start-up transient
        recent = self.cycles[self._from_cycle + 1 :][-n:]
        largest = max((c.amplitude for c in recent), default=math.inf)
        if len(recent) == n and largest <= cfg.resolution:
            # counted cycles, not the start-up's first (a partial one can be any size)
            self._abort(
                f"the PV did not respond to the relay: its cycles' amplitude {largest:.3g} is "
                f"within {cfg.resolution:.3g} ({RESOLUTION:.0e} of its range; a "
                f"valve that does not move?), and would read K_u as {self.ku_of(largest):.3g}"
            )
            return
        if len(recent) == n:
            pu_spread = spread([c.period for c in recent])
            a_spread = spread([c.amplitude for c in recent])
            tol = self._agreement = max(
                cfg.tolerance,
                cfg.noise_agreement * self._noise / np.mean([c.amplitude for c in recent]),
            )
            pattern = None if pu_spread <= tol and a_spread <= tol else self._pattern()
            if pattern is not None:
                recent, pu_spread = pattern, spread([c.period for c in pattern])
                self.events.append(
                    Event(t1, "pattern", {"cycles": len(pattern), "pu_spread": pu_spread})
                )
            if (pu_spread <= tol and a_spread <= tol) or pattern is not None:
                self._stage1 = self._summarise(recent, pu_spread)
                if cfg.refine and self._stage1.points:
                    self._start_stage_two(t1)
                else:
                    self._conclude()
                return
        if len(self.cycles) - self._from_cycle >= cfg.max_cycles:
            self._abort(
                f"the last {n} of {len(self.cycles)} cycles still differ by more than "
                f"{self._agreement:.0%}"
            )

    def _pattern(self) -> list[Cycle] | None:
        """Stage 1's last counted cycles, where they repeat a pattern of m = 2 …
        ``pattern_cycles`` cycles (the last m each as the one m before, period and amplitude
        to ``pattern_match``) whose cycles differ by ``pattern_spread`` at most: as many whole
        patterns as cover ``cycles``; else None."""
        cfg = self.config
        if not cfg.pattern_cycles:
            return None
        counted = self.cycles[self._from_cycle + 1 :]
        match = cfg.pattern_match
        for m in range(2, cfg.pattern_cycles + 1):
            whole = m * math.ceil(cfg.cycles / m)
            if len(counted) < max(2 * m, whole):
                continue
            pairs = zip(counted[-m:], counted[-2 * m : -m], strict=True)
            if all(
                abs(a.period - b.period) <= match * b.period
                and abs(a.amplitude - b.amplitude) <= match * b.amplitude
                for a, b in pairs
            ):
                cycles = counted[-whole:]
                wide = max(
                    spread([c.period for c in cycles]), spread([c.amplitude for c in cycles])
                )
                return cycles if wide <= cfg.pattern_spread else None
        return None

    def _grows(self, t: float) -> bool:
        """Stage 1's last ``cycles`` counted cycles ride on the hysteresis (``grow_ratio``, on
        their mean amplitude): d grows and stage 1 counts again from here (True); False when
        they do not, or d may not grow by ``grow_least`` (``_held``: what holds it)."""
        cfg = self.config
        if cfg.grow_times is None or self._grow_checked:
            return False
        recent = self.cycles[self._from_cycle + 1 :][-cfg.cycles :]
        if len(recent) < cfg.cycles:
            return False
        self._grow_checked = True  # judged once (again after a growth or a widening)
        a = float(np.mean([c.amplitude for c in recent]))
        # a cycle within the transmitter's resolution rides on it as on a hysteresis: grown
        # too (a tiny but real gain, 0.001·6/((s+1)(s+2)(s+3)), cycled by 7e-6 of its range
        # and was aborted as "no response" where the step test read its gain: helper trial)
        eps = max(self._eps, cfg.resolution)
        ratio = eps / a if a > 0 else math.inf
        if ratio <= cfg.grow_ratio:
            return False
        if self._grown >= cfg.grow_times:
            self._held = f"its limit of {cfg.grow_times} growths"
            return False
        lo, hi = self._limits()
        pv_lo, pv_hi = self._abort_limits()  # where the test aborts
        # the largest of the cycles judged (noise can split one: a smaller mean) grown with
        # d (a ∝ d: an integrating one grows less) within half the room the noise leaves to
        # where the test aborts (its peaks, 4σ, come on top of the cycle's)
        largest = max(c.amplitude for c in recent)
        pv_room = min(pv_hi - self._r, self._r - pv_lo) - 4.0 * self._noise
        room = {  # how far each room lets d grow, by what holds it there
            "the output's room about its bias": min(self.bias - lo, hi - self.bias) / self._d,
            "the room to the PV limits (or the transmitter's range), less the noise's "
            "peaks (wider --pv-limits let it grow)": 0.5 * pv_room / largest
            if largest > 0
            else math.inf,
        }
        by = min(cfg.grow_factor, ratio / cfg.grow_target, *room.values())
        if not by >= cfg.grow_least:  # (the aim alone asks at least 2×: ratio > 0.5)
            self._held = min(room, key=lambda k: room[k])
            return False
        before, self._d = self._d, self._d * by
        self._grown += 1
        self._grow_checked = False
        self._from_cycle, self._relay_start = len(self.cycles), t
        self.events.append(
            Event(
                t,
                "amplitude",
                {
                    "relay_amplitude": self._d,
                    "from": before,
                    "amplitude": a,
                    "hysteresis": self._eps,
                    "reason": f"the cycle rides on the hysteresis (ε/a = {ratio:.2f})"
                    if eps == self._eps
                    else f"the cycle is within the transmitter's resolution ({eps:.3g}/a = "
                    f"{ratio:.2f})",
                },
            )
        )
        return True

    def ku_of(self, amplitude: float, d: float | None = None) -> float:
        """The describing-function K_u for a PV amplitude ``amplitude`` under a relay of
        amplitude ``d`` (%; None: the relay's now)."""
        a2 = amplitude**2 - self._eps**2
        d = self._d if d is None else d
        return 4.0 * d / (math.pi * math.sqrt(a2)) if a2 > 0 else math.inf

    def _summarise(self, recent: list[Cycle], pu_spread: float) -> StageOne:
        """Stage 1's describing-function estimate and its exact frequency points."""
        kus = [self.ku_of(c.amplitude) for c in recent]
        period = float(np.mean([c.period for c in recent]))
        op = [*self.op, self._out()]
        try:
            points = tuple(
                frequency_points(self.t, self.pv, op, recent[0].t_start, period, len(recent))
            )
            per_cycle = [
                p.g
                for c in recent
                for p in frequency_points(self.t, self.pv, op, c.t_start, c.period, 1, (1,))
            ]
        except ValueError:
            points, per_cycle = (), []
        t1 = recent[-1].t_start + recent[-1].period
        return StageOne(
            ku=float(np.mean(kus)),
            pu=period,
            ku_spread=spread(kus),
            pu_spread=pu_spread,
            amplitude=float(np.mean([c.amplitude for c in recent])),
            points=points,
            g_scatter=g_scatter(per_cycle),
            cycles=len(self.cycles),
            t_end=t1,
            window=(recent[0].t_start, period, len(recent)),
        )

    def _start_stage_two(self, t: float) -> None:
        """Re-aim the relay at −180°: stage 1's exact phase φ₁ at ω₁ shows how far off its
        cycle ran; the hysteresis level h moves the cycle's phase by about asin(h/a), so
        stage 2 asks for φ₁ + 180° more lag (or lead, with negative h), overshooting by
        ``overshoot`` (at least ``min_shift_deg``) so that the two stages bracket −180°. The
        low output drops to b − low_ratio·d when asked: the step in the mean output lets the
        model fitted on the record pin the static gain."""
        cfg, s1 = self.config, self._stage1
        assert s1 is not None
        a = s1.amplitude
        miss = math.radians(s1.points[0].phase_deg + 180.0)  # > 0: stage 1 ran short of −180°
        sign = 1.0 if miss >= 0 else -1.0
        shift = miss + sign * max(cfg.overshoot * abs(miss), math.radians(cfg.min_shift_deg))
        now = math.asin(min(self._eps / a, 1.0)) if a > 0 else 0.0
        bound = math.radians(cfg.max_level_deg)
        target = self._aim = min(max(now - shift, -bound), bound)
        self._level = a * math.sin(target)
        self._cross_margin = max(self._eps, cfg.cross_fraction * a)
        if self._level < self._eps:
            # a lead (or less hysteresis than the noise needs): arm the next switch only part
            # of the way from the switching level to the expected peak
            self._margin = max(self._eps, cfg.lead_fraction * (a - abs(self._level)))
        self._low = cfg.low_ratio
        # at an upward crossing of r: if the relay is still high, the PV came up from its
        # trough, past either level; if it has just switched low, it must first rise past the
        # new level for going high again
        self._switch_armed = self._state > 0
        self._arm(self.pv[-1])
        self._stage_two_from, self._stage_two_start = len(self.cycles), s1.t_end
        self.phase = "stage2"
        self.events.append(
            Event(t, "stage", {"stage": 2, "level": self._level, "low_ratio": self._low})
        )

    def _stage_two_harmonics(self) -> tuple[int, ...]:
        """The 2nd harmonic is excited only by a biased stage 2 (otherwise it is noise)."""
        return (1, 2, 3) if self._low < 1.0 else (1, 3)

    def _record(self) -> RelayRecord:
        t = np.asarray(self.t)
        return RelayRecord(
            t=t,
            pv=np.asarray(self.pv),
            op=np.asarray([*self.op, self._out()][: t.size]),
            sample_time=self.sample_time,
            op_start=self.op_start,
            rest_pv=self._r,
            noise=self._noise,
        )

    def _conclude(self, stage_two: bool = True) -> None:
        """Finished: the findings (``_finish``, with stage 2's cycle or without) are computed
        by ``identification``, once the output is back at rest (the driver's ``closing``)."""
        self.phase, self._stage_two_kept, self._ops_kept = "concluding", stage_two, len(self.op)

    def _compute_findings(self) -> None:
        """``_finish`` on the record as it was when the test decided to end (the last
        sample's output not yet recorded), through ``compute`` when given: the same result
        from a copy of this test (pure, so computed anywhere it is the same to the bit)."""
        stage_two, ops = self._stage_two_kept, self.op
        self.op = ops[: self._ops_kept]
        try:
            if self.compute is None:
                self._finish(stage_two)
                return
            done = self.compute(_finished, self, stage_two)
            self.result, self.phase, self.events = done.result, done.phase, done.events
        finally:
            self.op = ops

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["compute"] = None  # a worker's copy computes in its own thread
        return state

    def _finish(self, stage_two: bool = True) -> None:
        s1, est_cfg = self._stage1, self.config.estimate
        assert s1 is not None
        record = self._record()
        refined = None
        if stage_two and len(self.cycles) > s1.cycles:
            c = self.cycles[-1]
            op = [*self.op, self._out()]
            harmonics = self._stage_two_harmonics()
            try:
                second = tuple(
                    frequency_points(self.t, self.pv, op, c.t_start, c.period, 1, harmonics)
                )
            except ValueError:
                second = ()
            if second and self._rearmed and not self._moved(second[0]):
                second = ()  # set again, the cycle went back to stage 1's: no second point
            if second:
                correct = corrector(record, s1.window, (c.t_start, c.period, 1), harmonics)
                if self.config.steady_second and self._rearmed and self._settled():
                    correct = _steady_second(correct, second, self._agreement)
                refined = refine(s1, second, correct, est_cfg)
        if refined is None and s1.points:  # stage 2 missing: the model from stage 1 alone
            correct = corrector(record, s1.window, None, self._stage_two_harmonics())
            refined = refine(s1, (), correct, est_cfg)
        offset = self.config.fit_offset
        model = process_model(record, refined.candidates, offset) if refined else None
        est = estimate(s1, refined, model, est_cfg)
        ku_spread = refined.ku_uncertainty if refined else s1.ku_spread
        pu_spread = refined.pu_uncertainty if refined else s1.pu_spread
        order = None
        second_points = refined.points if refined else ()
        if refined and refined.points and s1.points and est.crossing != "not reached":
            order = order_contradiction(s1.points[0], refined.points[0])
            if order is not None:
                # stage 2's point is not the plant's: the estimate and the model from stage 1
                # alone, as where stage 2 is missing, as sure as its point (a crossing
                # bracketed by a point 79° off read K_u 60 % low on a noise-free FOPDT sampled
                # 7.7 times a period, and the exact model was refused against it: helper)
                correct = corrector(record, s1.window, None, self._stage_two_harmonics())
                refined = refine(s1, (), correct, est_cfg)
                model = process_model(record, refined.candidates, offset) if refined else None
                est = estimate(s1, refined, model, est_cfg)
                ku_spread = refined.ku_uncertainty if refined else s1.ku_spread
                pu_spread = refined.pu_uncertainty if refined else s1.pu_spread
                wide = stage_one_spreads(est.ku, est.pu, s1.points[0])
                ku_spread, pu_spread = max(ku_spread, wide[0]), max(pu_spread, wide[1])
        self.result = RelayResult(
            ku=est.ku,
            pu=est.pu,
            amplitude=s1.amplitude,
            relay_amplitude=self._d,
            relay_amplitude_start=self.config.amplitude if self._grown else None,
            relay_growth_held=self._held,
            hysteresis=self._eps,
            bias=self._actual(self.bias),
            noise_std=self._noise,
            cycles=len(self.cycles),
            ku_spread=ku_spread,
            pu_spread=pu_spread,
            order_contradiction=order,
            rest_pv=self._r,
            frequency=s1.points,
            ku_df=s1.ku,
            pu_df=s1.pu,
            stage_one_cycles=s1.cycles,
            stage_one_periods=s1.window[2],
            second=second_points,
            static_gain=(
                model.gain if model is not None and model.kind != "ipdt" and self._low < 1 else None
            ),
            model=model,
            crossing=est.crossing,
            phase_reached_deg=est.phase_reached_deg,
            cycle_period=s1.pu,
            ku_method=est.ku_method,
            sample_time=self.sample_time,
            inverse_dip=self._inverse_dip(s1.amplitude),
        )
        self.phase = "done"
        t_done = self.cycles[-1].t_start + self.cycles[-1].period
        # not measured (the cycle short of −180°), the figures are the model's own: named so,
        # not plotted beside measured ones as K_u (lvl1's 18,243 %/m, its result's K_u null)
        found = (
            {"ku": est.ku, "pu": est.pu}
            if self.result.measured
            else {"ku_model": est.ku, "pu_model": est.pu}
        )
        self.events.append(Event(t_done, "done", found))


def _steady_second(correct: Corrector, second: Points, agreement: float) -> Corrector:
    """``correct``, but stage 2's points kept as measured where the correction would move its
    fundamental by more than ``agreement``: set again, stage 2 ran until two cycles agreed
    within that, so its window leaks less than such a correction, which is then the error of
    a model fitted to cut-short cycles (a relay without bias leaves its static gain free)."""

    def keep(model: ProcessFit) -> tuple[Points, Points]:
        first, later = correct(model)
        if later and (moved := abs(later[0].g / second[0].g - 1.0)) > agreement:
            # kept as measured: as unsure as the correction it was not given says
            return first, (dataclasses.replace(second[0], leak=moved), *second[1:])
        return first, later

    return keep


def _finished(test: RelayTest, stage_two: bool) -> RelayTest:
    """``test`` (a copy) with its findings computed (``RelayTest._conclude``)."""
    test._finish(stage_two)
    return test


def build(settings: Settings, setup: Setup) -> RelayTest:
    """The relay test a request and a loop's set-up ask for; ValueError naming the setting
    that cannot work. With the loop's ``time_scale`` (s) and no ``max_time``, the relay
    before its first cycles is budgeted 100 time scales (and 400 samples at least)."""
    if setup.op_start is None or setup.direction is None:
        raise ValueError("op_start, direction: required for a relay test")
    ts, scale = setup.sample_time, setup.time_scale
    budget = {"max_time": settings.max_time} if settings.max_time else {}
    if scale and not settings.max_time:
        budget = {"max_time": min(RelayConfig.max_time, max(100 * scale, 400 * ts))}
    cfg = RelayConfig(
        amplitude=settings.amplitude,
        hysteresis=settings.hysteresis,
        cycles=settings.cycles,
        tolerance=settings.tolerance,
        low_ratio=1.0 - settings.relay_bias,
        stuck_periods=RelayConfig.stuck_periods if setup.stage_two_rearm else None,
        arm_at_turn=bool(setup.stage_two_turn),
        wrong_way=bool(setup.relay_wrong_way),
        rest_twice=bool(setup.relay_rest_twice),
        steady_second=bool(setup.stage_two_steady),
        chatter_widenings=RelayConfig.chatter_widenings if setup.relay_chatter else None,
        grow_times=RelayConfig.grow_times
        if setup.relay_grow and not settings.amplitude_given
        else None,
        fit_offset=bool(setup.relay_offset),
        resolution=setup.resolution_floor(),
        pattern_cycles=RelayConfig.pattern_cycles if setup.relay_pattern else None,
        noise_chatter=bool(setup.relay_noise),
        smooth_floor=bool(setup.relay_smooth_floor),
        early_crossing=RelayConfig.early_crossing if setup.relay_noise else None,
        **budget,
    )
    return RelayTest(
        cfg,
        setup.op_start,
        setup.op_limits,
        setup.pv_limits,
        ts,
        setup.direction,
        outputs_from_samples=bool(setup.outputs_from_samples),
        pv_range=setup.pv_range if setup.pv_clip else None,
        allowance=allowance_of(setup),
    )
