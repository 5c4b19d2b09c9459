"""A fast oscillation in a verification that the process model does not have.

The rules' margins (Ms, gain margin) are the identified model's. A model fitted to the loop's
slow response leaves out a lightly damped mode well above its bandwidth, and a derivative's
gain there can take that mode's damping away. Seen: 100·e^{−s}/(5s³ + 2s² + 501s + 100),
about a 5 s lag with a resonance at 10 rad/s (ζ 0.01), tuned from a step test's FOPDT. AMIGO PID
was predicted at Ms 1.45, gain margin 3.3; on the plant it is Ms 26, gain margin 1.05. Its
setpoint step rang at 0.72 s, 0.96 of its amplitude kept each period, but `ringing` smooths a
response over a twelfth of the loop's time scale (9 s), so it could not see that mode, and the
run ended `ok`.

Here the verification's setpoint step is compared with the model's own response to it: the
same gains, the loop's sample time, the PID block's equations (``setpoint_step``). The
residual holds what the model does not: its slow misfit, the noise, and any unmodelled mode.
An oscillation in it that stands out of the noise (``ringing``, the residual smoothed over a
twelfth of a third of the time scale: unsmoothed, the noise's own turning points made every
verification fit a sinusoid to noise, 0.2 s a verification) counts only if it is fast, its
period under ``1/FAST`` of the loop's time scale. A slower one is the loop's own mode, read
off the response itself by ``ringing``; in a residual it is mostly the model's misfit (seen:
a SOPDT on a third-order lag, an IPDT on an inverse response). It cannot tell a mode the
gains took damping from from the process's own, which any gains leave ringing (TL PI from a
relay on the plant above: 0.94 a period, as open loop): both fail the verification.
"""

from __future__ import annotations

import math

import numpy as np

from services.autotuner.design.ringing import Ringing, ringing
from shared.control.forms import IsaGains
from shared.control.lti import discretize, tf_to_ss
from shared.control.setpoint_steps import setpoint_step
from shared.control.transfer import DelayedTF

FAST = 3.0  # a mode counts if its period is under 1/FAST of the loop's time scale
# the residual is read over its first WINDOW time scales: a mode that counts (a period under
# a third of one) shows six periods there, and one that decays by less than the decay ratio
# limit is at its clearest; the model's simulation is most of the check's cost (read over the
# whole step, unsmoothed, the heat exchanger's verification in process took 66 µs a sample,
# against 9.5 without the check)
WINDOW = 2.0
BLOWN = 1e6  # the model's loop past this many steps: unstable on the model, judged elsewhere


def model_step(
    gains: IsaGains,
    model: DelayedTF,
    sample_time: float,
    samples: int,
    n: float = 10.0,
    step: float = 1.0,
) -> np.ndarray | None:
    """The model's closed-loop response to a unit setpoint step under ``gains``, one value a
    sample as the loop reports them after the step: the first is still 0 (that sample's PV is
    measured before its PID execution sees the new setpoint), the PID block at
    ``sample_time``, its derivative filter Td/``n``. None where the model's loop is
    unstable or cannot be simulated. The model's gain is taken positive: the loop's action
    makes the feedback negative either way. ``step``: the step's size, PV units, the response
    still given per unit of it (the PID block's output limits, 0–100 % about a 50 % rest,
    bound a unit step of a level loop's Kc of 1,800 %/m, not its verification's 0.018 m)."""
    num = np.trim_zeros(np.asarray(model.num, dtype=float), "f")
    den = np.trim_zeros(np.asarray(model.den, dtype=float), "f")
    if num.size == 0 or den.size == 0:
        return None
    last = den[np.nonzero(den)[0][-1]]  # an integrator's den ends in 0: its gain's sign
    if num[-1] * last < 0:
        num = -num
    try:
        system = discretize(*tf_to_ss(list(num), list(den)), sample_time, model.delay)
        y = setpoint_step(gains, system, max(samples - 1, 0), step, BLOWN, n=n)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None
    return None if y is None else np.concatenate(([0.0], y))[:samples]


def unmodelled_mode(
    t: np.ndarray,
    y: np.ndarray,
    y0: float,
    step: float,
    gains: IsaGains,
    model: DelayedTF | None,
    sample_time: float,
    noise: float,
    timescale: float,
    n: float = 10.0,
) -> Ringing | None:
    """The fast mode in a setpoint step's response (``t`` s and ``y`` PV units, a sample each
    from the step on; ``y0`` where it started, ``step`` its size, PV units) that the model's
    response to the same step lacks (``gains`` with the derivative filter Td/``n``); None
    without a model, or none that stands out."""
    if model is None or y.size < 16 or not (timescale > 0 and math.isfinite(timescale)):
        return None
    read = max(64, math.ceil(WINDOW * timescale / sample_time))  # samples
    t, y = np.asarray(t, dtype=float)[:read], np.asarray(y, dtype=float)[:read]
    predicted = model_step(gains, model, sample_time, y.size, n, step)
    if predicted is None:
        return None
    residual = y - (y0 + step * predicted)
    mode = ringing(t, residual, noise, timescale / FAST)
    return mode if mode is not None and mode.period < timescale / FAST else None
