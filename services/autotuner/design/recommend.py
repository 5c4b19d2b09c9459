"""Which rule's gains to recommend, judged on the identified model.

Every ultimate-point rule is a candidate. With a model (the relay's fitted FOPDT/SOPDT/IPDT,
checked by ``model_check``), each candidate's maximum sensitivity Ms is computed on it — on the
sampled loop (``sampled_loop``: the plant held and sampled at the loop's T, the PID block's own
discrete transfer function) when the sample time is known, else in continuous time; among the
candidates inside the safety envelope (below), with Ms within the bound (default 2.0, with a
margin for the model's own error), the one with the largest integral gain Kc/Ti wins — the
AMIGO design criterion: the best rejection of load disturbances that the robustness allows
(Åström & Hägglund, *Advanced PID Control*, 2006, §7.3).

Without a model, or when the model was refused, the fallback is Tyreus–Luyben PI: Kc = K_u/3.2,
Ti = 2.2·P_u. It needs only K_u and P_u, which the relay measures well even when the record
its model was fitted to is not (issue 10: K_u right, the model's gain seven times too small).
At the measured crossover its integral adds only atan(1/(2.2·2π)) ≈ 4° of lag, so its gain
margin stays close to 3.2 whatever the plant's shape (2.9 on the heat exchanger): room for
the hold's lag at coarse sample times (2.4 at 17 samples per period there) and for error in
K_u; its Ms is 1.5–1.6 on FOPDT plants (control-references.md), 2.0 on the lag-dominated heat
exchanger. Halved ZN PI has a lower gain but Ti = P_u/1.2 costs 11° there, and on
lag-dominated plants that alone can destabilise the loop; the PID rules' derivative acts at
high frequency, where without a model nothing says what the plant does. After a step test
(no K_u) the fallback is AMIGO PI (designed for Ms ≈ 1.4), if its model passed its checks.

The aim (``--aim``) chooses among the same safe candidates: ``balanced`` (the default) is the
above; ``robust``, with a model, takes the first of lambda-pi, lambda-pid, then the robust
fallbacks (tl-pi, amigo-pi, simc-pi-int) that is within the margin of the Ms bound (else as
balanced); ``fast``, with a model, takes the largest integral gain Kc/Ti within the margin of
the Ms bound without preferring a calm predicted step (else as balanced).

The safety envelope: a candidate with Kc at or above the measured K_u, or predicted unstable,
or with Ms above the bound, is never recommended (``envelope_problem``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.autotuner.design.output_noise import noise_gain
from services.autotuner.design.predicted_response import (
    StepFigures,
    predicted_setpoint_steps,
    simulation_step,
)
from services.autotuner.design.robustness import Robustness, robustness
from services.autotuner.design.rules import RULES, UltimatePoint, apply_rules
from services.autotuner.design.sampled_loop import SampledPlant, sampled_plant, sampled_robustness
from services.autotuner.identify.model_fit import ProcessFit
from services.autotuner.parts import Parts, in_turn
from shared.control.forms import IsaGains
from shared.control.transfer import DelayedTF

MS_BOUND = 2.0
MODEL_MARGIN = 0.9  # recommend only below 0.9 × the bound: the model is an approximation
# … and below 0.75 × the bound for PID on a model that fits clearly worse than the noise allows:
# the derivative acts where such a model is least certain (a zero approximated by a delay)
APPROXIMATE_PID_MARGIN = 0.75
# the judging model's source where the test saw an inverse response (a right-half-plane
# zero none of the models has a term for): every rule's predicted Ms is optimistic there
# (PIs by up to 1.3×: SIMC PI 1.59 predicted, 2.06 on (1 − 2s)/((s+1)(3s+1)) by ramp), so
# every rule is held to the approximate model's tighter margin
INVERSE_SOURCE = "inverse response"
# … and where the model's Ms for some rule lies below what the measured K_u and P_u alone
# imply (``measured_point``): it misses the plant, and none of its predictions is sure
MISFIT_SOURCE = "misses the measured point"
# … and where its fit leaves much of its record unexplained (``selection.RECORD_MISFIT``)
RECORD_MISFIT_SOURCE = "misses its record"
UNSURE_SOURCES = (INVERSE_SOURCE, MISFIT_SOURCE, RECORD_MISFIT_SOURCE)
FALLBACKS = ("tl-pi", "amigo-pi", "simc-pi-int")  # robust by design, in this order
ROBUST_RULES = ("lambda-pi", "lambda-pid", *FALLBACKS)  # --aim robust, in this order
AIMS = ("balanced", "robust", "fast")


@dataclass(frozen=True)
class Assessment:
    rule: str
    gains: IsaGains
    # on the identified model (None without one): the sampled loop's when the sample time is
    # known (``robustness.sample_time`` set), else the continuous loop's
    robustness: Robustness | None
    step: StepFigures | None = None  # the closed loop's setpoint step on the model
    continuous: Robustness | None = None  # the continuous loop's, beside a sampled judgement
    # Ms taken from the measured ultimate point alone (the model misses the plant there:
    # ``selection``); the margins, overshoot and decay ratio beside it are still the model's
    ms_from_point: bool = False
    # the output noise the gains make of the PV's measured noise on the sampled loop of the
    # model (% of output, σ(Δu)/√2 as the verification measures it; ``output_noise``); None
    # where not predicted (no sampled loop, or not stable on it)
    op_noise: float | None = None

    def to_dict(self) -> dict[str, float | bool | None]:
        rb, st = self.robustness, self.step
        if rb is None:
            return {}
        out: dict[str, float | bool | None] = {
            "ms": _number(rb.ms),
            "gain_margin": _number(rb.gain_margin),
            "phase_margin_deg": _number(rb.phase_margin_deg),
            "stable": bool(self.stable),
            "sampled": rb.sample_time is not None,
        }
        if self.ms_from_point:
            out["ms_from_point"] = True
        if rb.sample_time is not None:
            out["sample_time"] = _number(rb.sample_time)
        if self.continuous is not None:
            out["ms_continuous"] = _number(self.continuous.ms)
            out["gain_margin_continuous"] = _number(self.continuous.gain_margin)
            out["phase_margin_deg_continuous"] = _number(self.continuous.phase_margin_deg)
        if st is not None:
            out["overshoot_pct"] = _number(st.overshoot)
            # the quarter-decay figure (``predicted_response``), None without a second overshoot
            out["decay_ratio"] = _number(st.overshoot_decay)
        if self.op_noise is not None:
            out["op_noise_pct"] = _number(self.op_noise)
        return out

    def noisy(self, limit: float | None) -> bool:
        """The predicted output noise is above ``limit`` (% of output; None: no limit)."""
        return limit is not None and self.op_noise is not None and self.op_noise > limit

    @property
    def stable(self) -> bool | None:
        rb = self.robustness
        if rb is None:
            return None
        if rb.stable is not None:  # the sampled loop's Nyquist count
            return rb.stable
        return bool(rb.gain_margin > 1.0 and rb.phase_margin_deg > 0.0)

    def within(self, bound: float) -> bool | None:
        rb = self.robustness
        return None if rb is None else bool(self.stable) and rb.ms <= bound


def _number(x: float | None) -> float | None:
    """A plain float for JSON (numpy scalars are not), None for an infinite or undefined one."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def envelope_problem(
    a: Assessment,
    ultimate: UltimatePoint | None,
    ms_bound: float,
    implied: tuple[float, float] | None = None,
) -> str | None:
    """Why a candidate is outside the safety envelope (None if inside): Kc at or above the
    measured K_u (the loop's own proportional gain would sustain or grow an oscillation), or,
    with none measured, above the K_u a step test's record implies by itself (``implied``:
    K_u and its relative uncertainty; Kc past K_u·(1 + it)), predicted unstable, or predicted
    Ms above the bound."""
    g = a.gains
    if ultimate is not None and g.kc >= ultimate.ku:
        return (
            f"Kc {g.kc:.4g} at or above the measured K_u {ultimate.ku:.4g} "
            f"({g.kc / ultimate.ku:.3g} × K_u)"
        )
    if ultimate is None and implied is not None and g.kc >= implied[0] * (1.0 + implied[1]):
        return (
            f"Kc {g.kc:.4g} above the K_u {implied[0]:.4g} the step's record implies by itself "
            f"(± {100 * implied[1]:.2g} %; {g.kc / implied[0]:.3g} × K_u)"
        )
    rb = a.robustness
    if rb is None:
        return None
    on = "the sampled loop" if rb.sample_time is not None else "the continuous loop"
    if not a.stable:
        return (
            f"predicted unstable on {on} (gain margin {rb.gain_margin:.3g}, phase margin "
            f"{rb.phase_margin_deg:.3g}°)"
        )
    if rb.ms > ms_bound:
        return f"predicted Ms {above(rb.ms, ms_bound)} above the bound {ms_bound:g} on {on}"
    return None


def above(x: float, bound: float) -> str:
    """``x`` to 3 significant digits, or as many more as it takes to read above ``bound``
    (Ms 2.0019 was printed "2 above the bound 2")."""
    for digits in range(3, 10):
        text = f"{x:.{digits}g}"
        if float(text) > bound:
            return text
    return repr(x)


def judge_all(
    gains: dict[str, IsaGains], tf: DelayedTF | None, sample_time: float | None
) -> tuple[dict[str, tuple[Robustness | None, Robustness | None, float | None]], bool]:
    """Every candidate's robustness on ``tf``: (on the sampled loop when ``sample_time`` s is
    given and the plant samples, else continuous; the continuous figures; the output's noise
    per unit of the PV's on the sampled loop, ``output_noise.noise_gain``, where it is judged
    stable there), and whether the sampled loop was judged. None for a figure that could not
    be computed."""
    plant: SampledPlant | None = None
    if tf is not None and sample_time is not None and sample_time > 0:
        try:
            plant = sampled_plant(tf, sample_time)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            plant = None
    judged: dict[str, tuple[Robustness | None, Robustness | None, float | None]] = {}
    for name, g in gains.items():
        rb, cont, gain = None, None, None
        if tf is not None:
            try:
                cont = robustness(g, tf)
            except (ValueError, ArithmeticError):
                cont = None
            rb = cont
            if plant is not None:
                try:
                    rb = sampled_robustness(g, plant)
                    gain = noise_gain(g, plant) if rb.stable else None
                except (ValueError, ArithmeticError, np.linalg.LinAlgError):
                    rb = None
        judged[name] = (rb, cont, gain)
    return judged, plant is not None


def assess(
    ultimate: UltimatePoint | None,
    model: ProcessFit | None,
    gains: dict[str, IsaGains] | None = None,
    simulate: bool = False,
    sample_time: float | None = None,
    parts: Parts = in_turn,
    noise: float = 0.0,
) -> dict[str, Assessment]:
    """Every candidate's robustness on the model (rules needing K_u and P_u unless given):
    on the sampled loop when ``sample_time`` (s) is given, beside the continuous figures and
    the output noise the gains make of the PV's white noise of σ ``noise`` (PV units); with
    ``simulate`` also its closed-loop setpoint step at the loop's sample time.

    The robustness and the steps are independent (a hundred milliseconds, half each), so
    they are computed as two ``parts``: the steps of every candidate, though only those
    judged are kept; in the rare case that one could not be judged, the steps of the others
    are simulated again, as they always were, so the figures are the same to the bit."""
    gains = apply_rules(ultimate, None) if gains is None else gains
    # the closed loop's time scale: P_u, measured or else the model's own (its slowest lag is
    # the open loop's, hundreds of times longer for a level, and would coarsen the simulation
    # of a fast loop past its own sample time)
    own = model.ultimate_point() if ultimate is None and model is not None else None
    timescale = (
        ultimate.pu
        if ultimate
        else float(own[1])
        if own
        else (model.delay + model.lag if model else 0.0)
    )
    if not math.isfinite(timescale) or timescale <= 0:
        timescale = 10.0 * model.delay if model else 0.0
    if sample_time and timescale > 0:
        # no sampled loop swings faster than two samples a period: a model whose own
        # continuous P_u is shorter (no −180° crossing but by a delay of a few ms, the relay
        # measuring none) had its steps simulated over no sample at all, and the run failed
        timescale = max(timescale, 2.0 * sample_time)
    tf = model.transfer if model is not None else None
    calls: list = [(judge_all, (gains, tf, sample_time))]  # what ``parts`` computes
    simulated = simulate and tf is not None and timescale > 0
    if simulated:  # every candidate's setpoint step, simulated together
        calls.append((predicted_setpoint_steps, (gains, tf, timescale, sample_time)))
    done = parts(calls)
    judged, sampled = done[0]
    steps: dict[str, StepFigures] = {}
    if simulated:
        kept = {k: g for k, g in gains.items() if judged[k][0] is not None}
        steps = (
            done[1]
            if len(kept) == len(gains)
            else predicted_setpoint_steps(kept, tf, timescale, sample_time)
        )
        steps.update(_resolved(kept, judged, steps, tf, timescale, sample_time))
    return {
        name: Assessment(
            name,
            g,
            judged[name][0],
            steps.get(name),
            judged[name][1] if sampled else None,
            op_noise=None if judged[name][2] is None else noise * judged[name][2],
        )
        for name, g in gains.items()
    }


# samples per period of a candidate's crossover (2π/ω_c on the sampled loop) below which its
# simulated step, made coarser than the loop's sample time to watch 30 time scales, is not its
# loop's: simulated again on its own time scale
MIN_CROSSOVER_SAMPLES = 20.0


def _resolved(
    gains: dict[str, IsaGains],
    judged: dict[str, tuple[Robustness | None, Robustness | None, float | None]],
    steps: dict[str, StepFigures],
    tf: DelayedTF,
    timescale: float,
    sample_time: float | None,
) -> dict[str, StepFigures]:
    """The setpoint steps of the candidates whose loop the common simulation did not resolve
    (its step coarser than the loop's sample time, and under ``MIN_CROSSOVER_SAMPLES`` of it
    to a period of their crossover), simulated again over 30 periods of it. Why: a lag with no
    dead time has no ultimate point, so the time scale was the model's lag, 300 s on
    1/(300s + 1) at 0.1 s; watched for 30 of them in 2000 samples the PI of Kc 2625, Ti 0.35 s
    (Ms 1.6 on the sampled loop, crossing over at 8.8 rad/s) ran at 4.5 s a sample, grew, and
    its step was printed 9743.6 % of overshoot, "within 20 points" of which the verification
    passed its 30.9 % (helper trial); at the loop's 0.1 s it is 31.0 %."""
    coarse = simulation_step(timescale, sample_time)
    if not sample_time or coarse <= sample_time:
        return {}
    out: dict[str, StepFigures] = {}
    for name, g in gains.items():
        rb = judged[name][0]
        wc = rb.omega_c if rb is not None and rb.stable else None
        if name not in steps or wc is None or not (wc > 0 and math.isfinite(wc)):
            continue
        period = 2.0 * math.pi / wc
        if coarse * MIN_CROSSOVER_SAMPLES > period:
            out[name] = predicted_setpoint_steps({name: g}, tf, period, sample_time)[name]
    return out


@dataclass(frozen=True)
class Recommendation:
    rule: str
    gains: IsaGains
    predicted_ms: float | None
    reason: str
    # every candidate within the margin was predicted above the output-noise limit: this one
    # is the least noisy (``quieter``), not one within it
    noisy: bool = False


CALM_OVERSHOOT = 25.0  # %: predicted setpoint overshoot preferred (verification limit 35 %;
# a model's prediction misses the plant's by some 5–10 points)
CALM_DECAY = 0.25  # predicted decay ratio preferred (verification limit 0.35)
# the least share of a passable candidate's integral gain (``_passable``) that the calm
# preference may keep: a unit load step leaves an integrated error of 1/Ki (Åström & Hägglund), so
# below it the calm candidate answers a load at least four times worse, where one predicted
# within the verification's own limits does not. Why: on e^{−0.5s}/((100s + 1)(s + 1)) by
# step, AMIGO PI predicted 25.001 % of overshoot and only lambda PID (Ti = T, λ = T) was left
# calm, at 0.0016 of AMIGO PID's Ki (31 % predicted, Ms 1.39); it was applied: Ms 1.01, a
# load's IAE 500 against AMIGO PI's 2.1 on another noise seed
CALM_KI_SHARE = 0.25


def _step_within(a: Assessment, overshoot: float, decay: float) -> bool:
    """The candidate's predicted setpoint step keeps within ``overshoot`` (%) and the decay
    ratio ``decay``."""
    st = a.step
    return (
        st is not None
        and st.stable
        and st.overshoot <= overshoot
        and (st.overshoot_decay or 0.0) <= decay
    )


def _calm(a: Assessment) -> bool:
    """The candidate's predicted setpoint step keeps inside the preferred overshoot and decay."""
    return _step_within(a, CALM_OVERSHOOT, CALM_DECAY)


# the verification's default limits (``TuneRequest.max_overshoot``, ``max_decay_ratio``; the
# core does not load the bus's schema, a test holds them equal): a candidate predicted within
# them is expected to pass it, if less comfortably than a calm one
PASSABLE_OVERSHOOT = 35.0  # %
PASSABLE_DECAY = 0.35


def _passable(a: Assessment) -> bool:
    """The candidate's predicted setpoint step keeps inside the verification's own limits."""
    return _step_within(a, PASSABLE_OVERSHOOT, PASSABLE_DECAY)


def _integral_gain(a: Assessment) -> float:
    """Kc/Ti (% of output per PV unit per s; 0 without an integral)."""
    return a.gains.kc / (a.gains.ti or math.inf)


# integral gains this close are one: the tie is broken by the lower Ms, not by rounding
SAME_KI = 1e-9


def _largest_integral_gain(pool: list[Assessment]) -> Assessment:
    """The candidate of ``pool`` with the largest integral gain; of several within SAME_KI
    of it, the most robust (the least Ms, then the first). Why: on an integrating loop two
    rules can give the same Kc/Ti with different Kc (SIMC PI and lambda PI on lvl2:
    100.41179161275672 and …74), and the last bits of the arithmetic picked one (helper
    trial)."""
    top = max(_integral_gain(a) for a in pool)
    ties = [a for a in pool if _integral_gain(a) >= top * (1.0 - SAME_KI)]
    return min(ties, key=lambda a: a.robustness.ms if a.robustness else math.inf)


def recommend(
    ultimate: UltimatePoint | None,
    model: ProcessFit | None,
    ms_bound: float = MS_BOUND,
    candidates: dict[str, Assessment] | None = None,
    without_model: str | None = None,
    aim: str = "balanced",
    pooled: bool = False,
    implied: tuple[float, float] | None = None,
    max_op_noise: float | None = None,
) -> Recommendation | None:
    """The rule to apply by default for the ``aim`` (see the module's docstring); ``candidates`` as
    ``assess`` gives them (every ultimate-point rule if not given); ``without_model`` says
    why there is no model to judge on (a refusal by ``model_check``); ``pooled``: the
    candidates are fewer than the rules computed (the others left out, said in a warning),
    so the reason names them; ``implied``: a step's record's K_u (``envelope_problem``);
    ``max_op_noise``: the output noise (% of output, σ) the verification accepts: candidates
    predicted above it are passed over where another is within the margin (``quieter``).
    None when no candidate is inside the safety envelope."""
    if aim not in AIMS:
        raise ValueError(f"unknown aim {aim!r}; expected one of {', '.join(AIMS)}")
    candidates = assess(ultimate, model) if candidates is None else candidates
    safe = {
        k: a
        for k, a in candidates.items()
        if RULES[a.rule].controller != "P"
        and envelope_problem(a, ultimate, ms_bound, implied) is None
    }
    if model is not None:
        sampled = any(
            a.robustness is not None and a.robustness.sample_time is not None for a in safe.values()
        )
        on = (
            f"the sampled loop of the identified {model.kind.upper()} model"
            if sampled
            else (f"the identified {model.kind.upper()} model")
        )

        def margin(rule: str) -> float:
            if model.source in UNSURE_SOURCES:  # every rule's Ms is unsure
                return APPROXIMATE_PID_MARGIN
            pid = RULES[rule].controller == "PID"
            return APPROXIMATE_PID_MARGIN if pid and model.approximate else MODEL_MARGIN

        ok = [a for a in safe.values() if a.within(margin(a.rule) * ms_bound)]
        ok, hushed = quieter(ok, max_op_noise)
        if ok and all(a.noisy(max_op_noise) for a in ok):
            least = ok[0]
            return Recommendation(
                least.rule,
                least.gains,
                _number(least.robustness.ms),
                f"the least output noise of the rules with {_margins(model, ms_bound)} on {on}: "
                f"{least.op_noise:.3g} % predicted (σ), above the {max_op_noise:g} % the "
                f"verification accepts{hushed}",
                noisy=True,
            )
        if aim == "robust":
            first = next((a for r in ROBUST_RULES for a in ok if a.rule == r), None)
            if first is not None:
                return Recommendation(
                    first.rule,
                    first.gains,
                    _number(first.robustness.ms),
                    f"aim robust: the first of {', '.join(ROBUST_RULES)} with "
                    f"Ms ≤ {margin(first.rule) * ms_bound:.2g} on {on}{hushed}",
                )
        # the verification will hold the loop to its overshoot and decay limits: prefer the
        # candidates whose predicted step already keeps well inside them (not when the aim
        # is fast)
        calm = [] if aim == "fast" else [a for a in ok if _calm(a)]
        costly = ""  # why the calm candidates were passed over
        passable = [a for a in ok if _passable(a)]
        if calm and passable:
            quiet, fair = _largest_integral_gain(calm), _largest_integral_gain(passable)
            if _integral_gain(quiet) < CALM_KI_SHARE * _integral_gain(fair):
                costly = (
                    f" (the best with a predicted overshoot ≤ {CALM_OVERSHOOT:g} % and decay "
                    f"ratio ≤ {CALM_DECAY:g}, {quiet.rule}, has "
                    f"{_integral_gain(quiet) / _integral_gain(fair):.2g} of its integral gain)"
                )
                calm = [fair]
        if ok:
            best = _largest_integral_gain(calm or ok)
            lead = "aim fast: " if aim == "fast" else ""
            also = f" and a predicted overshoot ≤ {CALM_OVERSHOOT:g} %" if calm else ""
            if costly:
                also = (
                    " and a predicted step within the verification's limits (overshoot ≤ "
                    f"{PASSABLE_OVERSHOOT:g} %, decay ratio ≤ {PASSABLE_DECAY:g})"
                )
            # the rules that met the condition named, and the pool's where it is one:
            # "largest integral gain" alone read as of every rule in the table, beside a
            # warning that the recommendation is Tyreus–Luyben's (helper 74), and "of <the
            # pool> with Ms ≤ 1.8" as if each of them had it, two UNSTABLE on the model
            # among them (helper trial)
            met = passable if costly else (calm or ok)
            among = f" (of the candidates {', '.join(sorted(candidates))})" if pooled else ""
            return Recommendation(
                best.rule,
                best.gains,
                _number(best.robustness.ms) if best.robustness else None,
                f"{lead}largest integral gain of the rules with {_margins(model, ms_bound)}"
                f"{also} on {on}{costly}: {', '.join(sorted(a.rule for a in met))}{among}"
                f"{hushed}",
            )
        judged = [a for a in safe.values() if a.robustness is not None]
        kept = " kept (the warning says why)" if pooled else ""
        safest = min(judged, key=lambda a: a.robustness.ms, default=None)
        if safest is not None:
            return Recommendation(
                safest.rule,
                safest.gains,
                _number(safest.robustness.ms),
                # the candidates named: the table lists every rule, and some outside the
                # pool may be within the margin (hx1 by relay: lambda-pid at 1.13 beside
                # "none within the margin": helper 52)
                # where the pool is the warning's (the relay's Tyreus–Luyben), the rules of
                # the table within the margin are not candidates: said so (hx1 by relay's
                # "the only candidate … none within the margin" read against amigo-pi at
                # 1.36 in the table: helper trial)
                (
                    f"the only candidate{kept} on {on}"
                    if len(judged) == 1
                    else f"the most robust of the candidates{kept} "
                    f"{', '.join(sorted(a.rule for a in judged))} on {on}"
                )
                + f" (none within the margin {_margins(model, ms_bound)})",
            )
    fallback = next((safe[r] for r in FALLBACKS if r in safe), None)
    if fallback is None:
        return None
    rb = fallback.robustness
    if model is not None:
        reason = f"no candidate within {_margins(model, ms_bound)} on the model"
    elif without_model:
        reason = f"{without_model}: the robust default, from K_u and P_u alone"
    else:
        reason = "no model to judge the candidates on: the robust default"
    return Recommendation(fallback.rule, fallback.gains, _number(rb.ms) if rb else None, reason)


def quieter(pool: list[Assessment], limit: float | None) -> tuple[list[Assessment], str]:
    """``pool`` less the candidates predicted to make more output noise than ``limit`` (%),
    and the reason's words for those passed over ("" if none). Where every candidate is
    above it, the least noisy alone is kept: the verification, which measures the noise,
    then decides. Why: the recommendation's largest integral gain is the noisiest gain on a
    lag with little dead time (SIMC PI, Kc 497 %/% on 0.1/(5s + 1) at 0.1 s: 34.5 % of output
    noise from a PV noise of 0.05, applied as ok, where lambda PI made 0.6 %)."""
    loud = [a for a in pool if a.noisy(limit)]
    if not loud:
        return pool, ""
    rest = [a for a in pool if not a.noisy(limit)]
    kept = rest or [min(loud, key=lambda a: a.op_noise or 0.0)]
    dropped = sorted((a for a in loud if a not in kept), key=lambda a: a.rule)
    if not dropped:
        return kept, ""
    told = ", ".join(f"{a.rule} {a.op_noise:.3g} %" for a in dropped)
    return kept, (
        f"; passed over for a predicted output noise above {limit:g} % (σ, the PV's noise "
        f"through the gains): {told}"
    )


def _margins(model: ProcessFit, ms_bound: float) -> str:
    """The Ms margins a model's candidates were held to, as the reason states them."""
    if model.source == INVERSE_SOURCE:
        return (
            f"Ms ≤ {APPROXIMATE_PID_MARGIN * ms_bound:.2g} for every rule on a model with no "
            "term for the inverse response"
        )
    if model.source == MISFIT_SOURCE:
        return (
            f"Ms ≤ {APPROXIMATE_PID_MARGIN * ms_bound:.2g} for every rule on a model that "
            "misses the measured ultimate point"
        )
    if model.source == RECORD_MISFIT_SOURCE:
        return (
            f"Ms ≤ {APPROXIMATE_PID_MARGIN * ms_bound:.2g} for every rule on a model that "
            "misses its record"
        )
    text = f"Ms ≤ {MODEL_MARGIN * ms_bound:.2g}"
    if model.approximate:
        text += f", PID ≤ {APPROXIMATE_PID_MARGIN * ms_bound:.2g} on a model this approximate"
    return text
