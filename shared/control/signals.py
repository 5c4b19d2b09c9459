"""Signal helpers on sampled records: numpy arrays of a PV (its engineering units) or an output
(% of span), and their sample times t in s.

Rest and noise (``noise_level``, ``difference_noise``, ``at_rest``, ``range_end``), the first
crossing of a level (``first_crossing``), turning points (``extrema``, after ``smooth``), a
step response's decay ratio from them (``decay_ratio``), the least move that is a response
(``no_response_floor``) and the trapezoid integral (``trapezoid``): what identification and
the response figures read off a record. The sample type the experiments are fed
(``Sample``): anything with ``t`` (s, sim time), ``pv`` (PV units) and ``op`` (% of output),
as the bus's ``ProcessSample`` and a replayed record are.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from typing import Protocol

import numpy as np

from shared.control.rest_window import RESOLUTION


class Sample(Protocol):
    """One sample of a loop: sim time t (s), PV (engineering units), output op (%)."""

    @property
    def t(self) -> float: ...

    @property
    def pv(self) -> float: ...

    @property
    def op(self) -> float: ...


# --- noise and rest --------------------------------------------------------------------------


def noise_level(y: np.ndarray) -> float:
    """Standard deviation of ``y`` about its straight-line trend, in ``y``'s units (0 for fewer
    than 3 points). A slow swing in the record counts as noise here; ``difference_noise`` does
    not count it."""
    if y.size < 3:
        return 0.0
    x = np.arange(y.size, dtype=float)
    coef = np.polyfit(x, y, 1)
    return float(np.std(y - np.polyval(coef, x), ddof=2))


def line_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """The least-squares line through (x, y): (slope, its value at x = 0, the slope's
    standard error from the scatter about it; 0 for three points or fewer, or no spread in
    x). Why the error: a trend read over a short, noisy window is judged against it (a step
    test's approach to a limit, a PV on its way back or not)."""
    slope, level = np.polyfit(x, y, 1)
    sxx = float(np.sum((x - x.mean()) ** 2))
    if x.size <= 3 or not sxx > 0:
        return float(slope), float(level), 0.0
    resid = y - (slope * x + level)
    return float(slope), float(level), math.sqrt(float(np.sum(resid * resid)) / (x.size - 2) / sxx)


def difference_noise(y: np.ndarray) -> float:
    """Standard deviation of white noise on ``y`` read from its sample-to-sample changes
    (σ(Δy)/√2), in ``y``'s units: a trend or a slow swing barely counts."""
    return float(np.std(np.diff(y)) / math.sqrt(2.0))


def range_end(
    y: np.ndarray, pv_range: tuple[float, float], noise_std: float | None = None
) -> str | None:
    """'top' or 'bottom' when the PV sits at, or within 3σ of, an end of ``pv_range``.

    The transmitter clips the measurement to its range, so a PV there is flat and noise-free
    whatever the process does: any sample at the end, or a mean within 3σ of it, counts.
    σ (PV units) is ``noise_std`` if given, else the record's own ``noise_level`` (which
    clipping lowers).
    """
    y = np.asarray(y, dtype=float)
    if y.size == 0:
        return None
    lo, hi = pv_range
    tol = 1e-9 * max(1.0, abs(lo), abs(hi), hi - lo)
    sigma = noise_level(y) if noise_std is None else noise_std
    mean = float(np.mean(y))
    if np.any(y >= hi - tol) or mean >= hi - 3.0 * sigma - tol:
        return "top"
    if np.any(y <= lo + tol) or mean <= lo + 3.0 * sigma + tol:
        return "bottom"
    return None


def at_rest(
    y: np.ndarray, pv_range: tuple[float, float] | None = None, allowance: float = 0.0
) -> bool:
    """No trend beyond the noise: the straight-line fit moves less than 3σ (``noise_level``,
    and less than 1e-9 of the level, or than ``allowance`` in the PV's units: a drift the
    caller counts as rest) over the record; and, given the transmitter's ``pv_range``, the
    PV is not at or within noise of one of its ends (``range_end``). False for fewer than 3
    samples."""
    if y.size < 3:
        return False
    if pv_range is not None and range_end(y, pv_range) is not None:
        return False
    x = np.arange(y.size, dtype=float)
    slope = float(np.polyfit(x, y, 1)[0])
    drift = abs(slope) * (y.size - 1)
    floor = 1e-9 * max(1.0, float(np.max(np.abs(y))))
    return drift <= max(3.0 * noise_level(y), floor, allowance)


# --- crossings, turning points, integrals ------------------------------------------------------


def first_crossing(t: np.ndarray, z: np.ndarray, level: float) -> float | None:
    """The time (``t``'s units, s) where ``z`` first reaches ``level`` (z ≥ level), linearly
    interpolated between the samples either side; ``t[0]`` if the first sample already has;
    None if it never does."""
    above = np.nonzero(z >= level)[0]
    if above.size == 0:
        return None
    i = int(above[0])
    if i == 0:
        return float(t[0])
    return float(t[i - 1] + (level - z[i - 1]) / (z[i] - z[i - 1]) * (t[i] - t[i - 1]))


def smooth(y: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average over ``width`` samples (an even width is made odd by one more),
    the record's end values repeated beyond its ends so the output has ``y``'s length; ``y``
    itself for a width below 3."""
    if width < 3:
        return y
    width |= 1
    pad = width // 2
    padded = np.concatenate((np.full(pad, y[0]), y, np.full(pad, y[-1])))
    return np.convolve(padded, np.ones(width) / width, mode="valid")


def extrema(t: np.ndarray, y: np.ndarray, min_swing: float) -> list[tuple[float, float]]:
    """Turning points (t, y) (zigzag): a running maximum (minimum) counts once the record has
    fallen (risen) ``min_swing`` (``y``'s units) from it. The starting point is never one."""
    out: list[tuple[float, float]] = []
    direction, k = 0, 0
    # plain floats: the same doubles and the same arithmetic, without a numpy scalar per
    # element (this loop runs over every sample of a record, often)
    tv, yv = np.asarray(t, dtype=float).tolist(), np.asarray(y, dtype=float).tolist()
    for i in range(1, len(yv)):
        yi = yv[i]
        if direction == 0:
            if abs(yi - yv[0]) >= min_swing:
                direction, k = (1 if yi > yv[0] else -1), i
        elif direction > 0:
            if yi > yv[k]:
                k = i
            elif yv[k] - yi >= min_swing:
                out.append((tv[k], yv[k]))
                direction, k = -1, i
        else:
            if yi < yv[k]:
                k = i
            elif yi - yv[k] >= min_swing:
                out.append((tv[k], yv[k]))
                direction, k = 1, i
    return out


def _crests(turns: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The maxima among turning points (``extrema``'s, which alternate) that lie above zero."""
    kinds = [
        (j + 1 < len(turns) and v > turns[j + 1][1]) or (j > 0 and v > turns[j - 1][1])
        for j, (_, v) in enumerate(turns)
    ]
    return [(tc, v) for (tc, v), top in zip(turns, kinds, strict=True) if top and v > 0]


def decay_ratio(turns: list[tuple[float, float]], t: np.ndarray, dev: np.ndarray) -> float | None:
    """A step response's decay ratio from its turning points (``extrema`` of ``dev``, the
    deviation from the final value or the setpoint, at times ``t``): the crest after the
    largest over the largest (crests: maxima above zero; the quarter-decay aim is 0.25). Not
    the second crest over the first: a small crest of the approach ahead of the overshoot is
    not the oscillation's (a stable flow loop's 0.7 % crest before its 4.65 % overshoot read
    7.9, a growing loop's figure). Where the largest is the last, the record tells: watched
    for 1.5 crest spacings after it, never again as far from zero, the oscillation has died
    (None, as for a single crest); else (cut short, or running on past it: growing, or
    drifting away without a crest) the largest over the one before, ≥ 1."""
    crests = _crests(turns)
    if not crests:
        return None
    m = max(range(len(crests)), key=lambda j: crests[j][1])
    if m + 1 < len(crests):
        return crests[m + 1][1] / crests[m][1]
    if m == 0:
        return None
    (tm, top), spacing = crests[m], crests[m][0] - crests[m - 1][0]
    t, dev = np.asarray(t, dtype=float), np.asarray(dev, dtype=float)
    after = np.abs(dev[t > tm])
    died = after.size and float(np.max(after)) <= top
    if died and float(t[-1]) - tm >= 1.5 * spacing:
        return None
    return top / crests[m - 1][1]


def slowest_decay(turns: list[tuple[float, float]], share: float = 0.25) -> float | None:
    """The largest ratio of a crest to the one before it, from the largest crest on, among
    crests of at least ``share`` of the largest (``extrema`` of the deviation, crests above
    zero): where the first swing is the setpoint kick's and the oscillation after it hardly
    decays, the crest after the largest over the largest says 0.66 of a loop whose crests
    then run 0.98, 1.01, 1.03, 1.00 (lvl2 under ZN PID, Ms 201: helper trial). None for
    fewer than two such crests."""
    crests = [v for _, v in _crests(turns)]
    if len(crests) < 2:
        return None
    m = max(range(len(crests)), key=lambda j: crests[j])
    big = [v for v in crests[m:] if v >= share * crests[m]]
    ratios = [b / a for a, b in itertools.pairwise(big)]
    return max(ratios) if ratios else None


def overshoot_decay(dev: np.ndarray, band: float, share: float = 0.25) -> float | None:
    """A stable step response's decay ratio as an engineer reads it (the quarter-decay
    figure), from ``dev``, its deviation from the final value (positive on the overshoot's
    side): the peak of the overshoot after the largest over the largest's. An overshoot is a
    lobe of the response beyond the final value, and lobes are separated by crossings of the
    final value by more than ``band``: a ripple on a slow tail that never comes back through
    the final value is one lobe, not a second overshoot (TL PID on e^{−s}/(10s + 1): 7.1 %
    overshoot, its ripple's crests above the final value 0.90 of each other, its oscillatory
    pole pair decaying 0.19 a period, and no second overshoot at all). The largest, not the
    first: a first overshoot made small by a zero is not yet the oscillation's. Where the
    overshoots of at least ``share`` of the largest go on decaying more slowly than the first
    two did (a setpoint kick's swing, then an oscillation that hardly decays), their mean
    decay a period instead, (last / largest)^(1/count). At most 1. None where no overshoot
    follows the largest (no oscillation about the final value, or one that died below
    ``band``: nothing to state). For a pure second-order response, e^{2πσ/ω} exactly (σ ± jω
    its poles).

    It reads the response alone: a growing one is for the caller to tell (it ends with its
    largest overshoot: None)."""
    d = np.asarray(dev, dtype=float)
    idx = np.flatnonzero(np.abs(d) > band)
    if idx.size == 0:
        return None
    side = d[idx] > 0
    # one lobe per run of one side, the samples within the band between ignored: its side
    # and its peak's distance from the final value
    cuts = np.flatnonzero(side[1:] != side[:-1]) + 1
    lobes = [(bool(d[run[0]] > 0), float(np.max(np.abs(d[run])))) for run in np.split(idx, cuts)]
    peaks = [v for above, v in lobes if above]  # the overshoots, in order
    if len(peaks) < 2:
        return None
    m = max(range(len(peaks)), key=lambda j: peaks[j])
    top = peaks[m]
    if m + 1 == len(peaks):  # no overshoot after the largest
        return None
    first = peaks[m + 1] / top
    n = m + 1
    while n + 1 < len(peaks) and peaks[n + 1] >= share * top:
        n += 1
    mean = (peaks[n] / top) ** (1.0 / (n - m))
    return max(first, mean)


def no_response_floor(pv_range: tuple[float, float]) -> float:
    """PV units: a move within this of the rest is no response to the output: what no
    transmitter resolves, ``rest_window.RESOLUTION`` of the range ``pv_range`` (0 for a range
    that is not finite), as for rest. A noise-free simulation shows any change: a valve stuck
    in its deadband gave 2e-9 of the range for a 5 % step, read as a gain of 4e-8 and a PI Kc
    of 1.1e9 that the verification put on the loop (helper trial); 6/((s+1)(s+2)(s+3)) cycles
    by 6e-3."""
    span = abs(pv_range[1] - pv_range[0])
    return RESOLUTION * span if math.isfinite(span) else 0.0


def trapezoid(y: np.ndarray, t: np.ndarray) -> float:
    """∫ y dt over the record by the trapezoid rule (``y``'s units × s); 0 for fewer than two
    samples."""
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(t))) if t.size > 1 else 0.0


def outside(pv: float, below: float | None, above: float | None) -> bool:
    """``pv`` at or past either bound (None: no bound on that side), or not a number: where a
    lockstep advance with stops ends (``AdvanceCommand.stops_at``), and where a relay's band
    ends (``identify.experiments.Band``) — one test, so that the plant and the tuner agree on
    the sample that ends a batch."""
    return not ((below is None or pv > below) and (above is None or pv < above))


def ends_batch(
    pv: float,
    op: float | None,
    pv_stops: tuple[float | None, float | None],
    op_stops: tuple[float | None, float | None],
) -> bool:
    """A sample (PV ``pv``, output ``op`` %, None: not known) ends a banded batch: its PV at
    or past a PV stop, or its output at or past an output stop (``outside``; a side with no
    stop is None). The one test of the plant's advance and the tuner's band."""
    return end_test(pv_stops, op_stops)(pv, op)


def end_test(
    pv_stops: tuple[float | None, float | None],
    op_stops: tuple[float | None, float | None],
) -> Callable[[float, float | None], bool]:
    """``ends_batch`` with its stops fixed, as a function of the sample: asked of every sample
    of a batch (by the plant as it steps, by the tuner as it takes them), where building the
    stops' tuples each time cost more than the test."""
    below, above = pv_stops
    op_below, op_above = op_stops
    no_op_stop = op_below is None and op_above is None

    def ends(pv: float, op: float | None = None) -> bool:
        if outside(pv, below, above):
            return True
        if op is None or no_op_stop:
            return False
        return outside(op, op_below, op_above)

    return ends
