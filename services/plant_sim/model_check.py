"""Check a process model open loop before anyone tunes it: any ProcessModel — a preset, a
transfer function, a user's class or an FMU.

From rest at its operating point the model is stepped up and down at two sizes (2 % and
10 % of output, within the loop's output limits), each run until it settles, ramps or runs
away. From the responses:

* **behaviour**: self-regulating (settles), integrating (ends on a constant slope), unstable
  (accelerates without bound; said so, with its doubling time where it grows exponentially)
  or out of range (leaves 100 times its range without accelerating: a gain out of all
  proportion to it, not an instability);
* **static gain** (PV units per %; for an integrating model, PV units/s per %) for each step,
  and the **nonlinearity**: the largest over the smallest gain, up vs down and small vs large;
* **dead time**: when the PV first moves, to a fraction of a sample (the onset fitted through
  its first three samples: for a self-regulating response the gamma distribution's
  P(r, (t − L)/τ), exact for a first-order lag and for a chain of equal lags, and for
  unequal ones nearer than a power law; else, and where no such curve goes through the
  three, c·(t − L)^r, exact for a pure power law);
* **time constants**: T63 (to 63 % of the final change, after the dead time), the sum of the
  lags (mean residence time − dead time: exact for lags and dead time in series), and the
  reaction curve's apparent dead time and lag (the tangent at the inflection);
* **ultimate point** K_u (% per PV unit), P_u (s): exact from the transfer function for the
  linear models that have one, and for every model from its sampled step response: the pulse
  response's z-transform on the unit circle, the zero-order hold divided out, gives G(jω) up
  to aliasing (negligible when the period spans many samples), and the first phase crossing
  of −180° is solved for. The small up and down steps are averaged (a central difference:
  the even-order nonlinearity cancels), so this is the model's linear part at op0;
* **sample time** against the dynamics: samples per ultimate period, a warning below 20.

A model whose PV is not a finite number, whose ``step`` raises, that does not move at all
for any step, or whose ``reset`` does not put it back as it was, is refused. Pure computation
over the model (numpy), no I/O.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import brentq, least_squares
from scipy.special import gammainc

from services.plant_sim.load_bound import models_own
from services.plant_sim.simulation.loop import ModelFailure, SimLoop, model_pv
from shared.control.rest_window import RESOLUTION, rest_allowance, rest_window
from shared.control.transfer import model_transfer, model_ultimate_point

SMALL_STEP = 2.0  # % of output
LARGE_STEP = 10.0  # % of output
MIN_STEP = 0.05  # % of output: less room than this at op0 and that direction is not stepped
FIRST_WINDOW = 64  # samples: the first look at a response, doubled until it is judged
MAX_SAMPLES = 2**17  # samples per step response at most
REST_SAMPLES = 256  # samples held at op0 to see the model is at rest
SETTLED = 5e-4  # a response moving less than this fraction of its size in its last quarter
RAMPING = 1e-3  # slopes of the last two quarters agreeing to this fraction: a ramp
RUNAWAY = 100.0  # spans of the PV range (or of the rest PV): a response past it runs away
HELD = "the run held at op0"
MIN_SAMPLES_PER_PERIOD = 20  # fewer per ultimate period and sampling shapes the loop
FINE_SAMPLES_PER_PERIOD = 40  # read a step-response point again at this many (refine_step_point)
LINEAR = 0.01  # gains spread no more than this: linear
DYNAMIC_SPREAD = 0.3  # the steps' K/T63 spread beyond this (and twice the gains'): said
UNRESOLVED = 0.05  # within this of its end value at the first sample: settled within a sample


@dataclass
class StepResponse:
    """One open-loop step from rest at op0: ``size`` (%, signed), PV at t = k·T."""

    size: float
    pv: np.ndarray
    behaviour: str  # self-regulating, integrating, unstable, out of range, not settled, no response
    gain: float | None = None  # PV units per % (integrating: PV units/s per %)
    growth: float | None = None  # unstable: 1/s

    @property
    def label(self) -> str:
        return f"{self.size:+g} %"


@dataclass
class ModelReport:
    """What ``check_model`` found for one loop; ``refused`` says why a model cannot be tuned."""

    loop: str
    model: str
    sample_time: float
    op0: float
    pv0: float | None
    pv_units: str
    pv_range: tuple[float, float]
    behaviour: str = "unknown"
    gains: dict[str, float] = field(default_factory=dict)
    gain: float | None = None
    nonlinearity: float | None = None
    unmoved: list[str] = field(default_factory=list)  # steps that moved nothing (a deadband)
    linear_step: float | None = None  # %: the size of the steps the linear figures come from
    dead_time: float | None = None
    onset_order: float | None = None
    t63: float | None = None
    lag_sum: float | None = None
    apparent_dead_time: float | None = None
    apparent_lag: float | None = None
    doubling_time: float | None = None
    ku_exact: float | None = None
    pu_exact: float | None = None
    ku_step: float | None = None
    pu_step: float | None = None
    # s: the sample time the step-response point was read at (the loop's, or a finer one
    # where the loop's is too coarse to resolve it: ``refine_step_point``)
    step_sample_time: float | None = None
    samples_per_period: float | None = None
    rest_drift: float | None = None  # PV units/s with the output held at op0
    horizon: float | None = None  # s, the longest response run
    warnings: list[str] = field(default_factory=list)
    refused: str | None = None
    responses: list[StepResponse] = field(default_factory=list)

    @property
    def ku(self) -> float | None:
        return self.ku_exact if self.ku_exact is not None else self.ku_step

    @property
    def pu(self) -> float | None:
        return self.pu_exact if self.pu_exact is not None else self.pu_step

    def to_dict(self) -> dict[str, Any]:
        """Everything but the raw responses, JSON-ready (non-finite numbers as None)."""

        def clean(v: Any) -> Any:
            if isinstance(v, float) and not math.isfinite(v):
                return None
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, list | tuple):
                return [clean(x) for x in v]
            return v

        out = {k: v for k, v in vars(self).items() if k != "responses"}
        out["status"] = "refused" if self.refused else "ok"
        out["ku"], out["pu"] = self.ku, self.pu
        out["steps"] = [
            {"size": r.size, "behaviour": r.behaviour, "gain": r.gain, "samples": len(r.pv) - 1}
            for r in self.responses
        ]
        return clean(out)


class Refused(Exception):
    """The model cannot be checked (and so must not be tuned): non-finite PV, a step that
    raises, a model that ignores its input."""


# the calls into the model the check still expects to make → why it cannot afford them, or
# None (the shell's bound on the time a user's model may take: ``load_bound.call_bound``)
Pace = Callable[[int], str | None]


def check_loop(loop_id: str, loop: SimLoop, pace: Pace | None = None) -> ModelReport:
    """Check a built loop's process model (noise, PID block and transmitter range aside)."""
    s = loop.settings
    report = check_model(
        loop.process,
        loop_id=loop_id,
        model=s.model_name,
        sample_time=s.sample_time,
        op_limits=s.op_limits,
        pv_range=s.pv_range,
        pv_units=s.pv_units,
        pace=pace,
    )
    _own_sample_time(report, loop.process)
    if loop.pid.mode == "manual" or loop.pid.gains.ti is None:  # else its PID holds it
        _tune_rest(report, rest_window(s.sample_time, loop.pid.gains.ti), s.noise_std)
    # a reverse-acting PID is for a process whose PV rises with the output, a direct one for
    # one whose PV falls: the other way round, the loop runs away in auto, and a relay or a
    # ramp pushes the PV away from where it would switch
    wants = "direct" if report.gain is not None and report.gain < 0 else "reverse"
    if report.gain is not None and report.gain != 0 and s.action != wants:
        moves = "falls" if wants == "direct" else "rises"
        report.warnings.append(
            f"the process gain is {report.gain:.4g} (its PV {moves} as the output rises) but "
            f"the loop's PID is {s.action}-acting: in auto it would run away, and a relay or "
            f'ramp test pushes the PV the wrong way (action = "{wants}")'
        )
    return report


def _own_sample_time(report: ModelReport, process: Any) -> None:
    """A warning where the model's own ``sample_time`` is not the loop's: the loop steps it
    once per the plant file's sample time, and a class that advances by its own (0.5 s where
    the file said 0.1 s) runs that many times too fast, every time figure off by as much; it
    was checked "ok" without a word (user trial)."""
    try:
        own = getattr(process, "sample_time", None)
    except BaseException as err:  # a user's property: read at load, but read again here
        if not models_own(err):
            raise
        return
    file = report.sample_time
    if isinstance(own, numbers.Real) and not isinstance(own, bool):
        if math.isfinite(own) and abs(own - file) <= 1e-9 * file:
            return
        told = f"{float(own):g} s"
    else:
        told = f"{own!r}, not a number"
    report.warnings.append(
        f"the model's own sample_time is {told}, the plant file's {file:g} s: the loop steps "
        f"it once every {file:g} s of sim time, so a model that advances by its own sample "
        "time each step runs at the wrong speed and every time figure here is off; build the "
        "class to keep the sample_time it is given"
    )


def _tune_rest(report: ModelReport, window: float, noise_std: float) -> None:
    """A warning where the model drifts at op0 by more than the tuner takes as rest over its
    window (``shared.control.rest_window``): every tune would end before its test, "the PV
    did not come to rest", while the check gave the drift as corrected for (0.002 %/s on a
    noise-free loop: helper trial). Only for a loop held in manual (or without integral
    action): in auto its PID takes the drift out, and the tuner looks for rest as it is."""
    drift = report.rest_drift
    if drift is None or report.refused:
        return
    span = report.pv_range[1] - report.pv_range[0]
    moved, allowed = abs(drift) * window, rest_allowance(noise_std, span)
    if moved <= allowed:
        return
    units = report.pv_units or "PV units"
    report.warnings.append(
        f"a tune will not start: held at op0 the PV moves {moved:.3g} {units} over the "
        f"{window:g} s the tuner watches for rest, beyond the {allowed:.3g} it takes as rest "
        f"(3σ of the loop's noise, and at least {RESOLUTION:g} of the span); give the model "
        "a balance at op0"
    )


def check_model(
    process: Any,
    *,
    loop_id: str = "",
    model: str = "",
    sample_time: float,
    op_limits: tuple[float, float] = (0.0, 100.0),
    pv_range: tuple[float, float] = (0.0, 100.0),
    pv_units: str = "",
    max_samples: int = MAX_SAMPLES,
    pace: Pace | None = None,
) -> ModelReport:
    """Step ``process`` open loop from rest at its ``op0`` and report what it does; ``pace``,
    before each run, with the calls of the model the check expects to make from there:
    refused with its reason if it gives one (a model whose step() took 50 ms was stepped
    2816 times in 143 s, silent, for a 5 s lag at 0.1 s samples: helper trial)."""
    op0 = float(process.op0)
    report = ModelReport(loop_id, model, sample_time, op0, None, pv_units, pv_range)
    try:
        _check(process, report, op_limits, max_samples, pace)
    except Refused as err:
        report.refused = str(err)
    return report


# --- running the model -------------------------------------------------------------------


def _run(
    process: Any, op: float, label: str, t_step: float, n: int, y: list[float] | None, scale: float
) -> list[float]:
    """Extend the response ``y`` (PV at t = k·T from rest, y[0] at reset) to n + 1 samples
    with the output at ``op``; Refused naming the step if the model fails."""
    if y is None:
        y = [_pv(process, "reset()", process.reset, label, 0.0)]
    y0 = y[0]
    while len(y) <= n:
        t = len(y) * t_step
        value = _pv(process, "step()", process.step, label, t, op)
        y.append(value)
        if abs(value - y0) > RUNAWAY * scale:
            break
    return y


def _paced(pace: Pace | None, calls: int) -> None:
    """Refused where ``pace`` says the check cannot afford ``calls`` more calls of the model."""
    why = pace(calls) if pace is not None else None
    if why is not None:
        raise Refused(why)


def _pv(process: Any, what: str, fn: Callable[..., Any], label: str, t: float, *args: Any) -> float:
    try:
        return model_pv(what, fn, *args)
    except ModelFailure as err:
        raise Refused(f"{err.reason} (at t = {t:g} s of {label})") from None


def _classify(d: np.ndarray, dt: float, final: bool) -> tuple[str, float | None, float | None]:
    """(behaviour, end value or slope, growth rate) of a response d (PV change) at t = k·dt;
    'pending' when more samples are needed to tell."""
    n = len(d) - 1
    size = float(np.max(np.abs(d)))
    if size == 0.0 or n < 8:
        return ("no response" if final else "pending"), None, None
    q = n // 4
    last = d[n - q :]
    if float(np.ptp(last)) <= SETTLED * size:
        return "self-regulating", float(d[n]), None
    s2 = (d[n - 2 * q] - d[n - 3 * q]) / (q * dt)
    s3 = (d[n - q] - d[n - 2 * q]) / (q * dt)
    s4 = (d[n] - d[n - q]) / (q * dt)
    mid = d[n - q // 2] - 0.5 * (d[n] + d[n - q])  # the last quarter's bow from a straight line
    if s4 != 0 and abs(s4 - s3) <= RAMPING * abs(s4) and abs(mid) <= RAMPING * abs(s4 * q * dt):
        return "integrating", float(s4), None
    growing = s2 != 0 and s3 / s2 > 1.0 + RAMPING and s4 / s3 > 1.0 + RAMPING
    rate = math.log(s4 / s3) / (q * dt) if growing and _exponential(s3 / s2, s4 / s3) else None
    if final:
        return ("unstable" if growing else "not settled"), None, rate
    return "pending", None, rate


def _respond(
    process: Any,
    op0: float,
    size: float,
    dt: float,
    scale: float,
    max_samples: int,
    ahead: Callable[[int, int], None] | None = None,
) -> StepResponse:
    """Step to op0 + size and run until the response is judged (or max_samples);
    ``ahead(n, have)`` before each window of n samples, ``have`` of them in hand."""
    label = f"the {size:+g} % step"
    y: list[float] | None = None
    n = FIRST_WINDOW
    rates: list[float] = []
    while True:
        if ahead is not None:
            ahead(n, len(y) if y is not None else 0)
        y = _run(process, op0 + size, label, dt, n, y, scale)
        d = np.asarray(y) - y[0]
        ran_away = len(y) <= n
        final = ran_away or n >= max_samples
        kind, value, rate = _classify(d, dt, final)
        if ran_away:
            if not _accelerating(d):  # a stable response, of a gain out of all proportion
                return StepResponse(size, np.asarray(y), "out of range")
            growth = _growth(d, dt)
            return StepResponse(size, np.asarray(y), "unstable", None, growth or rate)
        if rate is not None:
            rates.append(rate)
            if len(rates) >= 4 and _consistent(rates[-4:]) and rate * n * dt > 6.0:
                return StepResponse(size, np.asarray(y), "unstable", None, rate)
        else:
            rates.clear()
        if kind != "pending":
            gain = value / size if value is not None else None
            return StepResponse(size, np.asarray(y), kind, gain, rate)
        n *= 2


def _ahead(pace: Pace | None, report: ModelReport, later: int) -> Callable[[int, int], None]:
    """``_respond``'s look ahead: a window of n samples (``have`` in hand: a reset and n steps
    in all), then ``later`` runs (the steps still to come and the first run again) taken to
    be as long as this one, or as the longest so far."""
    done = max((len(r.pv) - 1 for r in report.responses), default=0)

    def ahead(n: int, have: int) -> None:
        _paced(pace, n + 1 - have + later * (max(n, done) + 1))

    return ahead


def _consistent(rates: list[float]) -> bool:
    return min(rates) > 0 and max(rates) <= 1.2 * min(rates)


def _exponential(first: float, second: float) -> bool:
    """Two successive growth ratios (each > 1) of one response tell an exponential runaway
    (they agree: a doubling time means something) from a power law's (a double integrator's
    t², whose ratios fall towards 1 as it runs: no doubling time)."""
    a, b = math.log(first), math.log(second)
    return abs(a - b) <= 0.1 * max(a, b)  # a power law's differ by 22 % or more


def _accelerating(d: np.ndarray) -> bool:
    """The response (PV change) moved faster and faster up to where it ran away: the last
    three moves it made grow. A stable lag with a gain out of all proportion to the range
    leaves it too, but slowing down — or in fewer moves than tell either."""
    steps = np.abs(np.diff(d[np.nonzero(d)[0][0] - 1 :])) if np.any(d) else np.array([])
    return steps.size >= 3 and steps[-1] > steps[-2] > steps[-3]


def _growth(d: np.ndarray, dt: float) -> float | None:
    """Exponential growth rate (1/s) of a response that ran away, from its last samples; None
    unless the two halves of that stretch grew at one rate (see ``_exponential``)."""
    a = np.abs(d[len(d) // 2 :])
    a = a[a > 0]
    if len(a) < 7:
        return None
    k = len(a) // 3  # three stretches: the growth over the last two compared
    if not (a[-1] > a[-1 - k] > a[-1 - 2 * k]) or not _exponential(
        a[-1 - k] / a[-1 - 2 * k], a[-1] / a[-1 - k]
    ):
        return None
    return math.log(a[-1] / a[-1 - k]) / (k * dt)


def _blows_up(rest: list[float], dt: float, span: float, scale: float) -> None:
    """Refused where, held at op0 with no step at all, the PV leaves ``RUNAWAY`` times its
    range without accelerating (an unstable model not balanced at op0 accelerates, and is
    judged by its steps): a model returning 1e300 × its PV (50 at reset, then 5e301) was told
    "it ignores its input: the PV did not move in 0.1 s", its steps lost against a drift of
    5e301 (user trial)."""
    d = np.asarray(rest) - rest[0]
    far = np.nonzero(np.abs(d) > RUNAWAY * scale)[0]
    if len(far) == 0 or _accelerating(d[: far[0] + 1]):
        return
    k = int(far[0])
    raise Refused(
        f"its PV blows up: held at op0, with no step at all, it went from {rest[0]:.6g} at "
        f"reset to {rest[k]:.6g} by t = {k * dt:g} s, past {RUNAWAY:g} times its range "
        f"({span:g}): a PV out of any range a transmitter reads"
    )


# --- the analysis --------------------------------------------------------------------------


def _check(
    process: Any,
    report: ModelReport,
    op_limits: tuple[float, float],
    max_n: int,
    pace: Pace | None = None,
) -> None:
    dt = report.sample_time
    op0 = report.op0
    lo, hi = op_limits
    span = report.pv_range[1] - report.pv_range[0]
    up, down = hi - op0, op0 - lo
    sizes = _sizes(up, down)
    # the run at rest, then each step and the first again (its reset checked), a window each
    _paced(pace, REST_SAMPLES + 1 + (len(sizes) + 1) * (FIRST_WINDOW + 1))
    # at rest?
    rest = _run(process, op0, HELD, dt, REST_SAMPLES, None, math.inf)
    report.pv0 = rest[0]
    scale = max(span, abs(rest[0]), 1.0)
    _blows_up(rest, dt, span, scale)
    report.rest_drift = (rest[-1] - rest[0]) / (REST_SAMPLES * dt)
    if not sizes:
        raise Refused(f"op0 = {op0:g} % leaves no room to step within the output limits {[lo, hi]}")
    for i, size in enumerate(sizes):
        ahead = _ahead(pace, report, len(sizes) - i)
        report.responses.append(_respond(process, op0, size, dt, scale, max_n, ahead))
    responses = report.responses
    report.horizon = max(len(r.pv) - 1 for r in responses) * dt
    drifts = abs(rest[-1] - rest[0]) > 1e-12 * scale
    longest = max(len(r.pv) for r in responses)
    _paced(pace, len(responses[0].pv) + (longest if drifts else 0))
    _check_reset(process, report, scale)
    if drifts:
        _paced(pace, longest)
        _correct_drift(process, report)
    if all(r.behaviour == "no response" for r in responses):
        raise Refused(
            f"it ignores its input: the PV did not move in {report.horizon:g} s after steps of "
            f"{', '.join(r.label for r in responses)}"
        )
    kinds = {r.behaviour for r in responses} - {"no response"}
    silent = report.unmoved = [r.label for r in responses if r.behaviour == "no response"]
    if silent:
        # some steps moved it and some did not: a deadband, backlash or stiction at op0, no
        # linear process (a valve with 4 % of backlash was called "linear … ok", its ±2 %
        # steps dropped unsaid; a relay of ±5 % on 12 % then never switched: helper trial F)
        report.warnings.append(
            f"no response to the steps of {', '.join(silent)} while larger ones moved it: a "
            "deadband, backlash or stiction at op0 (not linear: a relay or step smaller than "
            "it moves nothing, and the loop's PID limit-cycles through it)"
        )
        report.nonlinearity = math.inf
    for r in responses:
        if r.gain is not None:
            report.gains[r.label] = r.gain
    for kind in ("out of range", "unstable", "not settled", "integrating", "self-regulating"):
        if kind in kinds:
            report.behaviour = kind
            break
    if len(kinds) > 1:
        report.warnings.append(
            "the steps disagree on its behaviour: "
            + ", ".join(f"{r.label} {r.behaviour}" for r in responses)
        )
    if report.behaviour == "out of range":
        far = next(r for r in responses if r.behaviour == "out of range")
        moved = float(far.pv[-1] - far.pv[0])
        report.warnings.append(
            f"out of range: the {far.label} step moved the PV by {moved:.3g} in "
            f"{(len(far.pv) - 1) * dt:g} s, past {RUNAWAY:g} times its range, and not "
            "accelerating: a gain out of all proportion to the PV range (its units?), not "
            "an instability; a relay or step test would only drive it to a limit"
        )
    elif report.behaviour == "unstable":
        rates = [r.growth for r in responses if r.growth]
        if rates:
            report.doubling_time = math.log(2.0) / max(rates)
        report.warnings.append(
            "unstable: the PV runs away open loop"
            + (
                f" (doubling every {report.doubling_time:.3g} s)"
                if report.doubling_time
                else " (accelerating, but not exponentially: no doubling time)"
            )
            + "; a relay or step test would drive it to a limit"
        )
    elif report.behaviour == "not settled":
        report.warnings.append(
            f"not settled after {report.horizon:g} s: oscillating, or slower than the check runs"
        )
    gains = list(report.gains.values())
    if not silent and len(gains) >= 2 and all(g != 0 for g in gains):
        mags = [abs(g) for g in gains]
        report.nonlinearity = max(mags) / min(mags) - 1.0
        if any(g * gains[0] < 0 for g in gains):
            report.nonlinearity = math.inf
        if report.nonlinearity > LINEAR:
            report.warnings.append(
                f"nonlinear: the gain varies by {_pct(report.nonlinearity)} between the steps "
                "(the ultimate point is that of its linear part at op0)"
            )
    _dynamic_spread(report)
    lo, hi = report.pv_range
    if report.pv0 is not None and not lo <= report.pv0 <= hi:
        report.warnings.append(
            f"the process rests at PV {report.pv0:.6g}, out of pv_range {list(report.pv_range)}: "
            "its transmitter reads the limit, and no test can see it move until it comes back"
        )
    for r in responses:
        if r.behaviour in ("self-regulating", "integrating"):
            peak = r.pv[int(np.argmax(np.abs(r.pv - r.pv[0])))]
            if not report.pv_range[0] <= peak <= report.pv_range[1]:
                report.warnings.append(
                    f"the {r.label} step takes the PV to {peak:.6g}, out of pv_range "
                    f"{list(report.pv_range)}: the transmitter would clip it"
                )
                break
    _shape(report)
    _inverse_response(report)
    exact = model_ultimate_point(process) if _has_transfer(process) else None
    if exact is not None:
        report.ku_exact, report.pu_exact = exact
    tf = model_transfer(process) if _has_transfer(process) else None
    if tf is not None:  # what its transfer function says that its steps may not
        poles = np.roots(np.trim_zeros(np.asarray(tf.den, dtype=float), "f"))
        if exact is not None:
            _resonance(report, poles)
        _short_horizon(report, poles)
    if report.pu is not None:
        report.samples_per_period = report.pu / dt
        if report.samples_per_period < MIN_SAMPLES_PER_PERIOD:
            report.warnings.append(_coarse(report))


COARSE = "sample time "  # how the warning of too few samples per period starts


def _coarse(report: ModelReport) -> str:
    """The warning of a loop sampled too coarsely for its ultimate period."""
    return (
        f"{COARSE}{report.sample_time:g} s is {report.samples_per_period:.3g} samples per "
        f"ultimate period (P_u {report.pu:.4g} s): below {MIN_SAMPLES_PER_PERIOD}, sampling "
        "shapes the loop; sample faster"
    )


def _blurred(report: ModelReport, fine: float, why: str) -> str:
    """The warning of a step-response ultimate point left as read at the loop's own samples."""
    return (
        f"the step response's K_u and P_u are read at the loop's own {report.sample_time:g} s "
        f"samples ({report.samples_per_period:.3g} a period), which blur them (G is exact "
        f"there only far below Nyquist); they could not be read again at {fine:.4g} s: {why}"
    )


def _dynamic_spread(report: ModelReport) -> None:
    """A warning where the steps' K/T63 (their gain over the time to 63 % of their change:
    what sets K_u of a lag-dominant loop, whose gain near ω_u is about K/(T·ω)) spread far
    more than their static gains: a conical tank's gain varied 22 % over ±10 %, its K_u 3.7
    times, and a PI tuned at op0 was unstable 15 % below it (helper trial F)."""
    dt, rates = report.sample_time, {}
    for r in report.responses:
        if r.behaviour != "self-regulating" or not r.gain:
            continue
        d = np.abs(r.pv - r.pv[0])
        end = float(d[-1])
        reached = np.nonzero(d >= 0.632 * end)[0]
        if end <= 0 or reached.size == 0 or reached[0] == 0:
            continue
        t63 = float(reached[0]) * dt
        rates[r.label] = abs(r.gain) / t63
    if len(rates) < 2:
        return
    spread = max(rates.values()) / min(rates.values()) - 1.0
    if spread > DYNAMIC_SPREAD and spread > 2.0 * (report.nonlinearity or 0.0):
        told = ", ".join(f"{k}: {v:.3g}" for k, v in rates.items())
        report.warnings.append(
            f"the dynamics vary more than the gain: K/T63 (what sets K_u of a lag-dominant "
            f"loop) varies by {_pct(spread)} between the steps ({told} per s): gains tuned "
            "at op0 have less margin on one side of it; tune where the loop runs, or for the "
            "least margin"
        )


def _has_transfer(process: Any) -> bool:
    """The model states a transfer function (``num``, ``den``); a user's class whose attribute
    look-up raises (its own ``__getattr__``) states none."""
    try:
        num, den = getattr(process, "num", None), getattr(process, "den", None)
    except BaseException as err:
        if not models_own(err):
            raise
        return False
    return num is not None and den is not None


def _pct(x: float) -> str:
    return "sign" if not math.isfinite(x) else f"{100 * x:.3g} %"


def _sizes(up: float, down: float) -> list[float]:
    """The signed steps: small and large, up and down, as far as the limits allow."""
    out: list[float] = []
    for step in (SMALL_STEP, LARGE_STEP):
        both = min(step, up, down)
        for sign, room in ((1.0, up), (-1.0, down)):
            size = both if both >= MIN_STEP else min(step, room)
            if size >= MIN_STEP and sign * size not in out:
                out.append(sign * size)
    return out


# the other cause of a model that does not repeat itself from a reset, and its remedy (a
# user's FOPDT adding its own N(0, 0.002) was told only that its reset kept its state: review)
_OWN_RANDOMNESS = (
    "; or the model draws random numbers of its own: a model must repeat itself from a reset "
    "(the check and a run's replay step it once more), its measurement noise left to the "
    "plant file's noise_std, drawn from the plant's seed"
)


def _check_reset(process: Any, report: ModelReport, scale: float) -> None:
    """Refused where ``reset()`` does not put the model back as it was: every run starts
    from a reset, so the PV it returns must be the same each time, and the first step run
    again after the others must give the same response. A reset that kept its state was read
    as a gain of 3 and "NONLINEAR, spread 100 %" where it was 2 (user trial)."""
    dt, pv0 = report.sample_time, report.pv0
    for r in report.responses:
        if abs(r.pv[0] - pv0) > 1e-9 * scale:
            raise Refused(
                f"reset() does not reset the model: before the {r.label} step it returned PV "
                f"{r.pv[0]:.6g}, where the first reset returned {pv0:.6g}; it must leave the "
                "process at rest at op0 whatever ran before (every run of the check starts "
                f"from a reset){_OWN_RANDOMNESS}"
            )
    first = report.responses[0]
    label = f"the {first.label} step run again"
    again = np.asarray(
        _run(process, report.op0 + first.size, label, dt, len(first.pv) - 1, None, scale)
    )
    n = min(len(again), len(first.pv))
    size = float(np.max(np.abs(first.pv[:n] - first.pv[0])))
    diff = np.abs(again[:n] - first.pv[:n])
    worst = int(np.argmax(diff))
    if len(again) != len(first.pv) or diff[worst] > 1e-6 * size + 1e-12 * scale:
        raise Refused(
            f"reset() does not reset the model: the {first.label} step run again after a reset "
            f"differs from its first run by {diff[worst]:.3g} at t = {worst * dt:g} s (of a "
            f"change of {size:.3g}); it must leave the process at rest at op0 whatever ran "
            f"before (every run of the check starts from a reset){_OWN_RANDOMNESS}"
        )


def _correct_drift(process: Any, report: ModelReport) -> None:
    """The PV moves with the output held at op0: subtract that run, as long as the longest
    step's, from every step (exact for a linear model, whatever the drift's shape), judge the
    steps again, and say so."""
    dt = report.sample_time
    longest = max(len(r.pv) for r in report.responses) - 1
    base = np.asarray(_run(process, report.op0, HELD, dt, longest, None, math.inf))
    for r in report.responses:
        n = len(r.pv)
        r.pv = r.pv - (base[:n] - base[0])
        if r.behaviour != "unstable":
            kind, value, _ = _classify(r.pv - r.pv[0], dt, final=True)
            r.behaviour, r.gain = kind, (value / r.size if value is not None else None)
    drift = report.rest_drift or 0.0
    report.warnings.append(
        f"not at rest at op0 = {report.op0:g} %: the PV drifts {drift:.3g} "
        f"{report.pv_units or 'PV units'}/s with the output held (the step figures are corrected "
        "for it: each step minus the run held at op0); an FMU may need settle = SECONDS, or op0 "
        "at its balance point"
    )


def _linear_response(report: ModelReport) -> tuple[np.ndarray, float] | None:
    """(response per % of the small steps, central difference where both exist; step size)."""
    small = [r for r in report.responses if r.behaviour == report.behaviour]
    if not small:
        return None
    size = min(abs(r.size) for r in small)
    pair = [r for r in small if abs(r.size) == size]
    n = min(len(r.pv) for r in pair)
    if len(pair) == 2:
        upr, dnr = sorted(pair, key=lambda r: -r.size)
        s = ((upr.pv[:n] - upr.pv[0]) - (dnr.pv[:n] - dnr.pv[0])) / (2 * size)
    else:
        r = pair[0]
        s = (r.pv[:n] - r.pv[0]) / r.size
    return s, size


def _shape(report: ModelReport) -> None:
    """Gain, dead time, time constants and the ultimate point from the linear response."""
    got = _linear_response(report)
    if got is None or report.behaviour not in ("self-regulating", "integrating"):
        return
    s, report.linear_step = got
    dt = report.sample_time
    t = np.arange(len(s)) * dt
    integrating = report.behaviour == "integrating"
    n = len(s) - 1
    q = n // 4
    # the end value (PV units per %), or the final slope (PV units/s per %)
    k_gain = (s[n] - s[n - q]) / (q * dt) if integrating else float(s[n])
    report.gain = k_gain
    if k_gain == 0:
        return
    report.dead_time, report.onset_order = _dead_time(s, dt, None if integrating else k_gain)
    if integrating:
        report.apparent_dead_time = float(t[n] - s[n] / k_gain)  # the asymptote's intercept
    else:
        _time_constants(report, s, t, k_gain)
        moved = np.nonzero(np.abs(s) > 1e-9 * float(np.max(np.abs(s))))[0]
        first = int(moved[0]) if len(moved) else 1
        if n >= 1 and abs(s[1] - k_gain) <= UNRESOLVED * abs(k_gain):
            # settled by the first sample after the step: its lags are below the sample
            # time, and the figures above are the sampling's, not the process's (τ 0.1 s at
            # 5 s samples was given T63 3.16 s and "ok": helper trial F)
            report.warnings.append(
                f"settles within one sample ({dt:g} s): its time constants are shorter than the "
                "sample time and not resolved (the T63 and lags above are the sampling's); at "
                "this sample time the loop is a static gain, which integral action alone "
                "controls: sample faster to see its dynamics"
            )
        elif first <= n and s[first] / k_gain >= 1.0 - math.exp(-1.0):
            # 63 % of the change by the first sample that moved: the dead time read off
            # that sample's onset and the lags after it are the sampling's (the heat
            # exchanger at 100 s samples: dead time 95.3 s, T63 −1.50 s, and "ok")
            report.warnings.append(
                f"reaches 63 % of its change by the first sample that moves ({dt:g} s): its "
                "dead time and time constants are not resolved at this sample time (the "
                "figures above are the sampling's); sample faster to see its dynamics"
            )
    for name in ("t63", "lag_sum"):  # a time constant below zero is no time constant
        value = getattr(report, name)
        if value is not None and value < 0:
            setattr(report, name, None)
    report.ku_step, report.pu_step = _ultimate_from_step(s, dt, integrating) or (None, None)
    if report.ku_step is not None:
        report.step_sample_time = dt


def _inverse_response(report: ModelReport) -> None:
    """A warning where the small steps' response first goes the other way from its change by
    more than 2 % of it: a right-half-plane zero, which the tuner's models have no term for
    ((1 − 10s)/(5s + 1)³ dips 31.8 %, and the check said "nothing stands in the way")."""
    got = _linear_response(report)
    if got is None or report.behaviour != "self-regulating" or not report.gain:
        return
    frac = got[0] / report.gain  # the response as a fraction of its change
    dip = float(-np.min(frac))
    if dip > 0.02:
        report.warnings.append(
            f"inverse response: after a step the PV first goes {100 * dip:.3g} % of its change "
            "the other way (a right-half-plane zero): the tuner's FOPDT/SOPDT models have no "
            "term for it, so the robustness they predict is optimistic; it offers PIDs but "
            "does not recommend them once its test sees the dip"
        )


def _short_horizon(report: ModelReport, poles: np.ndarray) -> None:
    """A warning where the steps were read as a ramp but the transfer function has no pole
    at 0: the first moments of a lag's response, sampled finely, look like one (a 10 s lag at
    1e-4 s samples was called integrating after 6.4 ms, and "nothing stands in the way":
    helper review)."""
    if report.behaviour != "integrating" or np.any(poles == 0):  # an integrator: s divides den
        return
    slowest = max((1.0 / -p.real for p in poles if p.real < 0), default=None)
    samples = round((report.horizon or 0.0) / report.sample_time)
    report.warnings.append(
        f"read as integrating from steps of {report.horizon:g} s ({samples} samples at "
        f"{report.sample_time:g} s), but its transfer function has no integrator"
        + (f" and a slowest time constant of {slowest:.4g} s" if slowest else "")
        + ": a lag's first moments look like a ramp, and the step figures here are not its "
        "own; check it at a coarser sample_time"
    )


RESONANT_ZETA = 0.2  # a pair of poles damped less than this is a resonance worth a word
ABOVE_BANDWIDTH = 2.0  # times ω_u: where the tuner's slow models have nothing


def _resonance(report: ModelReport, poles: np.ndarray) -> None:
    """A warning where the transfer function has a lightly damped pair of poles well above
    the ultimate frequency: the tuner's FOPDT/SOPDT models, fitted to the loop's slow
    response, have nothing there, and a derivative's gain can take the mode's damping away
    (100·e^{−s}/(5s³ + 2s² + 501s + 100), ζ 0.01 at 10 rad/s: "nothing stands in the way",
    then AMIGO PID at a gain margin of 1.05 on it)."""
    if report.pu is None or report.pu <= 0:
        return
    w_u = 2 * math.pi / report.pu
    for p in sorted((p for p in poles if p.imag > 0), key=abs):
        w_n = float(abs(p))
        zeta = float(-p.real / w_n)
        if zeta < RESONANT_ZETA and w_n > ABOVE_BANDWIDTH * w_u:
            report.warnings.append(
                f"a lightly damped mode at {w_n:.4g} rad/s (ζ {zeta:.2g}, period "
                f"{2 * math.pi / w_n:.3g} s), {w_n / w_u:.3g} times the ultimate frequency: "
                "the tuner's models have nothing there and its predicted margins leave it "
                "out; a derivative's gain there can take its damping away (the verification "
                "rejects gains under which it rings); PI, or a filter for the mode, is safer"
            )
            return


def _dead_time(
    s: np.ndarray, dt: float, k_gain: float | None = None
) -> tuple[float | None, float | None]:
    """(L, r): where the PV first moves, and how (like (t − L)^r), from the first three samples
    that moved. With the end value ``k_gain`` (a self-regulating response), the onset is
    the gamma distribution's P(r, (t − L)/τ) through them (``_gamma_onset``): exact for a
    first-order lag (r = 1) and for a chain of equal lags (r their number), and nearer than a
    power law for unequal ones. Without it, or where no such curve goes through the three,
    the power law c·(t − L)^r, the gamma curve's limit for lags long against the samples. A
    power law bends over a first-order onset's curvature by moving L late: e^{−10s}/(35s + 1)
    at 1 s samples read 10.046 s, e^{−10s}/(5s + 1) 10.287 s and e^{−10s}/(s + 1) 10.859 s;
    the gamma curve reads 10 s for all three."""
    size = float(np.max(np.abs(s)))
    moved = np.nonzero(np.abs(s) > 1e-9 * size)[0]
    if len(moved) == 0:
        return None, None
    k = int(moved[0])
    if k + 2 >= len(s):
        return (k - 1) * dt, None
    d1, d2, d3 = (abs(s[k + i]) for i in range(3))
    t1, t2, t3 = k * dt, (k + 1) * dt, (k + 2) * dt
    if not (0 < d1 < d2 < d3) or np.sign(s[k]) != np.sign(s[k + 2]):
        return (k - 1) * dt, None
    ratio = math.log(d3 / d2) / math.log(d2 / d1)

    def g(lag: float) -> float:
        return math.log((t3 - lag) / (t2 - lag)) / math.log((t2 - lag) / (t1 - lag)) - ratio

    a, b = t1 - dt, t1 - 1e-9 * dt
    if g(a) <= 0:  # started at once on the sample before: no dead time within it
        lag = a
    elif g(b) >= 0:
        lag = b
    else:
        lag = brentq(g, a, b, xtol=1e-12 * max(dt, 1.0))
    order = math.log(d2 / d1) / math.log((t2 - lag) / (t1 - lag))
    if k_gain:
        frac = np.array([s[k], s[k + 1], s[k + 2]]) / k_gain
        onset = _gamma_onset(frac, np.array([t1, t2, t3]), dt, lag, order)
        if onset is not None:
            lag, order = onset
    return max(lag, 0.0), order


def _gamma_onset(
    frac: np.ndarray, t: np.ndarray, dt: float, lag: float, order: float
) -> tuple[float, float] | None:
    """(L, r) of the gamma distribution's P(r, (t − L)/τ) through the fractions ``frac`` of
    the end value at the three times ``t`` (s; the first samples that moved), L within the
    sample before the first; searched from the power law's ``lag`` and ``order`` and from τ
    long to τ a sample; None where no such curve goes through all three (to 1e-9 of each
    fraction's logarithm: a response past its end value, an inverse response, a process that
    is no chain of lags at its start)."""
    if not np.all((frac > 0) & (frac < 1)):
        return None
    # L may not lie before the sample before the first that moved (it did not move), but the
    # search may: a dead time of whole samples puts L on that bound, and the end value read
    # off a record that has settled to within its last few parts in 1e5 moves the curve
    # through the three by as much (e^{−10s}/(5s + 1) at 1 s samples: 9.99991 s)
    lo = np.array([t[0] - 1.5 * dt, math.log(1e-3), math.log(1e-3 * dt)])
    hi = np.array([t[0] - 1e-9 * dt, math.log(50.0), math.log(1e9 * dt)])
    target = np.log(frac)

    def residual(p: np.ndarray) -> np.ndarray:
        x = np.maximum((t - p[0]) / math.exp(p[2]), 1e-300)
        return np.log(np.maximum(gammainc(math.exp(p[1]), x), 1e-300)) - target

    start_lag = min(max(lag, lo[0]), hi[0])
    start_order = math.log(min(max(order, 1.01e-3), 49.0))
    best = None
    for tau in (1e3 * dt, 30.0 * dt, 3.0 * dt, dt):
        try:
            got = least_squares(
                residual,
                [start_lag, start_order, math.log(tau)],
                bounds=(lo, hi),
                xtol=1e-15,
                ftol=1e-15,
                gtol=1e-15,
            )
        except (ValueError, FloatingPointError, OverflowError):  # no finite curve from there
            continue
        if best is None or got.cost < best.cost:
            best = got
    if best is None or float(np.max(np.abs(best.fun))) > 1e-9:
        return None
    return max(float(best.x[0]), float(t[0] - dt)), math.exp(float(best.x[1]))


def _time_constants(report: ModelReport, s: np.ndarray, t: np.ndarray, k_gain: float) -> None:
    """T63, the sum of lags and the tangent's apparent dead time and lag."""
    dt = report.sample_time
    lag = report.dead_time or 0.0
    frac = s / k_gain
    above = np.nonzero(frac >= 1.0 - math.exp(-1.0))[0]
    if len(above) and above[0] > 0:
        i = int(above[0])
        f0, f1 = frac[i - 1], frac[i]
        t_63 = t[i - 1] + dt * ((1.0 - math.exp(-1.0)) - f0) / (f1 - f0)
        report.t63 = float(t_63 - lag)
    area = float(np.trapezoid(1.0 - frac, t))  # mean residence time
    report.lag_sum = area - lag
    slope = np.gradient(frac, dt)
    k = int(np.argmax(slope))
    onset = int(np.nonzero(np.abs(frac) > 1e-9)[0][0])
    if k <= onset + 1 and onset + 3 < len(frac):  # steepest as it starts: a first-order onset
        mids = t[onset : onset + 3] + dt / 2
        secants = np.diff(frac[onset : onset + 4]) / dt
        m = float(np.polyval(np.polyfit(mids, secants, 2), lag))
        report.apparent_dead_time = lag
        report.apparent_lag = 1.0 / m if m > 0 else None
        return
    lo, hi = max(k - 3, 0), min(k + 4, len(frac))
    if hi - lo < 5:
        return
    p = np.polyfit(t[lo:hi] - t[k], frac[lo:hi], 3)
    if p[0] != 0:
        x = -p[1] / (3 * p[0])  # the cubic's inflection
        x = x if abs(x) <= dt else 0.0
    else:
        x = 0.0
    m = float(np.polyval(np.polyder(p), x))
    v = float(np.polyval(p, x))
    if m > 0:
        report.apparent_dead_time = float(t[k] + x - v / m)
        report.apparent_lag = 1.0 / m


def _ultimate_from_step(s: np.ndarray, dt: float, integrating: bool) -> tuple[float, float] | None:
    """(K_u, P_u) of the model whose sampled unit-step response is ``s`` (s[0] = 0)."""
    h = np.diff(s)  # pulse response, h[k−1] ↔ z^−k
    hinf = 0.0
    if integrating:
        q = max(len(h) // 8, 1)
        hinf = float(np.mean(h[-q:]))
    r = h - hinf
    n = len(r)
    size = 1 << max(math.ceil(math.log2(16 * n)), 12)

    def g_of(w: np.ndarray) -> np.ndarray:
        z1 = np.exp(-1j * w * dt)
        return z1 * (1j * w * dt) / (1.0 - z1)  # z^−1 times the hold divided out

    spectrum = np.fft.rfft(r, size)  # Σ r_k e^{−jωkT}, k from 0 ↔ z^−(k+1)
    w = 2 * np.pi * np.fft.rfftfreq(size, dt)
    w, spectrum = w[1:], spectrum[1:]
    hold = g_of(w)
    g = spectrum * hold
    if integrating:
        g = g + hinf * hold / (1.0 - np.exp(-1j * w * dt))
    low = g[0] if not integrating else g[0] * 1j  # an integrator's phase starts at −90°
    sign = 1.0 if np.real(low) >= 0 else -1.0
    phase = np.unwrap(np.angle(sign * g))
    keep = w <= 0.95 * np.pi / dt
    below = np.nonzero((phase + np.pi < 0) & keep)[0]
    if len(below) == 0 or below[0] == 0:
        return None
    i = int(below[0])

    def g_at(om: float) -> complex:
        k = np.arange(n)
        val = complex(np.sum(r * np.exp(-1j * om * dt * k))) * complex(g_of(np.array([om]))[0])
        if integrating:
            val += hinf * complex(g_of(np.array([om]))[0]) / (1.0 - np.exp(-1j * om * dt))
        return val

    def f(om: float) -> float:
        return float(np.angle(-sign * g_at(om)))

    try:
        wu = brentq(f, w[i - 1], w[i], xtol=1e-14, rtol=1e-13)
    except ValueError:
        wu = float(w[i])
    return 1.0 / abs(g_at(wu)), 2 * math.pi / wu


def refine_step_point(
    report: ModelReport, rebuild: Callable[[float], SimLoop | str], pace: Pace | None = None
) -> None:
    """The step-response ultimate point read again from the model sampled faster, where the
    loop's own samples are too few per period to resolve it (below
    ``MIN_SAMPLES_PER_PERIOD``) and no transfer function gives it exactly. A sampled step
    response holds the continuous one only at the samples: dividing the hold out of its
    spectrum is exact at low frequency and blurs G near Nyquist (lvl1 at 4 samples a period
    read K_u 12,736 against the continuous 15,719, its relay 15,660). ``rebuild(T)``: the
    same loop built with sample time T (or why it cannot be); its point is taken, with
    the sample time it was read at (``step_sample_time``). Where it cannot be read again, a
    warning says the point is the blurred one, and why (it was printed as if it were sound)."""
    spp = report.samples_per_period
    if report.ku_exact is not None or report.ku_step is None or spp is None:
        return
    if spp >= MIN_SAMPLES_PER_PERIOD:
        return
    fine = report.sample_time / math.ceil(FINE_SAMPLES_PER_PERIOD / spp)
    loop = rebuild(fine)
    if isinstance(loop, str):
        report.warnings.append(_blurred(report, fine, loop))
        return
    s = loop.settings
    again = check_model(
        loop.process,
        sample_time=fine,
        op_limits=s.op_limits,
        pv_range=s.pv_range,
        max_samples=MAX_SAMPLES * math.ceil(report.sample_time / fine),
        pace=pace,
    )
    if again.refused or again.ku_step is None:
        why = f"refused: {again.refused}" if again.refused else "no ultimate point read there"
        report.warnings.append(_blurred(report, fine, why))
        return
    report.ku_step, report.pu_step = again.ku_step, again.pu_step
    report.step_sample_time = fine
    report.samples_per_period = report.pu_step / report.sample_time
    report.warnings = [_coarse(report) if w.startswith(COARSE) else w for w in report.warnings]
