"""The one driver: runs an experiment over a loop, whatever the loop is.

The loop is a ``LoopPort``: a source of samples that holds what it is told. The live tuner's
port speaks to the plant over the bus, the offline analysis's replays a recording (and holds
nothing), the benchmark's and the tests' step a model in the same process. The driver feeds
each sample to the experiment and, between batches, tells the loop what changed in its
demand; the experiment alone decides.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

from services.autotuner.identify.experiments import Band, Demand, Experiment, Identification
from shared.control.signals import Sample

S = TypeVar("S", bound=Sample)


class LoopPort(Protocol):
    """A loop as the driver sees it."""

    def samples(self, n: int, band: Band | None = None) -> Sequence[Sample]:
        """The next ``n`` samples, holding what was applied (fewer, or none, at the end of a
        record or of the time allowed); with ``band``, ending with the first sample whose PV
        or output leaves it (``Band.ends``): a loop in lockstep must not step past that one."""
        ...

    def apply(self, demand: Demand, before: Demand) -> None:
        """Hold ``demand`` from now on (called only when it differs from ``before``)."""
        ...

    def hold_time(self) -> float:
        """The sim time (s) from which the last applied demand holds (asked only by an
        experiment that ``needs_hold_time``)."""
        ...


def drive(
    experiment: Experiment,
    loop: LoopPort,
    held: Demand | None = None,
    max_chunk: int = 1,
    watch: Callable[[Sample], None] | None = None,
) -> Identification | None:
    """Run ``experiment`` on ``loop`` until it finishes or the loop has no more samples;
    return its findings (None if it has none: ``experiment.reason`` says why).

    ``held``: what the loop holds at the start (default: what the experiment starts from).
    Samples come in batches of ``experiment.horizon(max_chunk)``, each ending early where
    the PV leaves the experiment's ``band`` (a relay's half-cycle in one batch, ending at the
    sample that switches it); only the demand after a batch's last sample is applied, and once
    it has finished only its ``closing`` demand, before its findings are computed. ``watch``
    is called after each batch, its demand applied, with the last sample fed."""
    held = experiment.demand if held is None else held
    while not experiment.finished:
        n = experiment.horizon(max_chunk)
        band = experiment.band() if n > 1 else None
        batch = loop.samples(n) if band is None else loop.samples(n, band)
        if not batch:
            break
        want, last = held, batch[0]
        for s in batch:
            want, last = experiment.feed(s), s
            if experiment.finished:
                break
        if not experiment.finished and want != held:
            loop.apply(want, held)
            held = want
            if experiment.needs_hold_time:
                experiment.held(loop.hold_time())
        if watch is not None:
            watch(last)
    closing = experiment.closing if experiment.finished else None
    if closing is not None and closing != held:  # before the findings' seconds of work
        loop.apply(closing, held)
    return experiment.identification()


def until_band(step: Callable[[], S], n: int, band: Band | None) -> list[S]:
    """``n`` samples from ``step``, ending with the first whose PV leaves ``band`` (None: all
    ``n``): a port's batch as the driver asks for it."""
    out: list[S] = []
    ends = band.end_test() if band is not None else None
    for _ in range(n):
        out.append(step())
        if ends is not None and ends(out[-1].pv, out[-1].op):
            break
    return out
