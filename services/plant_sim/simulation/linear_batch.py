"""Many linear loops of one sample time stepped together: one vectorised update per period.

A ``LinearBatch`` holds, as arrays over its loops, exactly what ``SimLoop.advance`` changes
for a linear model (``TransferFunctionModel`` and the presets built on it): the state x, the
input delay line, the measured PV, the PID block's state, the held output and the sample
count. One ``tick`` does for every loop what ``SimLoop.advance(held_op)`` does for one, in the
same floating-point operations in the same order (the state update is a stacked ``matmul``,
the same BLAS call per loop as ``Φ @ x``), so each loop's samples equal the per-loop
stepping's to the bit. Noise is drawn from each loop's own generator, as before.

The loop objects stay the truth for everything else (settings, gains, commands): before a
command touches a loop its state is written back into its ``SimLoop`` (``export``) and read
again afterwards (``load``). A loop whose model or PID block fails (a value that is not
finite) is handed back to its ``SimLoop`` faulted, exactly as the per-loop stepping faults it,
and leaves the batch.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from services.plant_sim.simulation.linear_steps import steppable
from services.plant_sim.simulation.loop import SimLoop
from shared.control.pid import PidTerms
from shared.control.pid_batch import PidGainArrays, execute, filtered_rate


def batchable(loop: SimLoop) -> bool:
    """A loop whose model is a plain linear one (the class's stepping is ours) and not faulted."""
    return steppable(loop)


def line_width(delay_samples: int) -> int:
    """Columns of the ring that holds a delay line of ``delay_samples`` whole samples: at
    least n + 3 (the line's n + 2 values survive one write), rounded up to a power of two so
    that loops of similar dead time share a batch."""
    return 1 << (delay_samples + 2).bit_length()


def batch_key(loop: SimLoop) -> tuple[float, int, int]:
    """Loops with equal keys can share a batch: sample time (s), model order, ring width."""
    sys = loop.process.discrete
    return (loop.sample_time, sys.order, line_width(sys.delay_samples))


class LinearBatch:
    """The loops (all ``batchable``, one ``batch_key``) stepped as arrays."""

    def __init__(self, loops: list[SimLoop]):
        if not loops:
            raise ValueError("a batch needs at least one loop")
        keys = {batch_key(lp) for lp in loops}
        if len(keys) != 1 or not all(batchable(lp) for lp in loops):
            raise ValueError("a batch takes linear loops of one sample time, order and width")
        self.loops = list(loops)
        self.ids = [lp.settings.loop_id for lp in loops]
        self.sample_time, order, self.width = keys.pop()
        n = len(loops)
        systems = [lp.process.discrete for lp in loops]
        self.phi = np.array([s.phi for s in systems]).reshape(n, order, order)
        self.g_new = np.array([s.gamma_new[:, 0] for s in systems]).reshape(n, order)
        self.g_old = np.array([s.gamma_old[:, 0] for s in systems]).reshape(n, order)
        self.c = np.array([s.c[0] for s in systems]).reshape(n, 1, order)
        self.d = np.array([s.d for s in systems])
        self.delay = np.array([s.delay_samples for s in systems], dtype=np.int64)
        self.pv0 = np.array([lp.process.pv0 for lp in loops])
        self.op0 = np.array([lp.process.op0 for lp in loops])
        self.noise_std = np.array([lp.settings.noise_std for lp in loops])
        self.noisy = np.flatnonzero(self.noise_std > 0)
        self.pv_lo = np.array([lp.settings.pv_range[0] for lp in loops])
        self.pv_hi = np.array([lp.settings.pv_range[1] for lp in loops])
        self.op_lo = np.array([lp.pid.op_limits[0] for lp in loops])
        self.op_hi = np.array([lp.pid.op_limits[1] for lp in loops])
        self.sign = np.array([lp.pid.sign for lp in loops])
        self.sp_track = np.array([lp.settings.sp_track for lp in loops])
        self.rows = np.arange(n)
        self.pos = 0  # the ring's column holding the newest input
        self.x = np.zeros((n, order))
        self.ring = np.zeros((n, self.width))
        self.seq = np.zeros(n, dtype=np.int64)  # samples since the start
        self.pv = np.zeros(n)  # measured PV (PV units)
        self.sp = np.zeros(n)  # setpoint (PV units)
        self.op = np.zeros(n)  # the PID block's output now (%)
        self.held = np.zeros(n)  # the output latched at the last tick, held over this one (%)
        self.load = np.zeros(n)  # the load disturbance (% of output)
        # the PID block's state: terms (%), filtered dPV/dt (PV units/s), last PV
        self.p, self.i, self.dd = np.zeros(n), np.zeros(n), np.zeros(n)
        self.dpv, self.pv_prev = np.zeros(n), np.zeros(n)
        self.has_prev = np.zeros(n, dtype=bool)
        self.auto = np.zeros(n, dtype=bool)
        # its gains: Kc (% per PV unit), Ti, Td, Tf = Td/N (s), β; ``integral``: Ti given
        self.kc, self.ti, self.td = np.zeros(n), np.ones(n), np.zeros(n)
        self.tf, self.beta = np.zeros(n), np.ones(n)
        self.integral = np.zeros(n, dtype=bool)
        # the same arrays, as the shared block arithmetic takes them (``load_loop`` writes
        # their elements in place)
        self.gains = PidGainArrays(
            self.sign,
            self.kc,
            self.ti,
            self.td,
            self.tf,
            self.beta,
            self.integral,
            self.op_lo,
            self.op_hi,
            self.sample_time,
        )
        self.active = np.ones(n, dtype=bool)  # False: faulted, stepped by its SimLoop
        for j in range(n):
            self.load_loop(j)
            self.held[j] = self.op[j]

    # --- the bridge to the loop objects ---------------------------------------------------

    def load_loop(self, j: int) -> None:
        """Read loop ``j``'s state from its SimLoop (after a command changed it)."""
        lp = self.loops[j]
        sysm = lp.process._sys
        self.x[j] = sysm._x
        line = sysm._inputs  # line[k]: the input k periods before the newest
        for k, u in enumerate(line):
            self.ring[j, (self.pos - k) % self.width] = u
        self.load[j] = lp.process.load
        self.seq[j], self.pv[j], self.sp[j] = lp.seq, lp.pv, lp.sp
        pid = lp.pid
        self.op[j], self.auto[j] = pid.op, pid.mode == "auto"
        self.p[j], self.i[j], self.dd[j] = pid.terms.p, pid.terms.i, pid.terms.d
        self.dpv[j] = pid._dpv
        self.has_prev[j] = pid._pv_prev is not None
        self.pv_prev[j] = pid._pv_prev if pid._pv_prev is not None else 0.0
        g = pid.gains
        self.kc[j], self.td[j], self.beta[j] = g.kc, g.td, g.beta
        self.tf[j] = g.td / g.n
        self.integral[j] = g.ti is not None
        self.ti[j] = g.ti if g.ti is not None else 1.0

    def export(self, j: int) -> SimLoop:
        """Write loop ``j``'s state into its SimLoop, which is then exact; return it."""
        lp = self.loops[j]
        if not self.active[j]:
            return lp
        sysm = lp.process._sys
        sysm._x = self.x[j].copy()
        n = len(sysm._inputs)
        sysm._inputs = deque(
            (float(self.ring[j, (self.pos - k) % self.width]) for k in range(n)), maxlen=n
        )
        lp.process.load = float(self.load[j])
        lp.seq, lp.pv, lp.sp = int(self.seq[j]), float(self.pv[j]), float(self.sp[j])
        pid = lp.pid
        pid.op, pid.mode = float(self.op[j]), "auto" if self.auto[j] else "manual"
        pid.terms = PidTerms(float(self.p[j]), float(self.i[j]), float(self.dd[j]))
        pid._dpv = float(self.dpv[j])
        pid._pv_prev = float(self.pv_prev[j]) if self.has_prev[j] else None
        return lp

    def time(self, j: int) -> float:
        """Sim time of loop ``j``'s current sample, s."""
        if not self.active[j]:
            return self.loops[j].t
        return int(self.seq[j]) * self.sample_time

    # --- one period -----------------------------------------------------------------------

    def tick(self) -> list[int]:
        """Advance every active loop one period, as ``SimLoop.advance(held)`` does; return
        the loops that faulted (now held by their SimLoop, out of the batch)."""
        with np.errstate(all="ignore"):  # a value that is not finite is judged, not printed
            return self._tick()

    def _tick(self) -> list[int]:
        w = self.width
        pos = (self.pos + 1) % w
        u = self.held - self.op0 + self.load
        self.ring[:, pos] = u
        late = (pos - self.delay) % w
        u_new = self.ring[self.rows, late]
        u_old = self.ring[self.rows, (late - 1) % w]
        x = np.matmul(self.phi, self.x[:, :, None])[:, :, 0]
        x = x + self.g_new * u_new[:, None] + self.g_old * u_old[:, None]
        y = np.matmul(self.c, x[:, :, None])[:, 0, 0] if x.shape[1] else np.zeros(len(u))
        pv_true = self.pv0 + (y + self.d * u_new)
        model_ok = np.isfinite(pv_true)
        failed = [int(j) for j in np.flatnonzero(~model_ok & self.active)]
        for j in failed:  # the per-loop stepping faults it, from the state before this tick
            self.export(j)  # the column just written is not in its line (width ≥ n + 3)
            self.active[j] = False
            self.loops[j].advance(float(self.held[j]))
        self.pos = pos
        go = self.active.copy()
        self.x = np.where(go[:, None], x, self.x)
        self.seq = self.seq + go
        pv = pv_true.copy()
        if self.noisy.size:
            draw = [j for j in self.noisy if go[j]]
            z = np.array([self.loops[j]._rng.standard_normal() for j in draw])
            if draw:
                pv[draw] = pv[draw] + self.noise_std[draw] * z
        pv = np.minimum(np.maximum(pv, self.pv_lo), self.pv_hi)
        self.pv = np.where(go, pv, self.pv)
        faulted = self._pid(go)
        return failed + faulted

    def _pid(self, go: np.ndarray) -> list[int]:
        """The PID blocks' execution (auto) or tracking (manual), as ``PidBlock`` does it."""
        pv = self.pv
        dpv = filtered_rate(self.gains, self.dpv, pv, self.pv_prev, self.has_prev)
        self.dpv = np.where(go, dpv, self.dpv)
        self.pv_prev = np.where(go, pv, self.pv_prev)
        self.has_prev = self.has_prev | go
        auto = self.auto & go
        manual = ~self.auto & go
        # manual: setpoint tracking, the output held (clamped)
        self.sp = np.where(manual & self.sp_track, pv, self.sp)
        run = execute(self.gains, self.sp, pv, self.i, self.dpv)
        self.p = np.where(auto, run.p, self.p)
        self.dd = np.where(auto, run.d, self.dd)
        self.i = np.where(auto, run.i_next, self.i)
        held = np.minimum(np.maximum(self.op, self.op_lo), self.op_hi)
        self.op = np.where(go, np.where(auto, run.op, held), self.op)
        faulted = [int(j) for j in np.flatnonzero(auto & ~np.isfinite(self.op))]
        for j in faulted:  # the PID block's output overflowed: as SimLoop.advance faults it
            held = float(self.held[j])
            lp = self.export(j)
            self.active[j] = False
            g = lp.pid.gains
            lp._set_fault(
                f"the PID block's output became {lp.pid.op} (Kc {g.kc:g}, Ti {g.ti}, "
                f"Td {g.td:g}: gains out of all proportion to the PV range)",
                held,
                lp.t,
            )
        self.held = np.where(go, self.op, self.held)
        return faulted
