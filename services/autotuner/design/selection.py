"""From an identification to the gains to apply: every rule, judged on the model, one chosen.

Pure: the live run and the offline analysis of a recording both call ``select``. First the
model is checked against what was measured (``model_check``: its own ultimate point against
K_u and P_u, physics, its fit to the record); a refused model is not used — the model-based
rules (and after a step test, whose reaction curve is the model, the step rules too) are
unavailable, with the reason, and no robustness is predicted from it. Every rule the
identification supports is then computed; on the model (relay: fitted to the test; step: the
reaction curve's first order) each gets its maximum sensitivity Ms, margins and stability on
the sampled loop (the plant held and sampled at the loop's T, closed by the PID block's own
discrete transfer function: ``sampled_loop``) when the sample time is known, else in
continuous time, and the overshoot and decay ratio of a simulated setpoint step. The rule
``auto`` is the recommended one (``recommend``). The safety envelope: gains with Kc at or
above the measured K_u, predicted unstable, or with Ms above the bound, are refused unless
forced: the reason says which and by how much. L/T is reported with the seeds' guidance.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from services.autotuner.design.measured_point import ms_floor
from services.autotuner.design.output_noise import QUIET_SHARE, quiet_lambda
from services.autotuner.design.recommend import (
    APPROXIMATE_PID_MARGIN,
    INVERSE_SOURCE,
    MISFIT_SOURCE,
    RECORD_MISFIT_SOURCE,
    Assessment,
    Recommendation,
    assess,
    envelope_problem,
    recommend,
)
from services.autotuner.design.rules import (
    RULES,
    ZN_STEP_RANGE,
    UltimatePoint,
    apply_rules,
    fopdt_of,
    lambda_used,
)
from services.autotuner.design.sampled_loop import sampled_plant
from services.autotuner.identify.experiments import Identification
from services.autotuner.identify.model_check import ModelCheck, check_model, stated_spread
from services.autotuner.identify.model_fit import ProcessFit, model_of
from services.autotuner.parts import Parts, in_turn
from shared.control.forms import MAX_KC_PERCENT, IsaGains, kc_over_limit, kc_percent

UNBIASED_RELAY_RULES = ("tl-pid", "tl-pi")  # recommended when the static gain is unknown
MIN_TD_SAMPLES = 5.0  # a derivative time shorter than this many samples is not recommended
# a model's Ms this far below the measured point's floor (beyond twice the measurement's spread)
# misses the plant
MISFIT_TOLERANCE = 0.05
# … and a model whose fit of its record leaves more than this beyond the measurement noise
# (√(rms² − noise_rms²), of the PV's standard deviation) where an ultimate point was measured:
# it misses the plant's shape, whatever its ultimate point. Why: on the underdamped
# e^{−0.5s}/(s² + 0.4s + 1) the ramp's best SOPDT left 0.28 (no term for the resonance) and,
# from its extra starts, no longer missed the measured point: AMIGO PID was recommended at
# 1.43 on it (2.2 on the plant), and its verification rejected a decay ratio of 0.89. Over
# the benchmark's plants (seed 0; 0, 1 and 3 % noise) the ramp's fits leave 0.09 at most; the
# relay's 0.10, but on (1 − 2s)/(s + 1)³ (a zero no model has) 0.15–0.20 over seeds 0–3,
# where TL PI from K_u and P_u has Ms 1.49 on the plant
RECORD_MISFIT = 0.25


@dataclass
class Selection:
    rule: str  # the rule whose gains are chosen
    chosen: IsaGains | None
    table: dict[str, IsaGains]
    assessments: dict[str, Assessment]
    recommended: Recommendation | None
    l_over_t: float | None
    refusal: str | None = None  # why the chosen gains must not be applied (None: they may)
    contradiction: str | None = None  # why no rule's gains may be (``contradicted_point``)
    warnings: list[str] = field(default_factory=list)
    # rules this identification would give but that may not be used, and why (a refused model)
    unavailable: dict[str, str] = field(default_factory=dict)
    # candidates outside the safety envelope (Kc ≥ K_u, predicted unstable, Ms above the
    # bound), and why: never recommended, refused unless forced
    unsafe: dict[str, str] = field(default_factory=dict)
    model_check: ModelCheck | None = None  # the verdict on the identified model (None: none)
    sample_time: float | None = None  # s: the loop the figures are for (None: continuous)
    lambda_s: float | None = None  # s: the λ the lambda rules used (None: no lambda rule)
    # the relative spreads of K_u and P_u to state with them (``stated_spreads``)
    ku_spread: float | None = None
    pu_spread: float | None = None
    # the model's predictions are not sure (it misses the measured point or its record, or
    # the process answers inversely): the verification checks every rule's gain margin
    model_unsure: bool = False
    # what the model misses (the measured point, or its record), where it does: gains from
    # it are not applied untried (``TuningRun``: --no-verify refused unless forced)
    model_misses: str | None = None
    # what ``force`` let through that would have been refused (the chosen gains outside the
    # safety envelope, a contradicted point): the run, if its gains pass, ends ``forced``
    forced: str | None = None


def l_over_t(ident: Identification, model: ProcessFit | None = None) -> float | None:
    """L/T of the step test (of its model as the rules take it: where the record did not
    resolve the dead time, the one the design takes, not the measured curve's), else of the
    (usable) model's first-order equivalent; None when unknown or not finite."""
    sm = ident.step_model
    if ident.step is not None and sm is not None and not sm.is_integrating and sm.time_constant:
        return _finite(sm.dead_time / sm.time_constant)  # the design's L, the curve's T
    if ident.step is not None:
        return _finite(ident.step.l_over_t)
    if model is None or model.kind == "ipdt":
        return None
    m = fopdt_of(model)
    return _finite(m.dead_time / m.time_constant) if m.time_constant > 0 else None


def _ratio_source(ident: Identification) -> str:
    """Whose L/T ``l_over_t`` gives: the step's reaction curve (its dead time the design's),
    else the model's first-order equivalent."""
    sm = ident.step_model
    # the design's L only where it is not the curve's own (a dead time the record did not
    # resolve): "the design's L" was said of the curve's 39.24 s, beside a model whose L was
    # 40.02 s (helper review)
    designed = sm is not None and sm.dead_time != getattr(ident.step, "dead_time", None)
    if ident.step is not None and designed and not sm.is_integrating and sm.time_constant:
        return "the step curve's T, the design's L"
    if ident.step is not None:
        return "the step curve's"
    return "the model's first-order equivalent"


def _finite(x: float | None) -> float | None:
    """A plain finite float, or None: JSON takes no inf or nan."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


# how far a fitted model's own ultimate point may lie from a measured (bracketed) one before
# the robustness judged on the model is said to be less sure
MODEL_POINT_TOLERANCE = 0.1
# how many times apart (K_u or P_u, either way) a bracketed ultimate point and its record's
# model's own may lie before the identification contradicts itself (``contradicted_point``)
CONTRADICTION = 2.0


def contradicted_point(ident: Identification, check: ModelCheck | None) -> str | None:
    """Why no gains from a ramp test may be applied where the ultimate point its trials
    bracketed and the one of the process model fitted to their record are ``CONTRADICTION``
    times apart or more (the model judged sound or not); None where they agree that well.

    Why: one of the two is then not this loop's, and every rule rests on one of them. Seen on
    loops whose trials oscillate in a faster mode than the ultimate one (near a pure delay
    the modes at 3ω_u, 5ω_u … go unstable just above K_u too; a process with gain at high
    frequencies): the fits gave P_u/3, the model's P_u was within 2–3 % of exact, and TL PI
    from the trials' P_u (Ti = 0.70 s for a P_u of 2.64 s) left the loop in a 0–100 % limit
    cycle after a verification that ended `ok` before its slow growth showed."""
    if check is None or not ident.ku_bracketed or not (ident.ku and ident.pu):
        return None
    apart = []
    for label, measured, model, unit in (
        ("K_u", ident.ku, check.ku_model, ""),
        ("P_u", ident.pu, check.pu_model, " s"),
    ):
        if model is None or not (math.isfinite(model) and model > 0):
            continue
        ratio = max(model / measured, measured / model)
        if ratio >= CONTRADICTION:
            apart.append(f"{label} {measured:.4g}{unit} against {model:.4g}{unit}")
    if not apart:
        return None
    return (
        f"the trials' ultimate point and the one of the model fitted to their record are "
        f"{CONTRADICTION:g} times apart or more ({'; '.join(apart)}): one of them is not this "
        "loop's, and the rules rest on one of them; trials that oscillate in a faster mode "
        "than the ultimate one (a long dead time, a resonance, gain at high frequencies) give "
        "a fraction of P_u — a relay test reads such a loop's ultimate point; or a load that "
        "changed during the trials, which the model fitted to their record does not have — "
        "the test again once it has passed"
    )


def check_identification(ident: Identification) -> ModelCheck | None:
    """``model_check`` on the identification's model with what was measured beside it (None
    without a model). A step test has no K_u: its reaction curve is checked on physics."""
    if ident.model is None:
        return None
    return check_model(
        ident.model,
        ident.ku,
        ident.pu,
        ident.ku_spread,
        ident.pu_spread,
        integrating=ident.integrating,
    )


def stated_spreads(
    ident: Identification, check: ModelCheck | None
) -> tuple[float | None, float | None]:
    """The spreads of K_u and P_u to state (``model_check.stated_spread``): the measured ones,
    widened to how far a sound model's own ultimate point lies from them, but for a K_u that
    two gains tried on the loop bracket (a ramp: hx1's model put K_u 13.8 % off exact where
    the bracket was 0.6 % wide and the K_u within 0.3 %)."""
    if check is None or not check.sound:
        return ident.ku_spread, ident.pu_spread
    ku_model = None if ident.ku_bracketed else check.ku_model
    return (
        stated_spread(ident.ku, ident.ku_spread, ku_model),
        stated_spread(ident.pu, ident.pu_spread, check.pu_model),
    )


# a stated spread beyond this (relative) is said as a warning of its own: the figure is not
# pinned down, whatever else the run says of it
LOOSE_SPREAD = 0.25


def _loose(ku_spread: float | None, pu_spread: float | None) -> list[str]:
    """A warning where K_u's or P_u's stated spread is beyond ``LOOSE_SPREAD``: the figure
    came out with its spread beside it and nothing else said (a biased relay's second stage
    on an underdamped process, ζ 0.2, read K_u 0.674 for 0.859, spread 81 %: helper trial)."""
    loose = [
        f"{label} ±{100 * s:.2g} %"
        for label, s in (("K_u", ku_spread), ("P_u", pu_spread))
        if s is not None and s > LOOSE_SPREAD
    ]
    if not loose:
        return []
    return [
        f"{' and '.join(loose)}: not pinned down (the experiment's measurements disagree that "
        "much); every rule's gains are no surer than that, and only the verification on the "
        "loop judges them: test again (a longer test, another method, or a relay without "
        "--relay-bias)"
    ]


def _widened(
    ident: Identification,
    check: ModelCheck | None,
    ku_spread: float | None,
    pu_spread: float | None,
) -> list[str]:
    """Why a stated spread is wider than the experiment's own: the model's figure beside it."""
    out = []
    for label, own, stated, model, unit in (
        ("K_u", ident.ku_spread, ku_spread, check.ku_model if check else None, ""),
        ("P_u", ident.pu_spread, pu_spread, check.pu_model if check else None, " s"),
    ):
        if stated is None or stated == own or model is None:
            continue
        was = f"{100 * own:.2g} %" if own is not None else "none"
        out.append(
            f"{label}'s spread is stated as {100 * stated:.2g} %: the identified model's own "
            f"{label} ({model:.4g}{unit}) lies that far from the measured one (the "
            f"experiment's own spread: {was}); take the figure as no surer than that"
        )
    if ident.ku_bracketed and check is not None and check.ku_model and ident.ku and ident.pu:
        # the bracket states K_u, not the model: but the rules' Ms and margins are judged on
        # the model, which is as sure there as its own ultimate point is near the measured
        off_k = check.ku_model / ident.ku - 1.0
        off_p = (check.pu_model / ident.pu - 1.0) if check.pu_model else 0.0
        if max(abs(off_k), abs(off_p)) > MODEL_POINT_TOLERANCE:
            out.append(
                f"the identified model's own ultimate point (K_u {check.ku_model:.4g}, P_u "
                f"{check.pu_model or math.nan:.4g} s) is {100 * off_k:+.2g} % / "
                f"{100 * off_p:+.2g} % from the measured one: the robustness figures (Ms, "
                "margins) are judged on that model, and are no surer than that"
            )
    return out


def _off_the_measured_point(
    assessments: dict[str, Assessment],
    ultimate: UltimatePoint | None,
    sample_time: float | None,
    ident: Identification,
    check: ModelCheck | None,
    unsure: float = 0.0,
) -> dict[str, float]:
    """The rules whose Ms on the model lies clearly below the floor the measured ultimate
    point sets (``measured_point.ms_floor``), with that floor: beyond the measurement's own
    spread or, for a step test's record point, its uncertainty (twice it) and 5 %, the model's
    loop is not the plant's there."""
    if ultimate is None:
        return {}
    ku_spread, pu_spread = stated_spreads(ident, check)
    tol = MISFIT_TOLERANCE + 2.0 * max(ku_spread or 0.0, pu_spread or 0.0, unsure)
    out: dict[str, float] = {}
    for name, a in assessments.items():
        rb = a.robustness
        if rb is None or not a.stable or not math.isfinite(rb.ms):
            continue
        floor = ms_floor(a.gains, ultimate, sample_time)
        if floor > rb.ms * (1.0 + tol):
            out[name] = floor
    return out


def _misses_the_record(model: ProcessFit | None, ultimate: UltimatePoint | None) -> float | None:
    """How much of the PV's spread the model's fit of its record leaves beyond the noise,
    where that is more than ``RECORD_MISFIT`` and an ultimate point was measured (the rules
    then have K_u and P_u to fall back on); None otherwise. Beyond the noise: the less of
    what the rest's noise estimate leaves and what the residual's own whiteness does
    (``ProcessFit.excess_rms``): flow1's exact plant left 0.41 of the PV's spread, all of
    it its σ 0.2 noise, where a rest that read σ 0.155 left 0.26 beyond it, and a ramp was
    refused for a model that missed nothing."""
    if model is None or ultimate is None or not math.isfinite(model.rms):
        return None
    excess = model.excess_rms
    return excess if excess > RECORD_MISFIT else None


def _beside(x: float, bound: float) -> str:
    """``x`` to three significant figures, or as many more as tell it from ``bound`` (0.1497
    read "0.15" beside "outside 0.15–0.6")."""
    for digits in range(3, 10):
        text = f"{x:.{digits}g}"
        if (float(text) < bound) == (x < bound) and float(text) != bound:
            return text
    return repr(x)


def guidance(
    ratio: float | None,
    model: ProcessFit | None,
    seen_integrating: bool = True,
    source: str | None = None,
) -> list[str]:
    """What the seeds and the benchmark say about rules at this L/T. ``seen_integrating``:
    the experiment saw the process integrate (a step test's steady ramp), not only a model
    that fits as an integrator near ω_u (a relay's cycles). ``source``: whose L/T it is, said
    beside it (a step's table shows the curve's and the model's: "L/T = 0.123: outside
    0.15–0.6" read beside "model … L/T = 0.153" as a contradiction, walkthrough)."""
    out = []
    if model is not None and model.kind == "ipdt" and seen_integrating:
        out.append("integrating process: simc-pi-int is the rule made for it (a level loop)")
    elif model is not None and model.kind == "ipdt":
        # lvl1, a 600 s lag cycled at 4 s, was called integrating beside model check's
        # "self-regulating" (helper 62)
        out.append(
            "integrating near the ultimate point: the test's oscillation fits an integrator, as "
            "a lag far longer than P_u fits it too (a step test or `autotune model check` "
            "tells the two apart); simc-pi-int is the rule made for an integrating loop"
        )
    if ratio is None:
        return out
    lo, hi = ZN_STEP_RANGE
    whose = f" ({source})" if source else ""
    if not lo <= ratio <= hi:
        out.append(
            f"L/T = {_beside(ratio, lo if ratio < lo else hi)}{whose}: outside {lo}–{hi}, "
            "where the step-response rules (zn-ol-*, cc-*) suit (seed 000)"
        )
    if ratio > 1.0:
        out.append(
            f"L/T = {_beside(ratio, 1.0)}{whose}: delay-dominated; derivative action helps "
            "little and Ziegler–Nichols PID is aggressive here: PI rules (tl-pi, amigo-pi, "
            "simc-pi) suit"
        )
    return out


def select(
    ident: Identification,
    rule: str,
    ms_bound: float = 2.0,
    force: bool = False,
    sample_time: float | None = None,
    lambda_s: float | None = None,
    aim: str = "balanced",
    parts: Parts = in_turn,
    max_op_noise: float | None = None,
    span: float | None = None,
) -> Selection:
    """The gains for ``rule`` ("auto": the recommended rule for the ``aim``, see
    ``recommend``), judged at the loop's ``sample_time`` (s; None: in continuous time),
    refused (``refusal``) outside the safety envelope unless ``force``; the lambda rules with
    ``lambda_s`` (s; None: their default). ``parts``: how the judging's two independent
    parts are computed (``assess``; the tuner: at once, in its workers); ``max_op_noise``:
    the output noise (% of output, σ) the verification accepts, which the recommendation
    keeps within where it can (``recommend.quieter``; None: no limit); ``span``: the PV's
    (None: not known), against which a gain above what any write of gains may ask
    (``kc_over_limit``) is outside the envelope, forced or not."""
    ku, pu = _finite(ident.ku), _finite(ident.pu)
    ultimate = UltimatePoint(ku, pu) if ku and pu and ku > 0 and pu > 0 else None
    ts = _finite(sample_time)
    ts = ts if ts and ts > 0 else None
    check = check_identification(ident)
    model = ident.model if check is None or check.ok else None
    unavailable: dict[str, str] = {}
    warnings: list[str] = []
    without_model = None
    if check is not None and not check.ok:
        step_test = ident.step_model is not None
        kinds = ("model", "open") if step_test else ("model",)
        what = "reaction curve" if step_test else f"{ident.model.kind.upper()} model"
        without_model = f"the {what} was refused ({check.summary()})"
        for name, r in RULES.items():
            if r.kind in kinds:
                unavailable[name] = f"the {what} was refused: {check.summary()}"
        warnings.append(
            f"the identified {what} was refused, so no rule uses it and no robustness is "
            f"predicted from it: {check.summary()}"
        )
    # the model rules are designs for a continuous controller: a digital one at sample time
    # T adds the hold's T/2 of dead time, which they are given (the usual allowance, e.g.
    # Åström & Hägglund 2006, §3.6); the judgement below is on the exact sampled loop
    design = dataclasses.replace(model, delay=model.delay + 0.5 * ts) if model and ts else model
    # what the lambda rules are designed on (``apply_rules``): the model, else the curve's
    lambda_source = (
        design if design is not None or ident.step_model is None else model_of(ident.step_model)
    )
    table = {
        name: g
        for name, g in apply_rules(
            ultimate,
            None if "open" in _kinds(unavailable) else ident.step_model,
            design,
            lambda_s,
        ).items()
        if name not in unavailable
    }
    for name, g in list(table.items()):  # JSON takes no inf or nan: such gains are no gains
        if g.ti is not None and not math.isfinite(g.ti):
            unavailable[name] = f"non-finite integral time {g.ti}"
            del table[name]
    assessments = assess(
        ultimate, model, table, simulate=True, sample_time=ts, parts=parts, noise=ident.noise
    )
    # the point the model is held to: the measured one, else the one a step test's record
    # implies by itself (no rule uses that one)
    point, unsure = ultimate, 0.0
    if point is None and ident.record_point is not None:
        ku_r, pu_r, unsure = ident.record_point
        point = UltimatePoint(ku_r, pu_r)
    misfit = _off_the_measured_point(assessments, point, ts, ident, check, unsure)
    for name, floor in misfit.items():  # judged by what the measurement alone implies
        a = assessments[name]
        assessments[name] = dataclasses.replace(
            a, robustness=dataclasses.replace(a.robustness, ms=floor), ms_from_point=True
        )
    missed = None if misfit else _misses_the_record(model, ultimate)
    unsure = None  # what the model misses, for the warning
    if misfit:
        told = ", ".join(f"{k} {misfit[k]:.3g}" for k in sorted(misfit))
        at = (
            "its measured ultimate point"
            if ultimate is not None
            else f"the ultimate point its step response implies by itself (K_u {point.ku:.4g}, "
            f"P_u {point.pu:.4g} s, read from the record, not from a model)"
        )
        unsure = (
            f"the identified model misses the plant at {at}: for {len(misfit)} of the rules it "
            f"predicts an Ms below what that point alone implies (at least {told}, taken as "
            "their Ms)"
        )
    elif missed is not None:
        unsure = (
            f"the identified {model.kind.upper()} model misses its record: its fit leaves "
            f"{missed:.2g} of the PV's spread beyond the noise (more than {RECORD_MISFIT:g})"
        )
    if unsure is not None:
        tl = any(k in UNBIASED_RELAY_RULES for k in assessments)
        warnings.append(
            f"{unsure}, so none of its predictions is sure: every rule is held to Ms ≤ "
            f"{APPROXIMATE_PID_MARGIN * ms_bound:.2g}"
            + (", and the recommendation is Tyreus–Luyben's, from K_u and P_u alone" if tl else "")
        )
    unsure_model = unsure is not None
    pool = assessments
    # why each rule judged but not in the pool is left out of it (a refusal names them)
    left_out: dict[str, str] = {}
    if model is not None and ultimate is not None and not ident.static_gain_known:
        # the relay's points pin G near ω_u, not its static gain nor its low frequencies:
        # every rule is computed and judged, but the recommendation is Tyreus–Luyben's, made
        # for K_u and P_u alone (its integral, Ti = 2.2 P_u, acts little where the model is
        # unsure; ZN's halved PI, at P_u/1.2, was seen at 38 % overshoot for 14 % predicted)
        robust = {k: a for k, a in assessments.items() if k in UNBIASED_RELAY_RULES}
        if robust:
            pool = robust
            for k in assessments.keys() - robust.keys():
                left_out[k] = "a relay without bias does not pin the static gain they need"
            warnings.append(
                "the relay does not measure the static gain (its mean output does not move): "
                "the model is sure only near the ultimate point, so the recommendation is "
                "Tyreus–Luyben's, from K_u and P_u; --relay-bias pins the gain for the others"
            )
    if unsure_model:
        # the model rules are designs on a model that misses the plant: the recommendation
        # is from K_u and P_u alone (on the underdamped plant above, AMIGO PID passed at 1.41
        # on the model, 2.33 on the plant; TL PI 1.81)
        robust = {k: a for k, a in pool.items() if k in UNBIASED_RELAY_RULES}
        if robust:
            why = "the measured ultimate point" if misfit else "its record"
            for k in pool.keys() - robust.keys():
                left_out[k] = f"the model misses {why}"
            pool = robust
    if ident.inverse_response:
        # a right-half-plane zero raises the gain at high frequencies, where a derivative
        # acts and where the models (no term for it) are least right: a PID's predicted Ms
        # is the least sure (seen: TL PID 1.75 predicted, 2.14 on (1 − 4s)/((10s+1)(5s+1));
        # AMIGO PID 1.45, 2.18 on (1 − 2s)/((s+1)(3s+1))). PIDs are offered, not recommended
        pids = {k for k, a in pool.items() if a.gains.td > 0}
        if pids and len(pids) < len(pool):
            pool = {k: a for k, a in pool.items() if k not in pids}
            for k in pids:
                left_out[k] = "an inverse response: derivative action is not recommended"
    if ts:
        # a derivative of a few samples is not the derivative the rule designed: the discrete
        # D term is then mostly gain at high frequency (TL PID at 23 samples per period, Td of
        # 3.7 samples, had Ms 2.6 on the plant): such PIDs are offered, not recommended
        coarse = {k for k, a in pool.items() if 0 < a.gains.td < MIN_TD_SAMPLES * ts}
        if coarse and len(coarse) < len(pool):
            pool = {k: a for k, a in pool.items() if k not in coarse}
            for k in coarse:
                left_out[k] = f"a derivative time below {MIN_TD_SAMPLES:g} samples"
            warnings.append(
                f"derivative times below {MIN_TD_SAMPLES:g} samples ({', '.join(sorted(coarse))}) "
                "are not recommended: the sampled derivative is then mostly high-frequency gain"
            )
    judge = model
    if model is not None and unsure_model:
        source = MISFIT_SOURCE if misfit else RECORD_MISFIT_SOURCE
        judge = dataclasses.replace(model, source=source)
    elif model is not None and ident.inverse_response:
        judge = dataclasses.replace(model, source=INVERSE_SOURCE)
    elif model is not None and not ident.static_gain_known:
        # unsure away from ω_u, the model judges a derivative (which acts above it) with the
        # tighter margin of an approximate model (TL PID on a sampled integrator: Ms 1.7
        # predicted on a two-lag fit, 2.6 true)
        judge = dataclasses.replace(model, source="relay points")
    # no measured K_u: the one a step's record implies bounds Kc as a measured one would
    # (a lead-lag's FOPDT fit, its dead time unresolved, gave AMIGO PI Kc 15 against the
    # record's K_u of 4.4; its verification saturated the output and rejected it)
    implied = None
    if ultimate is None and ident.record_point is not None:
        implied = (ident.record_point[0], ident.record_point[2])

    def recommend_of(candidates: dict[str, Assessment]) -> Recommendation | None:
        return recommend(
            ultimate,
            judge,
            ms_bound,
            {k: a for k, a in candidates.items() if kc_over_limit(a.gains.kc, span) is None},
            without_model,
            aim,
            pooled=bool(left_out),
            implied=implied,
            max_op_noise=max_op_noise,
        )

    rec = recommend_of(pool)
    lambda_quiet = None  # λ raised for the output noise (``_quieter_lambda``)
    if rec is not None and rec.noisy and lambda_s is None and not misfit and ts:
        raised = _quieter_lambda(
            lambda_source, model, ultimate, ts, ident.noise, max_op_noise, pool, parts
        )
        if raised is not None:
            lambda_quiet, again = raised
            table.update({k: a.gains for k, a in again.items()})
            assessments.update(again)
            pool = {**pool, **{k: a for k, a in again.items() if k in pool}}
            rec = recommend_of(pool)
            warnings.append(
                f"every rule within the Ms margin was predicted to make more than "
                f"{max_op_noise:g} % of output noise (σ) from the PV's noise: the lambda rules "
                f"are designed at λ = {lambda_quiet:.4g} s, raised from their default "
                f"{lambda_used(lambda_source, None):.4g} s, for "
                f"{QUIET_SHARE * max_op_noise:.3g} % or less (a slower loop; --lambda sets λ, "
                "--max-op-noise the limit)"
            )
    # a model that misses the measured point judges no rule surely: the envelope's bound is
    # then the approximate model's tighter one (ZN PI at 1.80 from K_u and P_u alone, 3.14 on
    # the plant, had passed at 2)
    bound = APPROXIMATE_PID_MARGIN * ms_bound if unsure_model else ms_bound
    unsafe = {
        name: p
        for name, a in assessments.items()
        if (p := envelope_problem(a, ultimate, bound, implied)) is not None
    }
    # above the most a write of gains may ask: outside the envelope, and no --force takes it
    # (`autotune set` and `apply` refuse it, so a run's `ok` would name gains they refuse)
    over = {name: p for name, a in assessments.items() if (p := kc_over_limit(a.gains.kc, span))}
    unsafe.update(over)
    ratio = l_over_t(ident, model)
    name = (rec.rule if rec else "") if rule == "auto" else rule
    ku_spread, pu_spread = stated_spreads(ident, check)
    warnings += _widened(ident, check, ku_spread, pu_spread)
    warnings += _loose(ku_spread, pu_spread)
    sel = Selection(
        name,
        table.get(name),
        table,
        assessments,
        rec,
        ratio,
        warnings=warnings + guidance(ratio, model, ident.integrating is True, _ratio_source(ident)),
        unavailable=unavailable,
        unsafe=unsafe,
        model_check=check,
        ku_spread=ku_spread,
        pu_spread=pu_spread,
        model_unsure=unsure_model or ident.inverse_response,
        model_misses=unsure,
        sample_time=ts if model is not None else None,
        lambda_s=_lambda_of(
            table,
            lambda_source,
            lambda_s if lambda_quiet is None else lambda_quiet,
        ),
    )
    if sel.chosen is None:
        if rule == "auto":
            why = [f"{k}: {v}" for k, v in unsafe.items() if k not in over]
            if over:
                flag = "--lambda" if "lambda-pi" in pool else "--rule lambda-pi --lambda"
                source = lambda_source if "lambda-pi" in table else None
                why.append(_over_told(over, assessments, span, flag, source))
            if without_model:
                why.insert(0, without_model)
            sel.refusal = "no rule could be recommended" + (
                f" (outside the safety envelope or unavailable: {'; '.join(why)})" if why else ""
            )
            inside: dict[str, list[str]] = {}
            for k in sorted(left_out.keys() - unsafe.keys()):
                inside.setdefault(left_out[k], []).append(k)
            if inside:
                told = "; ".join(f"{', '.join(ks)} ({why})" for why, ks in inside.items())
                sel.refusal += (
                    f"; within the envelope but not recommended: {told} (--rule takes one, "
                    "verified as any)"
                )
            if (
                ultimate is None
                and ident.step is not None
                and not (over and over.keys() == table.keys())
            ):
                # a step's rules all rest on its model or its curve: the relay's on K_u and
                # P_u, measured (an underdamped loop's SOPDT fit missed its record and no rule
                # was left; the relay tuned it, TL PID at Ms 1.57)
                sel.refusal += (
                    "; the relay test measures K_u and P_u, which its rules need no model for "
                    "(--method relay)"
                )
        elif name in unavailable:
            sel.refusal = f"rule {name}: unavailable: {unavailable[name]}"
        else:
            sel.refusal = (
                f"rule {name}: this identification does not give it "
                f"({RULES[name].kind} rule; {_why_missing(name, ident)})"
            )
        return sel
    a = assessments[name]
    if a.robustness is None:
        sel.warnings.append(
            "no usable process model: the gains' robustness is not predicted"
            if without_model
            else "no process model from this method: the gains' robustness is not predicted"
        )
    problem = unsafe.get(name)
    if problem and name in over:
        lam = _lambda_within(lambda_source, span) if "lambda-pi" in table else None
        sel.refusal = (
            f"refused: {name}: {problem}; not even with --force: `autotune set` and `apply` "
            "refuse it too"
            + (
                f"; lambda PI asks at most that with --rule lambda-pi --lambda {lam:.3g} (s) or "
                "more, a slower loop"
                if lam is not None
                else ""
            )
        )
    elif problem:
        problem = f"{name}: {problem}"
        if force:
            sel.warnings.append(problem + " — applied because forced")
            sel.forced = problem
        else:
            better = f"; the recommended rule is {rec.rule}" if rec and rec.rule != name else ""
            sel.refusal = f"refused: {problem} (--force to apply anyway{better})"
    if rule != "auto" and a.noisy(max_op_noise):
        # a rule asked for is not passed over for its noise (the verification measures it):
        # said here, for --no-verify and --no-apply have no verification to say it (SIMC PI
        # at 36 % predicted was applied unverified, or proposed, with no word of it)
        other = assessments.get(rec.rule) if rec is not None and rec.rule != name else None
        quiet = (
            f"; the recommended {other.rule}: {other.op_noise:.3g} %"
            if other is not None and other.op_noise is not None
            else ""
        )
        sel.warnings.append(
            f"{name}: predicted to make {a.op_noise:.3g} % of output noise (σ) from the PV's "
            f"noise, above the {max_op_noise:g} % limit (--max-op-noise): the verification "
            f"rejects gains measured above it{quiet}"
        )
    # rules passed over for the limit: said, as the recommendation's reason does not say it
    if sel.chosen is not None and over.keys() - {name}:
        pct = {k: kc_percent(assessments[k].gains.kc, span) for k in over if k != name}
        sel.warnings.append(
            f"{', '.join(f'{k} ({pct[k]:.4g} %/%)' for k in sorted(pct))}: Kc above the "
            f"{MAX_KC_PERCENT:g} % of output per % of span any write of gains may ask, so "
            "not offered for applying"
        )
    apart = sel.contradiction = contradicted_point(ident, check)
    if apart:
        if force:
            sel.warnings.append(apart + " — applied because forced")
            sel.forced = "; ".join(x for x in (sel.forced, apart) if x)
        elif sel.refusal is None:
            sel.refusal = f"refused: {apart} (--force to apply anyway)"
    return sel


def _over_told(
    over: dict[str, str],
    assessments: dict[str, Assessment],
    span: float,
    flag: str,
    source: ProcessFit | None,
) -> str:
    """The rules whose Kc is above what a write of gains may ask, in one line (their Kc in %
    per % of span), and the λ at which lambda PI would ask at most that, where there is one
    (``_lambda_within``) on the model they are designed on (``source``; None: no lambda PI),
    asked for with ``flag``; ``span``: the PV's."""
    pct = sorted(kc_percent(a.gains.kc, span) for k, a in assessments.items() if k in over)
    told = (
        f"{', '.join(sorted(over))}: Kc above the {MAX_KC_PERCENT:g} % of output per % of span "
        f"any write of gains may ask (theirs {pct[0]:.4g}–{pct[-1]:.4g} %/%, proportional bands "
        f"down to {100.0 / pct[-1]:.2g} %: a dead time short against the lag asks so much, "
        "or a PV range far wider than the output moves the PV over)"
    )
    lam = _lambda_within(source, span)
    if lam is not None:
        told += f"; lambda PI asks at most that with {flag} {lam:.3g} (s) or more, a slower loop"
    return told


def _lambda_within(source: ProcessFit | None, span: float | None) -> float | None:
    """The least λ (s, to 3 figures, rounded up) at which lambda PI on ``source`` has Kc
    within ``MAX_KC_PERCENT`` % per % of ``span`` (Kc falls as λ grows), None without a model
    or span, or where none up to 10⁷ s does."""
    if source is None or not span:
        return None
    rule = RULES["lambda-pi"]

    def within(lam: float) -> bool:
        try:
            g = rule.compute(source, lam)
        except (ValueError, ArithmeticError):
            return False
        return g is not None and kc_over_limit(g.kc, span) is None

    lo, hi = 1e-6, 1e7
    if within(lo) or not within(hi):
        return None
    for _ in range(200):  # on log λ, to a relative 1e-4
        if hi / lo < 1.0001:
            break
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if within(mid) else (mid, hi)
    unit = 10.0 ** (math.floor(math.log10(hi)) - 2)  # 3 significant figures, rounded up
    for n in range(math.ceil(hi / unit), math.ceil(hi / unit) + 3):
        if within(up := float(f"{n * unit:.3g}")):
            return up
    return None


def _quieter_lambda(
    source: ProcessFit | None,
    model: ProcessFit | None,
    ultimate: UltimatePoint | None,
    ts: float,
    noise: float,
    limit: float | None,
    pool: dict[str, Assessment],
    parts: Parts,
) -> tuple[float, dict[str, Assessment]] | None:
    """Where every candidate is above the output-noise ``limit`` (%): the λ at which lambda
    PI is predicted at ``QUIET_SHARE`` of it (``output_noise.quiet_lambda``), and the lambda
    rules of ``pool`` designed on ``source`` at it and judged on ``model`` as ``assess`` judges
    them. None where no lambda rule is a candidate, there is no model, or no λ helps. Why:
    on an integrator sampled at 0.1 s with a PV noise σ of 0.05 every rule within the margin
    was predicted at 11–13 % of output noise (lambda PI 11.1 %, 12.9 % measured), and the
    verification rejected the tune; lambda PI at a longer λ is slower and within the limit."""
    names = [k for k in pool if RULES[k].tuned_by_lambda]
    if not names or source is None or model is None or limit is None or noise <= 0:
        return None
    try:
        plant = sampled_plant(model.transfer, ts)
        lam = quiet_lambda(source, plant, noise, QUIET_SHARE * limit)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None
    if lam is None:
        return None
    gains = {}
    for k in names:
        try:
            gains[k] = RULES[k].compute(source, lam)
        except ValueError:
            continue
    if not gains:
        return None
    again = assess(ultimate, model, gains, simulate=True, sample_time=ts, parts=parts, noise=noise)
    return lam, again


def _lambda_of(
    table: dict[str, IsaGains], design: ProcessFit | None, lambda_s: float | None
) -> float | None:
    """The λ the lambda rules in ``table`` were designed with (None if none is there)."""
    if design is None or not any(RULES[k].tuned_by_lambda for k in table if k in RULES):
        return None
    try:
        return lambda_used(design, lambda_s)
    except ValueError:
        return None


def _kinds(unavailable: dict[str, str]) -> set[str]:
    return {RULES[name].kind for name in unavailable if name in RULES}


def _why_missing(name: str, ident: Identification) -> str:
    kind = RULES[name].kind
    if kind == "model" and ident.model is None:
        return "it needs a process model, which the ramp does not give"
    if kind == "model":
        return f"not defined for a {ident.model.kind.upper()} model"
    return "the identification lacks what it needs"


def assessments_dict(sel: Selection) -> dict[str, dict]:
    """Per rule, the figures for JSON (rules without a model to judge them on are left out);
    ``within_envelope`` False for a candidate that would be refused unless forced."""
    out = {}
    for k, a in sel.assessments.items():
        if d := a.to_dict():
            d["within_envelope"] = k not in sel.unsafe
            if k in RULES and RULES[k].tuned_by_lambda and sel.lambda_s is not None:
                d["lambda_s"] = sel.lambda_s  # the closed-loop time constant λ used, s
            out[k] = d
    return out
