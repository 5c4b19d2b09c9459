"""The ultimate point a step response implies, read from the record itself (no model).

A self-regulating process's frequency response follows from its step response y(t) to a step
of Δu held from t = 0 (y from its rest, y(∞) = y_end):

    G(jω) = [y_end + jω ∫₀^∞ (y(t) − y_end) e^{−jωt} dt] / Δu

(the Laplace transform of the step response is G(s)·Δu/s). Summed over the record's samples,
it gives G where the record resolves it: its phase crosses −180° at ω_u, K_u = 1/|G(jω_u)|,
P_u = 2π/ω_u. The step test's model is judged against that point (``design.measured_point``):
an FOPDT fit of (3s + 1)e^{−s}/((10s + 1)(s + 1)(0.5s + 1)) put the dead time at 0.45 s and its
K_u 4.5 times the plant's, and its SIMC PI, 1.33 × the plant's K_u, ran on the loop unstable
until the verification saw the output saturate.

Units: t and the sample time in s, y in PV units, Δu in % of output, K_u in % per PV unit.
"""

from __future__ import annotations

import math

import numpy as np

POINTS = 400  # frequencies on the grid (logarithmic) below the highest resolved
CHUNK = 16  # frequencies summed at once (× the record's samples: memory)
# the highest frequency read: an eighth of the Nyquist frequency (the sum's rectangle rule and
# the hold stay within a few per cent there)
RESOLVED = 1.0 / 8.0
# how unsure |G(jω_u)| may be, relative (the end value's error, the noise's share of the sum),
# for the point to be read at all
MAX_UNSURE = 0.1


def response_point(
    t: np.ndarray, y: np.ndarray, step: float, sample_time: float, noise_std: float = 0.0
) -> tuple[float, float, float] | None:
    """(K_u, P_u, how unsure |G(jω_u)| is, relative) from the samples ``y`` (PV units from
    the rest before the step, the process's gain positive) at times ``t`` (s from the step,
    > 0) of a step of ``step`` % held from t = 0; None where the record does not resolve a
    crossing of −180° (a lag-only process, a crossing beyond an eighth of the Nyquist
    frequency, a record too short, too noisy or not settled enough there)."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.size < 32 or step == 0 or not sample_time > 0:
        return None
    tail = max(4, t.size // 10)
    y_end = float(np.mean(y[-tail:]))
    # how sure the end value is: what the PV still moved over the record's last tenth, and
    # the noise of its mean. An error δ there moves G(jω) by up to 2δ/Δu, and at ω_u G is a
    # small part of the static gain (hx1: a sixteenth): the tail of a slow lag read K_u 14 %
    # low on hx1, a record "at rest" to the product's test
    creep = abs(y_end - float(np.mean(y[-2 * tail : -tail])))
    delta = creep + 2.0 * noise_std / math.sqrt(tail)
    if not y_end / step > 0:
        return None
    span = float(t[-1])
    w_hi = RESOLVED * math.pi / sample_time
    w_lo = 2.0 * math.pi / span
    if not w_hi > 4.0 * w_lo:
        return None
    # the trapezoid rule from the step itself (t = 0, the PV at its rest: y = 0), each sample
    # weighted by half the intervals beside it (the first sample alone, on the right ends,
    # left a j·ω·Δt/2 error in G: its phase 20° off at ω_u on e^{−s}/(5s + 1))
    t = np.concatenate(([0.0], t))
    y = np.concatenate(([0.0], y))
    dt = np.diff(t)
    weight = np.zeros(t.size)
    weight[:-1] += 0.5 * dt
    weight[1:] += 0.5 * dt
    rest = (y - y_end) * weight

    def response(w: np.ndarray) -> np.ndarray:
        """G(jω) at each ω of ``w``, a few at a time (ω × samples at once can be large)."""
        out = np.empty(w.size, dtype=complex)
        for k in range(0, w.size, CHUNK):
            part = w[k : k + CHUNK]
            out[k : k + CHUNK] = (
                y_end + 1j * part * (np.exp(-1j * np.outer(part, t)) @ rest)
            ) / step
        return out

    w = np.logspace(math.log10(w_lo), math.log10(w_hi), POINTS)
    g = response(w)
    phase = np.unwrap(np.angle(g))
    phase -= 2.0 * math.pi * round(float(phase[0]) / (2.0 * math.pi))  # 0 at low frequency
    below = np.nonzero(phase <= -math.pi)[0]
    if below.size == 0 or below[0] == 0:
        return None
    i = int(below[0])
    lo, hi = float(w[i - 1]), float(w[i])
    p_lo, g_lo = float(phase[i - 1]), complex(g[i - 1])
    for _ in range(40):  # bisection on the sum itself, the phase followed from the bracket's
        mid = math.sqrt(lo * hi)
        g_mid = complex(response(np.array([mid]))[0])
        p_mid = p_lo + float(np.angle(g_mid / g_lo))
        if p_mid <= -math.pi:
            hi = mid
        else:
            lo, p_lo, g_lo = mid, p_mid, g_mid
        if hi / lo - 1.0 < 1e-9:
            break
    wu = math.sqrt(lo * hi)
    mag = abs(complex(response(np.array([wu]))[0]))
    if not (mag > 0 and math.isfinite(mag)):
        return None
    noise = noise_std * wu * sample_time * math.sqrt(t.size) / abs(step)  # the sum's σ
    unsure = (2.0 * delta / abs(step) + noise) / mag  # relative, of |G(jω_u)|
    if unsure > MAX_UNSURE:
        return None
    return 1.0 / mag, 2.0 * math.pi / wu, unsure
