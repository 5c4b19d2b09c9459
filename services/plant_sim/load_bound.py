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
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
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


class ModelTooSlow(ConfigError):
    """A model's calls in one check would take, or took, longer together than the bound."""


MODEL_TIME = 600.0  # s of wall time a check may spend in one loop's model, all its calls
clock = time.monotonic  # what the bound on all its calls reads (a test's stand-in)


@dataclass
class _Spent:
    """Wall time spent in one loop's model so far, and over how many calls."""

    seconds: float = 0.0
    calls: int = 0


def _duration(seconds: float) -> str:
    """``seconds`` as a person reads it: 45 s, 17 min, 2.3 h."""
    if seconds < 120.0:
        return f"{seconds:.3g} s"
    if seconds < 7200.0:
        return f"{seconds / 60.0:.3g} min"
    return f"{seconds / 3600.0:.3g} h"


def _allow(seconds: float) -> str:
    """A ``--model-time`` that would allow ``seconds``: rounded up to two figures."""
    digits = 10.0 ** max(math.floor(math.log10(max(seconds, 1.0))) - 1, 0)
    return f"{math.ceil(seconds / digits) * digits:g}"


class CallBound:
    """What ``call_bound`` yields: ``guard(process, key, model)`` bounds that model's calls
    (``key``: its loop, whose budget a model rebuilt for it shares); ``pace(key)``: the
    check's look ahead for that loop (``calls`` it still needs → a refusal, or None)."""

    def __init__(self, guard: Callable[[Any, str, str], None], pace: Callable[[str], Any]):
        self.guard, self.pace = guard, pace


@contextmanager
def call_bound(
    seconds: float,
    flag: str = "--load-timeout",
    total: float = MODEL_TIME,
    total_flag: str = "--model-time",
) -> Iterator[CallBound]:
    """While the block runs (in the main thread), ``guard(process, key, model)`` bounds each
    later call of that model's ``reset()`` and ``step()`` to ``seconds`` of wall time, and
    all its calls together (with any model guarded under the same ``key``) to ``total``:
    past either the call is interrupted (``CallTimeout``, ``ModelTooSlow``; the caller names
    it as the model's failure), and again every second should the model catch it.
    ``autotune model check`` of a model whose step() blocked (a device that never answers)
    never ended, silent (user trial), and of one whose step() slept 50 ms took 143 s for a
    5 s lag at 0.1 s samples, 2.3 h for a 300 s one (helper trial). A call the model makes
    within one of its bounded calls (a step() that calls its own reset()) runs under the
    outer call's bound: it once set its own and cleared it as it returned, and the step()
    then blocked unbounded. ``pace(key)(calls)``: a one-line refusal where ``calls`` more
    at the cost per call measured so far would take the key's calls past ``total``, else
    None. A model whose methods cannot be replaced on the instance, and any model elsewhere,
    is not bound."""
    if not _bounded_here():
        yield CallBound(lambda process, key, model: None, lambda key: None)
        return

    why = f"has not returned after {seconds:g} s ({flag}): a model that blocks?"
    expired = _Strokes(CallTimeout, why)
    spent: dict[str, _Spent] = {}
    names: dict[str, str] = {}
    busy = [False]  # a bounded call is running: a call within it keeps its bound

    def too_slow(key: str, calls: int, before: float = 0.0, last: float = 0.0) -> str:
        """``last``: s the latest call has run, not returned; ``before``: s the calls before
        it took. A call that ran most of the bound is said as one, not averaged: a blocked
        fifth call read "5 calls (1e+03 ms a call)" (helper review)."""
        pace = (
            f"{calls - 1:,} of them took {before:.3g} s, then one ran {last:.3g} s and had not "
            "returned"
            if calls > 1 and last > 0.5 * total
            else f"{1e3 * total / calls:.3g} ms a call"
        )
        return (
            f"{names[key]} has taken {total:g} s of wall time in {calls:,} calls of this check "
            f"({pace}), its bound ({total_flag} {total:g}), and "
            f"the check is not done: {_HOW}, or allow it with a longer {total_flag}"
        )

    def bounded(fn: Callable[..., Any], key: str) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            if busy[0]:
                return fn(*args)
            s = spent[key]
            left = total - s.seconds
            if left <= 0.0:  # the last call ended past it, before the stroke
                raise ModelTooSlow(too_slow(key, s.calls))
            if left < seconds:  # the bound on all its calls comes first: said as of then
                expired.first = ModelTooSlow
                expired.why = too_slow(key, s.calls + 1, s.seconds, left)
            else:
                expired.first, expired.why = CallTimeout, why
            expired.count = 0
            busy[0] = True
            start = clock()
            signal.setitimer(signal.ITIMER_REAL, min(seconds, left), 1.0)
            try:
                return fn(*args)
            except StillLoading:  # past the model's own handler: its failure all the same
                raise expired.first(expired.why) from None
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0.0)
                busy[0] = False
                s.seconds += clock() - start
                s.calls += 1

        return call

    def guard(process: Any, key: str, model: str) -> None:
        spent.setdefault(key, _Spent())
        names[key] = model
        for name in ("reset", "step"):
            with contextlib.suppress(Exception):
                setattr(process, name, bounded(getattr(process, name), key))

    def pace(key: str) -> Callable[[int], str | None] | None:
        if key not in spent:
            return None

        def ahead(calls: int) -> str | None:
            s = spent[key]
            if s.calls == 0:
                return None
            cost = s.seconds / s.calls
            if s.seconds + calls * cost <= total:
                return None
            return (
                f"{names[key]} takes {_ms(s)} a call (measured over {s.calls:,} calls): the "
                f"check needs some {calls:,} more at least, {_duration(calls * cost)}, past its "
                f"bound on the model's time ({total_flag} {total:g}; {s.seconds:.3g} s spent): "
                f"{_HOW}, or allow it with {total_flag} {_allow(s.seconds + calls * cost)} or "
                "more"
            )

        return ahead

    # a load_bound within (a loop rebuilt) puts this handler back as it ends
    before = signal.signal(signal.SIGALRM, expired)
    try:
        yield CallBound(guard, pace)
    except StillLoading:
        if expired.first is CallTimeout:
            raise CallTimeout(f"a model's call {why}") from None
        raise ModelTooSlow(expired.why) from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, before)


_HOW = "give the loop a longer sample_time (fewer samples to the same response), a faster model"


def _ms(s: _Spent) -> str:
    """The mean wall time of a call."""
    return f"{1e3 * s.seconds / s.calls:.3g} ms" if s.calls else "—"


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
