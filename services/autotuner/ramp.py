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
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from services.autotuner.model_fit import (
    ProcessFit,
    choose_on_record,
    refine_on_record,
    through_ultimate_point,
)
from services.autotuner.oscillation import Oscillation, fit_oscillation
from services.autotuner.reaction_curve import at_rest, noise_level


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
    max_time: float = 86400.0  # s

    def __post_init__(self) -> None:
        if not (self.kc_start > 0 and math.isfinite(self.kc_start)):
            raise ValueError(f"kc_start {self.kc_start}: must be > 0")
        if not (self.bump > 0 and math.isfinite(self.bump)):
            raise ValueError(f"bump {self.bump}: must be > 0 PV units")
        if not self.factor > 1:
            raise ValueError(f"factor {self.factor}: must be > 1")
        if not 0 < self.tolerance < 0.5:
            raise ValueError(f"tolerance {self.tolerance}: must be between 0 and 0.5")


@dataclass(frozen=True)
class Demand:
    """What the experiment wants of the loop: P-only gain and setpoint, in auto."""

    kc: float
    sp: float


@dataclass(frozen=True)
class Trial:
    kc: float
    growth: float  # 1/s; −inf when the response did not oscillate
    period: float | None
    swings: int
    cut_short: bool


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


@dataclass
class RampTest:
    config: RampConfig
    pv_limits: tuple[float, float]
    sample_time: float
    sp_start: float = math.nan  # the setpoint held during the quiet period (NaN: first PV)
    op_limits: tuple[float, float] = (0.0, 100.0)  # the loop's output limits, %

    phase: str = "quiet"  # quiet → trial ⇄ settle → done | aborted
    reason: str = ""
    result: RampResult | None = None
    trials: list[Trial] = field(default_factory=list)
    events: list[tuple[float, str, dict]] = field(default_factory=list)

    def __post_init__(self) -> None:
        q = self.config.quiet if self.config.quiet is not None else 40 * self.sample_time
        self._quiet_n = max(10, math.ceil(q / self.sample_time))
        self._t: list[float] = []
        self._y: list[float] = []
        self._u: list[float] = []  # the loop's output, held from each sample
        self._quiet_end = 0  # samples of the quiet period: the record's rest
        self._start = math.nan
        self._r = math.nan
        self._noise = 0.0
        self.kc = self.config.kc_start
        self.sp = self.sp_start
        self._trial_start = 0  # index into the record
        self._trial_t0 = 0.0
        self._lo: Trial | None = None
        self._hi: Trial | None = None
        self._side = 0  # Illinois: which end was kept last
        self._period: float | None = None
        self._calm_kc = self.config.kc_start
        self._settle_start = 0

    @property
    def finished(self) -> bool:
        return self.phase in ("done", "aborted")

    def _abort(self, reason: str) -> Demand:
        self.phase, self.reason = "aborted", reason
        self.events.append((self._t[-1], "aborted", {"reason": reason}))
        return Demand(self.kc, self.sp)

    def feed(self, t: float, pv: float, op: float = math.nan) -> Demand:
        """Take the PV sampled at ``t`` (and the output the loop holds from ``t``, for the
        process model); return the gain and setpoint to hold from ``t`` on."""
        if self.finished:
            return Demand(self.kc, self.sp)
        self._t.append(t)
        self._y.append(pv)
        self._u.append(op)
        if math.isnan(self._start):
            self._start = t
            if math.isnan(self.sp):
                self.sp = pv
        lo, hi = self.pv_limits
        if not lo <= pv <= hi:
            return self._abort(f"PV {pv:.4g} left its limits [{lo:g}, {hi:g}] at t = {t:g} s")
        if t - self._start > self.config.max_time:
            return self._abort(f"no result within {self.config.max_time:g} s")
        if self.phase == "quiet":  # wait for the PV to be at rest (20 quiet periods at most)
            n = self._quiet_n
            if len(self._y) >= n:
                base = np.asarray(self._y[-n:])
                if at_rest(base):
                    self._r, self._noise = float(base.mean()), noise_level(base)
                    self._quiet_end = len(self._y)
                    self._begin_trial(t)
                elif len(self._y) >= 20 * n:
                    return self._abort("the PV is not at rest before the test (it keeps drifting)")
        elif self.phase == "trial":
            self._watch_trial(t)
        elif self.phase == "settle":
            self._watch_settle(t)
        return Demand(self.demand_kc, self.sp)

    def _begin_trial(self, t: float) -> None:
        n = len(self.trials)
        # from the present setpoint, not from where the PV rests: under P-only control the PV
        # settles off the setpoint, and a bump from the PV's rest would kick by that offset too
        self.sp += self.config.bump * (1 if n % 2 == 0 else -1)
        self._trial_start, self._trial_t0 = len(self._y) - 1, t
        self._next_check = 16
        self.phase = "trial"
        self.events.append((t, "trial", {"n": n + 1, "kc": self.kc, "sp": self.sp}))

    def _watch_trial(self, t: float) -> None:
        n = len(self._y) - self._trial_start
        if self._swing_limit_hit():
            self._close_trial(t, cut=True)
        elif self._period is not None:
            if t - self._trial_t0 >= (self.config.trial_periods + 0.5) * self._period:
                self._close_trial(t, cut=False)
        elif t - self._trial_t0 >= self.config.first_trial_time:
            self._close_trial(t, cut=False)
        elif n >= self._next_check:  # geometric spacing keeps the checks' cost near linear
            self._next_check = int(n * 1.25) + 16
            if self._died_out(n):
                self._close_trial(t, cut=False)
                return
            osc = self._fit()
            if osc is not None and osc.swings >= 2 * self.config.trial_periods + 1:
                self._close_trial(t, cut=False)

    def _died_out(self, n: int) -> bool:
        """The trial's response has come and gone: the PV moved, and it has been flat over
        the last half of the response and over twice the dead time it took to start moving (a
        delay-dominated loop's response is a staircase whose treads last one dead time: they
        are not its end)."""
        if n < 40:
            return False
        y = np.asarray(self._y[self._trial_start :])
        # "moved" only has to tell the response from the dead time before it: at a low gain
        # the PV moves by Kc·K/(1 + Kc·K) of the bump, which can be a small fraction of it
        level = max(0.02 * self.config.bump, 6 * self._noise)
        moving = np.nonzero(np.abs(y - self._r) >= level)[0]
        if moving.size == 0:
            return False
        dead = int(moving[0])
        # flat over the last half of the response so far, and over two dead times
        window = max(20, (n - dead) // 2, 2 * dead + 2)
        if n - dead < window:
            return False
        # flat: the means of ten stretches of the tail agree (the noise averaged in each)
        tail = y[-(window // 10) * 10 :].reshape(10, -1)
        spread = float(np.ptp(tail.mean(axis=1)))
        return spread < max(0.05 * self.config.bump, 6.0 * self._noise / math.sqrt(tail.shape[1]))

    def _swing_limit_hit(self) -> bool:
        """The PV has swung further from where it rested before the trial than allowed."""
        return abs(self._y[-1] - self._r) > self.config.swing_limit * self.config.bump

    def _fit(self) -> Oscillation | None:
        t = np.asarray(self._t[self._trial_start :])
        y = np.asarray(self._y[self._trial_start :])
        return fit_oscillation(t, y, self._noise, self._period)

    def _close_trial(self, t: float, cut: bool) -> None:
        osc = self._fit()
        watched = t - self._trial_t0
        if osc is not None and osc.period > watched / 1.5:
            osc = None  # "swings" of the noise, not an oscillation seen for 1.5 periods
        if osc is None or osc.swings < (2 if cut else 3):
            # no oscillation to fit: an overdamped response, or one that ran away at once
            trial = Trial(self.kc, math.inf if cut else -math.inf, None, 0, cut)
        else:
            trial = Trial(self.kc, osc.growth, osc.period, osc.swings, cut)
            self._period = osc.period
        self.trials.append(trial)
        self.events.append(
            (t, "trial_result", {"kc": trial.kc, "growth": trial.growth, "period": trial.period})
        )
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
            self.phase, self.reason = "aborted", f"no bracket within {len(self.trials)} trials"
            return
        self.kc = self._next_gain()
        self._calm_kc = 0.7 * (self._lo.kc if self._lo else self.kc / self.config.factor)
        self.phase = "settle"
        self._settle_start = len(self._y) - 1

    def _next_gain(self) -> float:
        lo, hi, f = self._lo, self._hi, self.config.factor
        if hi is None:
            return lo.kc * f
        if lo is None:
            return hi.kc / f
        width = hi.kc - lo.kc
        if math.isfinite(lo.growth) and math.isfinite(hi.growth) and hi.growth > lo.growth:
            k = lo.kc + width * (-lo.growth) / (hi.growth - lo.growth)
        else:
            k = math.sqrt(lo.kc * hi.kc)
        return min(max(k, lo.kc + 0.05 * width), hi.kc - 0.05 * width)

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
            self.phase, self.reason = "aborted", "the loop never oscillated"
            return True
        ku, pu = float(ku), float(pu)  # plain floats for JSON (the fits give numpy scalars)
        ku_plant, pu_plant = (float(x) for x in self._plant_crossover(ku, pu))
        self.result = RampResult(
            ku_plant,
            pu_plant,
            lo.kc,
            hi.kc,
            len(self.trials),
            self._noise,
            self._r,
            ku,
            pu,
            self._process_model(ku_plant, pu_plant),
        )
        self.phase = "done"
        self.events.append((self._t[-1], "done", {"ku": ku, "pu": pu}))
        return True

    def _process_model(self, ku: float, pu: float) -> ProcessFit | None:
        """A process model for the rules and the robustness figures: models through the
        measured ultimate point, each refined on the whole record (output error: the loop's
        outputs in, the PV out, from the rest of the quiet period), the best by BIC."""
        u = np.asarray(self._u, dtype=float)
        y = np.asarray(self._y, dtype=float)
        if u.size < 20 or not np.all(np.isfinite(u)) or self._quiet_end < 3:
            return None
        u0 = float(np.mean(u[: self._quiet_end]))
        y0 = float(np.mean(y[: self._quiet_end]))
        fits = [
            f
            for start in through_ultimate_point(ku, pu)
            if (f := refine_on_record(start, self.sample_time, u - u0, y - y0)) is not None
        ]
        best = choose_on_record(fits, y.size)
        if best is None:
            return None
        return dataclasses.replace(best, noise_rms=self._noise / (float(np.std(y)) or 1.0))

    def _plant_crossover(self, ku: float, pu: float) -> tuple[float, float]:
        """The plant's own ultimate point from the sampled loop's.

        The P-only loop runs through the zero-order hold, about e^{−sT/2}: it reaches −180°
        where the plant alone is at −180° + ωT/2, so its K_u sits below the plant's (by 2 %
        on a lag-dominated plant at 400 samples per period). Each oscillating trial's
        closed-loop pole s = g + jω satisfies L(s) = −1/Kc for the loop L = G·ZOH; together
        they give dL/ds, hence the phase and log-magnitude slopes of L at the crossover, and
        the frequency where arg L + ωT/2 = −π. Unchanged if the trials lack what it needs."""
        near = [
            tr
            for tr in self.trials
            if tr.period and math.isfinite(tr.growth) and 0.7 * ku <= tr.kc <= 1.3 * ku
        ]
        if len(near) < 2:
            return ku, pu
        # L(s) = −1/Kc at each trial's pole s = g + jω; a straight line in s through them
        # (least squares over every oscillating trial near K_u: the noise in each growth
        # rate averages out) gives dL/ds at the crossover
        s_pts = np.array([complex(tr.growth, 2 * math.pi / tr.period) for tr in near])
        l_pts = np.array([-1.0 / tr.kc for tr in near])
        design = np.column_stack((np.ones_like(s_pts), s_pts - s_pts.mean()))
        (_, slope), *_ = np.linalg.lstsq(design, l_pts, rcond=None)
        if not np.isfinite(slope) or np.ptp(s_pts.imag) + np.ptp(s_pts.real) == 0:
            return ku, pu
        q = slope * (-ku)  # (dL/ds)/L at the crossover, L = −1/K_u
        w_loop = 2 * math.pi / pu
        half = 0.5 * self.sample_time
        if q.real + half >= 0:  # the phase does not fall with frequency: no correction
            return ku, pu
        dw = -w_loop * half / (q.real + half)
        if abs(dw) > 0.2 * w_loop:
            return ku, pu
        return ku * math.exp(q.imag * dw), 2 * math.pi / (w_loop + dw)

    def _watch_settle(self, t: float) -> None:
        """Let the loop calm at a gain known to decay, then start the next trial from where
        the PV has come to rest."""
        window = max(20, round((self._period or 40 * self.sample_time) / self.sample_time))
        if len(self._y) - self._settle_start < window or len(self._y) % 8:
            return
        y = np.asarray(self._y[-window:])
        # calm: the means of ten stretches of the last period agree (the noise averaged)
        stretches = y[-(y.size // 10) * 10 :].reshape(10, -1)
        spread = float(np.ptp(stretches.mean(axis=1)))
        if spread < max(0.1 * self.config.bump, 6 * self._noise / math.sqrt(stretches.shape[1])):
            self._r = float(np.mean(y))
            self._begin_trial(t)

    def horizon(self, cap: int) -> int:
        """How many samples may pass before the next decision matters (≤ ``cap``): about 2 %
        of the oscillation's period once known, fewer early in a trial."""
        if self._period is not None:
            n = int(0.02 * self._period / self.sample_time)
        else:
            n = (len(self._y) - self._trial_start) // 50 if self.phase == "trial" else 1
        return max(1, min(cap, n))

    @property
    def demand_kc(self) -> float:
        """The gain to hold now: the trial's, or a calming one between trials."""
        return self._calm_kc if self.phase == "settle" else self.kc
