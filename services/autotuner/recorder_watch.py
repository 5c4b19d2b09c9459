"""Whether a logger recorded a run: its liveliness tokens watched for the run's length.

A run that no logger recorded is not on record: ``autotune history`` and ``revert`` cannot
know its change of the loop's gains (seen: a logger killed mid-run, the tune ended ok, and
revert answered "no change of hx1's gains on record"). The run's result says so."""

from __future__ import annotations

import threading

import zenoh

from shared import keys


class RecorderWatch:
    """The loggers announcing ``<prefix>/logger/*/alive`` from now until ``verdict()``."""

    def __init__(self, session: zenoh.Session, prefix: str):
        self.session, self.key = session, keys.logger_alive(prefix, "*")
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._seen = False  # any logger in sight since the start
        self._gap = False  # all out of sight at some moment after one was seen
        self._sub = session.liveliness().declare_subscriber(self.key, self._on, history=True)

    def _on(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr)
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(name)
                self._seen = True
            else:
                self._alive.discard(name)
                self._gap = self._gap or (self._seen and not self._alive)

    def verdict(self) -> str | None:
        """A warning for the run's result, or None when a logger was in sight throughout.
        Stops watching."""
        with self._lock:
            seen, gap, alive = self._seen, self._gap, bool(self._alive)
        if not seen:  # a run that ended within moments of its start: ask once more
            seen = alive = any(
                r.ok is not None for r in self.session.liveliness().get(self.key, timeout=0.5)
            )
        self._sub.undeclare()
        if not seen:
            return (
                f"no logger recorded this run (nothing announced {self.key}): neither the run "
                "nor its change of the loop's gains is on record (`autotune history` and "
                "`revert` will not know it)"
            )
        if gap:
            return (
                "the logger went out of sight during the run (killed or cut off): its record "
                f"of the run may be incomplete{'' if alive else ', and none is back'} "
                "(`autotune runs` shows what was written)"
            )
        return None
