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
harmonics from the Fourier components of those whole cycles (``fourier``);
it fails with a reason after a cycle or time budget, or when the PV leaves
its limits.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq

from services.autotuner.identify.fourier import FrequencyPoint, frequency_points
from services.autotuner.identify.model_fit import (
    ProcessFit,
    choose,
    choose_on_record,
    fit_models,
    refine_on_record,
    response_to,
)
from services.autotuner.identify.reaction_curve import at_rest, noise_level

STAGE_TWO_CYCLES = 2  # one to settle into the new cycle, one to measure
NEAR_DEG = 25.0  # a measured point this close to −180° makes the crossover "measured"
OVERSHOOT = 0.5  # stage 2 aims past −180° by half stage 1's miss…
MIN_SHIFT_DEG = 2.0  # … and moves the cycle's phase by at least this


@dataclass(frozen=True)
class RelayConfig:
    amplitude: float = 5.0  # d, % of output
    hysteresis: float | None = None  # ε, PV units; None: 3σ of the quiet period's noise
    quiet: float | None = None  # s; None: 40 samples
    cycles: int = 3  # N: how many of the last cycles must agree
    tolerance: float = 0.02  # their relative spread (max − min)/mean, period and amplitude
    max_cycles: int = 30
    max_time: float = 14400.0  # s of relay before the first full cycle (then a cycle budget)
    bias_adaptation: bool = True
    refine: bool = True  # run the second, phase-shifted and biased stage
    low_ratio: float = 1.0  # second stage: the low output is b − low_ratio·d (the bias)

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


@dataclass(frozen=True)
class RelayResult:
    ku: float
    pu: float
    amplitude: float  # a, PV units (mean over the agreeing cycles)
    relay_amplitude: float  # d, %
    hysteresis: float  # ε, PV units
    bias: float  # b at the end, %
    noise_std: float
    cycles: int  # how many cycles were run
    ku_spread: float  # (max − min)/mean over the agreeing cycles
    pu_spread: float
    rest_pv: float  # r
    frequency: tuple[FrequencyPoint, ...] = ()  # exact G(jkω), k = 1, 3, 5 (fourier module)
    ku_df: float = math.nan  # the describing-function estimate of stage 1
    pu_df: float = math.nan
    stage_one_cycles: int = 0
    second: tuple[FrequencyPoint, ...] = ()  # stage 2's exact G(jkω₂), k = 1, 2, 3
    # the process gain of the model fitted on a record with stage 2's bias (None: no bias);
    # the bias's step in the mean output is what pins it (the DC ratio of two short stages is
    # not yet settled)
    static_gain: float | None = None
    model: ProcessFit | None = None  # fitted to both stages' points (model_fit)
    # how K_u and P_u were found: "bracketed" (the stages' points lie on both sides of
    # −180°), "near" (a point within NEAR_DEG of it: a short interpolation), or "not reached"
    # (both far from it: ku/pu are then the model's own ultimate point, NaN without a model)
    crossing: str = "bracketed"
    phase_reached_deg: float = -180.0  # the measured phase closest to −180°
    cycle_period: float = math.nan  # s, stage 1's mean period


@dataclass
class RelayTest:
    config: RelayConfig
    op_start: float
    op_limits: tuple[float, float]
    pv_limits: tuple[float, float]
    sample_time: float
    direction: float = 1.0  # +1 reverse-acting loop (PV rises with the output), −1 direct

    phase: str = "quiet"  # quiet → relay → done | aborted
    reason: str = ""
    result: RelayResult | None = None
    cycles: list[Cycle] = field(default_factory=list)
    events: list[tuple[float, str, dict]] = field(default_factory=list)
    t: list[float] = field(default_factory=list)
    pv: list[float] = field(default_factory=list)
    op: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        d, lo, hi = self.config.amplitude, *self.op_limits
        if not (lo <= self.op_start - d and self.op_start + d <= hi):
            raise ValueError(
                f"relay amplitude {d:g} %: the output would swing {self.op_start - d:g}–"
                f"{self.op_start + d:g} %, beyond the loop's limits [{lo:g}, {hi:g}] %"
            )
        quiet = self.config.quiet if self.config.quiet is not None else 40 * self.sample_time
        self._quiet_samples = max(10, math.ceil(quiet / self.sample_time))
        self.bias = self.op_start
        self._state = 1.0  # +1: pushing the PV up
        self._r = math.nan
        self._eps = 0.0
        self._noise = 0.0
        self._relay_start = math.nan
        self._crossings: list[float] = []  # upward crossings of r (interpolated)
        self._armed = False  # an upward crossing counts only after the relay went up, below r
        self._level = 0.0  # h: switch down above r + h, up below r − h (stage 1: h = ε)
        self._switch_armed = True  # the next switch may happen (stage 2's lead needs a lockout)
        self._margin = 0.0  # how far past the opposite level the PV must go to arm a switch
        self._cross_margin = 0.0  # how far below r the PV must go to arm a cycle's crossing
        self._agreement = self.config.tolerance  # asked of the cycles (wider with noise)
        self._low = 1.0  # the low output is b − low·d (stage 2: the bias)
        self._stage1: _StageOne | None = None

    @property
    def finished(self) -> bool:
        return self.phase in ("done", "aborted")

    def _out(self) -> float:
        swing = 1.0 if self._state > 0 else -self._low
        return self.bias + self.direction * swing * self.config.amplitude

    def _abort(self, reason: str) -> float:
        self.phase, self.reason = "aborted", reason
        self.events.append((self.t[-1] if self.t else 0.0, "aborted", {"reason": reason}))
        return self.op_start

    def feed(self, t: float, pv: float) -> float:
        """Take the PV sampled at ``t``; return the output to hold from ``t`` on."""
        if self.finished:
            return self.op_start
        self.t.append(t)
        self.pv.append(pv)
        lo, hi = self.pv_limits
        if not lo <= pv <= hi:
            return self._abort(f"PV {pv:.4g} left its limits [{lo:g}, {hi:g}] at t = {t:g} s")
        out = self._quiet(t) if self.phase == "quiet" else self._relay(t, pv)
        self.op.append(out)
        return out

    def _quiet(self, t: float) -> float:
        """Wait until the last quiet period shows the PV at rest (no trend beyond its noise);
        give up after 20 quiet periods."""
        n = self._quiet_samples
        if len(self.pv) < n:
            return self.op_start
        base = np.asarray(self.pv[-n:])
        if not at_rest(base):
            if len(self.pv) >= 20 * n:
                return self._abort("the PV is not at rest before the test (it keeps drifting)")
            return self.op_start
        self._r = float(base.mean())
        self._noise = noise_level(base)
        h = self.config.hysteresis
        self._eps = 3.0 * self._noise if h is None else h
        self._level = self._eps
        self._margin = self._eps
        self._cross_margin = self._eps
        self._relay_start = t
        self.phase = "relay"
        self.events.append(
            (
                t,
                "relay_start",
                {"rest_pv": self._r, "noise_std": self._noise, "hysteresis": self._eps},
            )
        )
        self.events.append((t, "switch", {"op": self._out()}))
        return self._out()

    def _relay(self, t: float, pv: float) -> float:
        r, h = self._r, self._level
        self._arm(pv)
        if self._switch_armed and self._state > 0 and pv > r + h:
            self._state, self._switch_armed = -1.0, False
            self.events.append((t, "switch", {"op": self._out()}))
        elif self._switch_armed and self._state < 0 and pv < r - h:
            self._state, self._switch_armed = 1.0, False
            self.events.append((t, "switch", {"op": self._out()}))
        self._arm(pv)
        if self._state > 0 and pv < r - self._cross_margin:
            # the next upward crossing of r closes a cycle: the relay is high and the PV has
            # been below r by the margin (stage 2 may switch high while still above r, so
            # there the PV must first be half-way down to its trough)
            self._armed = True
        # upward crossing of r, interpolated between the last two samples
        if self._armed and len(self.pv) >= 2 and self.pv[-2] < r <= pv:
            t0, y0 = self.t[-2], self.pv[-2]
            tc = t0 + (r - y0) / (pv - y0) * (t - t0)
            self._armed = False
            self._crossings.append(tc)
            s1 = self._stage1
            if s1 is not None and tc - self._crossings[-2] < 0.6 * s1.pu:
                self._crossings.pop()  # noise, not a cycle: stage 2 runs near stage 1's period
                self.events.append((t, "spurious_crossing", {"t": tc}))
            elif len(self._crossings) >= 2:
                self._close_cycle(self._crossings[-2], tc)
                if self.finished:
                    return self.op_start
        s1 = self._stage1
        if s1 is not None and t - s1.t_end > 2.0 * STAGE_TWO_CYCLES * s1.pu:
            # stage 2 never settled into its cycle: keep what stage 1 measured
            self.events.append((t, "stage", {"stage": 2, "abandoned": True}))
            self._finish(stage_two=False)
            return self.op_start if self.finished else self._out()
        budget = self.config.max_time
        if len(self.cycles) >= 3:  # the cycle grows from nothing at start-up (and noise can
            # close a short first cycle): budget on the longest once there are a few
            budget = (self.config.max_cycles + 2) * max(c.period for c in self.cycles)
        if t - self._relay_start > budget:
            return self._abort(
                f"no limit cycle that repeats within {self.config.tolerance:.0%} after "
                f"{len(self.cycles)} cycles and {t - self._relay_start:g} s"
            )
        return self._out()

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
        t, y, u = np.asarray(self.t), np.asarray(self.pv), np.asarray([*self.op, self._out()])
        sel = (t >= t0) & (t <= t1)
        ys = y[sel]
        if self._noise > 0 and ys.size >= 9:
            w = max(3, ys.size // 20) | 1
            ys = np.convolve(ys, np.ones(w) / w, mode="valid")
        amplitude = 0.5 * float(ys.max() - ys.min())
        high = u[sel] > self.bias
        cycle = Cycle(t0, t1 - t0, amplitude, float(high.mean()) if high.size else 0.5, self.bias)
        self.cycles.append(cycle)
        self.events.append(
            (
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
        steady = (
            len(self.cycles) >= 3
            and previous is not None
            and 0.8 <= amplitude / previous.amplitude <= 1.25
            and 0.8 <= cycle.period / previous.period <= 1.25  # noise can split a cycle
        )
        if self.config.bias_adaptation and steady and self._stage1 is None:
            skew = 2.0 * cycle.high_fraction - 1.0
            if abs(skew) > 2.5 * self.sample_time / cycle.period:
                d, (lo, hi) = self.config.amplitude, self.op_limits
                step = min(max(d * skew, -0.5 * d), 0.5 * d)  # a noisy cycle moves it less
                self.bias = min(max(self.bias + step, lo + d), hi - d)
                self.events.append((t1, "bias", {"bias": self.bias}))
        if self._stage1 is not None:
            if len(self.cycles) - self._stage1.cycles >= STAGE_TWO_CYCLES:
                self._finish()
            return
        n = self.config.cycles
        recent = self.cycles[1:][-n:]  # the first cycle is the start-up transient
        if len(recent) == n:
            pu_spread = _spread([c.period for c in recent])
            a_spread = _spread([c.amplitude for c in recent])
            # noise scatters each cycle's period and amplitude by about σ/a: the Fourier
            # points average it out, so the agreement asked for is no tighter than that
            tol = self._agreement = max(
                self.config.tolerance, 2.0 * self._noise / np.mean([c.amplitude for c in recent])
            )
            if pu_spread <= tol and a_spread <= tol:
                self._stage1 = self._summarise(recent, pu_spread)
                if self.config.refine and self._stage1.points:
                    self._start_stage_two(t1)
                else:
                    self._finish()
                return
        if len(self.cycles) >= self.config.max_cycles:
            self.phase, self.reason = (
                "aborted",
                (
                    f"the last {n} of {len(self.cycles)} cycles still differ by more than "
                    f"{self._agreement:.0%}"
                ),
            )

    def ku_of(self, amplitude: float) -> float:
        """The describing-function K_u for a PV amplitude ``amplitude``."""
        a2 = amplitude**2 - self._eps**2
        return 4.0 * self.config.amplitude / (math.pi * math.sqrt(a2)) if a2 > 0 else math.inf

    def _summarise(self, recent: list[Cycle], pu_spread: float) -> _StageOne:
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
        return _StageOne(
            ku=float(np.mean(kus)),
            pu=period,
            ku_spread=_spread(kus),
            pu_spread=pu_spread,
            amplitude=float(np.mean([c.amplitude for c in recent])),
            points=points,
            g_scatter=_g_scatter(per_cycle),
            cycles=len(self.cycles),
            t_end=t1,
            window=(recent[0].t_start, period, len(recent)),
        )

    def _start_stage_two(self, t: float) -> None:
        """Re-aim the relay at −180°: stage 1's exact phase φ₁ at ω₁ shows how far off its
        cycle ran; the hysteresis level h moves the cycle's phase by about asin(h/a), so
        stage 2 asks for φ₁ + 180° more lag (or lead, with negative h), overshooting by
        half (at least 2°) so that the two stages bracket −180°. The low output drops to
        b − low_ratio·d when asked: the step in the mean output lets the model fitted on the
        record pin the static gain."""
        s1 = self._stage1
        assert s1 is not None
        a = s1.amplitude
        miss = math.radians(s1.points[0].phase_deg + 180.0)  # > 0: stage 1 ran short of −180°
        sign = 1.0 if miss >= 0 else -1.0
        shift = miss + sign * max(OVERSHOOT * abs(miss), math.radians(MIN_SHIFT_DEG))
        now = math.asin(min(self._eps / a, 1.0)) if a > 0 else 0.0
        target = min(max(now - shift, -math.radians(60.0)), math.radians(60.0))
        self._level = a * math.sin(target)
        self._cross_margin = max(self._eps, 0.5 * a)
        if self._level < self._eps:
            # a lead (or less hysteresis than the noise needs): arm the next switch only half-way
            # from the switching level to the expected peak, so noise cannot make it chatter
            self._margin = max(self._eps, 0.5 * (a - abs(self._level)))
        self._low = self.config.low_ratio
        # at an upward crossing of r: if the relay is still high, the PV came up from its
        # trough, past either level; if it has just switched low, it must first rise past the
        # new level for going high again
        self._switch_armed = self._state > 0
        self._arm(self.pv[-1])
        self.events.append((t, "stage", {"stage": 2, "level": self._level, "low_ratio": self._low}))

    def _stage_two_harmonics(self) -> tuple[int, ...]:
        """The 2nd harmonic is excited only by a biased stage 2 (otherwise it is noise)."""
        return (1, 2, 3) if self._low < 1.0 else (1, 3)

    def _corrector(self, s1: _StageOne, window2: tuple[float, float, int] | None) -> Corrector:
        """Remove what the window's non-periodicity leaks into the Fourier points.

        Over a window that is not a steady cycle (stage 2's second period still carries the
        change of stage), Y/U ≠ G(jω). The model, simulated over the same output record from
        the same rest, leaks in nearly the same way; so G ≈ M(jω) + (Y − Ŷ)/U, which is exact
        for a perfect model and leaves only the model's error times the (small) leakage."""
        t = np.asarray(self.t)
        op = np.asarray([*self.op, self._out()][: t.size])

        def correct(model: ProcessFit) -> tuple[Points, Points]:
            try:
                y_hat = response_to(model, self.sample_time, op - self.op_start)
            except (ValueError, np.linalg.LinAlgError):
                return (), ()
            residual = np.asarray(self.pv) - y_hat

            def points(window: tuple[float, float, int], harmonics: tuple[int, ...]) -> Points:
                start, period, n = window
                try:
                    found = frequency_points(t, residual, op, start, period, n, harmonics)
                except ValueError:
                    return ()
                return tuple(
                    FrequencyPoint(p.omega, p.g + complex(model.response(p.omega))) for p in found
                )

            first = points(s1.window, (1, 3, 5))
            return first, (points(window2, self._stage_two_harmonics()) if window2 else ())

        return correct

    def _process_model(self, candidates: tuple[ProcessFit, ...]) -> ProcessFit | None:
        """The process model for rules and robustness: each model fitted to the frequency
        points, refined on the whole record from rest (which adds the slow response and the
        static gain), the best by its information criterion."""
        y = np.asarray(self.pv) - self._r
        u = np.asarray([*self.op, self._out()][: y.size]) - self.op_start
        refined = [
            f
            for start in candidates
            if (f := refine_on_record(start, self.sample_time, u, y)) is not None
        ]
        best = choose_on_record(refined, y.size)
        if best is None:
            return choose(candidates)
        return dataclasses.replace(best, noise_rms=self._noise / (float(np.std(y)) or 1.0))

    def _finish(self, stage_two: bool = True) -> None:
        s1 = self._stage1
        assert s1 is not None
        refined = None
        if stage_two and len(self.cycles) > s1.cycles:
            c = self.cycles[-1]
            op = [*self.op, self._out()]
            try:
                second = tuple(
                    frequency_points(
                        self.t, self.pv, op, c.t_start, c.period, 1, self._stage_two_harmonics()
                    )
                )
            except ValueError:
                second = ()
            if second:
                refined = _refine(s1, second, self._corrector(s1, (c.t_start, c.period, 1)))
        if refined is None and s1.points:  # stage 2 missing: the model from stage 1 alone
            refined = _refine(s1, (), self._corrector(s1, None))
        model = self._process_model(refined.candidates) if refined else None
        ku, pu = (refined.ku, refined.pu) if refined else (s1.ku, s1.pu)
        phases = [p.phase_deg for p in (*s1.points[:1], *(refined.points[:1] if refined else ()))]
        closest = min(phases, key=lambda ph: abs(ph + 180.0), default=math.nan)
        if len(phases) == 2 and (phases[0] + 180.0) * (phases[1] + 180.0) <= 0:
            crossing = "bracketed"
        elif abs(closest + 180.0) <= NEAR_DEG and math.isfinite(ku):
            crossing = "near"
        else:
            crossing = "not reached"
            up = model.ultimate_point() if model is not None else None
            ku, pu = (float(up[0]), float(up[1])) if up else (math.nan, math.nan)
        self.result = RelayResult(
            ku=ku,
            pu=pu,
            amplitude=s1.amplitude,
            relay_amplitude=self.config.amplitude,
            hysteresis=self._eps,
            bias=self.bias,
            noise_std=self._noise,
            cycles=len(self.cycles),
            ku_spread=refined.ku_uncertainty if refined else s1.ku_spread,
            pu_spread=refined.pu_uncertainty if refined else s1.pu_spread,
            rest_pv=self._r,
            frequency=s1.points,
            ku_df=s1.ku,
            pu_df=s1.pu,
            stage_one_cycles=s1.cycles,
            second=refined.points if refined else (),
            static_gain=(
                model.gain if model is not None and model.kind != "ipdt" and self._low < 1 else None
            ),
            model=model,
            crossing=crossing,
            phase_reached_deg=float(closest),
            cycle_period=s1.pu,
        )
        self.phase = "done"
        t_done = self.cycles[-1].t_start + self.cycles[-1].period
        self.events.append((t_done, "done", {"ku": ku, "pu": pu}))


@dataclass(frozen=True)
class _StageOne:
    ku: float  # describing function
    pu: float
    ku_spread: float
    pu_spread: float
    amplitude: float
    points: tuple[FrequencyPoint, ...]
    g_scatter: float  # relative cycle-to-cycle scatter of G(jω₁)
    cycles: int
    t_end: float
    window: tuple[float, float, int]  # start, period, periods of the points


@dataclass(frozen=True)
class _Refined:
    ku: float
    pu: float
    ku_uncertainty: float
    pu_uncertainty: float
    points: tuple[FrequencyPoint, ...]
    model: ProcessFit | None = None
    candidates: tuple[ProcessFit, ...] = ()  # every model fitted to the points


def _g_scatter(values: list[complex]) -> float:
    if len(values) < 2:
        return 0.0
    g = np.asarray(values)
    return float(np.max(np.abs(g / np.mean(g) - 1.0)))


Points = tuple[FrequencyPoint, ...]
Corrector = Callable[[ProcessFit], tuple[Points, Points]]


def _fits(points: list[FrequencyPoint], p1: FrequencyPoint, p2: FrequencyPoint) -> list[ProcessFit]:
    weights = [10.0 if p in (p1, p2) else 1.0 / max(1.0, p.omega / p1.omega - 2.0) for p in points]
    try:
        return fit_models([p.omega for p in points], [p.g for p in points], weights)
    except ValueError:  # fewer than two points
        return []


def _refine(
    s1: _StageOne,
    second: Points,
    correct: Corrector | None = None,
) -> _Refined:
    """K_u and P_u where the phase crosses −180°, from the two stages' exact points.

    A low-order model is fitted to all the points (``model_fit``); its small misfit at the two
    fundamentals is interpolated linearly in log ω between them, so the model only supplies the
    curvature between two exact points a few degrees apart. Without a model, phase and
    log-magnitude are interpolated linearly. The uncertainty is the scatter of the measured
    point (cycle to cycle, over √cycles) plus the difference between the two interpolations
    of the same leakage-corrected points.
    """
    p1, p2 = s1.points[0], (second[0] if second else s1.points[0])
    fits = _fits([*s1.points, *second], p1, p2)
    model = choose(fits)
    for _ in range(2 if correct is not None else 0):
        if model is None:
            break
        first, later = correct(model)  # the transients' leakage taken out, using the model
        if not first or (second and not later):
            break
        p1, p2 = first[0], (later[0] if second else first[0])
        fits = _fits([*first, *later], p1, p2) or fits
        model = choose(fits) or model
    linear = _linear_crossing(p1, p2) if second else (1.0 / p1.magnitude, 2.0 * math.pi / p1.omega)
    crossing = _model_crossing(model, p1, p2) if model is not None else None
    if crossing is not None and not _plausible(crossing, p1, p2):
        crossing = None
    if not _plausible(linear, p1, p2):
        linear = (1.0 / p1.magnitude, 2.0 * math.pi / p1.omega)
    ku, pu = crossing or linear
    scatter = s1.g_scatter / math.sqrt(max(1, s1.window[2]))  # of the mean over the cycles
    return _Refined(
        ku=ku,
        pu=pu,
        ku_uncertainty=scatter + abs(ku / linear[0] - 1.0),
        pu_uncertainty=0.5 * scatter * abs(math.log(p2.omega / p1.omega)) / math.pi
        + abs(pu / linear[1] - 1.0),
        points=second,
        model=model,
        candidates=tuple(fits),
    )


def _plausible(estimate: tuple[float, float], p1: FrequencyPoint, p2: FrequencyPoint) -> bool:
    """The crossover lies near the two measured points (the cycles ran within tens of degrees
    of −180°); an estimate far outside comes from a fit gone astray, not from the plant."""
    ku, pu = estimate
    if not (math.isfinite(ku) and math.isfinite(pu) and ku > 0 and pu > 0):
        return False
    w = 2.0 * math.pi / pu
    lo, hi = min(p1.omega, p2.omega), max(p1.omega, p2.omega)
    kus = (1.0 / p1.magnitude, 1.0 / p2.magnitude)
    return lo / 1.3 <= w <= hi * 1.3 and min(kus) / 1.5 <= ku <= max(kus) * 1.5


def _linear_crossing(p1: FrequencyPoint, p2: FrequencyPoint) -> tuple[float, float]:
    """Phase and log-magnitude linear in log ω through the two points, at −180°."""
    x1, x2 = math.log(p1.omega), math.log(p2.omega)
    f1, f2 = p1.phase_deg, p2.phase_deg
    m1, m2 = math.log(p1.magnitude), math.log(p2.magnitude)
    frac = (-180.0 - f1) / (f2 - f1) if abs(f2 - f1) > 1e-9 else 0.0
    xu, mu = x1 + frac * (x2 - x1), m1 + frac * (m2 - m1)
    return math.exp(-mu), 2.0 * math.pi / math.exp(xu)


def _model_crossing(
    model: ProcessFit, p1: FrequencyPoint, p2: FrequencyPoint
) -> tuple[float, float] | None:
    """The model's crossover, corrected by its misfit at the two points (linear in log ω)."""
    x1, x2 = math.log(p1.omega), math.log(p2.omega)
    span = x2 - x1 if abs(x2 - x1) > 1e-9 else math.inf  # one point: a constant misfit

    def misfit(p: FrequencyPoint) -> complex:
        r = complex(np.log(p.g / model.response(p.omega)))
        return complex(r.real, math.remainder(r.imag, 2.0 * math.pi))

    r1, r2 = misfit(p1), misfit(p2)

    def r_at(x: float) -> complex:
        return r1 + (x - x1) / span * (r2 - r1)

    def excess(x: float) -> float:
        return model.phase(math.exp(x)) + r_at(x).imag + math.pi

    lo, hi = min(x1, x2) - 0.5, max(x1, x2) + 0.5
    if not excess(lo) > 0 > excess(hi):
        return None
    xu = brentq(excess, lo, hi, xtol=1e-12)
    gain = float(abs(model.response(math.exp(xu)))) * math.exp(r_at(xu).real)
    return 1.0 / gain, 2.0 * math.pi / math.exp(xu)


def _spread(values: list[float]) -> float:
    m = float(np.mean(values))
    return float((max(values) - min(values)) / abs(m)) if m else math.inf
