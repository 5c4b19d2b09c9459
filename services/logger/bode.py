"""The frequency-response figure of a run: the measured points with their stated
uncertainty, the fitted model's curve and the −180° crossings (Bode and Nyquist data).

What each method measures (``services/autotuner/identify``):
- relay: stage 1's G(jkω₁), k = 1, 3, 5, and stage 2's G(jkω₂), k = 1, (2,) 3, from
  the Fourier components of whole cycles (``fourier``), as the result's ``experiment`` keeps
  them (``omega_k``, ``g_k_magnitude``, ``g_k_phase_deg``, ``stage2_…``);
- ramp: the ultimate point, G(jω_u) = −1/K_u at ω_u = 2π/P_u;
- step: no frequency point (the model alone).
The uncertainty stated with them is the result's ``ku_spread``: K_u = 1/|G(jω_u)| is known
to that relative amount, and it is read as the radius δ of a disc about each fundamental,
|ΔG| ≤ δ·|G| (magnitude ± δ, phase ± asin δ). A harmonic's disc is the noise's share of it
(``g_k_noise``, ``relay_result.harmonic_noise``; runs recorded before: none stated): weak
(1/k of the excitation, through a plant that falls off), a 5th harmonic is often ± 30 %.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from services.autotuner.identify.model_fit import ProcessFit
from services.logger.result_model import result_model
from shared.messages import TuneResult

CURVE_POINTS = 400  # of the model's curve, log-spaced
DECADES_BELOW, DECADES_ABOVE = 1.0, 0.5  # the curve's reach about the measured points


@dataclass(frozen=True)
class MeasuredPoint:
    stage: str  # "stage 1", "stage 2" (relay), "ultimate point" (ramp)
    harmonic: int  # k: G(jkω) of the stage's fundamental ω
    omega: float  # rad/s
    magnitude: float  # |G|, PV units per %
    phase_deg: float  # unwrapped (the lag grows with ω)
    uncertainty: float | None  # δ, relative radius of the disc about G (None: not stated)

    @property
    def g(self) -> complex:
        return self.magnitude * complex(np.exp(1j * math.radians(self.phase_deg)))

    @property
    def magnitude_bounds(self) -> tuple[float, float] | None:
        d = self.uncertainty
        return None if d is None else (self.magnitude * (1 - d), self.magnitude * (1 + d))

    @property
    def phase_bound_deg(self) -> float | None:
        """± degrees: the widest phase angle the disc subtends."""
        d = self.uncertainty
        return None if d is None else math.degrees(math.asin(min(d, 1.0)))


@dataclass(frozen=True)
class Curve:
    """The model's frequency response on a grid: ω (rad/s), |G|, phase (deg, continuous)."""

    label: str
    omega: np.ndarray
    magnitude: np.ndarray
    phase_deg: np.ndarray

    @property
    def g(self) -> np.ndarray:
        return self.magnitude * np.exp(1j * np.radians(self.phase_deg))


@dataclass(frozen=True)
class Crossing:
    """Where a phase reaches −180°: ω_u = 2π/P_u, |G| = 1/K_u."""

    source: str  # "model" or "result"
    omega: float
    magnitude: float
    ku_spread: float | None = None
    pu_spread: float | None = None


@dataclass(frozen=True)
class FrequencyFigure:
    points: tuple[MeasuredPoint, ...]
    model: Curve | None
    crossings: tuple[Crossing, ...]
    uncertainty_note: str

    @property
    def fundamentals(self) -> tuple[MeasuredPoint, ...]:
        return tuple(p for p in self.points if p.harmonic == 1)


def _num(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def relay_points(experiment: dict, delta: float | None) -> list[MeasuredPoint]:
    """The relay stages' exact points as the ``experiment`` object keeps them."""
    out = []
    for stage, head in (("stage 1", ""), ("stage 2", "stage2_")):
        for k in range(1, 8):
            w = _num(experiment.get(f"{head}omega_{k}"))
            m = _num(experiment.get(f"{head}g_{k}_magnitude"))
            ph = _num(experiment.get(f"{head}g_{k}_phase_deg"))
            if w is None or m is None or ph is None or w <= 0 or m <= 0:
                continue
            noise = _num(experiment.get(f"{head}g_{k}_noise"))
            if k == 1:  # K_u's spread, which holds the fundamental's noise and more
                out.append(MeasuredPoint(stage, k, w, m, ph, delta))
            else:
                out.append(MeasuredPoint(stage, k, w, m, ph, noise))
    return out


def model_phase_deg(model: ProcessFit, omega: np.ndarray) -> np.ndarray:
    """The model's continuous phase, degrees: −ωL − Σ atan(ωT) (− 90° for an integrator)."""
    ph = -omega * model.delay - sum(np.arctan(omega * tau) for tau in model.lags)
    return np.degrees(ph - (0.5 * math.pi if model.kind == "ipdt" else 0.0))


def model_crossing(model: ProcessFit) -> float | None:
    """ω (rad/s) where the model's phase, which falls monotonically, reaches −180°; None if
    it never does (no dead time and too few lags)."""
    from scipy.optimize import brentq

    def excess(w: float) -> float:
        return float(model_phase_deg(model, np.array([w]))[0]) + 180.0

    scale = max(model.delay + (model.lag if model.lags else 0.0), 1e-9)
    lo, hi = 1e-6 / scale, 1.0 / scale
    for _ in range(60):  # ×2 each: 18 decades
        if excess(hi) < 0:
            return float(brentq(excess, lo, hi, xtol=1e-14 / scale, rtol=1e-14))
        lo, hi = hi, 2 * hi
    return None


def model_curve(model: ProcessFit, omega: np.ndarray) -> Curve:
    g = model.response(omega)
    return Curve(f"{model.kind.upper()} model", omega, np.abs(g), model_phase_deg(model, omega))


def _grid(model: ProcessFit, anchors: list[float]) -> np.ndarray:
    """ω from a decade below the lowest anchor to half a decade above the highest, the
    anchors themselves included (the curve passes exactly through their frequencies)."""
    if not anchors:
        scale = max(model.delay + (model.lag if model.lags else 0.0), 1e-6)
        anchors = [1.0 / scale]
    lo, hi = min(anchors) * 10**-DECADES_BELOW, max(anchors) * 10**DECADES_ABOVE
    return np.unique(np.concatenate((np.geomspace(lo, hi, CURVE_POINTS), anchors)))


def _beside(p: MeasuredPoint, model_deg: float) -> MeasuredPoint:
    """The point's phase on the model's branch (a phase is known modulo 360°: a harmonic's,
    unwrapped from the fundamental's alone, may sit a turn away)."""
    turns = round((model_deg - p.phase_deg) / 360.0)
    if not turns:
        return p
    return dataclasses.replace(p, phase_deg=p.phase_deg + 360.0 * turns)


def frequency_figure(result: TuneResult | None) -> FrequencyFigure | None:
    """The figure's data; None where the run has neither a point nor a model to show."""
    if result is None:
        return None
    e = result.experiment or {}
    delta = _num(result.ku_spread)
    points: list[MeasuredPoint] = []
    note = ""
    if result.method == "relay":
        points = relay_points(e, delta)
        note = "±δ = ku_spread of the result" if delta is not None else "no uncertainty stated"
        if any(p.harmonic != 1 and p.uncertainty is not None for p in points):
            note += "; harmonics ± the noise's share"
    ku, pu = _num(result.ku), _num(result.pu)
    if result.method == "ramp" and ku and pu and ku > 0 and pu > 0:
        points = [MeasuredPoint("ultimate point", 1, 2 * math.pi / pu, 1 / ku, -180.0, delta)]
        note = "±δ = ku_spread of the result" if delta is not None else ""
    model = result_model(e, result.step)
    crossings = []
    if ku and pu and ku > 0 and pu > 0:
        crossings.append(
            Crossing("result", 2 * math.pi / pu, 1 / ku, delta, _num(result.pu_spread))
        )
    curve = None
    if model is not None:
        anchors = [p.omega for p in points] + [c.omega for c in crossings]
        wu = model_crossing(model)
        if wu is not None:
            crossings.append(Crossing("model", wu, float(np.abs(model.response(wu)))))
            anchors.append(wu)
        with np.errstate(all="ignore"):
            curve = model_curve(model, _grid(model, anchors))
        if not np.all(np.isfinite(curve.magnitude)):
            curve = None
        else:
            points = [
                _beside(p, float(model_phase_deg(model, np.array([p.omega]))[0])) for p in points
            ]
    if not points and curve is None:
        return None
    return FrequencyFigure(tuple(points), curve, tuple(crossings), note)
