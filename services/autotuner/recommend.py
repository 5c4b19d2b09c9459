"""Which rule's gains to recommend, judged on the identified model.

Every ultimate-point rule is a candidate. With a model (the relay's fitted FOPDT/SOPDT/IPDT),
each candidate's maximum sensitivity Ms is computed on it; among the stable candidates with
Ms within the bound (default 2.0, with a margin for the model's own error), the one with
the largest integral gain Kc/Ti wins — the AMIGO design criterion: the best rejection of load
disturbances that the robustness allows (Åström & Hägglund, *Advanced PID Control*, 2006,
§7.3). Without a model, Tyreus–Luyben PI (Ms about 1.5–1.6 on FOPDT plants, see
control-references.md) is the safe default (AMIGO PI after a step test, designed for Ms ≈ 1.4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from services.autotuner.closed_loop import StepFigures, setpoint_step
from services.autotuner.forms import IsaGains
from services.autotuner.model_fit import ProcessFit
from services.autotuner.robustness import Robustness, robustness
from services.autotuner.rules import RULES, UltimatePoint, apply_rules

MS_BOUND = 2.0
MODEL_MARGIN = 0.9  # recommend only below 0.9 × the bound: the model is an approximation
# … and below 0.75 × the bound for PID on a model that fits clearly worse than the noise allows:
# the derivative acts where such a model is least certain (a zero approximated by a delay)
APPROXIMATE_PID_MARGIN = 0.75
FALLBACKS = ("tl-pi", "amigo-pi", "simc-pi-int")  # robust by design, in this order


@dataclass(frozen=True)
class Assessment:
    rule: str
    gains: IsaGains
    robustness: Robustness | None  # on the identified model (None without one)
    step: StepFigures | None = None  # the closed loop's setpoint step on the model

    def to_dict(self) -> dict[str, float | bool | None]:
        rb, st = self.robustness, self.step
        if rb is None:
            return {}
        out: dict[str, float | bool | None] = {
            "ms": _number(rb.ms),
            "gain_margin": _number(rb.gain_margin),
            "phase_margin_deg": _number(rb.phase_margin_deg),
            "stable": bool(self.stable),
        }
        if st is not None:
            out["overshoot_pct"] = _number(st.overshoot)
            out["decay_ratio"] = _number(st.decay_ratio)
        return out

    @property
    def stable(self) -> bool | None:
        rb = self.robustness
        return None if rb is None else bool(rb.gain_margin > 1.0 and rb.phase_margin_deg > 0.0)

    def within(self, bound: float) -> bool | None:
        rb = self.robustness
        return None if rb is None else bool(self.stable) and rb.ms <= bound


def _number(x: float) -> float | None:
    """A plain float for JSON (numpy scalars are not), None for an infinite margin."""
    x = float(x)
    return x if math.isfinite(x) else None


def assess(
    ultimate: UltimatePoint | None,
    model: ProcessFit | None,
    gains: dict[str, IsaGains] | None = None,
    simulate: bool = False,
    sample_time: float | None = None,
) -> dict[str, Assessment]:
    """Every candidate's robustness on the model (rules needing K_u and P_u unless given),
    and with ``simulate`` its closed-loop setpoint step at the loop's sample time."""
    gains = apply_rules(ultimate, None) if gains is None else gains
    timescale = ultimate.pu if ultimate else (model.delay + model.lag if model else 0.0)
    if not math.isfinite(timescale) or timescale <= 0:
        timescale = 10.0 * model.delay if model else 0.0
    out = {}
    for name, g in gains.items():
        rb, st = None, None
        if model is not None:
            try:
                rb = robustness(g, model.num, model.den, model.delay)
            except (ValueError, ArithmeticError):
                rb = None
            if simulate and rb is not None and timescale > 0:
                st = setpoint_step(g, model, timescale, sample_time)
        out[name] = Assessment(name, g, rb, st)
    return out


@dataclass(frozen=True)
class Recommendation:
    rule: str
    gains: IsaGains
    predicted_ms: float | None
    reason: str


def recommend(
    ultimate: UltimatePoint | None,
    model: ProcessFit | None,
    ms_bound: float = MS_BOUND,
    candidates: dict[str, Assessment] | None = None,
) -> Recommendation | None:
    """The rule to apply by default (see the module's docstring); ``candidates`` as
    ``assess`` gives them (every ultimate-point rule if not given)."""
    candidates = assess(ultimate, model) if candidates is None else candidates
    if model is not None:

        def margin(rule: str) -> float:
            pid = RULES[rule].controller == "PID"
            return APPROXIMATE_PID_MARGIN if pid and model.approximate else MODEL_MARGIN

        ok = [
            a
            for a in candidates.values()
            if RULES[a.rule].controller != "P" and a.within(margin(a.rule) * ms_bound)
        ]
        if ok:
            best = max(ok, key=lambda a: a.gains.kc / (a.gains.ti or math.inf))
            return Recommendation(
                best.rule,
                best.gains,
                best.robustness.ms if best.robustness else None,
                f"largest integral gain with Ms ≤ {margin(best.rule) * ms_bound:.2g} on the "
                f"identified {model.kind.upper()} model",
            )
        judged = [
            a
            for a in candidates.values()
            if RULES[a.rule].controller != "P" and a.stable and a.robustness is not None
        ]
        safest = min(judged, key=lambda a: a.robustness.ms, default=None)
        if safest is not None and safest.robustness.ms <= ms_bound:
            return Recommendation(
                safest.rule,
                safest.gains,
                safest.robustness.ms,
                f"the most robust candidate on the identified {model.kind.upper()} model "
                f"(none within the margin Ms ≤ {MODEL_MARGIN * ms_bound:.2g})",
            )
    fallback = next((candidates[r] for r in FALLBACKS if r in candidates), None)
    if fallback is None:
        return None
    rb = fallback.robustness
    return Recommendation(
        fallback.rule,
        fallback.gains,
        rb.ms if rb else None,
        "no model to judge the candidates on: the robust default"
        if model is None
        else f"no candidate within Ms ≤ {MODEL_MARGIN * ms_bound:.2g} on the model",
    )
