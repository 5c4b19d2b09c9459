"""From an identification to the gains to apply: every rule, judged on the model, one chosen.

Pure: the live run and the offline analysis of a recording both call ``select``. Every rule
the identification supports is computed; on the identified model (relay: fitted to the test;
step: the reaction curve's first order) each gets its maximum sensitivity Ms, margins and the
overshoot and decay ratio of a simulated setpoint step. The rule ``auto`` is the recommended
one (``recommend``). Gains predicted unstable, or with Ms above the bound, are refused unless
forced: the reason says which and by how much. L/T is reported with the seeds' guidance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from services.autotuner.experiments import Identification
from services.autotuner.forms import IsaGains
from services.autotuner.model_fit import ProcessFit
from services.autotuner.recommend import Assessment, Recommendation, assess, recommend
from services.autotuner.rules import RULES, ZN_STEP_RANGE, UltimatePoint, apply_rules, fopdt_of


@dataclass
class Selection:
    rule: str  # the rule whose gains are chosen
    chosen: IsaGains | None
    table: dict[str, IsaGains]
    assessments: dict[str, Assessment]
    recommended: Recommendation | None
    l_over_t: float | None
    refusal: str | None = None  # why the chosen gains must not be applied (None: they may)
    warnings: list[str] = field(default_factory=list)


def l_over_t(ident: Identification) -> float | None:
    """L/T of the step test, else of the fitted model's first-order equivalent."""
    if ident.step:
        return ident.step.get("l_over_t")
    model: ProcessFit | None = ident.model
    if model is None or model.kind == "ipdt":
        return None
    m = fopdt_of(model)
    return m.dead_time / m.time_constant if m.time_constant > 0 else None


def guidance(ratio: float | None, model: ProcessFit | None) -> list[str]:
    """What the seeds and the benchmark say about rules at this L/T."""
    out = []
    if model is not None and model.kind == "ipdt":
        out.append("integrating process: simc-pi-int is the rule made for it (a level loop)")
    if ratio is None:
        return out
    lo, hi = ZN_STEP_RANGE
    if not lo <= ratio <= hi:
        out.append(
            f"L/T = {ratio:.3g}: outside {lo}–{hi}, where the step-response rules (zn-ol-*, "
            "cc-*) suit (seed 000)"
        )
    if ratio > 1.0:
        out.append(
            f"L/T = {ratio:.3g}: delay-dominated; derivative action helps little and "
            "Ziegler–Nichols PID is aggressive here: PI rules (tl-pi, amigo-pi, simc-pi) suit"
        )
    return out


def select(
    ident: Identification,
    rule: str,
    ms_bound: float = 2.0,
    force: bool = False,
    sample_time: float | None = None,
) -> Selection:
    ultimate = UltimatePoint(ident.ku, ident.pu) if ident.ku else None
    model = ident.model
    table = apply_rules(ultimate, ident.step_model, model)
    assessments = assess(ultimate, model, table, simulate=True, sample_time=sample_time)
    rec = recommend(ultimate, model, ms_bound, assessments)
    ratio = l_over_t(ident)
    name = (rec.rule if rec else "") if rule == "auto" else rule
    sel = Selection(
        name, table.get(name), table, assessments, rec, ratio, warnings=guidance(ratio, model)
    )
    if sel.chosen is None:
        sel.refusal = (
            "no rule could be recommended"
            if rule == "auto"
            else f"rule {name}: this identification does not give it "
            f"({RULES[name].kind} rule; {_why_missing(name, ident)})"
        )
        return sel
    a = assessments.get(name)
    if a is None or a.robustness is None:
        if model is None:
            sel.warnings.append(
                "no process model from this method: the gains' robustness is not predicted"
            )
        return sel
    rb = a.robustness
    problem = None
    if not a.stable:
        problem = (
            f"{name}: predicted unstable on the identified {model.kind.upper()} model "
            f"(gain margin {rb.gain_margin:.3g}, phase margin {rb.phase_margin_deg:.3g}°)"
        )
    elif rb.ms > ms_bound:
        problem = f"{name}: predicted Ms {rb.ms:.3g} above the bound {ms_bound:g}"
    if problem:
        if force:
            sel.warnings.append(problem + " — applied because forced")
        else:
            better = f"; the recommended rule is {rec.rule}" if rec and rec.rule != name else ""
            sel.refusal = f"refused: {problem} (force to apply anyway{better})"
    return sel


def _why_missing(name: str, ident: Identification) -> str:
    kind = RULES[name].kind
    if kind == "model" and ident.model is None:
        return "it needs a process model, which the ramp does not give"
    if kind == "model":
        return f"not defined for a {ident.model.kind.upper()} model"
    return "the identification lacks what it needs"


def assessments_dict(sel: Selection) -> dict[str, dict]:
    """Per rule, the figures for JSON (rules without a model to judge them on are left out)."""
    return {k: d for k, a in sel.assessments.items() if (d := a.to_dict())}
