"""Where the PV went past a run's PV limits, over every sample the run read.

An experiment aborts once the PV crosses ``--pv-limits``, and restores the loop; but the
process carries on for about its dead time (and its lags' inertia) after the output is
restored, so the PV goes further. The abort's reason gave the PV where it crossed (52.11),
never where it went (53.02, outside the limits for 7.5 s: helper trial on three lags and a
dead time). Every sample the run reads passes through here once (by its number), from its
start to its end, the wait for the PV's return included.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass


@dataclass
class LimitWatch:
    lo: float  # the run's PV limits, PV units
    hi: float
    peak: float | None = None  # the PV farthest outside them
    outside: int = 0  # samples outside them
    first_t: float | None = None  # s: the first sample outside
    last_t: float | None = None  # s: the last
    _seq: int = -1  # the last sample seen (a sample read twice counts once)

    def see(self, samples: Iterable[object]) -> None:
        for s in samples:
            seq, pv, t = getattr(s, "seq", None), getattr(s, "pv", math.nan), getattr(s, "t", 0.0)
            if seq is None or seq <= self._seq:
                continue
            self._seq = seq
            if not math.isfinite(pv) or self.lo <= pv <= self.hi:
                continue
            self.outside += 1
            self.first_t = t if self.first_t is None else self.first_t
            self.last_t = t
            if self.peak is None or _beyond(pv, self.lo, self.hi) > _beyond(
                self.peak, self.lo, self.hi
            ):
                self.peak = pv

    def to_dict(self, sample_time: float) -> dict | None:
        """The result's ``pv_outside``; None if the PV never left the limits."""
        if self.peak is None:
            return None
        return {
            "peak": self.peak,
            "samples": self.outside,
            "seconds": self.outside * sample_time,
            "first_t": self.first_t,
            "last_t": self.last_t,
        }

    def warning(self, sample_time: float, units: str) -> str | None:
        if self.peak is None:
            return None
        u = f" {units}" if units else ""
        return (
            f"the PV went past its limits [{self.lo:g}, {self.hi:g}]{u}: to {self.peak:.4g}{u}, "
            f"outside them for {self.outside * sample_time:.3g} s ({self.outside} samples from "
            f"t = {self.first_t:g} s); a process carries on past them for its dead time and "
            "lags once the output is restored, and a slow one takes as long again to come "
            "back: keep the experiment's push well inside the limits"
        )


def _beyond(pv: float, lo: float, hi: float) -> float:
    """How far ``pv`` lies outside [lo, hi] (0 inside)."""
    return max(lo - pv, pv - hi, 0.0)
