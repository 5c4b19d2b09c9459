"""Robustness of the loop as it really runs: sampled, held, and closed by the discrete PID.

The continuous margins (``robustness``) ignore the zero-order hold, which lags by ωT/2 at ω:
the gain margin of applied gains is a few % lower at 170 samples per period and far lower at
the 10–20 samples per period of DCS loops. Here the loop transfer function is the one the
plant's PID block closes:

* G(z): the plant num/den·e^{−Ls} (a ``DelayedTF``) discretised exactly with a zero-order
  hold at T, the delay split into n whole samples and a fraction f (``lti.discretize``):
  G(z) = z^{−n}·[C(zI − Φ)^{−1}(Γ_new + z^{−1}Γ_old) + D·z^{−1}];
* C(z): ``shared.control.pid`` as it executes (ISA form, integral by forward Euler, derivative by
  backward difference through its filter Tf = Td/N):
  C(z) = Kc·[1 + T/(Ti·(z − 1)) + Td·(z − 1)/((Tf + T)·z − Tf)].
  Derivative on the measurement and the setpoint weight change the response to setpoint
  changes, not the loop from the PV back to the output, so they do not enter.

L(z) = C(z)·G(z) is evaluated on z = e^{jωT} for 0 < ω ≤ π/T (beyond, the response repeats
and mirrors). Ms, the gain margin (the least over every phase crossover of −180° + k·360°,
which may lie at π/T itself: a discrete loop's phase there is a multiple of 180°) and the
phase margin follow as in
``robustness``; stability comes from the Nyquist criterion on the unit circle, with an
indentation around the integrators' poles at z = 1, so it holds even where the margins are
ambiguous (several crossovers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq, minimize_scalar

from services.autotuner.design.robustness import Robustness, nearest_crossing
from shared.control.forms import IsaGains
from shared.control.lti import DiscreteDelaySystem, discretize, tf_to_ss
from shared.control.transfer import DelayedTF

LOG_POINTS = 3000  # logarithmic grid from far below the plant's slowest time scale to π/T
PHASE_STEP = 0.2  # rad: the linear grid keeps the delay's phase step near π/T below this
MAX_LINEAR_POINTS = 200_000
UNIT_CIRCLE_TOLERANCE = 1e-6  # a pole within this of z = 1 is an integrator


@dataclass(frozen=True)
class SampledPlant:
    """G(e^{jωT}) of a plant held and sampled at T, on a grid up to the Nyquist frequency.

    ``unstable_poles``: poles of G(z) outside the unit circle; ``integrators``: its poles at
    z = 1 (the Nyquist count needs both)."""

    sample_time: float  # s
    omega: np.ndarray  # rad/s, increasing, ending at π/T
    response: np.ndarray  # G(e^{jωT}), PV units per %
    unstable_poles: int
    integrators: int
    system: DiscreteDelaySystem

    def at(self, omega: np.ndarray | float) -> np.ndarray:
        """G(e^{jωT}) at any ω (rad/s)."""
        return self.system.response(omega)


def pid_response(gains: IsaGains, sample_time: float, z: np.ndarray, n: float = 10.0) -> np.ndarray:
    """C(z) of ``shared.control.pid`` (u = −C(z)·y with the setpoint at rest), at complex ``z``."""
    z = np.asarray(z, dtype=complex)
    t = sample_time
    c = np.ones_like(z)
    if gains.ti is not None:
        c = c + t / (gains.ti * (z - 1.0))
    if gains.td > 0:
        tf = gains.td / n
        c = c + gains.td * (z - 1.0) / ((tf + t) * z - tf)
    return gains.kc * c


def sampled_plant(plant: DelayedTF, sample_time: float) -> SampledPlant:
    """The plant's sampled frequency response at ``sample_time`` (s), computed once for every
    candidate's gains."""
    delay = plant.delay
    sys = discretize(*tf_to_ss(plant.num, plant.den), sample_time, delay)
    nyquist = math.pi / sample_time
    poles = np.roots(np.trim_zeros(np.asarray(plant.den, dtype=float), "f"))
    slow = max([delay, sample_time, *(1.0 / abs(p.real) for p in poles if abs(p.real) > 1e-300)])
    w_lo = min(1e-4 / slow, 1e-4 * nyquist)
    n_lin = min(
        max(1000, math.ceil(math.pi * (delay / sample_time + 2) / PHASE_STEP)), MAX_LINEAR_POINTS
    )
    grid = np.union1d(
        np.logspace(math.log10(w_lo), math.log10(nyquist), LOG_POINTS),
        np.linspace(nyquist / n_lin, nyquist, n_lin),
    )
    grid[-1] = nyquist
    eig = np.linalg.eigvals(sys.phi) if sys.order else np.zeros(0)
    integrators = int(np.sum(np.abs(eig - 1.0) < UNIT_CIRCLE_TOLERANCE))
    unstable = int(np.sum(np.abs(eig) > 1.0 + UNIT_CIRCLE_TOLERANCE))
    return SampledPlant(sample_time, grid, sys.response(grid), unstable, integrators, sys)


def _wrap(x: float) -> float:
    """x wrapped to (−π, π]."""
    return x - 2.0 * math.pi * math.ceil((x - math.pi) / (2.0 * math.pi))


def _first_fall(w: np.ndarray, values: np.ndarray, exact, tol: float = 1e-9) -> float | None:
    """The first ω where ``values`` falls from above 0 to 0 (None if it never does): the grid
    finds the interval, ``exact`` (the function at any ω) the root. A value within ``tol`` of
    0 on the grid is the root itself: the phase at π/T is exactly a multiple of π."""
    above = values > tol
    falls = np.nonzero(above[:-1] & ~above[1:])[0]
    if falls.size == 0:
        return None
    i = int(falls[0]) + 1
    if abs(values[i]) <= tol:
        return float(w[i])
    return float(brentq(exact, w[i - 1], w[i], xtol=1e-14 * w[i], rtol=1e-12))


def sampled_robustness(gains: IsaGains, plant: SampledPlant, n: float = 10.0) -> Robustness:
    """Ms, margins and stability of the sampled loop L(z) = C(z)·G(z) (see the module)."""
    ts = plant.sample_time
    w = plant.omega
    if gains.kc <= 0:  # no feedback: the loop is the plant's own
        stable = plant.unstable_poles == 0 and plant.integrators == 0
        ms = 1.0 if stable else math.inf  # |S| = 1 everywhere: but an unstable loop has none
        return Robustness(ms, math.inf, math.inf, None, None, stable, ts, plant.unstable_poles)

    def loop(x: np.ndarray | float) -> np.ndarray:
        x = np.atleast_1d(np.asarray(x, dtype=float))
        return pid_response(gains, ts, np.exp(1j * x * ts), n) * plant.at(x)

    lw = pid_response(gains, ts, np.exp(1j * w * ts), n) * plant.response
    m = plant.integrators + (1 if gains.ti is not None else 0)
    base = -0.5 * math.pi * m  # arg L(e^{jωT}) as ω → 0+ (for a positive loop gain)

    phase = np.unwrap(np.angle(lw))
    # the branch that starts at the low-frequency limit (base, or base − π for a negative gain)
    phase -= 2.0 * math.pi * math.floor((phase[0] - base + 1.5 * math.pi) / (2.0 * math.pi))

    ret = 1.0 + lw
    sens = 1.0 / np.abs(ret)
    k = int(np.argmax(sens))
    best = minimize_scalar(
        lambda x: -1.0 / abs(1.0 + loop(x)[0]),
        bounds=(w[max(k - 1, 0)], w[min(k + 1, w.size - 1)]),
        method="bounded",
        options={"xatol": 1e-12 * w[k]},
    )
    ms = max(float(sens[k]), -float(best.fun))

    def exact_phase(x: float) -> float:
        raw = float(np.angle(loop(x)[0]))
        ref = float(np.interp(x, w, phase))
        return raw + 2.0 * math.pi * round((ref - raw) / (2.0 * math.pi))

    w180 = _first_fall(w, phase + math.pi, lambda x: exact_phase(x) + math.pi)
    gm = math.inf if w180 is None else 1.0 / float(abs(loop(w180)[0]))
    other = nearest_crossing(w, phase, np.abs(lw), w180)
    if other is not None:  # the least margin over every crossing, not the first's alone
        i, crossed = other
        if abs(phase[i + 1] - crossed) <= 1e-9:  # on the grid: at π/T, a multiple of π
            wo = float(w[i + 1])
        else:
            wo = float(
                brentq(lambda x: exact_phase(x) - crossed, w[i], w[i + 1], xtol=1e-14 * w[i + 1])
            )
        go = 1.0 / float(abs(loop(wo)[0]))
        if go < gm:
            gm, w180 = go, wo
    log_mag = np.log(np.abs(lw))
    wc = _first_fall(w, log_mag, lambda x: math.log(abs(loop(x)[0])))
    if wc is None:  # |L| < 1 everywhere, or still ≥ 1 at π/T (no crossover: no margin)
        pm = math.inf if np.max(log_mag) < 0 else math.nan
    else:
        pm = 180.0 + math.degrees(exact_phase(wc))

    # Nyquist: closed-loop poles outside = open-loop poles outside − (net turns of 1 + L about
    # the origin along the unit circle, the integrators' poles at z = 1 passed outside, each
    # turning the image by −π). The half circle gives half the turns (conjugate symmetry).
    turn = np.unwrap(np.angle(ret))
    start = turn[0]
    if m:
        d0 = _wrap(start - base)
        if abs(d0) > 0.5 * math.pi:  # a negative loop gain starts half a turn away
            d0 = _wrap(d0 - math.pi)
        start -= d0
    half = float(turn[-1] - start)
    outside = plant.unstable_poles - (2.0 * half - m * math.pi) / (2.0 * math.pi)
    # Ms is the stable loop's distance to −1 (1/Ms): an unstable loop has none, and a finite
    # figure beside "unstable" read as a robustness (zn-ol-pi on lvl1: Ms 4.74 and an
    # overshoot of 55,000 %; helper trial)
    if not (math.isfinite(outside) and abs(outside - round(outside)) < 0.25):
        # the count is not a whole number: the grid missed a turn; the margins decide
        stable = bool(gm > 1.0 and pm > 0.0)
        return Robustness(ms if stable else math.inf, gm, pm, w180, wc, stable, ts, None)
    stable = round(outside) == 0
    return Robustness(ms if stable else math.inf, gm, pm, w180, wc, stable, ts, round(outside))


def sampled_loop_robustness(
    gains: IsaGains, plant: DelayedTF, sample_time: float, n: float = 10.0
) -> Robustness:
    """``sampled_robustness`` for one set of gains on ``plant`` held at T = ``sample_time``."""
    return sampled_robustness(gains, sampled_plant(plant, sample_time), n)
