"""How a pure step's independent parts are computed: ``parts([(fn, args), …])`` returns
``[fn(*args), …]`` in the calls' order.

A step with parts that do not depend on each other (the design's robustness and its
simulated steps; the ramp's models refined on the record) takes its ``parts`` as a value:
``in_turn`` here (the offline analysis, the benchmark, the tests), and in the tuner each part
in a worker process, all at once (``compute_pool.compute_all``). The parts are pure, so the
results are the same to the bit either way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

Calls = Sequence[tuple[Callable[..., Any], tuple]]
Parts = Callable[[Calls], list[Any]]


def in_turn(calls: Calls) -> list[Any]:
    """Each call in this thread, in order."""
    return [fn(*args) for fn, args in calls]
