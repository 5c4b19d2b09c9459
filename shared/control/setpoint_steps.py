"""Setpoint steps of many PID tunings closing one sampled plant, simulated together.

Each candidate's loop is the plant's own PID block (``pid``: ISA form, derivative on the
measurement through its filter Tf = Td/N, anti-windup, output limits 0–100 %) at rest at a
50 % output, closing the plant discretised exactly (``lti.discretize``), in deviations from
rest; at t = 0 its setpoint steps by that candidate's ``step``. All candidates advance
together, one array update per sample (``pid_batch``, and the plant's state as a stacked
``matmul``), in the same floating-point operations as ``PidBlock.update`` and
``DelayedLinearSystem.step`` stepped alone, so every sample equals theirs to the bit
(``tests/test_setpoint_steps.py``) — at a fraction of the cost: the tuner judges fifteen rules
at the end of every run, and the per-sample Python loop of each was most of its CPU time.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from shared.control.forms import IsaGains
from shared.control.lti import DelayedLinearSystem, DiscreteDelaySystem
from shared.control.pid import PidBlock, PidSettings
from shared.control.pid_batch import PidGainArrays, coefficients, execute, filtered_rate

REST_OP = 50.0  # % : the output at rest, 50 % from either limit
OP_LIMITS = (0.0, 100.0)  # %


def setpoint_steps(
    gains: Sequence[IsaGains],
    system: DiscreteDelaySystem,
    samples: int,
    steps: Sequence[float],
    limit: float,
    n: float = 10.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(y, blown): y[j, k] the PV (in units of ``steps[j]``) at the end of sample k of
    candidate j's loop (derivative filter N = ``n``); ``blown[j]`` True once its y left
    ±``limit`` or was not finite — the samples after that are not meaningful (a lone loop
    would have stopped there). The sample time is the ``system``'s. ValueError for gains a
    PID block refuses (``PidSettings``)."""
    settings = [PidSettings(kc=g.kc, ti=g.ti, td=g.td, n=n) for g in gains]
    count = len(settings)
    ts = system.sample_time
    ones = np.ones(count)
    g = PidGainArrays(
        sign=ones,
        kc=np.array([s.kc for s in settings]),
        ti=np.array([s.ti if s.ti is not None else 1.0 for s in settings]),
        td=np.array([s.td for s in settings]),
        tf=np.array([s.td / s.n for s in settings]),
        beta=np.array([s.beta for s in settings]),
        integral=np.array([s.ti is not None for s in settings], dtype=bool),
        lo=OP_LIMITS[0] * ones,
        hi=OP_LIMITS[1] * ones,
        sample_time=ts,
    )
    fixed = coefficients(g)  # the settings stay as they are over the whole step
    sp = np.asarray(steps, dtype=float).reshape(count)
    order, delay = system.order, system.delay_samples
    phi = np.broadcast_to(system.phi, (count, order, order))
    g_new, g_old = system.gamma_new[:, 0], system.gamma_old[:, 0]
    c = np.broadcast_to(system.c[0], (count, 1, order))
    width = delay + 2  # the inputs of the last n + 2 samples, newest at ``pos``
    ring = np.zeros((count, width))
    x = np.zeros((count, order))
    i = np.full(count, REST_OP)  # bumpless at rest: the integral term holds the output
    dpv = np.zeros(count)
    pv = np.zeros(count)
    pv_prev = np.zeros(count)
    has_prev = np.zeros(count, dtype=bool)  # a block's first sample has no rate yet
    after_first = np.ones(count, dtype=bool)
    y = np.empty((count, samples))
    blown = np.zeros(count, dtype=bool)
    with np.errstate(all="ignore"):  # a blown loop's values are judged, not printed
        for k in range(samples):
            dpv = filtered_rate(g, dpv, pv, pv_prev, has_prev, fixed)
            pv_prev, has_prev = pv, after_first
            run = execute(g, sp, pv, i, dpv, fixed)
            i = run.i_next
            pos = k % width
            ring[:, pos] = run.op - REST_OP
            u_new = ring[:, (pos - delay) % width]
            if order:
                u_old = ring[:, (pos - delay - 1) % width]
                x = np.matmul(phi, x[:, :, None])[:, :, 0] + g_new * u_new[:, None]
                x = x + g_old * u_old[:, None]
                out = np.matmul(c, x[:, :, None])[:, 0, 0]
            else:
                out = np.zeros(count)
            pv = out + system.d * u_new
            y[:, k] = pv / sp
            blown |= ~(np.abs(y[:, k]) <= limit)
            if blown.all():
                break
    return y, blown


def setpoint_step(
    gains: IsaGains,
    system: DiscreteDelaySystem,
    samples: int,
    step: float,
    limit: float,
    n: float = 10.0,
) -> np.ndarray | None:
    """One candidate's ``setpoint_steps``: y[k] the PV (in units of ``step``) at the end of
    sample k; None once it leaves ±``limit`` or is not finite. The plant's own blocks
    (``PidBlock``, ``DelayedLinearSystem``) stepped on scalars, the same samples to the bit: a
    fourteenth of the batch's cost for one candidate (its arrays of one element cost 64 µs a
    sample, most of a verification's time where it simulated the model's response to its
    step; these 4.5)."""
    plant = DelayedLinearSystem(system)
    settings = PidSettings(kc=gains.kc, ti=gains.ti, td=gains.td, n=n)
    pid = PidBlock(settings, system.sample_time, OP_LIMITS, mode="auto", op=REST_OP)
    y = np.empty(samples)
    pv = 0.0
    for k in range(samples):
        pv = plant.step(pid.update(step, pv) - REST_OP)
        y[k] = pv / step
        if not abs(y[k]) <= limit:
            return None
    return y
