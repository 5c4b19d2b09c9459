"""A lockstep advance of one linear loop in a tight loop: ``SimLoop.advance`` many times over,
the same samples to the bit, at a fraction of the cost per sample (about 3 µs against 7).

``SimLoop.advance`` goes through the model's ``step``, the transmitter's ``_measure`` and the
PID block's ``update`` (or ``track``) once per sample: attribute look-ups, a dataclass per
execution and a random draw per call are most of its time. Here, for a plain linear model
(``TransferFunctionModel`` with the class's own stepping), the same floating-point operations
in the same order run on local variables: the state update is the very same ``Φ @ x`` as
``DelayedLinearSystem.step``'s (numpy's product, whose rounding no loop over floats
matches), the block's products of its settings are formed once as ``PidBlock`` forms them,
and the noise of the whole advance is drawn at once (a generator's draws in one call equal
its draws one by one; the draws of samples an advance does not reach are put back). The
loop's objects hold the state again when it returns. The samples come as plain dicts of a
ProcessSample's fields: the plant's own values, encoded for the bus as they are
(``wire.encode_samples``), made ProcessSamples only in process.

A value that is not finite (the model's PV, the block's output) is left to ``SimLoop``: the
sample that would give it is stepped there, which faults the loop exactly as always.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

from services.plant_sim.simulation.models import TransferFunctionModel
from shared.control.pid import PidTerms

if TYPE_CHECKING:
    from services.plant_sim.simulation.loop import SimLoop

# the methods a linear model's class must not override to be stepped as ours
_LINEAR_METHODS = ("reset", "step", "disturbance_names", "set_disturbance")


def plain_linear(process: object) -> bool:
    """A plain linear model: a ``TransferFunctionModel`` whose class steps it as ours does
    (a user's subclass that overrides its stepping is stepped by its own methods)."""
    cls = type(process)
    return isinstance(process, TransferFunctionModel) and all(
        getattr(cls, m) is getattr(TransferFunctionModel, m) for m in _LINEAR_METHODS
    )


def steppable(loop: SimLoop) -> bool:
    """A loop whose model is a plain linear one, not faulted."""
    return loop.fault is None and loop.plain_linear


def advance(
    loop: SimLoop, steps: int, stops_at: Callable[[float, float], bool] | None
) -> list[dict]:
    """``steps`` periods of a ``steppable`` loop as ``SimLoop.advance_many`` does them, ending
    after the first sample ``stops_at`` names; the samples in order, each as the dict of a
    ProcessSample's fields (``SimLoop.advance_rows``)."""
    proc = loop.process
    sysm = proc._sys
    settings = loop.settings
    pid = loop.pid
    g = pid.gains
    loop_id, mode, ts = settings.loop_id, pid.mode, loop.sample_time
    auto = mode == "auto"
    op0, load, pv0 = proc.op0, proc.load, proc.pv0
    line, n = sysm._inputs, sysm._n
    phi, g_new, g_old, c, d = sysm._phi, sysm._g_new, sysm._g_old, sysm._c, sysm._d
    order = sysm.sys.order
    x = sysm._x
    lo_pv, hi_pv = settings.pv_range
    lo, hi = pid.op_limits
    sigma = settings.noise_std
    rng = loop._rng
    if sigma > 0:
        before = rng.bit_generator.state
        noise = rng.standard_normal(steps).tolist()
    # the block's products of its settings, formed as PidBlock forms them
    tf = g.td / g.n
    keep, span = tf / (tf + ts), tf + ts
    p_gain = pid.sign * g.kc
    d_gain = -pid.sign * g.kc * g.td
    beta = g.beta
    p_off = p_gain * (beta - 1.0)  # × sp: P at zero error, which I's bounds leave room for
    integral = g.ti is not None
    i_gain = pid.sign * g.kc * ts / g.ti if integral else 0.0
    track_sp = settings.sp_track
    seq, sp, op = loop.seq, loop.sp, pid.op
    dpv, pv_prev = pid._dpv, pid._pv_prev
    terms = pid.terms
    p, i, dd = terms.p, terms.i, terms.d
    out: list[dict] = []
    left = None  # a sample whose value is not finite: stepped by the SimLoop
    for k in range(steps):
        line.appendleft(op - op0 + load)
        u_new = line[n]
        if order:
            x_next = phi @ x + g_new * u_new
            if g_old is not None:
                x_next = x_next + g_old * line[n + 1]
            y = float(c @ x_next) + d * u_new
        else:
            x_next = x
            y = 0.0 + d * u_new
        pv_true = pv0 + y
        if not math.isfinite(pv_true):
            line.popleft()
            left = k
            break
        pv = pv_true
        if sigma > 0:
            pv += sigma * noise[k]
        pv = min(max(pv, lo_pv), hi_pv)
        rate = 0.0 if pv_prev is None else keep * dpv + (pv - pv_prev) / span
        if auto:
            pp = p_gain * (beta * sp - pv)
            pd = d_gain * rate
            v = pp + i + pd
            u = min(max(v, lo), hi)
            if not math.isfinite(u):
                line.popleft()
                left = k
                break
            p, dd = pp, pd
            if integral:
                step = i_gain * (sp - pv)
                if not ((v >= hi and step > 0) or (v <= lo and step < 0)):
                    off = p_off * sp
                    i_next = i + step
                    if step > 0 and i_next > hi - off:
                        i_next = max(i, hi - off)
                    elif step < 0 and i_next < lo - off:
                        i_next = min(i, lo - off)
                    i = i_next
            op = u
        else:
            if track_sp:
                sp = pv
            op = min(max(op, lo), hi)
        x, dpv, pv_prev = x_next, rate, pv
        seq += 1
        out.append(
            {"loop": loop_id, "seq": seq, "t": seq * ts, "pv": pv, "sp": sp, "op": op, "mode": mode}
        )
        if stops_at is not None and stops_at(pv, op):
            break
    if sigma > 0 and len(out) < steps:  # the draws of samples not stepped go back
        rng.bit_generator.state = before
        if out:
            rng.standard_normal(len(out))
    sysm._x = x
    if out:
        loop.seq, loop.sp, loop.pv = seq, sp, out[-1]["pv"]
        pid.op, pid._dpv, pid._pv_prev = op, dpv, pv_prev
        if auto:
            pid.terms = PidTerms(p, i, dd)
    if left is not None:  # stepped as always: the loop faults there, the rest held
        out += [s.model_dump() for s in loop.advance_slowly(steps - left, stops_at)]
    return out
