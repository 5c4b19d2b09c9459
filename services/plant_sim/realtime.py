"""The realtime clock's stepping: loops grouped by sample time, linear ones stepped as arrays.

Every loop of one sample time is due at the same instants (k·T/speed after the start), so
they advance together: the linear loops in batches (``LinearBatch``: one vectorised update
per batch), the others (physical models, FMUs, user classes, faulted loops) one by one through
their ``SimLoop``. Each tick gives the samples as ready JSON payloads, one per loop: the
per-loop ``pv`` keys carry every sample, without building a pydantic model per sample.

The batches hold the state of their loops between ticks; ``check_out`` makes a loop's
``SimLoop`` exact before anything reads or changes it (a command, a status, a lease's
restore) and ``check_in`` takes the changes back (``release`` when it was only read). The
caller holds one lock over all of them and over ``tick``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from services.plant_sim.simulation.linear_batch import LinearBatch, batch_key, batchable
from services.plant_sim.simulation.loop import SimLoop
from shared import wire
from shared.messages import ProcessSample

# A JSON object the same as ProcessSample.model_dump_json()'s up to number formatting
# (Python's shortest round-trip repr: the same float on decoding).
_SAMPLE = '"seq":{},"t":{!r},"pv":{!r},"sp":{!r},"op":{!r},"mode":"{}"}}'


def sample_head(loop_id: str) -> str:
    """The start of every sample payload of ``loop_id`` (ids are JSON-safe by their pattern)."""
    return '{"loop":' + json.dumps(loop_id) + ","


def sample_json(
    head: str, seq: int, t: float, pv: float, sp: float, op: float, auto: bool
) -> bytes:
    """One ProcessSample payload: ``head`` from ``sample_head``, then the sample's fields."""
    return (head + _SAMPLE.format(seq, t, pv, sp, op, "auto" if auto else "manual")).encode()


@dataclass
class Group:
    """The loops of one sample time: batches of linear loops, and the rest one by one."""

    sample_time: float
    batches: list[LinearBatch] = field(default_factory=list)
    singles: list[SimLoop] = field(default_factory=list)
    held: dict[str, float] = field(default_factory=dict)  # singles' output latched at a tick

    @property
    def size(self) -> int:
        return sum(len(b.loops) for b in self.batches) + len(self.singles)


@dataclass
class Tick:
    """What one tick produced: (loop id, payload) per loop, and the loops that faulted."""

    samples: list[tuple[str, bytes]]
    faulted: list[SimLoop]


class RealtimeSteppers:
    """The loops of one plant process grouped for the realtime clock."""

    def __init__(self, loops: dict[str, SimLoop], batch: bool = True):
        self.loops = loops
        by_time: dict[float, Group] = {}
        linear: dict[tuple[float, int, int], list[SimLoop]] = {}
        for lp in loops.values():
            group = by_time.setdefault(lp.sample_time, Group(lp.sample_time))
            if batch and batchable(lp):
                linear.setdefault(batch_key(lp), []).append(lp)
            else:
                group.singles.append(lp)
                group.held[lp.settings.loop_id] = lp.op
        self._where: dict[str, tuple[LinearBatch, int]] = {}
        for key, members in linear.items():
            b = LinearBatch(members)
            by_time[key[0]].batches.append(b)
            for j, lid in enumerate(b.ids):
                self._where[lid] = (b, j)
        self.groups = list(by_time.values())
        self._heads = {lid: sample_head(lid) for lid in loops}
        self._out: set[str] = set()

    def check_out(self, loop_id: str) -> SimLoop:
        """The loop, its SimLoop made exact (held until ``check_in``)."""
        where = self._where.get(loop_id)
        if where is not None and loop_id not in self._out and where[0].active[where[1]]:
            where[0].export(where[1])
            self._out.add(loop_id)
        return self.loops[loop_id]

    def check_in(self) -> None:
        """Take back into the batches what commands changed in the loops checked out."""
        for lid in self._out:
            batch, j = self._where[lid]
            if batch.active[j]:
                batch.load_loop(j)
        self._out.clear()

    def release(self) -> None:
        """Forget the loops checked out only to be read (nothing to take back)."""
        self._out.clear()

    def latest(self, loop_id: str) -> float:
        """The PV of the loop's current sample, read where its state is held."""
        where = self._where.get(loop_id)
        if where is not None and loop_id not in self._out and where[0].active[where[1]]:
            return float(where[0].pv[where[1]])
        return self.loops[loop_id].pv

    def times(self) -> dict[str, float]:
        """Sim time of every loop's current sample, s."""
        out = {}
        for lid, lp in self.loops.items():
            where = self._where.get(lid)
            out[lid] = where[0].time(where[1]) if where is not None else lp.t
        return out

    def tick(self, group: Group) -> Tick:
        """Advance every loop of ``group`` one period (the output latched at its last tick)."""
        if self._out:
            self.check_in()
        samples: list[tuple[str, bytes]] = []
        faulted: list[SimLoop] = []
        left: list[SimLoop] = []  # faulted out of a batch: stepped one by one from now on
        for b in group.batches:
            for j in b.tick():
                lp = b.loops[j]
                faulted.append(lp)
                left.append(lp)
                group.held[b.ids[j]] = lp.op
                samples.append((b.ids[j], wire.encode(lp.sample())))
            live = b.active.nonzero()[0].tolist()
            seq, pv, sp, op, auto = (a.tolist() for a in (b.seq, b.pv, b.sp, b.op, b.auto))
            tt = (b.seq * b.sample_time).tolist()
            heads, ids = self._heads, b.ids
            samples += [
                (ids[j], sample_json(heads[ids[j]], seq[j], tt[j], pv[j], sp[j], op[j], auto[j]))
                for j in live
            ]
        for lp in group.singles:
            lid = lp.settings.loop_id
            had = lp.fault
            s: ProcessSample = lp.advance(group.held[lid])
            group.held[lid] = s.op
            if lp.fault and not had:
                faulted.append(lp)
            samples.append((lid, wire.encode(s)))
        group.singles += left
        return Tick(samples, faulted)
