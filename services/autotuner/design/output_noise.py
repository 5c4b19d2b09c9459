"""The output noise a set of gains makes of the PV's measurement noise, predicted on the
sampled loop.

Measurement noise n (white, σ_n in PV units) reaches the output through the closed loop:
u = −C(z)·S(z)·n with S = 1/(1 + C(z)·G(z)) (``sampled_loop``: C as the plant's PID block
executes, G the held and sampled plant). The figure is the one the verification measures at
rest, σ(Δu)/√2 (``TuningRun._verify``: the sample-to-sample change, so that a slow drift
does not count), which for white noise through H = C·S is

    σ_n · √[(1/π) ∫₀^π |H(e^{jθ})|² (1 − cos θ) dθ]

(Parseval: |1 − e^{−jθ}|² = 2(1 − cos θ), the √2 taken out). For a P controller alone on a
slow plant (S ≈ 1 at the frequencies that count) it is Kc·σ_n: the proportional gain passes
the noise through whole; a derivative adds its high-frequency gain Kc·Td/(Tf + T) on top.
Why it matters: a high gain on a lag with little dead time is robust by Ms and still
useless, the valve thrashing with the noise (SIMC PI Kc 497 %/% on 0.1/(5s + 1) at 0.1 s,
σ_n 0.05: 34.5 % of output noise measured).
"""

from __future__ import annotations

import math

import numpy as np

from services.autotuner.design.rules import RULES, lambda_used
from services.autotuner.design.sampled_loop import SampledPlant, pid_response
from services.autotuner.identify.model_fit import ProcessFit
from shared.control.forms import IsaGains

# % of output (σ): the output noise the verification accepts unless told (TuneRequest's
# ``max_op_noise``). A valve moved by ±10 % (1σ) sample to sample by noise alone is worn out,
# not controlled; the presets' tunes make at most 7.3 % (a level's PI on a noisy gauge).
# More than half of it, 5 %, is worth a warning whatever the limit (``tuning.OP_NOISE_WARN``)
DEFAULT_LIMIT = 10.0


def limit_of(asked: float | None) -> float:
    """The output-noise limit a request asks (% of output; None: ``DEFAULT_LIMIT``)."""
    return DEFAULT_LIMIT if asked is None else asked


def noise_gain(gains: IsaGains, plant: SampledPlant, n: float = 10.0) -> float | None:
    """The output's noise per unit of the PV's white noise (σ(Δu)/√2 over σ_n, % of output per
    PV unit) on the sampled loop of ``plant`` closed by ``gains``; None where the integral
    is not finite (a pole of the closed loop on the unit circle)."""
    ts = plant.sample_time
    w = plant.omega
    c = pid_response(gains, ts, np.exp(1j * w * ts), n)
    h = c / (1.0 + c * plant.response)
    theta = np.concatenate(([0.0], w * ts))
    # the integrand at θ = 0 is 0: C·S → 1/G(1), finite, times 1 − cos 0
    power = np.concatenate(([0.0], np.abs(h) ** 2 * (1.0 - np.cos(w * ts))))
    value = float(np.trapezoid(power, theta)) / math.pi
    if not math.isfinite(value):
        return None
    return math.sqrt(value)


# the share of the limit the lambda rules are designed to when every rule is above it: the
# model's prediction missed the plant's by 16 % on an integrator fitted with a dead time it
# does not have (11.1 % predicted, 12.9 % measured)
QUIET_SHARE = 0.75
MAX_DOUBLINGS = 30  # λ up to 2³⁰ times its default: past that, no λ is said to help
BISECTIONS = 40


def quiet_lambda(
    design: ProcessFit, plant: SampledPlant, noise: float, target: float, rule: str = "lambda-pi"
) -> float | None:
    """The least λ (s, within 2⁻⁴⁰ of it relatively) at which ``rule``'s gains on ``design``
    make at most ``target`` % of output noise from the PV's white noise of σ ``noise`` (PV
    units) on the sampled loop of ``plant``; None where its default λ already does, or no λ
    up to 2³⁰ times it does. A larger λ is a slower loop with a smaller gain: the lambda
    rules' own knob for a noisy measurement (Åström & Hägglund 2006, §4.6: the noise sets
    how high the controller's gain may go)."""
    lam0 = lambda_used(design, None)

    def loud(lam: float) -> bool:
        try:
            gain = noise_gain(RULES[rule].compute(design, lam), plant)
        except ValueError:
            return True
        return gain is None or noise * gain > target

    if not loud(lam0):
        return None
    lo, hi = lam0, lam0
    for _ in range(MAX_DOUBLINGS):
        lo, hi = hi, 2.0 * hi
        if not loud(hi):
            break
    else:
        return None
    for _ in range(BISECTIONS):
        mid = math.sqrt(lo * hi)
        if loud(mid):
            lo = mid
        else:
            hi = mid
    return hi
