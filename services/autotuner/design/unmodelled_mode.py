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
It is read two ways, the more lasting mode kept: as it is, by ``ringing`` (its fit started
from the turning points of the residual smoothed over a twelfth of a third of the time scale:
unsmoothed, the noise's own made every verification fit a sinusoid to noise), and on its fast
part (``fast_part``: less its moving average over a third of the time scale) from its
spectrum's tallest peak (``fast_mode``: where a mode rings under the noise, the turning
points are the noise's), where the mode counts if it stands out of the noise
(``ringing.stands_out``, at least LEAST of the step tall). Either counts only a fast mode, its
period under ``1/FAST`` of the loop's time scale. A slower one is the loop's own mode, read off the
response itself by ``ringing``; in a residual it is mostly the model's misfit (seen: a SOPDT
on a third-order lag, an IPDT on an inverse response).

This alone cannot tell a mode the gains took damping from from the process's own, which any
gains leave ringing (TL PI from a relay on the plant above: 0.94 a period, as open loop):
the verification's gain-margin check reads the same mode at twice the gain (``mode_near``),
where the first grows and the second still decays.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import savgol_filter

from services.autotuner.design.ringing import Ringing, ringing, stands_out
from services.autotuner.identify.oscillation import DecayingSine, Oscillation, levenberg_marquardt
from services.autotuner.parts import Parts, in_turn
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
# the least height of a mode, a share of the step (``ringing``'s ``least``: one under the
# noise's 4σ then counts where it lasts): the models' own misfit on noise-free loops, whose
# σ is ~0, rang 2e-6–5e-4 of the step in the residual (a big dead time, lags 100 times
# apart), a resonance under TL PI 0.04–0.14
LEAST = 0.01
SAME_MODE = 0.3  # a mode sought near a period is that mode within this share of it
QUIET = 0.3  # a mode read again at under this share of its amplitude does not ring there
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
    parts: Parts = in_turn,
) -> Ringing | None:
    """The fast mode in a setpoint step's response (``t`` s and ``y`` PV units, a sample each
    from the step on; ``y0`` where it started, ``step`` its size, PV units) that the model's
    response to the same step lacks (``gains`` with the derivative filter Td/``n``); None
    without a model, or none that stands out. ``parts``: how the residual's ringing fit
    computes its independent starts (``ringing``)."""
    if model is None or y.size < 16 or not (timescale > 0 and math.isfinite(timescale)):
        return None
    read = max(64, math.ceil(WINDOW * timescale / sample_time))  # samples
    t, y = np.asarray(t, dtype=float)[:read], np.asarray(y, dtype=float)[:read]
    predicted = model_step(gains, model, sample_time, y.size, n, step)
    if predicted is None:
        return None
    residual = y - (y0 + step * predicted)
    # read two ways, the more lasting kept: from the spectrum of the residual's fast part,
    # which finds a mode under the noise, and from the turning points of the residual as it
    # is, which found one on a noise-free loop (0.42 s, 0.94 a period) whose fast part's
    # tallest peak was elsewhere
    modes = (
        fast_mode(t, residual, noise, timescale, sample_time, step),
        ringing(t, residual, noise, timescale / FAST, parts=parts),
    )
    fast = [m for m in modes if m is not None and m.period < timescale / FAST]
    return max(fast, key=lambda m: m.decay, default=None)


def fast_mode(
    t: np.ndarray,
    y: np.ndarray,
    noise: float,
    timescale: float,
    sample_time: float,
    step: float,
) -> Ringing | None:
    """The oscillatory mode of record (``t`` s, ``y`` PV units) whose period is under
    1/FAST of the loop's ``timescale`` (s), read on the record's fast part (``fast_part``)
    from its spectrum's tallest peak there, at least LEAST of ``step`` (PV units) tall; None:
    none that stands out. Why the spectrum: a fit started from the record's turning points
    starts from the noise's where a mode rings under it (``mode_near``)."""
    t, y = fast_part(t, y, max(3, round(timescale / FAST / sample_time)))
    if t.size < 16 or not np.all(np.isfinite(y)):
        return None
    size = 8 * (1 << (t.size - 1).bit_length())  # zero-padded: the peak to 1/8 of a bin
    power = np.abs(np.fft.rfft(y - y.mean(), size))
    freq = np.fft.rfftfreq(size, sample_time)
    fast = (freq > FAST / timescale) & (freq < 0.4 / sample_time)  # under 2.5 samples: none
    if not fast.any():
        return None
    peak = float(freq[fast][np.argmax(power[fast])])
    mode = _fit_near(t, y, noise, 1.0 / peak, LEAST * abs(step))
    return mode if mode is not None and mode.period < timescale / FAST else None


def fast_part(t: np.ndarray, y: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """``y`` less its centred moving average over ``width`` samples (made odd; at each end,
    the straight line fitted to the first or last ``width`` samples, a Savitzky–Golay
    filter of order 1): (t, that). Why: the residual holds the model's slow misfit beside
    the fast mode, and a fit of both started a sinusoid on the misfit (amplitude 1e-30,
    growth 7.9/s) where a resonance rang 0.96 a period; a moving average is a linear
    filter, so a mode's period and decay pass through it unchanged, and the ends' lines
    keep the record whole (a decaying mode is largest at its start)."""
    w = int(width) | 1
    if y.size <= w:
        return t, y
    return t, y - savgol_filter(y, w, 1, mode="interp")


def mode_near(
    t: np.ndarray,
    y: np.ndarray,
    noise: float,
    mode: Ringing,
    sample_time: float,
    step: float,
) -> Ringing | None:
    """``mode`` (a verification's fast mode) read again in a record (``t`` s, ``y`` PV units,
    after a step of ``step``) made at another gain: on the record less its moving average
    over two of its periods (which passes that period whole and takes off what is slower), a
    decaying sinusoid fitted from the period within SAME_MODE of the mode's where the
    record's sinusoid (least squares) is tallest. A decay of 0 where nothing rings there:
    that sinusoid under LEAST of the step, or, where the fit does not read the mode, under
    QUIET of the mode's own amplitude (a mode that grows there is as tall as it was or
    taller: 1.2–2.1 times, where those that decayed were 0.13–0.27). None where the fit
    ends farther (SAME_MODE) or the mode does not stand out of the noise, and it is not
    that quiet.

    Why not ``ringing``: its fit starts from the period of the turning points, which the
    noise makes where a small mode rings under it (a gain-margin check's record at Kc × 2
    started at 0.26 s, half the 0.41 s mode growing 1.03 a period there, and fitted the
    noise)."""
    period = mode.period
    t, y = fast_part(t, y, max(3, round(2.0 * period / sample_time)))
    if t.size < 16 or not (period > 0 and np.all(np.isfinite(y))):
        return None
    least = LEAST * abs(step)
    # the tallest sinusoid within SAME_MODE of the period (the doubled gain moves a mode
    # a little, and over many periods a sinusoid a tenth off fits one of its own period
    # with almost nothing)
    tt = t - t[0]
    grid = period * np.linspace(1.0 - SAME_MODE, 1.0 + SAME_MODE, 61)
    amplitude, near = max((_sine_at(tt, y, p)[1], float(p)) for p in grid)
    if amplitude < least:
        return Ringing(0.0, near, amplitude)
    found = _fit_near(t, y, noise, near, least)
    if found is not None and abs(found.period - period) <= SAME_MODE * period:
        return found
    return Ringing(0.0, near, amplitude) if amplitude < QUIET * mode.amplitude else None


def _sine_at(tt: np.ndarray, y: np.ndarray, period: float) -> tuple[float, float, float]:
    """(offset, amplitude, phase) of the sinusoid of ``period`` s that best fits (``tt`` s,
    ``y``) by linear least squares."""
    w = 2.0 * math.pi / period
    basis = np.column_stack((np.ones_like(tt), np.sin(w * tt), np.cos(w * tt)))
    c, a, b = np.linalg.lstsq(basis, y, rcond=None)[0]
    return float(c), math.hypot(a, b), math.atan2(b, a)


def _fit_near(
    t: np.ndarray, y: np.ndarray, noise: float, period: float, least: float
) -> Ringing | None:
    """A decaying sinusoid fitted to (``t`` s, ``y``), started at ``period`` (s) with its
    amplitude and phase by linear least squares there; judged by ``ringing.stands_out``
    (``least``: PV units); None where the fit fails, ends SAME_MODE or more from
    ``period``, or does not stand out."""
    if not (period > 0 and math.isfinite(period)):
        return None
    tt = t - t[0]
    c, a, phi = _sine_at(tt, y, period)
    sine = DecayingSine(tt, y)
    x0 = [c, a, 0.0, 2.0 * math.pi / period, phi]
    with np.errstate(over="ignore", invalid="ignore"):
        x, fun, ok = levenberg_marquardt(sine.resid, sine.jac, x0, 2000)
    if not ok or not (x[3] > 0 and np.all(np.isfinite(x))):
        return None
    _, amp, g, w, _ = (float(v) for v in x)
    found = 2.0 * math.pi / w
    osc = Oscillation(
        growth=g,
        period=found,
        amplitude=abs(amp),
        offset=float(x[0]),
        rms=float(np.sqrt(np.mean(fun**2))),
        swings=int(2.0 * float(tt[-1]) / found),
    )
    if abs(found - period) > SAME_MODE * period or not stands_out(t, y, osc, noise, least):
        return None
    return Ringing(math.exp(min(g * found, 50.0)), found, abs(amp))
