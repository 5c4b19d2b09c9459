"""The plant's outputs through declared publishers, one per key, declared on first use.

Why: ``session.put`` on a key given as a string resolves it against the session's routing
tables every time, and with a liveliness token per loop that costs time in proportion to the
number of loops (measured: 66 µs a put with 1,000 loops, 340 µs with 4,000); a declared
publisher's put takes under 1 µs whatever the count. Same wire as ``wire.put``: the JSON
payload, ``application/json;<Model>``, congestion control BLOCK (never dropped).
"""

from __future__ import annotations

import threading
import time

import zenoh

from shared import wire
from shared.messages import Message


class Publishers:
    """A publisher per key expression (the per-loop pv and status keys), for one session."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()
        self._closed = False
        # thread → monotonic time its put began, while it lasts: a put blocked behind a
        # subscriber that stopped reading (its link's queue full) holds the plant up
        self._putting: dict[int, float] = {}

    def _publisher(self, key: str, model: type[Message]) -> zenoh.Publisher | None:
        pub = self._pubs.get(key)
        if pub is None:
            with self._lock:
                if self._closed:
                    return None
                pub = self._pubs.get(key)
                if pub is None:
                    pub = self.session.declare_publisher(
                        key,
                        encoding=wire.encoding_for(model),
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
                    self._pubs[key] = pub
        return pub

    def declare(self, keys: list[str], model: type[Message]) -> None:
        """Declare the publishers of ``keys`` now (each declaration costs time in proportion
        to the keys already declared: the realtime clock's are made before it starts)."""
        for key in keys:
            self._publisher(key, model)

    def put(self, key: str, msg: Message) -> None:
        """Publish ``msg`` on ``key`` as ``wire.put`` does."""
        self.put_json(key, type(msg), wire.encode(msg))

    def put_json(self, key: str, model: type[Message], payload: bytes) -> None:
        """Publish a payload already encoded as ``model``'s JSON (nothing once closed)."""
        pub = self._publisher(key, model)
        if pub is not None:
            me = threading.get_ident()
            self._putting[me] = time.monotonic()
            try:
                pub.put(payload)
            finally:
                del self._putting[me]

    def held_since(self) -> float | None:
        """The monotonic time the oldest put still under way began (None: none is). A put
        lasts microseconds; one that lasts is blocked behind a subscriber that stopped
        reading (a paused logger): Zenoh's reliable publication waits for room in its
        link's queue, up to 5 s before it closes the link."""
        return min(tuple(self._putting.values()), default=None)

    def close(self) -> None:
        """Undeclare every publisher; later puts are dropped (the service is stopping)."""
        with self._lock:
            self._closed = True
            pubs, self._pubs = list(self._pubs.values()), {}
        for pub in pubs:
            pub.undeclare()
