"""Did this process stop running for a while: SIGSTOP, a suspended VM, a starved CPU?

A wait that times out cannot tell by itself: paused for its whole timeout, it ends on time
and looks like silence from the plant (a tuner paused 5 s in a 5 s wait blamed the plant).
A daemon thread that ticks every ``PERIOD`` s can: while the process is stopped no thread
runs, so its next tick comes late by the stall. ``stalled(since)`` is the time lost to such
stalls since a moment (the one in progress too, when the ticker has not run yet since).
"""

from __future__ import annotations

import threading
import time
from collections import deque

PERIOD = 0.1  # s between ticks
THRESHOLD = 1.0  # s: a tick this late is a stall (a busy machine delays a tick by far less)


class StallWatch:
    """The stalls of this process (monotonic start and end), the last 32."""

    def __init__(self, period: float = PERIOD, threshold: float = THRESHOLD):
        self.period = period
        self.threshold = threshold
        self._lock = threading.Lock()
        self._stalls: deque[tuple[float, float]] = deque(maxlen=32)
        self._last = time.monotonic()
        threading.Thread(target=self._tick, name="stall-watch", daemon=True).start()

    def _tick(self) -> None:
        while True:
            time.sleep(self.period)
            now = time.monotonic()
            with self._lock:
                if now - self._last > self.threshold:
                    self._stalls.append((self._last, now))
                self._last = now

    def stalled(self, since: float) -> float:
        """Seconds this process did not run since ``since`` (monotonic), in stalls of more
        than the threshold."""
        now = time.monotonic()
        with self._lock:
            spans = list(self._stalls)
            if now - self._last > self.threshold:  # one in progress: the ticker not yet back
                spans.append((self._last, now))
        return sum(max(0.0, end - max(start, since)) for start, end in spans if end > since)


_watch: StallWatch | None = None
_started = threading.Lock()


def stall_watch() -> StallWatch:
    """The process's one watch, started on first use."""
    global _watch
    with _started:
        if _watch is None:
            _watch = StallWatch()
        return _watch
