"""A refusal's log line, rate-limited per reason: a flood of bad messages (20,000 malformed
commands in 0.18 s; 137,000 malformed samples on a watched loop) must not flood the log, and
the count of what went unsaid is said."""

from __future__ import annotations

import logging
import threading
import time


class RejectLog:
    """Log every refusal, but at most ``burst`` lines per reason in any ``window`` seconds."""

    def __init__(self, log: logging.Logger, burst: int = 10, window: float = 10.0):
        self.log, self.burst, self.window = log, burst, window
        self._seen: dict[str, tuple[float, int, int]] = {}
        self._lock = threading.Lock()  # refusals come on Zenoh's threads, ``flush`` on ours

    def __call__(self, category: str, message: str) -> None:
        now = time.monotonic()
        with self._lock:
            start, shown, hidden = self._seen.get(category, (now, 0, 0))
            if now - start > self.window:
                if hidden:
                    self.log.warning("%d more %s rejects were not logged", hidden, category)
                start, shown, hidden = now, 0, 0
            if shown < self.burst:
                self.log.warning("rejected (%s): %s", category, message)
                shown += 1
            else:
                hidden += 1
            self._seen[category] = (start, shown, hidden)

    def flush(self, now: float) -> None:
        """Say how many refusals went unlogged in each window that has passed (monotonic
        ``now``): the count was said only when another refusal of the kind came after it."""
        with self._lock:
            for category, (start, _, hidden) in list(self._seen.items()):
                if hidden and now - start > self.window:
                    self.log.warning("%d more %s rejects were not logged", hidden, category)
                    self._seen[category] = (now, 0, 0)
