"""The lifecycle every service shares on the bus: declare, serve, announce, wait, stop.

A service declares its subscribers and queryables through a ``ServiceShell``: each gets a
FIFO channel of bounded capacity (a full channel holds the sender back, nothing is dropped)
and one daemon thread that hands its samples or queries, in order, to a handler. Liveliness
tokens announce the service; it then waits for ``stop`` (SIGINT, SIGTERM), calling its tick.
On the way out it undeclares its inputs (their threads' loops end), joins its threads with
a bounded wait (a stuck handler cannot hold the process) and withdraws its tokens. The order
of those steps is the service's own: the autotuner cancels its runs between them, the logger
finishes its files before its token goes.
"""

from __future__ import annotations

import gc
import logging
import threading
from collections.abc import Callable
from typing import Protocol

import zenoh

from shared.cli import install_stop_handlers
from shared.session import ZenohSettings, open_session

Input = zenoh.Subscriber | zenoh.Queryable


class ServiceShell:
    """One service's declarations on a session and the threads that serve them."""

    def __init__(self, session: zenoh.Session, log: logging.Logger):
        self.session = session
        self.log = log
        self._inputs: list[Input] = []
        self._threads: list[threading.Thread] = []
        self._tokens: list[zenoh.LivelinessToken] = []

    def subscribe(
        self,
        key: str,
        handler: Callable[[zenoh.Sample], None],
        capacity: int,
        *,
        liveliness: bool = False,
        history: bool = False,
        direct: bool = False,
    ) -> zenoh.Subscriber:
        """Hand every sample on ``key`` (or, with ``liveliness``, every token appearing and
        vanishing; ``history``: those already there too) to ``handler`` on its own thread.

        ``direct``: call ``handler`` on Zenoh's own receiving thread instead, in order, with
        no channel and no thread between: a hot path's message costs half the CPU (no
        thread wakes per message). A slow handler holds the sender back as a full channel
        would; it must never wait for another message of the same session."""
        if direct and not liveliness:
            sub = self.session.declare_subscriber(key, self._guarded(key, handler))
            self._inputs.append(sub)
            return sub
        fifo = zenoh.handlers.FifoChannel(capacity)
        if liveliness:
            sub = self.session.liveliness().declare_subscriber(key, fifo, history=history)
        else:
            sub = self.session.declare_subscriber(key, fifo)
        self._serve(sub, key, handler)
        return sub

    def queryable(
        self, key: str, handler: Callable[[zenoh.Query], None], capacity: int
    ) -> zenoh.Queryable:
        """Hand every query on ``key`` to ``handler`` on its own thread; the query is
        finalised (its last reply sent) when the handler returns or raises."""
        queryable = self.session.declare_queryable(key, zenoh.handlers.FifoChannel(capacity))

        def answer(query: zenoh.Query) -> None:
            with query:
                handler(query)

        self._serve(queryable, key, answer)
        return queryable

    def _guarded(self, key: str, handler: Callable) -> Callable:
        """``handler``, its exceptions logged: a bug leaves the input served."""

        def call(item: object) -> None:
            try:
                handler(item)
            except Exception:  # the service's handlers log their own
                self.log.exception("handling %s failed", key)

        return call

    def _serve(self, source: Input, key: str, handler: Callable) -> None:
        call = self._guarded(key, handler)

        def loop() -> None:
            for item in source:  # ends when ``source`` is undeclared
                call(item)

        self._inputs.append(source)
        self.thread(loop, name=key)

    def thread(self, target: Callable[[], None], name: str | None = None) -> None:
        """Start a thread of the service's own (a watchdog, a clock); it must end when the
        service's ``stop`` is set. Joined by ``join``."""
        th = threading.Thread(target=target, name=name, daemon=True)
        self._threads.append(th)
        th.start()

    def announce(self, key: str) -> None:
        """Declare a liveliness token on ``key``, withdrawn by ``withdraw``."""
        self._tokens.append(self.session.liveliness().declare_token(key))

    def wait(
        self, stop: threading.Event, interval: float, tick: Callable[[], None] | None = None
    ) -> None:
        """Block until ``stop`` is set, calling ``tick`` every ``interval`` s meanwhile."""
        while not stop.wait(interval):
            if tick is not None:
                tick()

    def undeclare(self, *inputs: Input) -> None:
        """Undeclare ``inputs`` (all that remain if none is named): they take nothing more."""
        for source in inputs or list(self._inputs):
            if source in self._inputs:
                self._inputs.remove(source)
                source.undeclare()

    def join(self, timeout: float) -> None:
        """Wait up to ``timeout`` s for each thread (its input undeclared, or ``stop`` set)."""
        for th in self._threads:
            th.join(timeout=timeout)

    def withdraw(self) -> None:
        """Undeclare the service's liveliness tokens: the bus learns it is gone."""
        for token in self._tokens:
            token.undeclare()
        self._tokens.clear()


class Service(Protocol):
    def run(self, stop: threading.Event) -> None: ...


def run_until_stopped(settings: ZenohSettings, make: Callable[[zenoh.Session], Service]) -> None:
    """Open a session, build the service on it and run it until SIGINT or SIGTERM."""
    stop = threading.Event()
    install_stop_handlers(stop)
    with open_session(settings) as session:
        service = make(session)
        # what start-up made (modules, the plant's models) lives as long as the process: out of
        # the collector's sight, a full collection on the hot path takes microseconds, not the
        # tens of milliseconds of walking every module's objects (measured: 25-30 ms pauses
        # mid-advance in the tuner)
        gc.freeze()
        service.run(stop)
