"""A loop's trend: PV, setpoint and output over the last minutes of sim time, for the page.

Samples come in at the loop's rate (thousands a second in lockstep); the page gets them in
batches a few times a second, thinned to a bounded number of points per batch and per
snapshot by keeping each bucket's extreme PV (a spike stays visible), so a fast run never
floods the websocket nor the browser.
"""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass, field

import numpy as np

HISTORY = 600.0  # s of sim time kept (the page's trend window)
MAX_KEPT = 200_000  # samples kept per loop at most, whatever the rate
BATCH_POINTS = 400  # points per loop per push at most
SNAPSHOT_POINTS = 3000  # points per loop in a new page's first picture at most


def thin(n: int, limit: int, pv: np.ndarray | None = None) -> np.ndarray:
    """Indices of at most ``limit`` of ``n`` points, the last always kept: all of them when
    they fit; else one per bucket of equal width, the one farthest from the bucket's mean PV
    (its first without ``pv``)."""
    if n <= limit:
        return np.arange(n)
    if limit < 2:
        return np.array([n - 1])
    edges = np.linspace(0, n - 1, limit).astype(int)  # limit − 1 buckets, then the last point
    out = []
    for lo, hi in itertools.pairwise(edges):
        if pv is None or hi <= lo + 1:
            out.append(lo)
            continue
        chunk = pv[lo:hi]
        out.append(lo + int(np.argmax(np.abs(chunk - chunk.mean()))))
    out.append(n - 1)
    return np.array(out)


@dataclass
class Trend:
    """One loop's samples (t in sim s, PV in PV units, SP, OP in %) within ``history`` s of
    the newest; ``take_new`` gives what arrived since its last call."""

    history: float = HISTORY
    rows: deque = field(default_factory=lambda: deque(maxlen=MAX_KEPT))
    new: list = field(default_factory=list)

    def add(self, t: float, pv: float, sp: float, op: float) -> None:
        if self.rows and t < self.rows[-1][0]:  # the plant restarted (sim time from 0)
            self.rows.clear()
            self.new.clear()
        self.rows.append((t, pv, sp, op))
        self.new.append((t, pv, sp, op))
        while self.rows and self.rows[0][0] < t - self.history:
            self.rows.popleft()

    def take_new(self, limit: int = BATCH_POINTS) -> dict[str, list[float]] | None:
        """The samples since the last call, thinned to ``limit``; None when there are none."""
        rows, self.new = self.new, []
        return _columns(rows, limit) if rows else None

    def snapshot(self, limit: int = SNAPSHOT_POINTS) -> dict[str, list[float]]:
        """The whole window, thinned to ``limit``."""
        return _columns(list(self.rows), limit)


def _columns(rows: list[tuple[float, float, float, float]], limit: int) -> dict[str, list[float]]:
    a = np.asarray(rows, dtype=float).reshape(-1, 4)
    keep = thin(len(a), limit, a[:, 1])
    a = a[keep]
    return {
        "t": a[:, 0].tolist(),
        "pv": a[:, 1].tolist(),
        "sp": a[:, 2].tolist(),
        "op": a[:, 3].tolist(),
    }
