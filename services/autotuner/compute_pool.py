"""Worker processes for a run's CPU-heavy pure steps: the relay's model fits, the design.

Why: one tuner runs many loops' tunes at once, each on its own thread, but Python runs one
thread at a time (the GIL). A run's steps between samples are light; its two heavy steps —
the relay's closing fits (dozens of least-squares fits of process models) and the design
(every rule judged on the sampled loop, its setpoint step simulated) — are hundreds of
milliseconds of pure Python and numpy each. Done in worker processes they run on every core
while the runs' threads go on exchanging samples, so N tunes through one tuner add up.

The steps are pure functions of picklable values, so a worker computes exactly what the
run's own thread would (the same code on the same numbers: results equal to the bit). The
tuner service forks its workers at start-up (``fork_now``), before its Zenoh session opens:
from a process that runs no other thread a fork is safe, and the workers have every module
the tuner imported, up at no cost of CPU before any run (a fork server imports them anew,
0.7 s of CPU, which took a core from the first run's samples). Any pool made later (one
that replaces a broken pool, or one of a process whose threads already run) forks from a
clean server process (``forkserver``), not from the tuner, whose Zenoh threads a fork would
copy in an unknown state; the server imports the heavy modules once, so each worker starts
in milliseconds, and it starts with the next run, in the background while the run measures
the loop's rest. A pool that breaks (a worker killed) is replaced, and that step computed in
the run's own thread: a run never fails for want of a worker. A tuner killed outright takes
its workers with it: each watches the tuner and ends when it has gone (then the server, and
the resource tracker, end as their last user does).
"""

from __future__ import annotations

import importlib
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

from shared.errors import AutotuneError

log = logging.getLogger("autotuner")

T = TypeVar("T")

# what the workers run: imported once by the server they fork from, and by the tuner before
# it forks them. The scipy modules too: the library imports them where they are used (every
# `autotune` command loads it, most never fit anything), and a tuner whose workers forked
# without them paid for them in its first run (the design's scipy.signal, 0.5 s of CPU in
# each worker: the first ramp tune's trials 145-177 µs a sample over the bus, against 66 next)
PRELOAD = [
    "scipy.linalg",
    "scipy.optimize",
    "scipy.signal",
    "services.autotuner.design.selection",
    "services.autotuner.identify.relay",
]


def preload() -> None:
    """Import ``PRELOAD`` in this process (the tuner, before its workers fork)."""
    for name in PRELOAD:
        importlib.import_module(name)


WAIT = 600.0  # s: a step no run's thread would finish either is a failure, said as such
PARENT_CHECK = 0.5  # s between a worker's checks that the tuner is still there


def _started(pid: int) -> str | None:
    """Process ``pid``'s start time (clock ticks since boot; None if it is gone): with the
    pid, it names that process and no later one given the same number."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _outlive_not(tuner: int, started: str | None) -> None:
    """In each worker: end when the tuner has ended. A tuner killed outright (SIGKILL) tells
    nobody, and a worker waiting for work would wait forever (it holds its own queue's pipe,
    and the server it was forked from lives while any worker does). A SIGINT is not the
    worker's to act on: Ctrl-C at a terminal reaches the tuner's whole process group, and a
    worker forked from the tuner has its command line (``pkill -f``); the tuner stops its
    workers as it stops (a worker interrupted printed a KeyboardInterrupt's traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while True:
            time.sleep(PARENT_CHECK)
            if _started(tuner) != started:
                os._exit(0)

    threading.Thread(target=watch, daemon=True, name="tuner-watch").start()


def _alone() -> bool:
    """This process runs one thread, native ones counted (Linux's /proc; elsewhere: not
    known, so False)."""
    try:
        return threading.active_count() == 1 and len(os.listdir("/proc/self/task")) == 1
    except OSError:
        return False


def inline(fn: Callable[..., T], *args: Any) -> T:
    """A step computed in the caller's thread (tests, offline analysis, a tuner of one)."""
    return fn(*args)


def compute_all(
    compute: Callable[..., Any], calls: Sequence[tuple[Callable[..., Any], tuple]]
) -> list[Any]:
    """[fn(*args), …] for ``calls``, each through ``compute`` and all at once: the first in
    this thread, the others each in a thread of its own, so that a pool's workers compute
    them side by side (the design's robustness and its simulated steps, 50 ms each: one
    worker after the other took 100). ``inline``: in turn, in this thread. Every call is
    waited for; then the first error (in the calls' order) is raised."""
    if compute is inline or len(calls) < 2:
        return [compute(fn, *args) for fn, args in calls]
    out: list[tuple[bool, Any]] = [(False, None)] * len(calls)

    def one(i: int) -> None:
        fn, args = calls[i]
        try:
            out[i] = (True, compute(fn, *args))
        except BaseException as err:  # raised again in the caller's thread
            out[i] = (False, err)

    threads = [
        threading.Thread(target=one, args=(i,), daemon=True, name="compute-part")
        for i in range(1, len(calls))
    ]
    for th in threads:
        th.start()
    one(0)
    for th in threads:
        th.join()
    for ok, value in out:
        if not ok:
            raise value
    return [value for _, value in out]


class ComputePool:
    """``workers`` processes that compute a run's heavy steps (``call``)."""

    def __init__(self, workers: int):
        if workers < 1:
            raise ValueError(f"workers {workers}: need at least one")
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()
        self._warmed = False

    def _executor(self, method: str = "forkserver") -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                ctx = multiprocessing.get_context(method)
                if method == "forkserver":
                    ctx.set_forkserver_preload(PRELOAD)
                self._pool = ProcessPoolExecutor(
                    self.workers,
                    mp_context=ctx,
                    initializer=_outlive_not,
                    initargs=(os.getpid(), _started(os.getpid())),
                )
            return self._pool

    def fork_now(self) -> bool:
        """Start the workers now, forked from this process, if it runs no other thread (at
        start-up, before a Zenoh session opens: a fork copies other threads' locks in an
        unknown state); True if they were. Each has what this process imported, at once and
        at no cost of CPU, where the fork server imports it anew. Measured: the first ramp
        tune of a tuner whose server started with it took 78 µs a sample in its trials, 57
        with the workers already up. A pool made later (one that replaces a broken pool)
        comes from the fork server."""
        if not _alone():
            log.info("compute workers: started with the first run (threads run already)")
            return False
        with self._lock:
            if self._pool is not None or self._warmed:
                return False
            self._warmed = True
        pool = self._executor("fork")
        try:
            for _ in range(self.workers):  # a fork pool starts all its workers with the first
                pool.submit(int)
        except OSError as err:  # no fork to be had (a process limit, memory): the server's
            log.warning("compute workers not forked at start-up (%s): started with a run", err)
            with self._lock:
                self._pool, self._warmed = None, False
            # those forked before the refusal: the pool never started the thread that would
            # stop them, and they would wait for work as long as the tuner lives
            for proc in list(getattr(pool, "_processes", {}).values()):
                proc.terminate()
                proc.join(5.0)
            pool.shutdown(wait=False, cancel_futures=True)
            return False
        return True

    def warm(self) -> None:
        """Start the server and the workers now (a run about to start will need them); once."""
        with self._lock:
            if self._warmed:
                return
            self._warmed = True
        pool = self._executor()
        for _ in range(self.workers):
            pool.submit(int)

    def call(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in a worker; in this thread if the pool broke (then replaced)."""
        pool = self._executor()
        try:
            return pool.submit(fn, *args).result(timeout=WAIT)
        except TimeoutError:
            raise AutotuneError(f"{fn.__name__}: not computed within {WAIT:g} s") from None
        except BrokenProcessPool as err:
            log.warning("a compute worker was lost (%s): computing in the run's thread", err)
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            return fn(*args)

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
