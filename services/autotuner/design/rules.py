"""Tuning rules, each with its sources. Gains in ISA form (Kc % per PV unit, Ti, Td in s).

Where the seeds disagree with each other we use the standard and say so:

* Ziegler–Nichols closed loop PID is Kc = 0.6·K_u, Ti = P_u/2, Td = P_u/8: seed 003
  (Table 6-1) and seed 000 (Table 2) agree on 0.6·K_u; seed 002 (Figure 4) prints 1.6·K_u, a
  typo; seed 000 prints Ti = T_u, against Ti = 0.5·P_u in seeds 002 and 003.
* Ziegler–Nichols open loop PI is Ti = 3.33·L (= L/0.3): seeds 001, 002 and 003 (3.3θ); seed
  000 prints 3L.

The "-half" variants halve the controller gain, as seeds 001 and 002 recommend to trade the
quarter-decay response for robustness.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from services.autotuner.identify.model_fit import ProcessFit, StepModel, model_of
from shared.control.forms import IsaGains


@dataclass(frozen=True)
class UltimatePoint:
    """K_u (% per PV unit) and P_u (s) of the loop."""

    ku: float
    pu: float


@dataclass(frozen=True)
class Rule:
    name: str
    kind: str  # "closed" (K_u, P_u), "open" (a step test) or "model" (a fitted model)
    controller: str  # "P", "PI", "PID"
    source: str
    compute: Callable[..., IsaGains]
    tuned_by_lambda: bool = False  # compute(source, lambda_s): λ in s, None for the default


def _zn_closed_p(u: UltimatePoint) -> IsaGains:
    """Ziegler & Nichols 1942; seeds 000 (Table 2), 002 (Figure 4), 003 (Table 6-1)."""
    return IsaGains(0.5 * u.ku)


def _zn_closed_pi(u: UltimatePoint) -> IsaGains:
    return IsaGains(0.45 * u.ku, u.pu / 1.2)


def _zn_closed_pid(u: UltimatePoint) -> IsaGains:
    return IsaGains(0.6 * u.ku, u.pu / 2.0, u.pu / 8.0)


def _tl_pi(u: UltimatePoint) -> IsaGains:
    """Tyreus & Luyben 1992; seed 003 (Table 6-2)."""
    return IsaGains(u.ku / 3.2, 2.2 * u.pu)


def _tl_pid(u: UltimatePoint) -> IsaGains:
    return IsaGains(u.ku / 2.2, 2.2 * u.pu, u.pu / 6.3)


def _a(m: StepModel) -> float:
    """a = R·L = K·L/T (seed 000); the open-loop rules are all in terms of it."""
    if m.dead_time <= 0:
        raise ValueError("the open-loop rules need a dead time L > 0")
    return m.reaction_rate * m.dead_time


def _zn_open_p(m: StepModel) -> IsaGains:
    """Ziegler & Nichols 1942, reaction curve; seeds 000 (Table 1), 001, 002, 003 (Table 6-3)."""
    return IsaGains(1.0 / _a(m))


def _zn_open_pi(m: StepModel) -> IsaGains:
    return IsaGains(0.9 / _a(m), m.dead_time / 0.3)


def _zn_open_pid(m: StepModel) -> IsaGains:
    return IsaGains(1.2 / _a(m), 2.0 * m.dead_time, 0.5 * m.dead_time)


def _cc(m: StepModel) -> tuple[float, float, float]:
    if m.is_integrating:
        raise ValueError("Cohen–Coon needs a self-regulating process (a gain K and lag T)")
    if m.dead_time <= 0:
        raise ValueError("Cohen–Coon needs a dead time θ > 0")
    return m.gain, m.time_constant, m.dead_time


def _cc_p(m: StepModel) -> IsaGains:
    """Cohen & Coon 1953; seed 003 (Table 6-4); Seborg, Edgar & Mellichamp, Table 12.3."""
    k, tau, th = _cc(m)
    return IsaGains(tau / (k * th) * (1.0 + th / (3.0 * tau)))


def _cc_pi(m: StepModel) -> IsaGains:
    k, tau, th = _cc(m)
    r = th / tau
    return IsaGains(tau / (k * th) * (0.9 + r / 12.0), th * (30.0 + 3.0 * r) / (9.0 + 20.0 * r))


def _cc_pid(m: StepModel) -> IsaGains:
    k, tau, th = _cc(m)
    r = th / tau
    return IsaGains(
        tau / (k * th) * (4.0 / 3.0 + r / 4.0),
        th * (32.0 + 6.0 * r) / (13.0 + 8.0 * r),
        4.0 * th / (11.0 + 2.0 * r),
    )


def _amigo_pi(m: StepModel) -> IsaGains:
    """AMIGO PI for K·e^{−Ls}/(Ts+1) (Åström & Hägglund, *Advanced PID Control*, 2006,
    §7.6): K = 0.15/K_p + (0.35 − LT/(L+T)²)·T/(K_p L), Ti = 0.35L + 13LT²/(T² + 12LT + 7L²).
    Designed for robustness (Ms ≈ 1.4) rather than quarter decay."""
    k, t, lag = m.gain, m.time_constant, m.dead_time
    if lag <= 0:
        raise ValueError("AMIGO needs a dead time L > 0")
    kc = 0.15 / k + (0.35 - lag * t / (lag + t) ** 2) * t / (k * lag)
    return IsaGains(kc, 0.35 * lag + 13 * lag * t**2 / (t**2 + 12 * lag * t + 7 * lag**2))


def _amigo_pid(m: StepModel) -> IsaGains:
    """AMIGO PID (ibid., §7.7): K = (0.2 + 0.45T/L)/K_p, Ti = (0.4L + 0.8T)·L/(L + 0.1T),
    Td = 0.5LT/(0.3L + T)."""
    k, t, lag = m.gain, m.time_constant, m.dead_time
    if lag <= 0:
        raise ValueError("AMIGO needs a dead time L > 0")
    return IsaGains(
        (0.2 + 0.45 * t / lag) / k,
        (0.4 * lag + 0.8 * t) * lag / (lag + 0.1 * t),
        0.5 * lag * t / (0.3 * lag + t),
    )


def _simc_pi(m: StepModel) -> IsaGains:
    """SIMC PI with τc = θ (Skogestad, J. Process Control 13, 2003): Kc = τ₁/(k·2θ),
    Ti = min(τ₁, 8θ)."""
    k, tau, th = m.gain, m.time_constant, m.dead_time
    if th <= 0:
        raise ValueError("SIMC with τc = θ needs a dead time θ > 0")
    return IsaGains(tau / (k * 2.0 * th), min(tau, 8.0 * th))


def fopdt_of(m: ProcessFit) -> StepModel:
    """The first-order-plus-dead-time equivalent of a fitted model: a SOPDT by Skogestad's
    half rule (half of τ₂ to the lag, half to the delay; J. Process Control 13, 2003, §3)."""
    if m.kind == "ipdt":
        raise ValueError("an integrating model has no first-order equivalent")
    t2 = m.lags[1] if len(m.lags) > 1 else 0.0
    return StepModel(m.gain, m.delay + t2 / 2.0, m.lags[0] + t2 / 2.0)


def _on_fopdt(rule: Callable[[StepModel], IsaGains]) -> Callable[[ProcessFit], IsaGains]:
    def on_model(m: ProcessFit) -> IsaGains:
        return rule(fopdt_of(m))

    on_model.__doc__ = rule.__doc__
    return on_model


def _simc_pid(m: ProcessFit) -> IsaGains:
    """SIMC PID with τc = θ for k·e^{−θs}/((τ₁s+1)(τ₂s+1)) (Skogestad 2003, Table 3; Grimholt
    & Skogestad 2018): series form Kc' = τ₁/(k·2θ), τI' = min(τ₁, 8θ), τD' = τ₂, given here
    in ISA form (Kc = Kc'(1 + τD'/τI'), Ti = τI' + τD', Td = τI'τD'/(τI' + τD')). A first-order
    model gives τD' = 0: SIMC PI."""
    if m.kind == "ipdt":
        raise ValueError("SIMC PID needs a self-regulating model; use simc-pi-int")
    k, th = m.gain, m.delay
    t1, t2 = m.lags[0], (m.lags[1] if len(m.lags) > 1 else 0.0)
    if th <= 0:
        raise ValueError("SIMC with τc = θ needs a dead time θ > 0")
    kc_s, ti_s = t1 / (k * 2.0 * th), min(t1, 8.0 * th)
    f = 1.0 + t2 / ti_s
    return IsaGains(kc_s * f, ti_s + t2, ti_s * t2 / (ti_s + t2))


def _simc_pi_int(m: ProcessFit) -> IsaGains:
    """SIMC PI with τc = θ for an integrating process k'·e^{−θs}/s (a level; Skogestad 2003,
    Table 3): Kc = 1/(k'·2θ), Ti = 8θ. A first-order model with τ₁ > 8θ is integrating over
    the closed loop's time scale, k' = k/τ₁ (ibid., §4.3); a second-order one is first made
    first-order by the half rule, as for SIMC PI (τ₂/2 to the delay: its τ₂ was ignored, and
    a near-integrating SOPDT with τ₂ = 5 s, θ = 3 s got 1.8 × SIMC PI's Kc, Ms 4.3)."""
    if m.kind == "ipdt":
        k_int, th = m.gain, m.delay
    else:
        f = fopdt_of(m)
        th = f.dead_time
        if not f.time_constant > 8.0 * th:
            raise ValueError("not an integrating process (τ₁ ≤ 8θ): use simc-pi")
        k_int = f.gain / f.time_constant
    if th <= 0:
        raise ValueError("SIMC with τc = θ needs a dead time θ > 0")
    return IsaGains(1.0 / (k_int * 2.0 * th), 8.0 * th)


# a first-order equivalent whose lag is over this many dead times is an integrator to the
# lambda rules: λ = T would ask for a closed loop as slow as a lag no test can see
INTEGRATING_LAG = 1000.0


def integrator_of(m: ProcessFit) -> ProcessFit | None:
    """The model as the lambda rules take an integrating one: an IPDT as it is; a lag model
    whose first-order equivalent (half rule) has T over ``INTEGRATING_LAG`` × L as the
    integrator K/T·e^{−Ls}/s; else None. Why: a ramp's SOPDT of 0.05·e^{−s}/(s(2s + 1)) has
    T₁ = 4.8·10⁶ s (an integrator behind a lag, fitted from ``second_order_starts``), and
    λ = T gave lambda PI Kc 4.2·10⁻⁶ and Ti 4.8·10⁶ s, its loop stable but judged unstable
    on a frequency grid that starts above 1/Ti."""
    if m.kind == "ipdt":
        return m
    f = fopdt_of(m)
    if f.dead_time > 0 and f.time_constant > INTEGRATING_LAG * f.dead_time:
        return ProcessFit("ipdt", f.gain / f.time_constant, (), f.dead_time, m.rms)
    return None


def default_lambda(m: ProcessFit) -> float:
    """The default closed-loop time constant λ (s) of the lambda rules: the larger of the
    process lag T and 3 × the dead time L of the model's first-order equivalent (seed 001's
    robust choice, λ ≥ 3L); an integrating model (``integrator_of``) has no lag: 3 × L."""
    if (i := integrator_of(m)) is not None:
        return 3.0 * i.delay
    f = fopdt_of(m)
    return max(f.time_constant, 3.0 * f.dead_time)


def lambda_used(m: ProcessFit, lambda_s: float | None) -> float:
    """λ as asked for, else the default; ValueError unless positive and finite."""
    lam = default_lambda(m) if lambda_s is None else float(lambda_s)
    if not (math.isfinite(lam) and lam > 0):
        raise ValueError(f"lambda tuning needs λ > 0, got {lam}")
    return lam


def _lambda_int_pi(m: ProcessFit, lam: float) -> IsaGains:
    """Lambda PI for an integrating process K'·e^{−Ls}/s: Kc = (2λ + L)/(K'(λ + L)²),
    Ti = 2λ + L."""
    k, lag = m.gain, m.delay
    return IsaGains((2.0 * lam + lag) / (k * (lam + lag) ** 2), 2.0 * lam + lag)


def _lambda_pi(m: ProcessFit, lambda_s: float | None = None) -> IsaGains:
    """Lambda PI (Dahlin 1968; seed 001): on K·e^{−Ls}/(Ts + 1) (a SOPDT by the half rule)
    Kc = T/(K(λ + L)), Ti = T, so that the loop is e^{−Ls}/((λ + L)s); on an integrating
    model, Kc = (2λ + L)/(K'(λ + L)²), Ti = 2λ + L."""
    lam = lambda_used(m, lambda_s)
    if (i := integrator_of(m)) is not None:
        return _lambda_int_pi(i, lam)
    f = fopdt_of(m)
    k, t, lag = f.gain, f.time_constant, f.dead_time
    if t <= 0:
        raise ValueError("lambda PI needs a lag T > 0")
    return IsaGains(t / (k * (lam + lag)), t)


def _lambda_pid(m: ProcessFit, lambda_s: float | None = None) -> IsaGains:
    """Lambda PID, the IMC design with a first-order Padé for the delay (Rivera, Morari &
    Skogestad 1986): Kc = (T + L/2)/(K(λ + L/2)), Ti = T + L/2, Td = TL/(2T + L). On an
    integrating model it is the integrating lambda PI (no derivative)."""
    lam = lambda_used(m, lambda_s)
    if (i := integrator_of(m)) is not None:
        return _lambda_int_pi(i, lam)
    f = fopdt_of(m)
    k, t, lag = f.gain, f.time_constant, f.dead_time
    if t <= 0:
        raise ValueError("lambda PID needs a lag T > 0")
    return IsaGains(
        (t + lag / 2.0) / (k * (lam + lag / 2.0)), t + lag / 2.0, t * lag / (2.0 * t + lag)
    )


def _half(rule: Callable[..., IsaGains]) -> Callable[..., IsaGains]:
    def halved(x: UltimatePoint | StepModel) -> IsaGains:
        g = rule(x)
        return IsaGains(g.kc / 2.0, g.ti, g.td)

    return halved


ZN_STEP_RANGE = (0.15, 0.6)  # L/T where the ZN step-response rules work (seed 000)

_ZN_SRC = "Ziegler & Nichols 1942 (seeds 000, 002, 003)"
_OL_SRC = "Ziegler & Nichols 1942, reaction curve (seeds 000, 001, 002, 003)"
_LAMBDA_SRC = "Lambda tuning: Dahlin 1968 (seed 001)"
_IMC_SRC = (
    "Lambda/IMC with a first-order Padé: Rivera, Morari & Skogestad 1986 (seed 001); "
    "integrating model: the lambda PI"
)
_HALF = "; gain halved as seeds 001 and 002 recommend"

RULES: dict[str, Rule] = {
    r.name: r
    for r in (
        Rule("zn-p", "closed", "P", _ZN_SRC, _zn_closed_p),
        Rule("zn-pi", "closed", "PI", _ZN_SRC, _zn_closed_pi),
        Rule("zn-pid", "closed", "PID", _ZN_SRC, _zn_closed_pid),
        Rule("zn-p-half", "closed", "P", _ZN_SRC + _HALF, _half(_zn_closed_p)),
        Rule("zn-pi-half", "closed", "PI", _ZN_SRC + _HALF, _half(_zn_closed_pi)),
        Rule("zn-pid-half", "closed", "PID", _ZN_SRC + _HALF, _half(_zn_closed_pid)),
        Rule("tl-pi", "closed", "PI", "Tyreus & Luyben 1992 (seed 003)", _tl_pi),
        Rule("tl-pid", "closed", "PID", "Tyreus & Luyben 1992 (seed 003)", _tl_pid),
        Rule("zn-ol-p", "open", "P", _OL_SRC, _zn_open_p),
        Rule("zn-ol-pi", "open", "PI", _OL_SRC, _zn_open_pi),
        Rule("zn-ol-pid", "open", "PID", _OL_SRC, _zn_open_pid),
        Rule("zn-ol-pi-half", "open", "PI", _OL_SRC + _HALF, _half(_zn_open_pi)),
        Rule("zn-ol-pid-half", "open", "PID", _OL_SRC + _HALF, _half(_zn_open_pid)),
        Rule("cc-p", "open", "P", "Cohen & Coon 1953 (seed 003)", _cc_p),
        Rule("cc-pi", "open", "PI", "Cohen & Coon 1953 (seed 003)", _cc_pi),
        Rule("cc-pid", "open", "PID", "Cohen & Coon 1953 (seed 003)", _cc_pid),
        Rule("amigo-pi", "model", "PI", "Åström & Hägglund 2006, AMIGO", _on_fopdt(_amigo_pi)),
        Rule("amigo-pid", "model", "PID", "Åström & Hägglund 2006, AMIGO", _on_fopdt(_amigo_pid)),
        Rule("simc-pi", "model", "PI", "Skogestad 2003, SIMC with τc = θ", _on_fopdt(_simc_pi)),
        Rule("simc-pid", "model", "PID", "Skogestad 2003, SIMC with τc = θ", _simc_pid),
        Rule(
            "simc-pi-int",
            "model",
            "PI",
            "Skogestad 2003, SIMC for integrating processes, τc = θ",
            _simc_pi_int,
        ),
        Rule("lambda-pi", "model", "PI", _LAMBDA_SRC, _lambda_pi, tuned_by_lambda=True),
        Rule("lambda-pid", "model", "PID", _IMC_SRC, _lambda_pid, tuned_by_lambda=True),
    )
}


def apply_rules(
    ultimate: UltimatePoint | None,
    step: StepModel | None,
    model: ProcessFit | None = None,
    lambda_s: float | None = None,
) -> dict[str, IsaGains]:
    """Every rule the available identification supports, by name. Model rules (AMIGO, SIMC,
    lambda) take the fitted model, or else the step test's reaction curve as a first-order
    model; the lambda rules take ``lambda_s`` (s; None: ``default_lambda``)."""
    if model is None and step is not None:
        model = model_of(step)
    sources = {"closed": ultimate, "open": step, "model": model}
    out: dict[str, IsaGains] = {}
    for name, rule in RULES.items():
        source = sources[rule.kind]
        if source is None:
            continue
        try:
            if rule.tuned_by_lambda:
                out[name] = rule.compute(source, lambda_s)
            else:
                out[name] = rule.compute(source)
        except ValueError:
            continue
    return out


def check_rule(name: str) -> Rule:
    if name not in RULES:
        raise ValueError(f"unknown rule {name!r}; expected one of {', '.join(RULES)}")
    return RULES[name]
