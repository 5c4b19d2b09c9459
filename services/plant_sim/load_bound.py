"""A bound on the time a plant file's models take to load.

A user's model class runs its ``__init__`` and ``reset()`` as the plant file is read, before
the plant is on the bus: one that blocks (waits on a device, sleeps, loops) would hold
plant_sim there for good, silently. ``load_bound`` interrupts the load after ``seconds`` of
wall time (SIGALRM, in the main thread, where plant_sim loads its file) with ``LoadTimeout``,
a ConfigError: the model's call is named by the loader (``the model's reset() raised
LoadTimeout: …``), one line, exit 2; a model that catches it is interrupted again every
second by an exception no ``except Exception`` takes. A call blocked in native code (no
Python runs) is not interrupted. Elsewhere (another thread, no SIGALRM) it bounds nothing.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from shared.errors import ConfigError

LOAD_TIMEOUT = 60.0  # s of wall time: an FMU's or a Python model's start takes seconds at most
MAX_LOAD_TIMEOUT = 86400.0  # s: a day (the interval timer refused 1e10 s: exit 70)


def check_load_timeout(seconds: float, flag: str = "--load-timeout") -> None:
    """ConfigError naming ``flag`` unless ``seconds`` is in (0, MAX_LOAD_TIMEOUT]."""
    if not 0 < seconds <= MAX_LOAD_TIMEOUT:
        raise ConfigError(f"{flag} {seconds:g}: must be > 0 and at most {MAX_LOAD_TIMEOUT:g} s")


class LoadTimeout(ConfigError):
    """The plant file's models did not load within the bound."""


class StillLoading(BaseException):
    """The bound's next strokes, a second apart, should the model have caught the first
    (``except Exception``): past any handler of the model's, turned into a ConfigError."""


def _bounded_here() -> bool:
    """SIGALRM bounds a block only in the main thread, where the interval timer exists."""
    return threading.current_thread() is threading.main_thread() and hasattr(signal, "setitimer")


class _Strokes:
    """The SIGALRM handler: ``first(why)`` at the first stroke, StillLoading at the next ones
    (a model that caught the first); ``count`` set back to 0 starts again."""

    def __init__(self, first: type[ConfigError], why: str):
        self.first, self.why, self.count = first, why, 0

    def __call__(self, signum: int, frame: object) -> None:
        self.count += 1
        raise self.first(self.why) if self.count == 1 else StillLoading(self.why)


@contextmanager
def load_bound(
    seconds: float, what: str = "plant file", flag: str = "--load-timeout"
) -> Iterator[None]:
    """Raise LoadTimeout in the main thread if the block runs longer than ``seconds``;
    ``what``: the file being loaded, named where no loader's message names it."""
    if not _bounded_here():
        yield
        return

    why = f"still loading after {seconds:g} s ({flag}): a model's __init__ or reset() that blocks?"
    before = signal.signal(signal.SIGALRM, _Strokes(LoadTimeout, why))
    signal.setitimer(signal.ITIMER_REAL, seconds, 1.0)  # again every second until it ends
    try:
        yield
    except StillLoading:
        raise LoadTimeout(f"{what}: {why}") from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, before)


class CallTimeout(ConfigError):
    """One call of a model's reset() or step() did not return within the bound."""


@contextmanager
def call_bound(seconds: float, flag: str = "--load-timeout") -> Iterator[Callable[[Any], None]]:
    """While the block runs (in the main thread), ``guard(process)`` bounds each later call of
    that model's ``reset()`` and ``step()`` to ``seconds`` of wall time: past it the call is
    interrupted with ``CallTimeout`` (the caller names it as the model's failure), and again
    every second should the model catch it. ``autotune model check`` of a model whose
    step() blocked (a device that never answers) never ended, silent (user trial). A call the
    model makes within one of its bounded calls (a step() that calls its own reset()) runs
    under the outer call's bound: it once set its own and cleared it as it returned, and the
    step() then blocked unbounded (a 30 s sleep past a 0.5 s bound was checked "ok": helper
    trial). A model whose methods cannot be replaced on the instance, and any model
    elsewhere, is not bound."""
    if not _bounded_here():
        yield lambda process: None
        return

    why = f"has not returned after {seconds:g} s ({flag}): a model that blocks?"
    expired = _Strokes(CallTimeout, why)
    busy = [False]  # a bounded call is running: a call within it keeps its bound

    def bounded(fn: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            if busy[0]:
                return fn(*args)
            expired.count = 0
            busy[0] = True
            signal.setitimer(signal.ITIMER_REAL, seconds, 1.0)
            try:
                return fn(*args)
            except StillLoading:  # past the model's own handler: its failure all the same
                raise CallTimeout(why) from None
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0.0)
                busy[0] = False

        return call

    def guard(process: Any) -> None:
        for name in ("reset", "step"):
            with contextlib.suppress(Exception):
                setattr(process, name, bounded(getattr(process, name)))

    # a load_bound within (a loop rebuilt) puts this handler back as it ends
    before = signal.signal(signal.SIGALRM, expired)
    try:
        yield guard
    except StillLoading:
        raise CallTimeout(f"a model's call {why}") from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, before)


class _CtrlC:
    """Whether ``watch_ctrl_c`` is on, and whether the user pressed Ctrl-C under it."""

    watching = False
    pressed = False


@contextmanager
def watch_ctrl_c() -> Iterator[None]:
    """While the block runs (in the main thread), a ``KeyboardInterrupt`` is the user's only
    when SIGINT came: any other one was raised by a model, and ``models_own`` takes it as the
    model's failure (``autotune model check`` ended "interrupted", exit 130, for a model that
    raised it in its step(): user trial)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def pressed(signum: int, frame: object) -> None:
        _CtrlC.pressed = True
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGINT, pressed)
    was = (_CtrlC.watching, _CtrlC.pressed)
    _CtrlC.watching, _CtrlC.pressed = True, False
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before if before is not None else signal.default_int_handler)
        _CtrlC.watching, _CtrlC.pressed = was


def models_own(err: BaseException) -> bool:
    """Whether ``err``, out of a call into a user's model, is the model's own failure, to be
    said on one line (a loop faulted, a file refused): anything it raised, ``BaseException``
    subclasses and ``SystemExit`` included (a class of ``BaseException`` passed every ``except
    Exception`` and left a loop unanswered, its advance never ended), except this bound's
    strokes and, in the main thread, ``KeyboardInterrupt`` (the user's Ctrl-C, there) — under
    ``watch_ctrl_c`` only one that SIGINT raised."""
    if isinstance(err, StillLoading):
        return False
    if isinstance(err, KeyboardInterrupt) and threading.current_thread() is threading.main_thread():
        return _CtrlC.watching and not _CtrlC.pressed
    return True
