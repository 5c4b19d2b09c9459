"""Iinoya & Hotta (1958), "A study on the Ziegler and Nichols' rule for automatic controller
settings" (seed 004): their three figures for K·e^{−Ls}/(1 + sT), from their equations and
from the product's own experiments on the plant.

25 % damping is a closed-loop pole pair s = ω(−σ₄ + i), σ₄ = ln 4/(2π) (eq. 6): over one period
2π/ω its oscillation falls to e^{−2πσ₄} = ¼. With L = 1 and r = T/L (times in units of L, gains
as the loop gain M·K, M the plant's gain, R = M/T the reaction rate), each equation below was
re-derived from the characteristic equation and is checked against it in the tests:

* eq. 5, the ultimate point (s = iω₀): tan ω₀L = −Tω₀, M·K₀ = √(1 + (Tω₀)²). Fig. 2 plots
  K₀·R·L = M·K₀/r and τ₀/L = 2π/(ω₀L) against ZN's 2 and 4 (eq. 8);
* eq. 7, P control: [1 − σ₄ω₄L·r]·tan ω₄L + ω₄L·r = 0, M·K₄·e^{σ₄ω₄L} = ω₄T/sin ω₄L. Fig. 1
  plots K₀/K₄ (curve a; ZN's K₁ = K₀/2 gives 2) and K₁·M·L/T = K₄·R·L (curve b, K₁ there is
  the 25 % gain K₄; ZN's K₁ = 1/(R·L) gives 1);
* eq. 12, PI K(1 + 1/(T_I·s)) at ZN's K = 0.9/(R·L): r and T_I4/L as functions of x = ωL
  (Fig. 3 curve a, against ZN's T_I = 3.33 L);
* eq. 15, ideal PD K(1 + T_D·s) at K = λ/(R·L), λ = 1.2: r and T_D4/L as functions of x
  (Fig. 3 curves b and b', against the paper's T_D = 0.36–0.37 L, eq. 16).

Eqs. 12 and 15 give r as N(x)/D(x); for a given r the root finder works in x on N − r·D (no
poles), scanned over 0 < x ≤ 2π, and keeps the roots whose time is positive. P and PI have one:
the lowest-frequency pair, the dominant one. PD has two above r ≈ 1.49 (the paper reads 1.43;
exactly where K₄·R·L = λ, P alone at λ/(R·L) giving 25 %): the upper T_D (curve b, the higher
ω) and the lower (b', T_D → 0 at that r). The ideal PD's loop is a neutral delay equation: its
high-frequency roots tend to Re s·L = ln(λ·T_D/L) (s·T + K·M·T_D·s·e^{−Ls} ≈ 0), so below
r = 1/(2λ) ≈ 0.42 (found numerically, to 1e-12) they decay slower than the pair on curve b and
eq. 15 no longer gives a 25 %-damped response (``chain_decay``).

Measured points: the same figures from the product's experiments on the plant (M = 1 PV unit
per %, L = 1 s, T = r s), in process and without noise: K₀ and τ₀ from the relay
(``benchmark.run_relay``), R and L from the step test (``StepTest`` driven by ``driver.drive``
over a plant_sim loop), and the 25 % settings by a root search on setpoint steps through the
product's PID block (``shared.control.pid``, derivative on the measurement, its filter at the
block's largest N = 1000 so the derivative is the paper's ideal one to within the sample time)
closing the loop on the plant discretised exactly (``lti.discretize``; ``SampledPlant`` steps
it on floats, the samples of ``lti.DelayedLinearSystem`` at a tenth of its cost). The gains
come from the measured R and L (0.9/(R·L), 1.2/(R·L)): the step test under-reads R by 0.1 %,
and where that alone moves a curve by more than 1 % (curve b′ near T/L = 3) a note says so.

What is measured is the paper's 25 % damping itself: the decay of the response's dominant
oscillatory mode, not of its first two crests, on which faster roots still weigh (PI at ZN's
gain has a real root at −0.42…−0.69/L beside the pair's −0.25/L; P at T/L = 0.1 a second pair
at −0.88/L beside −0.63/L; the PD loops their high-frequency roots). Each setpoint step is
watched for L + 6 τ₀ (PI, whose period is up to 2.1 τ₀: 9 τ₀); from L + τ₀ on, a matrix pencil
(Hua & Sarkar 1990) fits up to 8 modes to its first differences sampled every τ₀/16, and the
oscillatory mode largest at the end is the dominant one: s = −α + iω, decay ratio e^{−2πα/ω}.
The search (brentq on a loop sampled at L/100 to bracket it, the secant method at L/1000, then
at L/4000 on curve b′, whose T_D moves 14 times as much as L near T/L = 3 and so with the
loop's half-sample lag) finds the setting where that ratio is 0.25. The dominance check
compares the mode with the whole response, sampled in full: over its last two periods above
rounding, its largest deviation from the final value must fall per period as the mode's does,
to 5 %, and its turning points (every one) repeat at the mode's period, to 2 %. Where they do
not, a mode the fit leaves out has taken the tail over (the ideal PD's high-frequency roots
below T/L ≈ 0.42), the paper's setting gives no 25 %-damped response, and the table says "none"
rather than a number. The product's own decay ratio of the first two crests
(``measured_setpoint_step``) is reported beside each point, as a trend would show it.
"""

from __future__ import annotations

import math
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.optimize import brentq

from services.autotuner.design.measured_response import measured_setpoint_step
from services.autotuner.identify.driver import drive
from services.autotuner.identify.step_test import StepTest, StepTestConfig
from services.offline.benchmark import Plant, decay_ratio, run_relay
from services.offline.local_loop import SimLoopPort
from services.plant_sim.plant_file import build_plant
from shared.control.forms import IsaGains
from shared.control.lti import discretize, tf_to_ss
from shared.control.pid import PidBlock, PidSettings

SIGMA4 = math.log(4.0) / (2.0 * math.pi)  # eq. 6: ¼ amplitude per period
QUARTER = 0.25  # the decay ratio of that pair
ZN_P_ULTIMATE = 2.0  # K₀/K₁ of ZN's P rule K₁ = K₀/2 (eq. 2)
ZN_P_REACTION = 1.0  # K₁·R·L of ZN's P rule K₁ = 1/(R·L) (eq. 9)
ZN_K0RL, ZN_TAU0 = 2.0, 4.0  # eq. 8: what ZN's two rules agreeing would need
PI_GAIN = 0.9  # ZN's PI gain, K·R·L (eq. 11)
ZN_TI = 1.0 / 0.3  # ZN's PI integral time, T_I/L = 3.33
PD_GAIN = 1.2  # λ of eq. 13, as in ZN's PID rule
PAPER_TD = (0.36, 0.37)  # T_D/L of the paper's PD rule (eq. 16)
X_MAX = 2.0 * math.pi  # ωL scanned over (0, X_MAX]
SCAN_POINTS = 4096

IH_RATIOS = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)  # the benchmark's table
FIGURE_RATIOS = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)  # the three figures' tables
MAX_WORKERS = 4  # processes measuring T/L values at once
TOLERANCE = 0.02  # a measured point further than this (relative) from its curve gets a note

# the closed-loop simulations: sample times in units of L (the ZOH lags ts/2), the derivative
# filter, how long a response is watched and how its tail is read
COARSE_TS = 1e-2  # the searches' brackets
FINE_TS = 1e-3  # the measured settings: ts/2 = 0.05 % of L
FINEST_TS = 2.5e-4  # curve b′, whose T_D moves up to 14× as fast as L (T/L ≈ 3)
DERIVATIVE_N = 1000.0  # the PID block's largest: T_f = T_D/1000, below the sample time
WATCH_PERIODS = 6.0  # a response is watched for L + this × τ₀ (the relay's) ...
WATCH_PERIODS_PI = 9.0  # ... PI's for longer, its period being up to 2.1 τ₀ ...
TAIL_FROM = 1.0  # ... and its tail read from L + this × τ₀ on,
TAIL_SAMPLES = 16  # every τ₀/16 by the matrix pencil,
PENCIL_ORDER = 8  # fitting this many modes at most
PENCIL_RANK = 1e-13  # singular values below this (relative) are rounding
CREST_FLOOR = 1e-7  # deviations below this share of the setpoint step: rounding near crests
CREST_RATIO_TOL = 0.05  # the late crests decay within 5 % of the mode's ratio ...
CREST_PERIOD_TOL = 0.02  # ... and repeat within 2 % of its period: the mode dominates
QUARTER_SLACK = 1e-3  # a crossing's mode ratio further from 0.25: a jump, not a crossing
JUMP = 0.02  # the coarse loop's: there the mode ratio jumps across 0.25 (another mode)
SOLVE_TOL = 1e-5  # the fine loop's crossings are solved to |mode ratio − 0.25| ≤ this
CLOSED_SLACK = 0.01  # the curve's exact setting on the sampled loop: 25 % to within this
RL_NOTE = 0.01  # a curve the step test's R·L error alone moves further than this: a note


# --- closed forms (L = 1, r = T/L) -------------------------------------------------------


def ultimate(r: float) -> tuple[float, float]:
    """Eq. 5: (ω₀L, M·K₀) of K·e^{−Ls}/(1 + sT) at T/L = r (dimensionless)."""
    w0 = brentq(lambda w: math.sin(w) + r * w * math.cos(w), math.pi / 2, math.pi, xtol=1e-15)
    return w0, math.hypot(1.0, r * w0)


def iinoya_hotta(t_over_l: float) -> tuple[float, float]:
    """Closed form for K·e^{−Ls}/(Ts+1): (K₀·R·L, τ₀/L) (Iinoya & Hotta 1958, eq. 5)."""
    w0, mk0 = ultimate(t_over_l)
    return mk0 / t_over_l, 2.0 * math.pi / w0


def _roots(h: Callable[[np.ndarray], np.ndarray], x_max: float = X_MAX) -> list[float]:
    """The roots of a continuous h(x) on (0, x_max], by sign changes on a fine grid refined
    with brentq; lowest first."""
    x = np.linspace(x_max / SCAN_POINTS, x_max, SCAN_POINTS)
    v = h(x)
    found = np.nonzero(np.sign(v[:-1]) * np.sign(v[1:]) < 0)[0]
    return [brentq(lambda z: float(h(np.asarray(z))), x[i], x[i + 1], xtol=1e-14) for i in found]


def quarter_p(r: float) -> tuple[float, float]:
    """Eq. 7: (ω₄L, M·K₄), P control's 25 % pair at T/L = r: the lowest root of
    (1 − σ₄xr)·sin x + xr·cos x = 0 (eq. 7 times cos x) in 0 < x < π, where sin x > 0 as
    M·K₄ = x·r·e^{−σ₄x}/sin x must be."""
    x = _roots(lambda x: (1 - SIGMA4 * x * r) * np.sin(x) + x * r * np.cos(x), math.pi)[0]
    return x, x * r * math.exp(-SIGMA4 * x) / math.sin(x)


def _pi_parts(x, c: float):
    """Eq. 12 at x = ωL, PI gain c = K·R·L: (numerator, denominator) of T/L and T_I4/L."""
    s, co, e = np.sin(x), np.cos(x), c * np.exp(SIGMA4 * x)
    num = SIGMA4 * s - co
    den = e - x * ((1 - SIGMA4**2) * s + 2 * SIGMA4 * co)
    return num, den, e * num / (x * (1 + SIGMA4**2) * (e * s - x))


def _pd_parts(x, lam: float):
    """Eq. 15 at x = ωL, PD gain λ = K·R·L: (numerator, denominator) of T/L and T_D4/L."""
    s, co, e = np.sin(x), np.cos(x), lam * np.exp(SIGMA4 * x)
    num = SIGMA4 * s + co
    den = (1 + SIGMA4**2) * x * s - e
    return num, den, (e * s - x) / (x * e * num)


def quarter_pi(r: float, gain: float = PI_GAIN) -> tuple[float, float]:
    """Eq. 12: (ωL, T_I4/L), the integral time giving 25 % damping with K = gain/(R·L) at
    T/L = r: the lowest-frequency root with T_I4 > 0. ValueError if there is none."""

    def h(x):
        num, den, _ = _pi_parts(x, gain)
        return num - r * den

    for x in _roots(h):
        ti = float(_pi_parts(x, gain)[2])
        if ti > 0:
            return x, ti
    raise ValueError(f"T/L = {r:g}: no integral time gives 25 % damping at K·R·L = {gain:g}")


def quarter_pd(r: float, lam: float = PD_GAIN) -> tuple[tuple[float, float], ...]:
    """Eq. 15: every (ωL, T_D4/L) with T_D4 > 0 giving 25 % damping with K = λ/(R·L) at
    T/L = r, lowest ω first: one (curve b) below r ≈ 1.49, two above (b' then b)."""

    def h(x):
        num, den, _ = _pd_parts(x, lam)
        return num - r * den

    out = []
    for x in _roots(h):
        td = float(_pd_parts(x, lam)[2])
        if td > 0:
            out.append((x, td))
    return tuple(out)


def chain_decay(td_over_l: float, lam: float = PD_GAIN) -> float:
    """−Re s·L of the ideal PD loop's high-frequency roots: they tend to
    e^{−Ls} = −T/(K·M·T_D), so Re s·L → ln(λ·T_D/L). At most 0: they do not decay."""
    return -math.log(lam * td_over_l)


@dataclass(frozen=True)
class ClosedForm:
    """The paper's figures at one T/L (eqs. 5, 7, 12, 15); frequencies as ωL, gains as M·K."""

    t_over_l: float
    w0l: float
    mk0: float
    w4l: float
    mk4: float
    pi_wl: float
    ti4: float  # T_I4/L
    pd: tuple[tuple[float, float], ...]  # (ωL, T_D4/L), lowest ω first

    @property
    def k0rl(self) -> float:
        return self.mk0 / self.t_over_l

    @property
    def tau0(self) -> float:
        """τ₀/L."""
        return 2.0 * math.pi / self.w0l

    @property
    def k0_over_k4(self) -> float:
        return self.mk0 / self.mk4

    @property
    def k4rl(self) -> float:
        """K₄·R·L = K₁·M·L/T of Fig. 1 curve b."""
        return self.mk4 / self.t_over_l

    @property
    def td4_upper(self) -> float:
        """T_D4/L on curve b (the higher ω), NaN if none."""
        return self.pd[-1][1] if self.pd else math.nan

    @property
    def td4_lower(self) -> float:
        """T_D4/L on curve b' (exists above T/L ≈ 1.49), NaN if none."""
        return self.pd[0][1] if len(self.pd) > 1 else math.nan

    def pd_dominated(self, branch: int) -> bool:
        """The pair of ``pd[branch]`` decays faster than the ideal PD's high-frequency
        roots (``chain_decay``): else eq. 15's setting is not a 25 %-damped response."""
        x, td = self.pd[branch]
        return chain_decay(td) > SIGMA4 * x


def closed_form(r: float) -> ClosedForm:
    """Every closed-form figure at T/L = r."""
    w0, mk0 = ultimate(r)
    w4, mk4 = quarter_p(r)
    pi_wl, ti4 = quarter_pi(r)
    return ClosedForm(r, w0, mk0, w4, mk4, pi_wl, ti4, quarter_pd(r))


def ti4_meets_zn() -> float:
    """T/L where eq. 12's T_I4 equals ZN's 3.33 L (the paper: 60); below it ZN's is larger."""
    return brentq(lambda r: quarter_pi(r)[1] - ZN_TI, 1.0, 1e4, xtol=1e-10)


def pd_two_branches_above() -> float:
    """T/L above which eq. 15 has two T_D (the paper: 1.43): where P alone at λ/(R·L) gives
    25 % damping, K₄·R·L = λ, and curve b' starts from T_D = 0."""
    return brentq(lambda r: quarter_p(r)[1] / r - PD_GAIN, 0.5, 20.0, xtol=1e-12)


def pd_chain_dominates_below() -> float:
    """T/L below which the ideal PD's high-frequency roots decay slower than curve b's pair."""

    def margin(r: float) -> float:
        x, td = quarter_pd(r)[-1]
        return chain_decay(td) - SIGMA4 * x

    return brentq(margin, 0.05, 5.0, xtol=1e-10)


def curves(ratios: Sequence[float]) -> dict[str, np.ndarray]:
    """The figures' closed-form curves over ``ratios`` (T/L), NaN where a branch is absent."""
    forms = [closed_form(r) for r in ratios]
    return {
        "t_over_l": np.asarray(ratios, float),
        "k0_over_k4": np.array([f.k0_over_k4 for f in forms]),
        "k4rl": np.array([f.k4rl for f in forms]),
        "k0rl": np.array([f.k0rl for f in forms]),
        "tau0": np.array([f.tau0 for f in forms]),
        "ti4": np.array([f.ti4 for f in forms]),
        "td4_upper": np.array([f.td4_upper for f in forms]),
        "td4_lower": np.array([f.td4_lower for f in forms]),
        "pd_dominated": np.array([bool(f.pd) and f.pd_dominated(-1) for f in forms]),
    }


# --- the product's experiments on the plant (M = 1, L = 1 s, T = r s) ---------------------


def fopdt(r: float) -> Plant:
    """The plant e^{−s}/(1 + r·s): gain 1 PV unit per %, L = 1 s, T = r s."""
    return Plant.of(f"fopdt T/L={r:g}", "fopdt", (1.0,), (r, 1.0), 1.0)


def step_test(r: float) -> tuple[float, float]:
    """(R in PV units/s per %, L in s) from the product's step test on the plant: a +5 %
    step from 50 %, read by the tangent. The sample time L/max(10, ⌈500·L/T⌉) is a whole
    part of L (L is read exactly) and ≤ T/500: the steepest secant between samples then
    under-reads R by ≤ 0.1 % (ts/(2T)); what that alone does to each curve is reported
    (``rl_shift``)."""
    ts = 1.0 / max(10, math.ceil(500.0 / r))
    spec = {
        "model": "transfer_function",
        "num": [1.0],
        "den": [r, 1.0],
        "delay": 1.0,
        "sample_time": ts,
        "noise_std": 0.0,
        "pv_range": [-1e9, 1e9],
    }
    loop = build_plant({"seed": 0, "loops": {"x": spec}})["x"]
    st = loop.settings
    test = StepTest(
        StepTestConfig(size=5.0), loop.op, st.op_limits, st.pv_range, ts, pv_range=st.pv_range
    )
    drive(test, SimLoopPort(loop, limit=200.0 * (1.0 + r)))
    if test.result is None:
        raise RuntimeError(f"step test at T/L = {r:g}: {test.reason or 'no result'}")
    return test.result.reaction_rate, test.result.dead_time


class SampledPlant:
    """e^{−s}/(1 + r·s) sampled every ``ts`` s, exactly (``lti.discretize``, zero-order hold),
    stepped on plain floats with a ring buffer for the dead time: the samples of
    ``lti.DelayedLinearSystem`` (to rounding, checked in the tests) at a fraction of its cost,
    whose delay line is a deque read in its middle."""

    def __init__(self, r: float, ts: float):
        sys = discretize(*tf_to_ss([1.0], [r, 1.0]), ts, 1.0)
        self.phi = float(sys.phi[0, 0])
        self.gamma_new = float(sys.gamma_new[0, 0])
        self.gamma_old = float(sys.gamma_old[0, 0])
        self.c = float(sys.c[0, 0])
        self.d = float(sys.d)
        self.n = sys.delay_samples
        self._line = [0.0] * (self.n + 2)  # u[k], u[k−1], … from index self._at on
        self._at = 0
        self._x = 0.0

    def step(self, u: float) -> float:
        """Hold ``u`` for one sample period; the PV at the end of it."""
        size = self.n + 2
        self._at = (self._at - 1) % size
        self._line[self._at] = u
        u_new = self._line[(self._at + self.n) % size]  # u[k−n]
        u_old = self._line[(self._at + self.n + 1) % size]
        self._x = self.phi * self._x + self.gamma_new * u_new + self.gamma_old * u_old
        return self.c * self._x + self.d * u_new


def setpoint_response(
    r: float, gains: PidSettings, ts: float, horizon: float, crossings: int | None = None
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """A setpoint step of the product's PID block (``gains``, sample time ``ts`` s) on
    e^{−s}/(1 + r·s), from rest: (t s, PV, the step, the loop's final value), in deviations
    (PV units). Watched for ``horizon`` s, or only until the PV has crossed the final value
    ``crossings`` times. P and PD leave an offset: the final value is M·K/(1 + M·K) of the
    step (M = 1), not the setpoint."""
    plant = SampledPlant(r, ts)
    pid = PidBlock(gains, ts, (0.0, 100.0), mode="auto", op=50.0)
    sp = min(1.0, 10.0 / gains.kc)  # a P kick of 10 % at most: the output limits stay away
    final = sp if gains.ti is not None else sp * gains.kc / (1.0 + gains.kc)
    y = np.zeros(round(horizon / ts) + 1)
    pv, above, crossed = 0.0, False, 0
    for k in range(1, y.size):
        pv = plant.step(pid.update(sp, pv) - 50.0)  # deviations: rest at PV 0, output 50 %
        y[k] = pv
        if crossings is not None and (pv > final) != above:
            above, crossed = not above, crossed + 1
            if crossed == crossings:
                y = y[: k + 1]
                break
    return ts * np.arange(y.size), y, sp, final


def first_crests(t: np.ndarray, y: np.ndarray, final: float) -> float:
    """The product's decay ratio of a setpoint step (``measured_setpoint_step``): its second
    crest over its first, about the final value; 0 with fewer than two."""
    dr = measured_setpoint_step(t, y, 0.0, 0.0, final)["decay_ratio"]
    return 0.0 if dr is None else float(dr)


def setpoint_decay_ratio(r: float, gains: PidSettings, ts: float, horizon: float) -> float:
    """``first_crests`` of a setpoint step watched to the fourth crossing of the final value
    (the second crest is then whole), for at most ``horizon`` s."""
    t, y, _, final = setpoint_response(r, gains, ts, horizon, crossings=4)
    return first_crests(t, y, final)


def tail_mode(t: np.ndarray, y: np.ndarray, t_from: float, h: float) -> complex | None:
    """The dominant oscillatory mode s (1/s) of the record's tail from ``t_from`` s: a matrix
    pencil (Hua & Sarkar 1990) on its first differences taken every ``h`` s (the final value
    drops out), ``PENCIL_ORDER`` modes at most; of the oscillatory ones, the largest at the
    record's end. None without one."""
    ts = float(t[1] - t[0])
    step = max(1, round(h / ts))
    z = np.diff(y[round(t_from / ts) :: step])
    if z.size < 4 * PENCIL_ORDER:
        return None
    hankel = np.lib.stride_tricks.sliding_window_view(z, z.size // 2 + 1)
    _, sv, vt = np.linalg.svd(hankel, full_matrices=False)
    order = min(PENCIL_ORDER, int(np.count_nonzero(sv > PENCIL_RANK * sv[0])))
    v = vt[:order].T
    lam = np.linalg.eigvals(np.linalg.pinv(v[:-1]) @ v[1:])
    amp = np.linalg.lstsq(lam[None, :] ** np.arange(z.size)[:, None], z, rcond=None)[0]
    size = np.abs(amp * lam ** (z.size - 1))
    osc = [k for k in range(lam.size) if lam[k].imag > 1e-12 * abs(lam[k])]
    if not osc:
        return None
    k = max(osc, key=lambda k: size[k])
    return complex(np.log(lam[k])) / (step * ts)


def late_crests(
    t: np.ndarray, y: np.ndarray, final: float, period: float, t_from: float, floor: float
) -> tuple[float | None, float | None]:
    """What the record itself shows over its last two ``period`` s (the mode's period) before
    its deviation from ``final`` sinks below ``floor`` (PV units; rounding below it): the
    largest deviation over the last period over that over the one before (the decay ratio
    about the final value, read late), and the period of its turning points there (s; every
    one counts, so a faster oscillation riding on the mode shortens it). (None, None) where
    that stretch would start before ``t_from`` s; the period None with fewer than three
    turning points."""
    dev = y - final
    above = np.nonzero(np.abs(dev) > floor)[0]
    if above.size == 0:
        return None, None
    end = float(t[above[-1]])
    if end - 2.0 * period < t_from:
        return None, None
    last = (t > end - period) & (t <= end)
    before = (t > end - 2.0 * period) & (t <= end - period)
    ratio = float(np.max(np.abs(dev[last])) / np.max(np.abs(dev[before])))
    tw = t[before | last]
    d = np.diff(dev[before | last])
    turns = tw[1:-1][d[:-1] * d[1:] < 0]
    if turns.size < 3:
        return ratio, None
    return ratio, float(2.0 * (turns[-1] - turns[0]) / (turns.size - 1))


@dataclass(frozen=True)
class Reading:
    """What one simulated setpoint response shows (times in s, rates in 1/s; here L = 1 s).

    The mode: the tail's dominant oscillatory mode s = −``mode_decay`` + i·``mode_omega``
    (``tail_mode``), its decay ratio e^{−2π·decay/ω} per period (0 without one). The crests:
    what the response itself shows over its last two periods above rounding (``late_crests``),
    its largest deviation from the final value per period over the one before, and the period
    of its turning points. ``dominant``: the mode accounts for the response's
    tail, which decays and repeats as the mode does (within ``CREST_RATIO_TOL`` and
    ``CREST_PERIOD_TOL``); not so where a mode the fit leaves out (the ideal PD's fast roots)
    takes the tail over. ``first_crests``: the product's decay ratio of the whole
    response, its second crest over its first, about the final value: what a trend shows,
    where faster modes still weigh."""

    mode_decay: float | None
    mode_omega: float | None
    mode_ratio: float
    crest_ratio: float | None
    crest_period: float | None
    first_crests: float
    dominant: bool

    @property
    def quarter(self) -> bool:
        """A 25 %-damped response: the dominant mode decays by ¼ per period (to
        ``QUARTER_SLACK``)."""
        return self.dominant and abs(self.mode_ratio - QUARTER) <= QUARTER_SLACK


def read_response(
    t: np.ndarray, y: np.ndarray, sp: float, final: float, dead: float, tau0: float
) -> Reading:
    """The ``Reading`` of a setpoint response; its tail starts ``TAIL_FROM`` ultimate periods
    (``tau0`` s, the relay's) after the dead time ``dead`` s (the step test's)."""
    t_from = dead + TAIL_FROM * tau0
    s = tail_mode(t, y, t_from, tau0 / TAIL_SAMPLES)
    ratio = 0.0 if s is None else math.exp(2.0 * math.pi * s.real / s.imag)
    cr, cp = (None, None)
    if s is not None:
        cr, cp = late_crests(t, y, final, 2.0 * math.pi / s.imag, t_from, CREST_FLOOR * abs(sp))
    dominant = (
        s is not None
        and cr is not None
        and cp is not None
        and abs(cr / ratio - 1.0) <= CREST_RATIO_TOL
        and abs(cp * s.imag / (2.0 * math.pi) - 1.0) <= CREST_PERIOD_TOL
    )
    return Reading(
        mode_decay=None if s is None else -s.real,
        mode_omega=None if s is None else s.imag,
        mode_ratio=ratio,
        crest_ratio=cr,
        crest_period=cp,
        first_crests=first_crests(t, y, final),
        dominant=dominant,
    )


@dataclass(frozen=True)
class Crossing:
    """A setting (K in % per PV unit, T_I or T_D in s) where the response's dominant mode
    decays by ¼ per period, found on the loop sampled every ``sample_time`` s, and the
    response there. ``quarter``: a 25 %-damped response; not so at a jump (the dominant mode
    changes there) or where the mode does not account for the response."""

    value: float
    sample_time: float
    reading: Reading
    quarter: bool


def _secant(
    g: Callable[[float], float], p: float, slope: float, lo: float, hi: float
) -> tuple[float | None, float]:
    """g(p) = 0 by the secant method from ``p`` (``slope`` a first guess of g′) to |g| ≤
    ``SOLVE_TOL`` within (lo, hi): the root (None if it leaves that range or does not settle)
    and the last slope."""
    gp = g(p)
    q = p - gp / slope if slope else p + 0.01 * (hi - lo)
    for _ in range(10):
        if abs(gp) <= SOLVE_TOL:
            return p, slope
        if not lo < q < hi:
            return None, slope
        gq = g(q)
        if gq == gp:
            return None, slope
        slope = (gq - gp) / (q - p)
        if abs(gq) <= SOLVE_TOL or abs(q - p) <= 1e-7 * (hi - lo):
            return q, slope
        p, gp, q = q, gq, q - gq / slope
    return None, slope


def _crossings(
    read_at: Callable[[float, float], Reading],
    grid: Sequence[float],
    fine_ts: Callable[[bool], tuple[float, ...]],
    lowest: float = 0.0,
) -> list[Crossing]:
    """Every setting where ``read_at(p, ts).mode_ratio`` crosses ¼: bracketed on ``grid``
    (a, b, falling) and solved on the coarse loop, then on finer ones (``fine_ts(falling)``,
    s) in turn by the secant method, each from the previous roots extrapolated in the sample
    time, within the bracket's cell and its neighbours (no lower than ``lowest``; brentq
    where the secant fails). A crossing where the ratio jumps (another mode takes the tail
    over) or where the mode does not account for the response is kept, not refined, and not
    ``quarter``."""

    def coarse(p: float) -> float:
        return read_at(p, COARSE_TS).mode_ratio - QUARTER

    values = [coarse(p) for p in grid]
    brackets = [
        (grid[i], grid[i + 1], values[i] > values[i + 1])
        for i in range(len(grid) - 1)
        if values[i] * values[i + 1] < 0 or values[i] == 0
    ]
    out = []
    for a, b, falling in brackets:
        pc = brentq(coarse, a, b, xtol=1e-3 * (b - a))  # a start: the fine loops refine it
        reading = read_at(pc, COARSE_TS)
        if abs(reading.mode_ratio - QUARTER) > JUMP:
            out.append(Crossing(pc, COARSE_TS, reading, False))
            continue
        stages = fine_ts(falling)
        reading = read_at(pc, stages[0])
        if not reading.dominant:
            out.append(Crossing(pc, stages[0], reading, False))
            continue
        roots: list[tuple[float, float]] = [(COARSE_TS, pc)]
        dp = 0.01 * (b - a)
        slope = (coarse(pc + dp) - coarse(pc)) / dp
        lo, hi = max(a - (b - a), lowest), b + (b - a)  # the bracket and its neighbours
        for ts in stages:
            (t1, p1), (t0, p0) = roots[-1], roots[-2] if len(roots) > 1 else roots[-1]
            start = p1 if t1 == t0 else p1 + (p1 - p0) * (ts - t1) / (t1 - t0)
            start = min(max(start, lo + dp), hi - dp)

            def fine(p: float, ts: float = ts) -> float:
                return read_at(p, ts).mode_ratio - QUARTER

            p, slope = _secant(fine, start, slope, lo, hi)
            for x0, x1 in ((a, b), (lo, hi)) if p is None else ():
                if fine(x0) * fine(x1) < 0:
                    p = brentq(fine, x0, x1, xtol=1e-6 * (b - a))
                    break
            if p is None:
                break
            roots.append((ts, p))
        ts, p = roots[-1]
        if ts != COARSE_TS:
            reading = read_at(p, ts)
            out.append(Crossing(p, ts, reading, reading.quarter))
    return out


@dataclass(frozen=True)
class Measured:
    """The figures at one T/L read off the product's experiments (M = 1, L = 1 s): K₀ and τ₀
    (s) from the relay, R (PV units/s per %) and L (s) from the step test, the 25 % settings
    found on the closed loop (K₄ % per PV unit, T_I4 and T_D4 in s: where the dominant mode
    is the 25 % pair, None or left out where no setting gives a 25 %-damped response), every
    crossing found with its response, the responses at the closed forms' exact settings, and
    the first-crest decay ratios at the closed-form settings and at ZN's two P rules."""

    t_over_l: float
    k0: float
    tau0: float
    rate: float
    dead_time: float
    k4: float | None
    ti4: float | None
    td4: tuple[float, ...]  # every 25 %-damped T_D, ascending
    dr_closed_p: float  # first crests, as ``Reading.first_crests``
    dr_closed_pi: float
    dr_closed_pd: tuple[float, ...]  # per closed-form branch, as ``ClosedForm.pd``
    dr_zn_ultimate: float  # K = K₀/2
    dr_zn_reaction: float  # K = 1/(R·L)
    p_crossings: tuple[Crossing, ...] = ()
    pi_crossings: tuple[Crossing, ...] = ()
    pd_crossings: tuple[Crossing, ...] = ()
    closed_p: Reading | None = None
    closed_pi: Reading | None = None
    closed_pd: tuple[Reading, ...] = ()

    @property
    def a(self) -> float:
        """R·L, PV units per %."""
        return self.rate * self.dead_time

    def to_dict(self) -> dict:
        return asdict(self)


def _watch(dead: float, tau0: float, periods: float = WATCH_PERIODS) -> float:
    """How long a response is watched, s."""
    return dead + periods * tau0


def measure(r: float, parts: Sequence[str] = ("p", "pi", "pd")) -> Measured:
    """Run the product's experiments on e^{−s}/(1 + r·s) and search the 25 % settings of
    ``parts`` (P, PI, PD); RuntimeError naming the experiment that failed."""
    outcome = run_relay(fopdt(r), 0.0)
    if not outcome.ok:
        raise RuntimeError(f"relay at T/L = {r:g}: {outcome.reason}")
    k0 = outcome.ku_exact * (1.0 + outcome.ku_error)
    tau0 = outcome.pu_exact * (1.0 + outcome.pu_error)
    rate, dead = step_test(r)
    a = rate * dead
    horizon = _watch(dead, tau0)
    cf = closed_form(r)
    memo: dict[tuple[PidSettings, float], Reading] = {}

    def read(gains: PidSettings, ts: float) -> Reading:
        if (gains, ts) not in memo:
            watch = horizon if gains.ti is None else _watch(dead, tau0, WATCH_PERIODS_PI)
            t, y, sp, final = setpoint_response(r, gains, ts, watch)
            memo[gains, ts] = read_response(t, y, sp, final, dead, tau0)
        return memo[gains, ts]

    def p_gains(kc: float) -> PidSettings:
        return PidSettings(kc=kc)

    def pi_gains(ti: float, kc: float = PI_GAIN / a) -> PidSettings:
        return PidSettings(kc=kc, ti=ti)

    def pd_gains(td: float, kc: float = PD_GAIN / a) -> PidSettings:
        return PidSettings(kc=kc, td=td, n=DERIVATIVE_N)

    def fine(_falling: bool) -> tuple[float, ...]:
        return (FINE_TS,)

    def pd_fine(falling: bool) -> tuple[float, ...]:  # b′: T_D moves 14× as fast as L there
        return (FINE_TS, FINEST_TS) if falling else (FINE_TS,)

    found: dict[str, list[Crossing]] = {"p": [], "pi": [], "pd": []}
    if "p" in parts:  # the decay ratio grows with the gain: one crossing
        grid = [k0 * f for f in (0.2, 0.35, 0.5, 0.65, 0.8, 0.95)]
        found["p"] = _crossings(lambda k, ts: read(p_gains(k), ts), grid, fine)
    if "pi" in parts:  # it falls as T_I grows: the largest 25 % T_I, the least integral action
        grid = list(dead * np.geomspace(0.01, 30.0, 10))
        found["pi"] = _crossings(lambda ti, ts: read(pi_gains(ti), ts), grid, fine, grid[0] / 2)
    if "pd" in parts:  # it may cross twice: falling at b′, rising at b
        grid = list(dead * np.linspace(0.0, 1.2, 13))
        found["pd"] = _crossings(lambda td, ts: read(pd_gains(td), ts), grid, pd_fine)
    quarter = {key: [c.value for c in cs if c.quarter] for key, cs in found.items()}
    # the responses at the closed forms' exact settings (M = L = 1)
    closed_p = read(p_gains(cf.mk4), FINE_TS) if "p" in parts else None
    closed_pi = read(pi_gains(cf.ti4, PI_GAIN * r), FINE_TS) if "pi" in parts else None
    pd_tds = [td for _, td in cf.pd] if "pd" in parts else []
    closed_pd = tuple(read(pd_gains(td, PD_GAIN * r), FINE_TS) for td in pd_tds)
    return Measured(
        t_over_l=r,
        k0=k0,
        tau0=tau0,
        rate=rate,
        dead_time=dead,
        k4=quarter["p"][0] if quarter["p"] else None,
        ti4=quarter["pi"][-1] if quarter["pi"] else None,
        td4=tuple(sorted(quarter["pd"])),
        dr_closed_p=math.nan if closed_p is None else closed_p.first_crests,
        dr_closed_pi=math.nan if closed_pi is None else closed_pi.first_crests,
        dr_closed_pd=tuple(c.first_crests for c in closed_pd),
        dr_zn_ultimate=setpoint_decay_ratio(r, p_gains(0.5 * k0), FINE_TS, horizon),
        dr_zn_reaction=setpoint_decay_ratio(r, p_gains(1.0 / a), FINE_TS, horizon),
        p_crossings=tuple(found["p"]),
        pi_crossings=tuple(found["pi"]),
        pd_crossings=tuple(found["pd"]),
        closed_p=closed_p,
        closed_pi=closed_pi,
        closed_pd=closed_pd,
    )


# --- the three tables ----------------------------------------------------------------------

MEASURED, NOT_DOMINANT, NO_CROSSING = "measured", "not dominant", "no crossing"


def _error(measured: float | None, closed: float) -> float | None:
    """measured/closed − 1, None without a measured value or a curve."""
    if measured is None or not math.isfinite(closed):
        return None
    return measured / closed - 1.0


def _gain_factor(m: Measured) -> float:
    """K·R·L with the plant's own R·L (= L/T = 1/r) over the rule's λ: the step test's R·L
    error alone makes the applied gain λ·this/(R·L)."""
    return 1.0 / (m.t_over_l * m.a)


def _ratio_text(reading: Reading) -> str:
    """How a response's tail behaves, for a note (L = 1 s)."""
    ratio, turns = reading.crest_ratio, reading.crest_period
    if ratio is None or not reading.mode_omega:
        return "leaves no oscillation above rounding to read"
    period = 2.0 * math.pi / reading.mode_omega
    change = f"grows {ratio:.3g}-fold" if ratio >= 1.0 else f"falls to {ratio:.3f}"
    spacing = "" if turns is None else f", turning every {turns / 2:.3g} L"
    return f"{change} per {period:.3g} L at its end{spacing}"


def _point(
    name: str,
    key: str,
    closed: float,
    wl: float,
    crossing: Crossing | None,
    crossings: Sequence[Crossing],
    at_curve: Reading | None,
    scale: float,
    rl_shift: float,
    symbol: str,
    dead: float,
) -> tuple[dict, list[str]]:
    """One measured setting beside its curve ``closed`` (and the curve's ωL ``wl``): the
    measured value (``crossing``'s, over ``scale``; None where no setting gives a 25 %-damped
    response), its error, status, mode and first crests there, what the response does at the
    curve's own setting (``at_curve``), the step test's R·L shift, and the notes (naming the
    setting ``symbol``; ``dead`` the measured L, s)."""
    notes: list[str] = []
    if at_curve is None and not crossings:  # this controller was not measured
        return {f"{key}_measured": None, f"{key}_error": None, f"{key}_status": None}, notes
    value = None if crossing is None else crossing.value / scale
    status = MEASURED if crossing is not None else NO_CROSSING
    if crossing is None and any(not c.quarter for c in crossings):
        status = NOT_DOMINANT
    pair_there = at_curve is not None and (
        at_curve.dominant and abs(at_curve.mode_ratio - QUARTER) <= CLOSED_SLACK
    )
    if at_curve is not None and not pair_there:
        notes.append(
            f"{name}: at the curve's setting the response is not 25 % damped: its tail "
            f"{_ratio_text(at_curve)}, the 25 % pair would decay 0.25 per "
            f"{2 * math.pi / wl:.2f} L (the pair does not dominate)"
        )
    if crossing is None and math.isfinite(closed):
        where = "; ".join(
            f"at {symbol} = {c.value / scale:.4g}, "
            + (
                "another mode takes the tail over (the ratio jumps)"
                if c.sample_time == COARSE_TS
                else f"the mode does not account for the response, which {_ratio_text(c.reading)}"
            )
            for c in crossings
            if not c.quarter
        )
        notes.append(
            f"{name}: no setting gives a 25 %-damped response: the decay ratio of the "
            + (
                f"response's dominant mode crosses 0.25 only where it is not dominant: {where}"
                if where
                else "response's dominant mode never crosses 0.25"
            )
        )
    err = _error(value, closed)
    if crossing is not None and at_curve is not None and pair_there:
        first = at_curve.first_crests
        if abs(first - QUARTER) > 0.01:
            notes.append(
                f"{name}: a trend's first two crests show {first:.3f} at the curve's "
                "setting (faster modes still weigh there), its tail decays as the 25 % pair"
            )
    if math.isfinite(rl_shift) and abs(rl_shift) > RL_NOTE:
        notes.append(
            f"{name}: the step test's R·L error alone moves this curve by "
            f"{100 * rl_shift:+.2f} % (the gain λ/(R·L) is applied with the measured R·L)"
        )
    if err is not None and abs(err) > TOLERANCE:
        share = (
            f", {100 * rl_shift:+.2f} % of it from the step test's R·L"
            if math.isfinite(rl_shift)
            else ""
        )
        notes.append(
            f"{name}: measured {value:.4g} is {100 * err:+.1f} % off the curve ({closed:.4g})"
            + share
        )
    row = {
        f"{key}_measured": value,
        f"{key}_error": err,
        f"{key}_status": status if math.isfinite(closed) else None,
        f"{key}_wl_measured": None if crossing is None else crossing.reading.mode_omega * dead,
        f"{key}_first_crests_measured": None if crossing is None else crossing.reading.first_crests,
        f"{key}_sample_time": None if crossing is None else crossing.sample_time,
        f"{key}_pair_dominates_at_closed_form": None if at_curve is None else pair_there,
        f"{key}_rl_shift": rl_shift if math.isfinite(rl_shift) else None,
    }
    return row, notes


def fig1_row(cf: ClosedForm, m: Measured | None) -> dict:
    """Fig. 1, P control: K₀/K₄ (ZN's K₀/2 rule: 2) and K₄·R·L (ZN's 1/(R·L) rule: 1)."""
    row = {
        "t_over_l": cf.t_over_l,
        "w4l": cf.w4l,
        "k0_over_k4": cf.k0_over_k4,
        "k4rl": cf.k4rl,
        "zn_k0_over_k1": ZN_P_ULTIMATE,
        "zn_k1rl": ZN_P_REACTION,
    }
    if m is None:
        return row | {"notes": []}
    crossing = next((c for c in m.p_crossings if c.quarter), None)
    point, notes = _point(
        "P K₄",
        "k4",
        cf.mk4,
        cf.w4l,
        crossing,
        m.p_crossings,
        m.closed_p,
        1.0,
        m.a * m.t_over_l - 1,
        "K",
        m.dead_time,
    )
    k4 = point.get("k4_measured")
    k0_over_k4 = None if k4 is None else m.k0 / k4
    k4rl = None if k4 is None else k4 * m.a
    return row | {
        "k0_over_k4_measured": k0_over_k4,
        "k0_over_k4_error": _error(k0_over_k4, cf.k0_over_k4),
        "k4rl_measured": k4rl,
        "k4rl_error": _error(k4rl, cf.k4rl),
        "k4_status": point.get("k4_status"),
        "w4l_measured": point.get("k4_wl_measured"),
        "k4rl_rl_shift": point.get("k4_rl_shift"),
        "decay_ratio_at_closed_form": m.dr_closed_p,
        "mode_decay_ratio_at_closed_form": None if m.closed_p is None else m.closed_p.mode_ratio,
        "pair_dominates_at_closed_form": point.get("k4_pair_dominates_at_closed_form"),
        "decay_ratio_at_measured": point.get("k4_first_crests_measured"),
        "decay_ratio_zn_ultimate": m.dr_zn_ultimate,
        "decay_ratio_zn_reaction": m.dr_zn_reaction,
        "notes": notes,
    }


def fig2_row(cf: ClosedForm, m: Measured | None) -> dict:
    """Fig. 2: K₀·R·L and τ₀/L (ZN's two rules agree where they are 2 and 4, eq. 8)."""
    row = {
        "t_over_l": cf.t_over_l,
        "k0rl": cf.k0rl,
        "tau0": cf.tau0,
        "zn_k0rl": ZN_K0RL,
        "zn_tau0": ZN_TAU0,
    }
    if m is None:
        return row | {"notes": []}
    k0rl, tau0 = m.k0 * m.a, m.tau0 / m.dead_time
    notes = []
    for name, value, closed in (("K₀·R·L", k0rl, cf.k0rl), ("τ₀/L", tau0, cf.tau0)):
        err = _error(value, closed)
        if err is not None and abs(err) > TOLERANCE:
            notes.append(f"{name}: measured {value:.4g} is {100 * err:+.1f} % off ({closed:.4g})")
    return row | {
        "k0rl_measured": k0rl,
        "k0rl_error": _error(k0rl, cf.k0rl),
        "k0rl_rl_shift": m.a * m.t_over_l - 1.0,
        "tau0_measured": tau0,
        "tau0_error": _error(tau0, cf.tau0),
        "notes": notes,
    }


def _match(closed: Sequence[float], measured: Sequence[Crossing]) -> list[Crossing | None]:
    """Each closed-form branch's nearest measured crossing (relative), none used twice."""
    left = list(measured)
    out: list[Crossing | None] = []
    for c in closed:
        if not left:
            out.append(None)
            continue
        best = min(left, key=lambda x: abs(x.value / c - 1.0))
        left.remove(best)
        out.append(best)
    return out


def _shifted(values: Sequence[float], shifted: Sequence[float]) -> list[float]:
    """Each value's relative shift, NaN where the shifted solution lost a branch."""
    if len(values) != len(shifted):
        return [math.nan] * len(values)
    return [s / v - 1.0 for v, s in zip(values, shifted, strict=True)]


def fig3_row(cf: ClosedForm, m: Measured | None) -> dict:
    """Fig. 3: T_I4/L at ZN's PI gain (ZN: 3.33) and T_D4/L at the PD gain 1.2/(R·L), both
    branches (the paper: 0.36–0.37)."""
    upper, lower = cf.td4_upper, cf.td4_lower
    row = {
        "t_over_l": cf.t_over_l,
        "pi_wl": cf.pi_wl,
        "ti4": cf.ti4,
        "zn_ti": ZN_TI,
        "td4_upper": upper,
        "td4_lower": lower if math.isfinite(lower) else None,
        "pd_wl": [x for x, _ in cf.pd],
        "pd_chain_decay": [chain_decay(td) for _, td in cf.pd],  # per L, ideal PD
        "pd_pair_decay": [SIGMA4 * x for x, _ in cf.pd],  # per L
        "paper_td": list(PAPER_TD),
    }
    notes = [
        f"PD ({'b' if i == len(cf.pd) - 1 else 'b′'}): the ideal derivative's high-frequency "
        f"roots decay at {chain_decay(td):.2f}/L, slower than the pair's {SIGMA4 * x:.2f}/L: "
        "eq. 15's T_D does not give a 25 % damped loop"
        for i, (x, td) in enumerate(cf.pd)
        if not cf.pd_dominated(i)
    ]
    if m is None:
        return row | {"notes": notes}
    f = _gain_factor(m)
    pi_cross = [c for c in m.pi_crossings if c.quarter][-1:]
    pi, pi_notes = _point(
        "PI T_I4",
        "ti4",
        cf.ti4,
        cf.pi_wl,
        pi_cross[0] if pi_cross else None,
        m.pi_crossings,
        m.closed_pi,
        m.dead_time,
        quarter_pi(m.t_over_l, PI_GAIN * f)[1] / cf.ti4 - 1.0,
        "T_I/L",
        m.dead_time,
    )
    names = ("lower", "upper")[2 - len(cf.pd) :]  # b′ then b, or b alone
    labels = {"lower": "b′", "upper": "b"}
    quarter = [c for c in m.pd_crossings if c.quarter]
    matched = _match([td for _, td in cf.pd], quarter)
    shifts = _shifted(
        [td for _, td in cf.pd], [td for _, td in quarter_pd(m.t_over_l, PD_GAIN * f)]
    )
    pd: dict = {}
    pd_notes: list[str] = []
    for i, branch in enumerate(names):
        point, n = _point(
            f"PD T_D4 ({labels[branch]})",
            f"td4_{branch}",
            cf.pd[i][1],
            cf.pd[i][0],
            matched[i],
            m.pd_crossings,
            m.closed_pd[i] if i < len(m.closed_pd) else None,
            m.dead_time,
            shifts[i],
            "T_D/L",
            m.dead_time,
        )
        pd |= point
        pd_notes += n
    extra = [c for c in quarter if c not in matched]
    if extra:
        pd_notes.append(
            "PD: the response is also 25 % damped at T_D/L = "
            + ", ".join(f"{c.value / m.dead_time:.3f}" for c in extra)
        )
    closed_pd = [c.mode_ratio for c in m.closed_pd]
    return (
        row
        | {f"td4_{b}_{k}": None for b in ("upper", "lower") for k in ("measured", "error")}
        | pi
        | pd
        | {
            "decay_ratio_pi_at_closed_form": m.dr_closed_pi,
            "decay_ratio_pd_upper_at_closed_form": _branch(m.dr_closed_pd, names, "upper"),
            "decay_ratio_pd_lower_at_closed_form": _branch(m.dr_closed_pd, names, "lower"),
            "mode_decay_ratio_pi_at_closed_form": m.closed_pi and m.closed_pi.mode_ratio,
            "mode_decay_ratio_pd_upper_at_closed_form": _branch(closed_pd, names, "upper"),
            "mode_decay_ratio_pd_lower_at_closed_form": _branch(closed_pd, names, "lower"),
            "td4_measured_all": [c.value / m.dead_time for c in quarter],
            "notes": pi_notes + notes + pd_notes,
        }
    )


def _branch(values: Sequence, names: Sequence[str], branch: str):
    """The value of ``branch`` ('lower' b′, 'upper' b) in per-branch ``values``, or None."""
    return values[names.index(branch)] if branch in names and len(values) == len(names) else None


def findings() -> dict[str, float]:
    """The T/L where the paper's statements turn, and its limits (T/L → ∞, at 10⁶)."""
    far = closed_form(1e6)
    return {
        "ti4_equals_zn_at_t_over_l": ti4_meets_zn(),
        "pd_two_branches_above_t_over_l": pd_two_branches_above(),
        "pd_chain_slower_than_pair_below_t_over_l": pd_chain_dominates_below(),
        "k0_over_k4_limit": far.k0_over_k4,
        "k4rl_limit": far.k4rl,
        "ti4_limit": far.ti4,
        "td4_upper_limit": far.td4_upper,
        "td4_lower_limit": far.td4_lower,
    }


@dataclass(frozen=True)
class Figures:
    """The three tables at ``ratios`` with measured points where measured, and findings."""

    fig1: list[dict]
    fig2: list[dict]
    fig3: list[dict]
    findings: dict[str, float]
    measured: list[Measured] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "plant": "K·e^{-Ls}/(1+sT); measured on K = 1 PV unit per %, L = 1 s, T = T/L s",
            "sigma4": SIGMA4,
            "fig1": self.fig1,
            "fig2": self.fig2,
            "fig3": self.fig3,
            "findings": self.findings,
            "experiments": [m.to_dict() for m in self.measured],
            "failures": self.failures,
            "sample_time_over_l": {
                "search": COARSE_TS,
                "measured": FINE_TS,
                "measured_curve_b_lower": FINEST_TS,
            },
            "derivative_filter_n": DERIVATIVE_N,
            "tail": {
                "watched_for": f"L + {WATCH_PERIODS:g} τ0 (PI: {WATCH_PERIODS_PI:g} τ0)",
                "read_from": f"L + {TAIL_FROM:g} τ0",
                "pencil_step_over_tau0": 1.0 / TAIL_SAMPLES,
                "pencil_order": PENCIL_ORDER,
                "crest_ratio_tolerance": CREST_RATIO_TOL,
                "crest_period_tolerance": CREST_PERIOD_TOL,
            },
            "tolerance": TOLERANCE,
        }


def _measure_or_reason(r: float) -> Measured | str:
    """``measure(r)``, or the reason it failed (a worker's result)."""
    try:
        return measure(r)
    except RuntimeError as err:
        return str(err)


def figures(
    ratios: Sequence[float], measure_at: Sequence[float], workers: int | None = None
) -> Figures:
    """Closed forms at every T/L of ``ratios`` and ``measure_at`` (ascending), the product's
    experiments at ``measure_at``, in up to ``workers`` processes (default: one per CPU, at
    most ``MAX_WORKERS``); an experiment that fails leaves its row unmeasured and a line in
    ``failures``."""
    rows = sorted(set(ratios) | set(measure_at))
    todo = sorted(set(measure_at), reverse=True)  # the longest first
    if workers is None:
        workers = min(os.cpu_count() or 1, MAX_WORKERS)
    workers = min(workers, len(todo))
    results: dict[float, Measured | str] = {}
    if workers > 1:
        # spawned, not forked: the parent may hold threads (a bus session, BLAS); where no
        # process can be started (no semaphores in a sandbox), one after the other below
        context = multiprocessing.get_context("spawn")
        try:
            with ProcessPoolExecutor(workers, mp_context=context) as pool:
                results = dict(zip(todo, pool.map(_measure_or_reason, todo), strict=True))
        except (OSError, BrokenProcessPool):
            results = {}
    for r in todo:
        if r not in results:
            results[r] = _measure_or_reason(r)
    measured = {r: v for r, v in sorted(results.items()) if isinstance(v, Measured)}
    failures = [v for _, v in sorted(results.items()) if isinstance(v, str)]
    forms = [closed_form(r) for r in rows]
    return Figures(
        fig1=[fig1_row(cf, measured.get(cf.t_over_l)) for cf in forms],
        fig2=[fig2_row(cf, measured.get(cf.t_over_l)) for cf in forms],
        fig3=[fig3_row(cf, measured.get(cf.t_over_l)) for cf in forms],
        findings=findings(),
        measured=list(measured.values()),
        failures=failures,
    )


# --- the benchmark's Fig. 2 table (moved here from ``benchmark``, which re-exports it) -------


@dataclass(frozen=True)
class IinoyaHottaRow:
    t_over_l: float
    krl_exact: float
    krl_measured: float
    tau_exact: float
    tau_measured: float
    decay_ratio_zn_p: float

    @property
    def krl_error(self) -> float:
        return self.krl_measured / self.krl_exact - 1.0

    @property
    def tau_error(self) -> float:
        return self.tau_measured / self.tau_exact - 1.0

    def to_dict(self) -> dict:
        return {**asdict(self), "krl_error": self.krl_error, "tau_error": self.tau_error}


def iinoya_hotta_row(t_over_l: float) -> IinoyaHottaRow:
    """The relay's K₀·R·L and τ₀/L (with the plant's exact R and L) against eq. 5, and the
    decay ratio of ZN's P rule 0.5·K₀ (``benchmark.decay_ratio``)."""
    plant = fopdt(t_over_l)
    outcome = run_relay(plant, 0.0)
    ku = outcome.ku_exact * (1.0 + outcome.ku_error)
    pu = outcome.pu_exact * (1.0 + outcome.pu_error)
    krl, tau = iinoya_hotta(t_over_l)
    dr = decay_ratio(IsaGains(0.5 * ku), plant, pu)
    return IinoyaHottaRow(t_over_l, krl, ku / t_over_l, tau, pu, dr)
