"""Is the loop at rest? The drift check every experiment starts with, and the return to rest
every run ends with.

An identification assumes the PV starts from rest: a relay or step test begun while the PV
still recovers from an earlier step reads that recovery as the process's response (seen: a
relay after a step test measured K_u right but fitted K = 0.135 for a true 1.0). A quiet
period of a few dozen samples cannot see a drift whose time constant is minutes, so the check
watches a window as long as the loop's slowest known dynamics: at least 40 samples, and at
least the loop's integral time (a tuned loop's Ti is of the order of its process lag or its
ultimate period), capped so that a level loop's hour-long Ti does not stall the tuner.

At rest means: no straight-line trend beyond 3σ of the noise over the window, nor beyond
1e-5 of the PV's span, what no transmitter resolves (σ about a
parabola fitted to the window, so that the curvature of a slow recovery is not taken for
noise); no swing either (the PV averaged over a tenth of the window keeps within 4σ of
white noise, as σ of the sample-to-sample change shows it, or 3σ about the parabola, whichever
is larger: a test's dying oscillation has no trend); and the measurement not pinned at an end
of the transmitter's range (a clipped PV is flat and noise-free, and says nothing about where
the process is).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from shared.control.rest_window import MAX_WINDOW, MIN_SAMPLES, RESOLUTION, rest_window
from shared.control.signals import difference_noise, range_end

WINDOWS = 10  # windows to wait for rest before giving up

__all__ = ["MAX_WINDOW", "MIN_SAMPLES", "RESOLUTION", "RestCheck", "rest_window"]


@dataclass
class RestCheck:
    """Fed one PV sample at a time until it is ``done``: ``at_rest`` or not (``reason``)."""

    sample_time: float
    window: float  # s
    pv_range: tuple[float, float]
    windows: int = WINDOWS
    t: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    done: bool = False
    at_rest: bool = False
    reason: str = ""
    drift: float = 0.0  # PV units per s over the last window
    noise: float = 0.0
    rest_pv: float = math.nan
    # a loop in auto with integral action is at rest only on its setpoint: ``target`` (PV
    # units) within ``band``; None: anywhere (manual, or a P-only controller's offset)
    target: float | None = None
    band: float = 0.0

    def __post_init__(self) -> None:
        self._n = max(MIN_SAMPLES, math.ceil(self.window / self.sample_time))
        self._checks = 0

    @property
    def samples(self) -> int:
        """Samples in one window."""
        return self._n

    @property
    def waited(self) -> float:
        return self.t[-1] - self.t[0] if len(self.t) > 1 else 0.0

    def feed(self, t: float, pv: float) -> None:
        if self.done:
            return
        self.t.append(t)
        self.y.append(pv)
        if len(self.y) < self._n or (len(self.y) - self._n) % max(1, self._n // 4):
            return
        self._checks += 1
        y = np.asarray(self.y[-self._n :])
        end = range_end(y, self.pv_range)
        x = np.arange(y.size, dtype=float) * self.sample_time
        # the noise about a parabola (a recovery's curvature is not noise: about a straight
        # line, the tail of an exponential inflates σ and hides its own drift), and from
        # sample-to-sample changes (white noise: σ·√2; a slow swing barely counts)
        wide = float(np.std(y - np.polyval(np.polyfit(x, y, 2), x), ddof=3))
        white = difference_noise(y)
        self.noise = min(wide, white) if white > 0 else wide
        self.drift = float(np.polyfit(x, y, 1)[0])
        # below what any transmitter resolves (a noise-free simulation's tail after a test
        # crept 5e-6 per s, and held a re-tune off for ten windows)
        lo, hi = self.pv_range
        span = hi - lo if math.isfinite(hi - lo) and hi > lo else 0.0
        tiny = max(1e-9 * max(1.0, float(np.max(np.abs(y)))), RESOLUTION * span)
        moved = abs(self.drift) * (x[-1] - x[0])
        # a swing left by the test (the relay's cycle dying out) has no trend over the window:
        # the range of the PV averaged over a tenth of it must stay within the noise too
        k = max(1, y.size // 10)
        smooth = np.convolve(y, np.ones(k) / k, mode="valid")
        swing = float(np.ptp(smooth))
        still = moved <= max(3.0 * wide, tiny) and swing <= max(4.0 * white, 3.0 * wide, tiny)
        off = self._off_target(float(np.mean(y)))
        if end is None and still and off is None:
            self.done, self.at_rest = True, True
            self.rest_pv = float(np.mean(y))
            return
        if self._checks >= 1 + 4 * (self.windows - 1):
            self.done = True
            lo, hi = self.pv_range
            self.reason = (
                f"the PV sits at the {end} of its range [{lo:g}, {hi:g}]: a clipped "
                "measurement is not a rest"
                if end
                else f"the PV did not come to rest within {self.waited:.4g} s ({off})"
                if still and off is not None
                else f"the PV did not come to rest within {self.waited:.4g} s (it still moves "
                f"by {self.drift:.3g} per s over the last {self._n * self.sample_time:.4g} s)"
            )

    def _off_target(self, mean: float) -> str | None:
        """Why a PV averaging ``mean`` is not at rest for a loop held to ``target`` (None:
        it is, or there is no target). A PI loop's integral moves its output until the PV
        averages its setpoint: a steady PV off it is a slow recovery still under way (seen: a
        relay begun 0.2 °C off after a ramp test fitted a static gain of 0.25 for 1.0)."""
        if self.target is None or abs(mean - self.target) <= self.band:
            return None
        return (
            f"it averages {mean:.6g}, {mean - self.target:+.3g} off its setpoint "
            f"{self.target:.6g}: the loop in auto is still settling"
        )

    def describe(self) -> str:
        """One progress line while waiting."""
        off = self._off_target(float(np.mean(self.y[-self._n :]))) if self.y else None
        if off is not None:
            return (
                f"{off}: waiting for rest, {self.waited:.4g} of at most "
                f"{self.windows * self._n * self.sample_time:.4g} s"
            )
        return (
            f"the PV still moves ({self.drift:.3g} per s over the last "
            f"{self._n * self.sample_time:.4g} s): waiting for rest, {self.waited:.4g} of at most "
            f"{self.windows * self._n * self.sample_time:.4g} s"
        )
