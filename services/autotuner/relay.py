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

import math
from dataclasses import dataclass, field

import numpy as np

from services.autotuner.fourier import FrequencyPoint, frequency_points
from services.autotuner.reaction_curve import at_rest, noise_level


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
        self._armed = False  # an upward crossing counts only after the relay went up

    @property
    def finished(self) -> bool:
        return self.phase in ("done", "aborted")

    def _out(self) -> float:
        return self.bias + self.direction * self._state * self.config.amplitude

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
        r, eps = self._r, self._eps
        if self._state > 0 and pv > r + eps:
            self._state = -1.0
            self.events.append((t, "switch", {"op": self._out()}))
        elif self._state < 0 and pv < r - eps:
            self._state = 1.0
            self._armed = True
            self.events.append((t, "switch", {"op": self._out()}))
        # upward crossing of r, interpolated between the last two samples
        if self._armed and len(self.pv) >= 2 and self.pv[-2] < r <= pv:
            t0, y0 = self.t[-2], self.pv[-2]
            tc = t0 + (r - y0) / (pv - y0) * (t - t0)
            self._armed = False
            self._crossings.append(tc)
            if len(self._crossings) >= 2:
                self._close_cycle(self._crossings[-2], tc)
                if self.finished:
                    return self.op_start
        budget = self.config.max_time
        if self.cycles:  # the cycle grows from nothing at start-up: budget on the longest
            budget = (self.config.max_cycles + 2) * max(c.period for c in self.cycles)
        if t - self._relay_start > budget:
            return self._abort(
                f"no limit cycle that repeats within {self.config.tolerance:.0%} after "
                f"{len(self.cycles)} cycles and {t - self._relay_start:g} s"
            )
        return self._out()

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
        steady = len(self.cycles) >= 3 and 0.8 <= amplitude / self.cycles[-2].amplitude <= 1.25
        if self.config.bias_adaptation and steady:
            skew = 2.0 * cycle.high_fraction - 1.0
            if abs(skew) > 2.5 * self.sample_time / cycle.period:
                d, (lo, hi) = self.config.amplitude, self.op_limits
                self.bias = min(max(self.bias + d * skew, lo + d), hi - d)
                self.events.append((t1, "bias", {"bias": self.bias}))
        n = self.config.cycles
        recent = self.cycles[1:][-n:]  # the first cycle is the start-up transient
        if len(recent) == n:
            pu_spread = _spread([c.period for c in recent])
            a_spread = _spread([c.amplitude for c in recent])
            if pu_spread <= self.config.tolerance and a_spread <= self.config.tolerance:
                self._finish(recent, pu_spread)
                return
        if len(self.cycles) >= self.config.max_cycles:
            self.phase, self.reason = (
                "aborted",
                (
                    f"the last {n} of {len(self.cycles)} cycles still differ by more than "
                    f"{self.config.tolerance:.0%}"
                ),
            )

    def ku_of(self, amplitude: float) -> float:
        """The describing-function K_u for a PV amplitude ``amplitude``."""
        a2 = amplitude**2 - self._eps**2
        return 4.0 * self.config.amplitude / (math.pi * math.sqrt(a2)) if a2 > 0 else math.inf

    def _finish(self, recent: list[Cycle], pu_spread: float) -> None:
        kus = [self.ku_of(c.amplitude) for c in recent]
        period = float(np.mean([c.period for c in recent]))
        try:
            points = tuple(
                frequency_points(
                    self.t, self.pv, [*self.op, self._out()], recent[0].t_start, period, len(recent)
                )
            )
        except ValueError:
            points = ()
        self.result = RelayResult(
            ku=float(np.mean(kus)),
            pu=period,
            amplitude=float(np.mean([c.amplitude for c in recent])),
            relay_amplitude=self.config.amplitude,
            hysteresis=self._eps,
            bias=self.bias,
            noise_std=self._noise,
            cycles=len(self.cycles),
            ku_spread=_spread(kus),
            pu_spread=pu_spread,
            rest_pv=self._r,
            frequency=points,
        )
        self.phase = "done"
        self.events.append(
            (
                recent[-1].t_start + recent[-1].period,
                "done",
                {"ku": self.result.ku, "pu": self.result.pu},
            )
        )


def _spread(values: list[float]) -> float:
    m = float(np.mean(values))
    return float((max(values) - min(values)) / abs(m)) if m else math.inf
