"""Low-order process models fitted to measured frequency points.

The relay test measures G(jω) exactly at a handful of frequencies (its two stages'
fundamentals and their harmonics). Three classic models are fitted to them by least squares on
the complex logarithm (log-magnitude and phase errors, in nepers and radians, weighted):

    FOPDT  K·e^{−Ls}/(Ts + 1)
    SOPDT  K·e^{−Ls}/((T₁s + 1)(T₂s + 1)),  T₁ ≥ T₂
    IPDT   K·e^{−Ls}/s           (integrating, e.g. a tank level)

and the one that fits best is chosen, a model with more parameters only when it fits clearly
better (its residual at most half the simpler one's). The model gives what the points alone do
not: the static gain, L/T for the rules' guidance, model-based rules (AMIGO, SIMC) and the
robustness (Ms) of candidate gains.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from shared.control.lti import discretize, simulate, tf_to_ss
from shared.control.transfer import DelayedTF

# scipy.optimize is imported where it is used, not here: it is a third of a second of the
# start of every `autotune` command that loads this module, and most never fit anything


@dataclass(frozen=True)
class ProcessFit:
    kind: str  # "fopdt" | "sopdt" | "ipdt"
    gain: float  # K: PV units per % (IPDT: PV units per % per second)
    lags: tuple[float, ...]  # time constants, s (none for IPDT)
    delay: float  # L, s
    rms: float  # weighted rms of the log residual (nepers ≈ radians); on a record: see there
    noise_rms: float = 0.0  # the rms the measurement noise alone would leave (record fits)
    source: str = "fit"  # "fit", or "reaction curve" (a tangent construction, never exact)
    # %: the held output's offset from the balance, fitted beside a model that integrates
    # over its record (``refine_on_record`` with ``offset``: an IPDT, the ramp's start behind
    # a lag); None: not fitted
    offset: float | None = None
    # a record fit's residual rms (over the PV's standard deviation) beyond white noise's:
    # √(rms² − ½·mean(Δr²)), the part of the residual one sample does not wash out. What the
    # model misses, read from its own residual, without the rest's noise estimate, which from a
    # short rest is off by ±20 % (flow1: 0.155–0.223 for σ 0.2). None: not a record fit
    structured_rms: float | None = None

    @property
    def approximate(self) -> bool:
        """The fit leaves clearly more than the noise (the plant is outside the model's
        class), or the model is a reaction curve's tangent construction (which ignores the
        response's shape): what it predicts away from its data is less certain."""
        return self.source != "fit" or self.rms > max(2.0 * self.noise_rms, 0.02)

    @property
    def excess_rms(self) -> float:
        """The fit's residual beyond the measurement noise (over the PV's standard deviation):
        √(rms² − noise_rms²), or the residual's own ``structured_rms`` where that is less (a
        rest that read the noise low makes the first a misfit the residual does not show)."""
        noise = self.noise_rms if math.isfinite(self.noise_rms) else 0.0
        excess = math.sqrt(max(self.rms**2 - noise**2, 0.0))
        return excess if self.structured_rms is None else min(excess, self.structured_rms)

    @property
    def num(self) -> list[float]:
        return [self.gain]

    @property
    def den(self) -> list[float]:
        if self.kind == "ipdt":
            return [1.0, 0.0]
        den = np.array([1.0])
        for tau in self.lags:
            den = np.polymul(den, [tau, 1.0])
        return [float(c) for c in den]

    @property
    def lag(self) -> float:
        """T: the dominant lag (FOPDT's T; SOPDT's T₁ + T₂; inf for an integrator)."""
        return float(sum(self.lags)) if self.lags else math.inf

    @property
    def normalised_delay(self) -> float:
        """L/T (0 for an integrator)."""
        return self.delay / self.lag if self.lags else 0.0

    @property
    def transfer(self) -> DelayedTF:
        """The model as a transfer function with dead time, K·e^{−Ls}/den(s)."""
        return DelayedTF.of(self.num, self.den, self.delay)

    def response(self, omega: np.ndarray | float) -> np.ndarray:
        """G(jω) at ω in rad/s."""
        return self.transfer.response(omega)

    def phase(self, omega: float) -> float:
        """The continuous (unwrapped) phase of G(jω), rad."""
        ph = -omega * self.delay - sum(math.atan(omega * tau) for tau in self.lags)
        return ph - (0.5 * math.pi if self.kind == "ipdt" else 0.0)

    def ultimate_point(self) -> tuple[float, float] | None:
        """(K_u in % per PV unit, P_u in s), or None if the phase never reaches −180°."""
        return self.transfer.ultimate_point()

    def to_dict(self) -> dict[str, float | str]:
        out: dict[str, float | str] = {
            "model": self.kind,
            "model_gain": self.gain,
            "model_delay": self.delay,
            "model_rms": self.rms,
        }
        for i, tau in enumerate(self.lags, start=1):
            out[f"model_lag_{i}"] = tau
        if self.offset is not None:
            out["model_offset"] = self.offset
        return out


def _shape(kind: str, x: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """log G(jω) of the model with parameters x = (ln K, ln T…, L)."""
    s = 1j * omega
    log_g = x[0] - s * x[-1]
    if kind == "ipdt":
        return log_g - np.log(s)
    for ln_tau in x[1:-1]:
        log_g = log_g - np.log1p(s * math.exp(ln_tau))
    return log_g


def _fit_one(kind: str, omega: np.ndarray, g: np.ndarray, weights: np.ndarray) -> ProcessFit | None:
    log_g = np.log(np.abs(g)) + 1j * np.angle(g)

    def residual(x: np.ndarray) -> np.ndarray:
        d = _shape(kind, x, omega) - log_g
        # the phase residual wrapped to (−π, π]: the model's own branch is continuous
        d = d.real + 1j * (np.mod(d.imag + math.pi, 2 * math.pi) - math.pi)
        return np.concatenate([d.real * weights, d.imag * weights])

    w0 = float(omega[0])
    starts = []
    n_lags = {"fopdt": 1, "sopdt": 2, "ipdt": 0}[kind]
    for lag_scale in (0.3, 3.0):
        for delay_scale in (0.1, 1.0):
            taus = [lag_scale / w0, 0.3 * lag_scale / w0][:n_lags]
            mag = abs(g[0]) * np.prod([math.hypot(1.0, w0 * t) for t in taus])
            if kind == "ipdt":
                mag = abs(g[0]) * w0
            starts.append(np.array([math.log(mag), *map(math.log, taus), delay_scale / w0]))
    # bounds keep the search finite: lags within 1e-4…1e5 of 1/ω, delay up to 20/ω
    lo = np.array([-60.0] + [math.log(1e-4 / w0)] * n_lags + [0.0])
    hi = np.array([60.0] + [math.log(1e5 / w0)] * n_lags + [20.0 / w0])
    from scipy.optimize import least_squares

    best = None
    for x0 in starts:
        try:
            sol = least_squares(
                residual, np.clip(x0, lo, hi), bounds=(lo, hi), x_scale="jac", max_nfev=200
            )
        except (ValueError, FloatingPointError, OverflowError):
            continue
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None or not np.all(np.isfinite(best.x)):
        return None
    x = best.x
    lags = tuple(sorted((math.exp(v) for v in x[1:-1]), reverse=True))
    rms = math.sqrt(2.0 * best.cost / max(1.0, float(np.sum(weights**2)) * 2.0))
    return ProcessFit(kind, math.exp(x[0]), lags, float(x[-1]), rms)


def fit_models(
    omega: Sequence[float], g: Sequence[complex], weights: Sequence[float] | None = None
) -> list[ProcessFit]:
    """Every model that could be fitted to the points, best fit first."""
    om = np.asarray(omega, dtype=float)
    gg = np.asarray(g, dtype=complex)
    if om.size < 2 or om.size != gg.size:
        raise ValueError("points: need at least two frequency points")
    order = np.argsort(om)
    om, gg = om[order], gg[order]
    wt = np.ones_like(om) if weights is None else np.asarray(weights, dtype=float)[order]
    fits = [f for kind in ("fopdt", "ipdt", "sopdt") if (f := _fit_one(kind, om, gg, wt))]
    return sorted(fits, key=lambda f: f.rms)


def choose(fits: Sequence[ProcessFit]) -> ProcessFit | None:
    """The simplest model whose fit is not clearly beaten: more parameters must halve the
    residual (an rms below 1e-3 counts as exact)."""
    if not fits:
        return None
    simple = [f for f in fits if f.kind in ("fopdt", "ipdt")]
    best_simple = min(simple, key=lambda f: f.rms) if simple else None
    sopdt = next((f for f in fits if f.kind == "sopdt"), None)
    if best_simple is None:
        return sopdt
    if sopdt is None or best_simple.rms <= max(2.0 * sopdt.rms, 1e-3):
        return best_simple
    return sopdt


def _params(fit: ProcessFit) -> np.ndarray:
    return np.array([math.log(fit.gain), *(math.log(t) for t in fit.lags), fit.delay])


def _from_params(kind: str, x: np.ndarray, rms: float) -> ProcessFit:
    lags = tuple(sorted((math.exp(v) for v in x[1:-1]), reverse=True))
    return ProcessFit(kind, math.exp(x[0]), lags, float(x[-1]), rms)


def response_to(fit: ProcessFit, sample_time: float, u: np.ndarray) -> np.ndarray:
    """The model's sampled response from rest to the held output deviations ``u``: element
    k is the PV deviation at sample k (so element 0 is 0)."""
    sys = discretize(*tf_to_ss(fit.num, fit.den), sample_time, fit.delay)
    return simulate(sys, u)[: len(u)]


MAX_RECORD = 4000  # samples a record fit works on (longer records are block-averaged)


def _blocks(
    u: np.ndarray, y: np.ndarray, sample_time: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """The record a fit works on: a record longer than MAX_RECORD samples in blocks of k
    samples (the output averaged over each, the PV at its start), and their sample time."""
    k = math.ceil(y.size / MAX_RECORD)
    if k <= 1:
        return u, y, sample_time
    n = (y.size // k) * k
    return u[:n].reshape(-1, k).mean(axis=1), y[:n:k], sample_time * k


def refine_on_record(
    start: ProcessFit, sample_time: float, u: np.ndarray, y: np.ndarray, offset: bool = False
) -> ProcessFit | None:
    """The model of ``start``'s kind that best reproduces a whole record (output error, least
    squares), starting from ``start``. ``u``: output deviations held from each sample; ``y``:
    PV deviations at the samples, both from a rest at the record's start. The record carries
    what the frequency points cannot: the slow response, and so the static gain. A record
    longer than MAX_RECORD samples is fitted in blocks (the output averaged over each, the PV
    at its start): a model, unlike the ultimate point, does not need every sample.

    With ``offset``, the model also fits the output's offset from its balance (``u`` − u₀),
    for a model that integrates over the record (an IPDT, or a lag far slower than the
    record: the callers ask it of those alone): a loop held for the test at an output off the
    one that balances its flows drifts from the start, and a level re-tuned from auto, held
    at its controller's mean output (a noisy mean: 0.6 % off), read "IPDT fit misses the
    record" with its dead time exact (the relay's bias found the balance; the model, without
    u₀, integrated the bias's move as a ramp the PV never made).

    The returned ``rms`` is the residual's rms over the PV's standard deviation."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    u, y, sample_time = _blocks(u, y, sample_time)
    scale = float(np.std(y)) or 1.0
    w0 = 1.0 / max(start.delay + start.lag if start.lags else start.delay, sample_time)
    n_lags = len(start.lags)
    lo = np.array([-60.0] + [math.log(sample_time / 100)] * n_lags + [0.0])
    hi = np.array([60.0] + [math.log(1e6 / w0)] * n_lags + [len(u) * sample_time / 2])
    x0 = _params(start)
    free = offset  # u₀, % of output: the last parameter
    if free:
        reach = float(np.max(np.abs(u))) + 1.0 if u.size else 1.0
        lo, hi, x0 = np.append(lo, -reach), np.append(hi, reach), np.append(x0, 0.0)

    def model_of(x: np.ndarray, rms: float) -> ProcessFit:
        if not free:
            return _from_params(start.kind, x, rms)
        return dataclasses.replace(_from_params(start.kind, x[:-1], rms), offset=float(x[-1]))

    def residual(x: np.ndarray) -> np.ndarray:
        try:
            held = u - x[-1] if free else u
            return (response_to(model_of(x, 0.0), sample_time, held) - y) / scale
        except (ValueError, np.linalg.LinAlgError, OverflowError):
            return np.full(y.size, 1e3)

    from scipy.optimize import least_squares

    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
    try:
        sol = least_squares(residual, x0, bounds=(lo, hi), x_scale="jac", max_nfev=100)
    except (ValueError, FloatingPointError, OverflowError):
        return None
    if not np.all(np.isfinite(sol.x)):
        return None
    rms = math.sqrt(2.0 * sol.cost / y.size)
    return dataclasses.replace(model_of(sol.x, rms), structured_rms=_structured(sol.fun, rms))


def _structured(residual: np.ndarray, rms: float) -> float | None:
    """``ProcessFit.structured_rms`` of a residual whose rms is ``rms``: white noise's
    residual has ½·mean(Δr²) = mean(r²); what a model misses changes little from one sample
    to the next, and adds to mean(r²) alone."""
    if residual.size < 3 or not np.all(np.isfinite(residual)):
        return None
    white = 0.5 * float(np.mean(np.diff(residual) ** 2))
    return math.sqrt(max(rms**2 - white, 0.0))


def delay_spread(fit: ProcessFit, sample_time: float, u: np.ndarray, y: np.ndarray) -> float | None:
    """The standard error (s) of ``fit``'s dead time as ``refine_on_record`` fitted it to the
    record (``u``, ``y`` as there): the linearised least-squares one, σ²·(JᵀJ)⁻¹ with σ the
    fit's residual rms and J the residual's derivatives in its parameters (central
    differences, on the record as the fit worked on it). What tells a dead time the record
    resolves from one it only does not rule out: a lag's response in noise fits any dead
    time up to seconds about as well, and the fit's own figure there is noise (the
    gravity-drain tank's 1 s read as 0.025 s). None: no such figure (an offset fitted,
    a singular J)."""
    if fit.offset is not None:
        return None
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    u, y, sample_time = _blocks(u, y, sample_time)  # as refine_on_record fitted it
    x = _params(fit)

    def residual(p: np.ndarray) -> np.ndarray:
        return response_to(_from_params(fit.kind, p, 0.0), sample_time, u) - y

    try:
        r0 = residual(x)
        cols = []
        for i in range(x.size):
            h = 1e-6 * max(1.0, abs(x[i])) if i < x.size - 1 else 1e-3 * sample_time
            lo, hi = x.copy(), x.copy()
            central = i < x.size - 1 or x[i] - h >= 0.0  # a dead time near 0: one-sided
            hi[i], lo[i] = x[i] + h, (x[i] - h if central else x[i])
            cols.append((residual(hi) - residual(lo)) / (2.0 * h if central else h))
        jac = np.column_stack(cols)
        dof = max(y.size - x.size, 1)
        cov = float(np.sum(r0**2)) / dof * np.linalg.inv(jac.T @ jac)
    except (ValueError, np.linalg.LinAlgError, OverflowError):
        return None
    var = float(cov[-1, -1])
    return math.sqrt(var) if math.isfinite(var) and var >= 0.0 else None


def choose_on_record(fits: Sequence[ProcessFit], samples: int) -> ProcessFit | None:
    """The fit with the least Bayesian information criterion N·ln(rms²) + p·ln N: more
    parameters must earn their place."""
    if not fits:
        return None

    samples = min(samples, MAX_RECORD)  # what the fits worked on

    def bic(f: ProcessFit) -> float:
        p = 2 + len(f.lags) + (f.offset is not None)  # a fitted offset is a parameter too
        return samples * math.log(max(f.rms, 1e-12) ** 2) + p * math.log(samples)

    return min(fits, key=bic)


def through_ultimate_point(ku: float, pu: float) -> list[ProcessFit]:
    """Starting models that share a measured ultimate point: first order with L/T of 0.1, 0.5
    and 2, second order with equal lags and L = T/5, and an integrator with dead time — for
    ``refine_on_record`` when no frequency points are known (the P-gain ramp)."""
    from scipy.optimize import brentq

    w = 2.0 * math.pi / pu
    out = []
    for ratio in (0.1, 0.5, 2.0):  # atan(x) + r·x = π, x = ωT
        x = brentq(lambda x, r=ratio: math.atan(x) + r * x - math.pi, 1e-9, math.pi / ratio)
        t = x / w
        out.append(ProcessFit("fopdt", math.hypot(1.0, x) / ku, (t,), ratio * t, math.inf))
    x = brentq(lambda x: 2.0 * math.atan(x) + 0.2 * x - math.pi, 1e-9, 5.0 * math.pi)
    t = x / w
    out.append(ProcessFit("sopdt", (1.0 + x * x) / ku, (t, t), 0.2 * t, math.inf))
    out.append(ProcessFit("ipdt", w / ku, (), math.pi / (2.0 * w), math.inf))
    return out


# the lags' ratios of ``second_order_starts``: apart (a heat exchanger's are 6 apart), and
# an integrator behind a lag (the slow lag's phase at ω_u within 0.3° of 90°: over a test's
# record it integrates)
LAGS_APART = 10.0
SLOW_LAG = 100.0


def second_order_starts(ku: float, pu: float) -> list[tuple[ProcessFit, bool]]:
    """More starts through a measured ultimate point for the second-order fit, each with
    whether ``refine_on_record`` should fit the output's offset beside it: lags ``LAGS_APART``
    apart, and an integrator behind a lag (lags ``SLOW_LAG`` apart: a level behind its valve,
    a transmitter's filter; the offset fitted, as an integrator's is); each with a dead time
    of a fifth of its faster lag.

    Why: from ``through_ultimate_point``'s equal lags the refine ends in the minimum nearest
    them, and the integrator has no term for a lag. The heat exchanger e^{−5s}/((10s + 1)(60s
    + 1)) by ramp fitted equal lags of 27 s and a 3.4 s dead time, on which SIMC PID was
    predicted Ms 2.0 and is 3.3 (from lags 10 apart: 60.1 s, 10.0 s, 5.0 s); 0.05·e^{−s}/(s(2s
    + 1)) fitted an IPDT 0.27 of the PV's spread off, refused (K·L·K_u 2.5, not π/2), and the
    tuner fell back to TL PI from K_u and P_u alone (Ms 2.26 on the plant), which its
    verification rejected for a 48 % overshoot (from behind a lag: 0.05/s, 2.0 s, 1.0 s)."""
    from scipy.optimize import brentq

    w = 2.0 * math.pi / pu
    out = []
    for ratio, offset in ((LAGS_APART, False), (SLOW_LAG, True)):
        # the slow lag at ratio·x, the fast at x = ωT, the dead time 0.2·x: π in all
        def phase(x: float, r: float = ratio) -> float:
            return math.atan(r * x) + math.atan(x) + 0.2 * x - math.pi

        x = brentq(phase, 1e-9, 5.0 * math.pi)
        gain = math.hypot(1.0, ratio * x) * math.hypot(1.0, x) / ku
        out.append(
            (ProcessFit("sopdt", gain, (ratio * x / w, x / w), 0.2 * x / w, math.inf), offset)
        )
    return out


@dataclass(frozen=True)
class StepModel:
    """Reaction-curve figures: process gain K, dead time L, time constant T (tangent), R = K/T.

    An integrating process (``StepModel.integrating``) has no K nor T (both inf): its
    reaction rate R, the ramp's slope per % of output, is given as ``rate``."""

    gain: float
    dead_time: float
    time_constant: float
    rate: float | None = None  # R, PV units per s per %, for an integrating process

    @classmethod
    def integrating(cls, rate: float, dead_time: float) -> StepModel:
        return cls(math.inf, dead_time, math.inf, rate)

    @property
    def is_integrating(self) -> bool:
        return self.rate is not None

    @property
    def reaction_rate(self) -> float:
        return self.rate if self.rate is not None else self.gain / self.time_constant


def model_of(step: StepModel) -> ProcessFit:
    """The step test's reaction curve as a first-order-plus-dead-time model (an integrating
    one's as K'·e^{−Ls}/s, K' = R)."""
    if step.is_integrating:
        return ProcessFit(
            "ipdt", step.reaction_rate, (), step.dead_time, 0.0, source="reaction curve"
        )
    return ProcessFit(
        "fopdt", step.gain, (step.time_constant,), step.dead_time, 0.0, source="reaction curve"
    )
