"""Where a verification record stops: settled at its target, or running away (the guard);
and where a P-gain ramp's calming ends (``calm_spread``, ``calm_test``).

A record is a loop run in auto under gains on trial, judged at fixed points: every ``judge``
samples (``judge_point``), the guard once a new whole window is in, ``settled`` at multiples
of 8·judge. The tuner judges them (``TuningRun._record``); in lockstep the plant asks the same
questions of the same samples as it steps (``record_test``, built from the advance's
``RecordStops``), so a whole record is one round trip and the loop still stops at the sample
that ends it. Why shared: one statement of each rule, the plant's and the tuner's answers the
same to the bit (the same functions on the same floats).

Units: PV in its engineering units, output in % of span, counts in samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np


def settled(y: np.ndarray, k: int, target: float, band: float, flat: float | None) -> bool:
    """Settled at ``target``: the last ``k`` samples' mean within ``band`` of it (the mean, not
    one noisy sample), and (``flat`` not None) their spread within ``flat``: that of the means
    of ten stretches of them (``calm_spread``: the noise averaged in each) from 20 samples on.
    Why not the samples' own spread: it grows with their number (about 2σ·√(2 ln k)), and a
    noisy level loop whose last 600 samples spread past 8σ was judged unsettled, "resting
    +5.4e-06 m off" its setpoint, and its gains rejected (2 of 3 step tunes of lvl1)."""
    if y.size < k:
        return False
    tail = y[-k:]
    if flat is not None:
        if not math.isfinite(float(tail[-1])):
            return False
        spread = calm_spread(tail)[0] if tail.size >= 20 else float(np.ptp(tail))
        if not spread <= flat:
            return False
    return abs(float(np.mean(tail)) - target) < band


@dataclass(frozen=True)
class SettleRule:
    """A record's end on settling at ``target`` (``settled``: the last ``k`` samples' mean
    within ``band``, their spread within ``flat``), once it is longer than ``after`` s of sim
    time (None: at once)."""

    k: int
    target: float
    band: float
    flat: float | None = None
    after: float | None = None

    def done(self, t: np.ndarray, y: np.ndarray) -> bool:
        """Whether the record (sample times ``t`` s, PVs ``y``) has settled."""
        if self.after is not None and not (t.size and t[-1] - t[0] > self.after):
            return False
        return settled(y, self.k, self.target, self.band, self.flat)

    def min_samples(self, ts: float) -> int:
        """The fewest samples (of period ``ts`` s) of a record that may be longer than
        ``after``: never more than ``done`` asks (a sample short where rounding could put the
        sim time either side), so a plant judging by the count stops wherever ``done`` would."""
        if self.after is None:
            return 1
        return max(1, math.ceil(self.after / ts - 1e-6))


def judge_point(m: int, judge: int, n_max: int) -> bool:
    """Whether a record holding ``m`` of ``n_max`` samples is judged now: at multiples of
    ``judge``, and at its end."""
    return m % judge == 0 or m >= n_max


def settle_point(m: int, judge: int) -> bool:
    """Whether ``settled`` is asked at a judging point holding ``m`` samples: the first judge
    of every 8·judge (about 8 % of a record: a settled loop is not in a hurry)."""
    return m % (8 * judge) < judge


class Guard:
    """Stops a record that runs away: the output saturated over two whole windows, or the
    largest deviation from the setpoint growing over two successive windows (by ≥ 10 % each
    and beyond the first window's) as an oscillation (it swings about the setpoint) or, not
    swinging, without slowing (each window's growth at least the last's): either shows
    within about three windows. A deviation that grows ever more slowly and does not swing
    is a loop settling to an offset (P-only control of an integrating process under a load),
    not a runaway."""

    def __init__(self, op_limits: tuple[float, float], window_samples: float):
        self.lo, self.hi = op_limits
        self.n = max(8, round(window_samples))

    def check(self, dev: np.ndarray, u: np.ndarray) -> str | None:
        """Why the record runs away (None: it does not); ``dev``: PV − setpoint, ``u``: the
        output (%), both from the record's first sample."""
        n = self.n
        k = dev.size // n
        if k < 2:
            return None
        at_limit = (u[: k * n] <= self.lo) | (u[: k * n] >= self.hi)
        sat = at_limit.reshape(k, n).mean(axis=1)
        if sat[-1] > 0.5 and sat[-2] > 0.5:
            return f"the output saturated ({100 * sat[-1]:.0f} % of the last window at a limit)"
        peaks = np.abs(dev[: k * n]).reshape(k, n).max(axis=1)
        if not (k >= 3 and peaks[-1] > 1.1 * peaks[-2] > 1.21 * peaks[-3]):
            return None
        if not peaks[-1] > peaks[0]:
            return None
        grown = f"{peaks[-3]:.3g} → {peaks[-2]:.3g} → {peaks[-1]:.3g} over successive windows"
        if swings(dev[(k - 3) * n : k * n], 0.25 * peaks[-1]) >= 2:
            return f"the oscillation grows (largest deviation {grown})"
        if peaks[-1] - peaks[-2] >= peaks[-2] - peaks[-3]:
            return f"the deviation runs away without swinging (largest deviation {grown})"
        return None


def swings(dev: np.ndarray, level: float) -> int:
    """Sign changes of ``dev`` counted only among its values beyond ±``level``: the swings of
    an oscillation about zero, not the noise's about a deviation near zero."""
    big = dev[np.abs(dev) > level]
    return int(np.count_nonzero(np.diff(np.sign(big)))) if big.size > 1 else 0


def record_test(
    steps: int,
    judge: int,
    settle: tuple[int, float, float, float | None, int] | None,
    guard: tuple[Guard, float] | None,
    band_ends: Callable[[float, float | None], bool],
) -> Callable[[float, float | None], bool]:
    """The test that ends a lockstep advance of ``steps`` samples that is a whole record from
    its first sample, asked of every sample in turn (PV, output %): the sample past the band
    (``band_ends``), or a judging point where the guard or ``settled`` would stop the record.

    ``settle``: (k, target, band, flat, min_samples): ``settled`` asked from ``min_samples``
    samples on; ``guard``: (the guard, the setpoint its deviations are from). The record's
    own "long enough" test is in sim time; the count given here is never above it, so the
    advance ends at every point the record would and at most at a few more, which the record
    reads as not ending (and goes on from). Stateful: one per advance."""
    y = np.empty(steps)
    u = np.empty(steps)
    m = 0
    windows = 0

    def ends(pv: float, op: float | None = None) -> bool:
        nonlocal m, windows
        y[m] = pv
        u[m] = math.nan if op is None else op
        m += 1
        if band_ends(pv, op):
            return True
        if not judge_point(m, judge, steps):
            return False
        if guard is not None and m // guard[0].n > windows:
            windows = m // guard[0].n
            if guard[0].check(y[:m] - guard[1], u[:m]):
                return True
        if settle is not None and settle_point(m, judge):
            k, target, band, flat, min_samples = settle
            if m >= min_samples and settled(y[:m], k, target, band, flat):
                return True
        return False

    return ends


def calm_spread(y: np.ndarray) -> tuple[float, int]:
    """A calming's check of the record ``y`` (its last period): the spread of the means of ten
    stretches of its last 10·⌊n/10⌋ samples (the noise averaged in each), and the stretch's
    length in samples. Calm when the spread is below a limit (``ramp.RampTest``)."""
    stretches = y[-(y.size // 10) * 10 :].reshape(10, -1)
    return float(np.ptp(stretches.mean(axis=1))), stretches.shape[1]


MAX_WINDOW = 1_000_000  # samples a calming's window may hold (and its message carry)


@dataclass(frozen=True)
class CalmCheck:
    """A ramp's calming checks, for the loop to make as it steps: the ramp had been fed
    ``fed`` samples, the last of them ``history`` (at most ``window``); from count ``start``
    on, at each multiple of ``every``, calm when ``calm_spread`` of the last ``window`` PVs is
    below ``limit`` (PV units)."""

    fed: int
    start: int
    every: int
    window: int
    limit: float
    history: tuple[float, ...]

    def end_test(
        self, band_ends: Callable[[float, float | None], bool]
    ) -> Callable[[float, float | None], bool]:
        """``calm_test`` of these checks, past ``band_ends`` too."""
        return calm_test(
            self.fed, self.start, self.every, self.window, self.limit, self.history, band_ends
        )


def calm_test(
    fed: int,
    start: int,
    every: int,
    window: int,
    limit: float,
    history: Sequence[float],
    band_ends: Callable[[float, float | None], bool],
) -> Callable[[float, float | None], bool]:
    """The test that ends a lockstep advance at a ramp's calming check that passes, past
    ``band_ends`` too, asked of every sample in turn (PV, output %): the test had been fed
    ``fed`` samples, the last of them ``history``; it checks at each count from ``start`` on
    that is a multiple of ``every``, whether ``calm_spread`` of the last ``window`` PVs is
    below ``limit``. Stateful: one per advance."""
    y = list(history)
    count = fed

    def ends(pv: float, op: float | None = None) -> bool:
        nonlocal count
        y.append(pv)
        count += 1
        if band_ends(pv, op):
            return True
        if count < start or count % every:
            return False
        return calm_spread(np.asarray(y[-window:]))[0] < limit

    return ends
