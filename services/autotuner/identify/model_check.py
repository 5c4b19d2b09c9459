"""Is a fitted process model fit to tune and judge gains with? Checked against what was measured.

A relay test measures K_u and P_u well even when the record it fits its model to is not (a PV
still moving when the test began, a load change mid-test): the model then comes out absurd —
a static gain seven times too small, an integrator with a gain of 1e-10 and a dead time of
minutes — and the model-based rules turn it into gains far beyond K_u. So before any rule may
use a model (``ProcessFit``) it must agree with the measurement on three counts:

(a) its own ultimate point against the measured K_u and P_u, within the measured spread plus
    KU_TOLERANCE and PU_TOLERANCE (the relay's exact points carry the model's phase to within
    a few %; the benchmark's worst healthy fits, out-of-class plants at 3 % noise, are 14 %
    off in K_u and 2 % in P_u);
(b) physics: a finite positive gain (PV units per %, the process as the tuner sees it: the
    loop's action already applied), finite positive lags and a finite delay ≥ 0; a dead time
    within what the measured phase allows — at ω_u = 2π/P_u the model must lag 180°, its lags
    give at most 90° each (an integrator 90°), so L ≥ (180° − lags' share)/ω_u and
    L ≤ 180°/ω_u (90°/ω_u for an integrator); a self-regulating lag model's gain at least
    1/K_u (its magnitude is largest at DC); an integrating model only where the record shows
    integration — without that evidence, only if its gain × delay gives the measured K_u
    (K·L·K_u = π/2 at an integrator's ultimate point);
(c) its prediction on the record it came from: the fit's residual beyond the measurement
    noise, √(rms² − noise_rms²) (both relative to the PV's standard deviation), or what of
    it is not white where that is less (``ProcessFit.excess_rms``), at most RMS_EXCESS_LIMIT
    — above it the model misses a sixth of what the PV did.

Each failure is one line, for the warnings and the refusal. A step test gives no K_u: its
reaction-curve model is checked on (b) without the ultimate point, and (c) when its fit
residual is known. Pure: numbers in, verdict out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from services.autotuner.identify.model_fit import ProcessFit

KU_TOLERANCE = 0.15  # relative, beyond the measured spread
PU_TOLERANCE = 0.05
RMS_EXCESS_LIMIT = 0.4  # of the PV's standard deviation: the model explains < 84 % beyond it
KINDS = {"fopdt": 1, "sopdt": 2, "ipdt": 0}  # how many lags each kind has


@dataclass(frozen=True)
class ModelCheck:
    """The verdict on a model: ``reasons`` empty when it may be used."""

    reasons: tuple[str, ...]
    ku_model: float | None = None  # the model's own ultimate point (% per PV unit, s)
    pu_model: float | None = None
    # it passed every check but (perhaps) the comparison of that point with the measured one:
    # a second estimate of the ultimate point, its disagreement a measure of their accuracy
    sound: bool = False

    @property
    def ok(self) -> bool:
        return not self.reasons

    def summary(self) -> str:
        return "; ".join(self.reasons)


def _finite(x: float | None) -> bool:
    return x is not None and math.isfinite(x)


def check_model(
    model: ProcessFit,
    ku: float | None = None,
    pu: float | None = None,
    ku_spread: float | None = None,
    pu_spread: float | None = None,
    integrating: bool | None = None,
) -> ModelCheck:
    """Check ``model`` against the measured ultimate point (K_u in % per PV unit, P_u in s,
    spreads relative; None for a step test) and the record's evidence of integration (True:
    the PV ramps under a constant output, False: it settles, None: not measured)."""
    reasons: list[str] = []
    kind = model.kind
    name = kind.upper()
    if kind not in KINDS or len(model.lags) != KINDS[kind]:
        return ModelCheck((f"model: unknown kind {kind!r} with {len(model.lags)} lags",))
    if not (_finite(model.gain) and model.gain > 0):
        reasons.append(
            f"{name} gain {model.gain:.3g}: must be finite and > 0 PV units per % (the process "
            "as the tuner sees it, the loop's action applied)"
        )
    if not all(_finite(t) and t > 0 for t in model.lags):
        lags = ", ".join(f"{t:.3g}" for t in model.lags)
        reasons.append(f"{name} lags ({lags}) s: must be finite and > 0")
    if not (_finite(model.delay) and model.delay >= 0):
        reasons.append(f"{name} delay {model.delay:.3g} s: must be finite and ≥ 0")
    if reasons:  # nothing below means anything for such a model
        return ModelCheck(tuple(reasons))

    measured = _finite(ku) and _finite(pu) and ku > 0 and pu > 0
    if kind == "ipdt" and integrating is False:
        reasons.append("integrating model, but the record shows the PV settling")
    if measured:
        reasons += _physics(model, ku, pu, integrating)

    # (c) the prediction on its own record
    if not _finite(model.rms):
        reasons.append(f"{name} fit: no residual on the record (rms {model.rms})")
    else:
        noise = model.noise_rms if _finite(model.noise_rms) else 0.0
        excess = model.excess_rms
        if excess > RMS_EXCESS_LIMIT:
            reasons.append(
                f"{name} fit misses the record: residual {model.rms:.2g} of the PV's spread "
                f"against noise {noise:.2g} (excess {excess:.2g} > {RMS_EXCESS_LIMIT:g})"
            )

    # (a) its own ultimate point against the measured one
    sound = not reasons
    ku_m = pu_m = None
    if measured:
        up = model.ultimate_point()
        if up is None:
            reasons.append(f"{name}: its phase never reaches −180°, yet the loop oscillated")
        else:
            ku_m, pu_m = float(up[0]), float(up[1])
            for label, got, want, spread, tol, unit in (
                ("K_u", ku_m, ku, ku_spread, KU_TOLERANCE, "% per PV unit"),
                ("P_u", pu_m, pu, pu_spread, PU_TOLERANCE, "s"),
            ):
                allowed = (spread if _finite(spread) else 0.0) + tol
                if abs(got / want - 1.0) > allowed:
                    reasons.append(
                        f"{name} predicts {label} {got:.4g} {unit}, measured {want:.4g} "
                        f"({100 * (got / want - 1):+.3g} %, allowed ±{100 * allowed:.3g} %)"
                    )
    return ModelCheck(tuple(reasons), ku_m, pu_m, sound)


def stated_spread(
    measured: float | None, spread: float | None, model: float | None
) -> float | None:
    """The relative spread to state with a measured K_u or P_u: its own (the cycles' scatter,
    the interpolations' difference, the bracket), or, where a sound model's own value of the
    same figure (``ModelCheck``) lies further off, that distance. Two estimates of one point
    that disagree by more than the scatter make the scatter an understatement: hx1 on the
    realtime clock on a loaded machine gave K_u +6.9 % of exact with a scatter of 0.65 %, its
    model's own K_u 6.7 % away (and within 0.2 % of exact); a ramp states no P_u scatter."""
    if not (_finite(measured) and measured > 0 and _finite(model) and model > 0):
        return spread
    gap = abs(model / measured - 1.0)
    return gap if spread is None or not math.isfinite(spread) or gap > spread else spread


def _physics(model: ProcessFit, ku: float, pu: float, integrating: bool | None) -> list[str]:
    """(b) against the measured ultimate point: dead time, static gain, integration."""
    out: list[str] = []
    name = model.kind.upper()
    wu = 2.0 * math.pi / pu
    lag_share = 0.5 * math.pi * (len(model.lags) + (1 if model.kind == "ipdt" else 0))
    slack = 1.0 + PU_TOLERANCE  # the measured phase crossover's own tolerance
    min_delay = max(0.0, math.pi - lag_share) / wu
    max_delay = (0.5 * math.pi if model.kind == "ipdt" else math.pi) / wu
    if model.delay < min_delay / slack:
        out.append(
            f"{name} delay {model.delay:.3g} s below the {min_delay:.3g} s that the measured "
            f"phase (−180° at P_u {pu:.4g} s) needs beyond its lags"
        )
    if model.delay > max_delay * slack:
        out.append(
            f"{name} delay {model.delay:.3g} s beyond what P_u {pu:.4g} s allows "
            f"({max_delay:.3g} s: the delay alone would lag past −180°)"
        )
    if model.kind == "ipdt":
        if integrating is not True:
            product = model.gain * model.delay * ku
            if abs(product / (0.5 * math.pi) - 1.0) > KU_TOLERANCE + PU_TOLERANCE:
                out.append(
                    f"IPDT gain × delay × K_u = {product:.3g}, not π/2 as an integrator's "
                    "ultimate point requires (and the record shows no integration)"
                )
    elif model.gain * ku < 1.0 - KU_TOLERANCE:
        out.append(
            f"{name} gain {model.gain:.3g} below 1/K_u = {1.0 / ku:.3g}: a lag model's gain "
            "is largest at DC, so the measured K_u needs at least that"
        )
    return out
