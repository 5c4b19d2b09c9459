"""Hägglund's oscillation detector, fed one sample at a time.

T. Hägglund, "A control-loop performance monitor", Control Engineering Practice 3(11), 1995
(and Åström & Hägglund, *Advanced PID Control*, 2006, on loop assessment). A load disturbance
is *detected* when the integrated absolute error between two successive zero crossings of the
control error exceeds

    IAE_lim = 2a/ω_u = a·T_u/π,

the IAE of one half-period of a sinusoid of amplitude a at the ultimate frequency ω_u = 2π/T_u
(a: the smallest oscillation worth flagging, 1 % of the PV's span by default). A loop is
*oscillating* when more than n_lim = 10 detections fall within the supervision time
T_sup = 50·T_u: five or more periods of an oscillation above a, out of fifty.

The error's zero crossings are read on it low-passed (first order, time constant T_u/4π: corner
at 2ω_u), which takes most of the measurement noise off and slows the noise's own crossings;
the filter is scaled to unit gain at ω_u, so that a sinusoid at the ultimate frequency keeps
its amplitude and the limit its meaning (a constant phase lag leaves the period alone). Noise
still splits a half-period near its crossings, but those slivers carry little IAE: the body
of the half-period keeps nearly all of it, as in Hägglund's rule on the raw error. The
amplitude a is raised to 4σ of the filtered noise at least (σ read from the PV's second
differences, which an oscillation or a load hardly touches), so that noise alone cannot build
a half-period's IAE. A loop without integral action keeps an offset, which its oscillation
need not cross: its error is high-passed too (first order, time constant T_u), the pair then
scaled to unit gain at ω_u.

The oscillation's period is the mean time between the ends of successive detections of the
same sign within the supervision time (those within a factor 1.5 of their median, so that a
period missed, or a setpoint step's first half, does not bias it): a whole period whatever
the halves' lengths (a level's 35 s up and 11 s down) and whether one side or both are
detected. Each end is where the filtered error first crosses zero after a half-period's body:
noise moves every end alike, not the spacing.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

AMPLITUDE_FRACTION = 0.01  # a: 1 % of the PV's span (Hägglund 1995)
DETECTION_LIMIT = 10  # n_lim: more detections than this within T_sup is an oscillation
SUPERVISION_PERIODS = 50.0  # T_sup = 50·T_u
HIGHPASS_PERIODS = 1.0  # high-pass time constant, × T_u
LOWPASS_PERIODS = 1.0 / (4.0 * math.pi)  # low-pass time constant, × T_u (corner at 2ω_u)
NOISE_FLOOR_SIGMAS = 4.0  # a is at least this many σ of the filtered noise
NOISE_SAMPLES = 200  # samples the noise estimate averages over (exponential forgetting)
GAP_SAMPLES = 2.5  # a step longer than this many sample times is a gap: start again
_MEAN_ABS_D2 = math.sqrt(6.0) * math.sqrt(2.0 / math.pi)  # E|Δ²n| / σ for white noise n


def unit_gain(period: float, offset: bool = False) -> float:
    """|H(jω_u)| of the filter at the ultimate frequency (the scale that gives it unit gain
    there): the low-pass, and with ``offset`` the high-pass too."""
    w = 2.0 * math.pi / period
    hp = w * HIGHPASS_PERIODS * period
    lp = w * LOWPASS_PERIODS * period
    return (hp / math.hypot(1.0, hp) if offset else 1.0) / math.hypot(1.0, lp)


class NoiseLevel:
    """σ of the white noise on a sampled signal, fed one value at a time: the mean |Δ²y| over
    the last NOISE_SAMPLES samples (exponential forgetting) over E|Δ²n|/σ = √6·√(2/π). A
    second difference hardly sees an oscillation (its (ωh)² is small), a load, or a ramp."""

    def __init__(self) -> None:
        self.sigma = 0.0
        self._n = 0
        self._mean = 0.0
        self._last: deque[float] = deque(maxlen=3)

    def restart(self) -> None:
        """A gap in the record: the next second difference spans no missing sample."""
        self._last.clear()

    def feed(self, y: float) -> None:
        self._last.append(y)
        if len(self._last) < 3:
            return
        d2 = abs(self._last[2] - 2.0 * self._last[1] + self._last[0])
        self._n += 1
        self._mean += (d2 - self._mean) / min(self._n, NOISE_SAMPLES)
        self.sigma = self._mean / _MEAN_ABS_D2


@dataclass(frozen=True)
class HalfPeriod:
    """The error between two successive zero crossings: [start, end] (s), its IAE on the
    filtered error (PV units·s), whether it exceeded the limit (a detection), and its sign
    (+1: the filtered error above zero, −1 below; 0: not known)."""

    start: float
    end: float
    iae: float
    detected: bool
    sign: int = 0


class OscillationDetector:
    """Feed (t, sp, pv) in auto; ``interrupt()`` when the loop leaves auto or the record has a
    gap. ``period`` T_u (s), ``amplitude`` a (PV units), ``sample_time`` (s); ``offset``: the
    loop has no integral action, so its error keeps an offset (high-passed away)."""

    def __init__(
        self,
        period: float,
        amplitude: float,
        sample_time: float,
        offset: bool = False,
        detection_limit: int = DETECTION_LIMIT,
        supervision_periods: float = SUPERVISION_PERIODS,
    ):
        if not period > 0 or not math.isfinite(period):
            raise ValueError(f"period: must be a finite number of seconds > 0, got {period}")
        if not amplitude > 0 or not math.isfinite(amplitude):
            raise ValueError(f"amplitude: must be > 0 (PV units), got {amplitude}")
        self.period = period
        self.amplitude = amplitude
        self.sample_time = sample_time
        self.offset = offset
        self.detection_limit = detection_limit
        self.supervision = supervision_periods * period
        self.gain = unit_gain(period, offset)
        self.half_periods: deque[HalfPeriod] = deque()  # the detected, ending within T_sup
        self.total_detections = 0
        self.max_count = 0  # the most detections within T_sup seen since ``clear_peak``
        self.peak_period: float | None = None  # the period measured while oscillating
        self.pv_noise = NoiseLevel()
        self.now = 0.0  # the last sample's time, s
        self.first: float | None = None  # the first sample's time, s
        self.interrupt()

    # --- state ----------------------------------------------------------------------------

    def interrupt(self) -> None:
        """Forget the filters and the half-period under way (the loop left auto, or samples
        are missing); the detections already counted stay."""
        self._t: float | None = None
        self._slow = self._y = 0.0
        self._crossed: tuple[float, float] | None = None  # the last zero crossing (t, iae)
        self._iae = 0.0  # ∫|filtered error| dt since the start, PV units·s
        self.pv_noise.restart()

    def clear_peak(self) -> None:
        """Start a new report window: the peak count starts from the present count."""
        self.max_count = self.count()
        self.peak_period = self.period_estimate() if self.oscillating() else None

    def count(self, now: float | None = None) -> int:
        """Detections within the supervision time before ``now`` (default: the last sample)."""
        now = self.now if now is None else now
        return sum(1 for h in self.half_periods if h.end > now - self.supervision)

    def open_half_period(self) -> HalfPeriod | None:
        """The half-period under way since the last zero crossing (not counted: it is counted
        when it ends), judged as if it ended now; None before a first crossing."""
        if self._t is None or self._crossed is None:
            return None
        iae = self._iae - self._crossed[1]
        return HalfPeriod(self._crossed[0], self.now, iae, iae > self.limit())

    def oscillating(self) -> bool:
        return self.count() > self.detection_limit

    def watched(self) -> float:
        """Seconds of samples behind the count, at most the supervision time: a detector that
        has watched less cannot reach n_lim on an oscillation slower than T_sup/(2·n_lim)."""
        return 0.0 if self.first is None else min(self.now - self.first, self.supervision)

    def filtered_noise(self, dt: float) -> float:
        """σ of the PV noise after the scaled filter (the low-pass decides it: a discrete
        first-order lag with α = 1 − e^{−dt/T} passes α/(2 − α) of white noise's variance)."""
        alpha = 1.0 - math.exp(-dt / (LOWPASS_PERIODS * self.period))
        return self.noise * math.sqrt(alpha / (2.0 - alpha)) / self.gain

    def limit(self, dt: float | None = None) -> float:
        """IAE_lim (PV units·s) = a·T_u/π, a raised to NOISE_FLOOR_SIGMAS σ of the filtered
        noise."""
        a = max(self.amplitude, NOISE_FLOOR_SIGMAS * self.filtered_noise(dt or self.sample_time))
        return a * self.period / math.pi

    def period_estimate(self) -> float | None:
        """The mean time between the ends of successive detections of the same sign within
        T_sup (those within a factor 1.5 of their median: a period missed, or a setpoint
        step's first half, does not count), s; None without two such intervals.

        One sign's detections a period apart are a period apart however the two halves
        differ: 2 × the mean time between any two detections read a level's 35 s up, 11 s
        down oscillation (46 s) as 61.9 s, and one detected only on its upper side (hx1 with
        Kc 14, the output at a limit) as twice its period."""
        now = self.now
        gaps: list[float] = []
        for sign in (1, -1, 0):
            ends = [
                h.end
                for h in self.half_periods
                if h.sign == sign and h.end > now - self.supervision
            ]
            gaps += [b - a for a, b in itertools.pairwise(ends)]
        if len(gaps) < 2:
            return None
        gaps.sort()
        n = len(gaps)
        med = gaps[n // 2] if n % 2 else 0.5 * (gaps[n // 2 - 1] + gaps[n // 2])
        kept = [g for g in gaps if med / 1.5 <= g <= 1.5 * med] or gaps
        return sum(kept) / len(kept)

    # --- input ----------------------------------------------------------------------------

    @property
    def noise(self) -> float:
        """σ of the PV's noise, PV units."""
        return self.pv_noise.sigma

    def feed(self, t: float, sp: float, pv: float) -> HalfPeriod | None:
        """One sample in auto; the half-period it ended (at a zero crossing), if any."""
        e = sp - pv
        if self._t is not None and not 0 < t - self._t <= GAP_SAMPLES * self.sample_time:
            self.interrupt()
        self.pv_noise.feed(pv)
        self.now = t
        if self.first is None:
            self.first = t
        if self._t is None:  # the filters start at rest on the first sample
            self._t, self._slow = t, e
            self._y = 0.0 if self.offset else e / self.gain
            return None
        dt = t - self._t
        x = e
        if self.offset:
            self._slow += (1.0 - math.exp(-dt / (HIGHPASS_PERIODS * self.period))) * (
                e - self._slow
            )
            x = e - self._slow
        a_lp = 1.0 - math.exp(-dt / (LOWPASS_PERIODS * self.period))
        y0 = self._y
        y1 = y0 + a_lp * (x / self.gain - y0)
        t0, self._t, self._y = self._t, t, y1
        if (y0 >= 0) == (y1 >= 0):
            self._iae += 0.5 * (abs(y0) + abs(y1)) * dt
            return None
        tc = t0 + y0 / (y0 - y1) * dt  # the zero crossing, interpolated
        at_tc = self._iae + 0.5 * abs(y0) * (tc - t0)
        self._iae = at_tc + 0.5 * abs(y1) * (t - tc)
        previous, self._crossed = self._crossed, (tc, at_tc)
        if previous is None:  # the first crossing: the half-period before it is not whole
            return None
        iae = at_tc - previous[1]
        half = HalfPeriod(previous[0], tc, iae, iae > self.limit(dt), 1 if y0 >= 0 else -1)
        if half.detected:
            self._detected(half)
        return half

    def _detected(self, half: HalfPeriod) -> None:
        self.half_periods.append(half)
        while self.half_periods and self.half_periods[0].end <= half.end - self.supervision:
            self.half_periods.popleft()
        self.total_detections += 1
        n = self.count(half.end)
        self.max_count = max(self.max_count, n)
        if n > self.detection_limit:
            self.peak_period = self.period_estimate()
