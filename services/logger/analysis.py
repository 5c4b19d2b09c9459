"""Re-run a recorded tuning run's identification and rules offline, through the live code.

The run's ``experiment`` event holds the set-up the live tuner built its state machine from
and the first sample it fed; the same recorded samples, fed through the same driver
(``identify.driver``) to a machine built the same way (``identify.methods``), reach the same
K_u, P_u or reaction curve, bit for bit, and every rule's gains follow without a new
experiment.

Nothing in the file is trusted: every record used is validated against its message model, the
request and the experiment's set-up against what the live tuner writes, and whatever is wrong
is one AutotuneError naming the record (topic, index, log time), the field and the reason.
Another run's messages in the file are left out; a message recorded twice is read once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import pydantic
from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.autotuner.design import output_noise
from services.autotuner.design.request_check import validate_request
from services.autotuner.design.selection import Selection, assessments_dict, select
from services.autotuner.identify import experiments, methods
from services.autotuner.identify.driver import drive
from services.autotuner.identify.experiments import Band, Demand
from services.autotuner.identify.reaction_curve import IntegratingCurve
from services.autotuner.identify.rest_drift import drift_notes
from services.autotuner.identify.step_test import HOLD_EVENTS
from services.logger.mcap_io import (
    decode,
    one_result,
    read_run,
    seq_gaps,
    unique_samples,
    validation_reason,
)
from shared import json_text, keys
from shared.control.forms import (
    GainForms,
    all_forms,
    kc_percent,
    process_gain_percent,
    pv_span,
    step_percent,
    unit,
)
from shared.errors import AutotuneError, one_line
from shared.messages import ProcessSample, TuneRequest, TuneResult, TunerEvent


class EndedEarly(AutotuneError):
    """The recorded samples re-run end the experiment before it found anything: ``reason``,
    the state machine's own; ``live``, the run's recorded result (None: none recorded).
    An aborted run re-run to the same end is no bad input: ``analyze`` reports it."""

    def __init__(
        self,
        message: str,
        path: str,
        loop: str,
        method: str,
        reason: str,
        live,
        stopped_by_run: bool = False,
    ):
        super().__init__(message)
        self.path, self.loop, self.method, self.reason, self.live = path, loop, method, reason, live
        # the record ends where the live run stopped the test before it ended (``reason``, the
        # run's: a cancel, a lost plant), not at an end of the test's own
        self.stopped_by_run = stopped_by_run

    def matches_live(self) -> bool:
        """The live run ended so, for the same reason (its result names the machine's), or
        it stopped the test itself where the record ends."""
        live = self.live
        if live is None or live.status not in ("aborted", "failed"):
            return False
        return self.stopped_by_run or (live.status == "aborted" and self.reason in live.reason)

    def to_dict(self) -> dict:
        live = self.live
        return {
            "file": self.path,
            "loop": self.loop,
            "method": self.method,
            "status": "aborted",
            "reason": self.reason,
            "live": None
            if live is None
            else {"status": live.status, "reason": live.reason, "ku": live.ku, "pu": live.pu},
            "matches_live": self.matches_live(),
            "stopped_by_run": self.stopped_by_run,
        }


@dataclass
class Analysis:
    path: str
    loop: str
    method: str
    ident: experiments.Identification
    gains: dict[str, GainForms]  # every rule's
    live: TuneResult | None
    selection: Selection | None = None
    pv_range: tuple[float, float] | None = None  # the transmitter's, as the run recorded it
    # samples missing from the record (gaps in the loop's seq), and the seq before the first
    # gap: the experiment then decided on a record with holes, not the live run's
    missing: int = 0
    first_gap: int | None = None
    pv_units: str | None = None  # the transmitter's, as the run recorded them
    # the PV still drifting as the test began, as the live result says it (``rest_drift``,
    # from the rest the result recorded)
    drift: list[str] = field(default_factory=list)

    @property
    def spreads(self) -> tuple[float | None, float | None]:
        """The K_u and P_u spreads as the live result states them (``stated_spreads``)."""
        if self.selection is None:
            return self.ident.ku_spread, self.ident.pu_spread
        return self.selection.ku_spread, self.selection.pu_spread

    @property
    def span(self) -> float | None:
        """The PV's span (PV units) for the % of span figures; None without a usable range."""
        return _span(self.pv_range)

    def to_dict(self, rule: str | None) -> dict:
        out = {
            "file": self.path,
            "loop": self.loop,
            "method": self.method,
            "ku": self.ident.ku,
            "pu": self.ident.pu,
            "ku_spread": self.spreads[0],
            "pu_spread": self.spreads[1],
            "step": self._step(),
            "l_over_t": self.selection.l_over_t if self.selection else None,
            "experiment": self.ident.experiment.to_dict() if self.ident.experiment else None,
            "gains": {name: g.to_dict() for name, g in self.gains.items()},
        }
        span = self.span
        if span is not None:  # as the live result has them (shared.control.forms)
            model = out["experiment"].get("model_gain") if out["experiment"] else None
            out.update(
                pv_range=list(self.pv_range or ()),
                ku_percent=kc_percent(self.ident.ku, span),
                step_percent=step_percent(out["step"], span),
                model_gain_percent=process_gain_percent(model, span),
            )
        if self.selection is not None:
            rec = self.selection.recommended
            out["robustness"] = assessments_dict(self.selection)
            out["recommended"] = (
                {"rule": rec.rule, "reason": rec.reason, "ms": rec.predicted_ms} if rec else None
            )
            out["refusal"] = self.selection.refusal  # why the chosen gains may not be applied
            out["warnings"] = self.warnings
        if rule:
            out["rule"] = rule
            out["chosen"] = self.gains[rule].to_dict() if rule in self.gains else None
        if self.live is not None:
            out["live"] = {
                "status": self.live.status,
                "reason": self.live.reason,
                "ku": self.live.ku,
                "pu": self.live.pu,
                "rule": self.live.rule,
                "chosen": self.live.chosen,
            }
            out["matches_live"] = self.matches_live()
        out["missing_samples"] = self.missing
        return out

    @property
    def warnings(self) -> list[str]:
        """The identification's notes and the design's warnings, as the live result gives
        them before its verification (``analyze`` left out the notes: a relay's "cycle ran
        at −136°, K_u and P_u were not measured" and a ramp's hold correction among them)."""
        said = list(self.ident.notes)
        said += [w for w in (self.selection.warnings if self.selection else []) if w not in said]
        return said + [w for w in self.drift if w not in said]

    def _step(self) -> dict | None:
        """The reaction curve as the result's ``step`` object (None: not a step test)."""
        return None if self.ident.step is None else self.ident.step.to_dict()

    def matches_live(self) -> bool:
        live = self.live
        if live is None:
            return False
        if live.step is not None:
            return live.step == self._step()
        return bool(live.ku == self.ident.ku and live.pu == self.ident.pu)


class Setup(BaseModel):
    """The ``experiment`` event's data: what the live loop gave the experiment (checked here,
    passed on as recorded so that the machine is rebuilt to the bit)."""

    model_config = ConfigDict(extra="allow", strict=True, allow_inf_nan=False)

    first_seq: int = Field(ge=0)
    sample_time: float = Field(gt=0.0, le=86400.0)
    op_lo: float = Field(ge=0.0, le=100.0)
    op_hi: float = Field(ge=0.0, le=100.0)
    pv_lo: float
    pv_hi: float
    pv_range_lo: float | None = None
    pv_range_hi: float | None = None
    pv_units: str | None = None
    time_scale: float | None = Field(default=None, gt=0.0)
    op_start: float | None = Field(default=None, ge=0.0, le=100.0)
    direction: float | None = None
    kc_start: float | None = Field(default=None, gt=0.0)
    bump: float | None = Field(default=None, gt=0.0)
    sp_start: float | None = None

    @model_validator(mode="after")
    def _ordered(self) -> Setup:
        for lo, hi in (("op_lo", "op_hi"), ("pv_lo", "pv_hi"), ("pv_range_lo", "pv_range_hi")):
            a, b = getattr(self, lo), getattr(self, hi)
            if a is not None and b is not None and not a < b:
                raise ValueError(f"{lo} {a:g} must be below {hi} {b:g}")
        return self

    def missing_for(self, method: str) -> str | None:
        """The first setting ``method`` needs that the event lacks (or has wrong)."""
        needs = methods.method(method).needs
        for name in needs:
            if getattr(self, name) is None:
                return f"{name}: required for a {method} test"
        if "direction" in needs and self.direction not in (1.0, -1.0):
            return f"direction: must be 1 or -1, got {self.direction:g}"
        return None


@dataclass
class _Run:
    """The records of one run that the analysis reads, decoded and checked."""

    request: TuneRequest
    setup: dict
    first_seq: int
    step_times: list[float]
    samples: list[ProcessSample]
    result: TuneResult | None


def _read(path: str | Path) -> tuple[dict[str, str], _Run]:
    meta, records = read_run(path)
    events = [(r, decode(path, r, TunerEvent)) for r in records if keys.leaf(r.topic) == "event"]
    run_id = meta.get("run_id") or next((e.run_id for _, e in events if e.kind == "request"), None)
    runs = sorted({e.run_id for _, e in events if e.kind == "request"})
    if runs and run_id not in runs:
        raise AutotuneError(
            f"{path}: metadata 'run', field run_id: {run_id!r} is none of the runs recorded "
            f"in the file ({', '.join(runs)})"
        )
    events = [(r, e) for r, e in events if e.run_id == run_id]  # another run's: not this one
    request = next(((r, e) for r, e in events if e.kind == "request"), None)
    setup = next(((r, e) for r, e in events if e.kind == "experiment"), None)
    if request is not None and setup is None:  # an apply run: gains, no experiment
        try:
            applied = TuneRequest.model_validate_json(request[1].data.get("request") or "")
        except pydantic.ValidationError:
            applied = None
        if applied is not None and applied.apply_from:
            raise AutotuneError(
                f"{path}: an apply run (the gains of run {applied.apply_from}, verified): it "
                "has no experiment to re-identify; analyse that run's file"
            )
    if request is None or setup is None:
        if meta.get("lost"):  # a file `autotune recover` copied without what it lost
            raise AutotuneError(
                f"{path}: the run's experiment is not in this file: it was recovered, and "
                f"{one_line(meta['lost'], 300)}"
            )
        raise AutotuneError(
            f"{path}: no experiment recorded in this run (it ended before the experiment started)"
        )
    r, e = request
    text = e.data.get("request")
    if not isinstance(text, str):
        raise AutotuneError(f"{path}: {r.where()}: data.request: missing, or not a string")
    try:
        req = TuneRequest.model_validate_json(text)
    except pydantic.ValidationError as err:
        raise AutotuneError(
            f"{path}: {r.where()}: {validation_reason(err, 'data.request')}"
        ) from None
    try:
        validate_request(req)
    except ValueError as err:
        raise AutotuneError(f"{path}: {r.where()}: data.request.{one_line(err)}") from None
    r, e = setup
    try:
        checked = Setup.model_validate(e.data)
    except pydantic.ValidationError as err:
        raise AutotuneError(f"{path}: {r.where()}: {validation_reason(err, 'data')}") from None
    problem = checked.missing_for(req.method)
    if problem:
        raise AutotuneError(f"{path}: {r.where()}: data.{problem}")
    step_times = []
    for r, e in events:
        if e.kind in HOLD_EVENTS:  # in the order held
            t = e.data.get("t")
            if isinstance(t, bool) or not isinstance(t, int | float) or not 0 <= t < math.inf:
                raise AutotuneError(f"{path}: {r.where()}: data.t: must be a time ≥ 0 s, got {t!r}")
            step_times.append(float(t))
    samples = unique_samples(path, records)
    results = [(r, decode(path, r, TuneResult)) for r in records if keys.leaf(r.topic) == "result"]
    result = one_result(path, [(r, x) for r, x in results if x.run_id == run_id])
    data = dict(setup[1].data)
    first_seq = int(data.pop("first_seq"))
    return meta, _Run(req, data, first_seq, step_times, samples, result)


def analyze_file(path: str | Path) -> Analysis:
    """Rebuild the run's experiment from the file and re-identify; AutotuneError (one line,
    naming the record and field) if the file does not hold a complete, valid experiment."""
    meta, run = _read(path)
    req, data = run.request, run.setup
    try:
        machine = methods.build(
            req.method, experiments.Settings.of(req), experiments.Setup.from_dict(data)
        )
    except (ValueError, TypeError, KeyError, ArithmeticError) as err:
        raise AutotuneError(
            f"{path}: the experiment event's set-up does not build a {req.method} test: "
            f"{one_line(err)}"
        ) from None
    fed = [s for s in run.samples if s.seq >= run.first_seq]
    missing, first_gap = seq_gaps([s.seq for s in fed])
    record = _Record(str(path), fed, run.step_times)
    try:
        last: list[float] = []  # the sample the test finished on (``rest_drift``)
        ident = drive(machine, record, watch=lambda s: last.append(s.t))
        if ident is None:
            why = machine.reason or (
                f"{missing} samples are missing from the record (the first gap after seq "
                f"{first_gap}): the test cannot be followed across them"
                if missing
                else "the recording ends first"
            )
            message = f"{path}: the recorded samples do not complete the {req.method} test ({why})"
            loop = meta.get("loop", req.loop)
            if machine.reason:  # the experiment's own end (an abort), not a short record
                raise EndedEarly(message, str(path), loop, req.method, why, run.result)
            live = run.result
            if not missing and live is not None and live.status in ("aborted", "failed"):
                # the live run stopped its test where the record ends (a cancel, a plant or a
                # lease lost: helper trial, `tune --wait 2`): no short record, but that run
                raise EndedEarly(
                    message, str(path), loop, req.method, live.reason or live.status, live, True
                )
            raise AutotuneError(message)
        sel = select(
            ident,
            req.rule,
            req.ms_bound,
            req.force,
            data.get("sample_time"),
            req.lambda_s,
            req.aim,
            max_op_noise=output_noise.limit_of(req.max_op_noise),
            span=_span(_pv_range(data)),
        )
    except (ValueError, TypeError, KeyError, IndexError, ArithmeticError) as err:
        raise AutotuneError(
            f"{path}: the recorded samples cannot be re-identified as a {req.method} test "
            f"({type(err).__name__}: {one_line(err)})"
        ) from None
    pv_range = _pv_range(data)
    span = _span(pv_range)
    return Analysis(
        str(path),
        meta.get("loop", req.loop),
        req.method,
        ident,
        {name: all_forms(g, span) for name, g in sel.table.items()},
        run.result,
        sel,
        pv_range,
        missing,
        first_gap,
        data.get("pv_units"),  # a string or None: the set-up is checked (``Setup``)
        drift_notes(
            ident,
            run.result.rest if run.result is not None else None,
            float(data.get("sample_time") or 0.0),
            fed[0].t if fed else None,
            last[-1] if last else None,
            data.get("pv_units") or "",
        ),
    )


def _pv_range(data: dict) -> tuple[float, float] | None:
    """The recorded loop's PV range (None where the record has none)."""
    lo, hi = data.get("pv_range_lo"), data.get("pv_range_hi")
    return None if lo is None or hi is None else (float(lo), float(hi))


def _span(pv_range: tuple[float, float] | None) -> float | None:
    """``pv_span``, None where the range is missing or unusable (no % of span figures)."""
    try:
        return pv_span(pv_range)
    except ValueError:
        return None


class _Record:
    """A recorded run as the experiment driver's loop: its samples from the first fed, and
    the times the live run's changed outputs held from (``step_started`` events). It holds
    nothing: the samples already show what the live loop held."""

    def __init__(self, path: str, samples: list[ProcessSample], hold_times: list[float]):
        self.path, self._samples, self._times = path, samples, list(hold_times)
        self._next = 0

    def samples(self, n: int, band: Band | None = None) -> list[ProcessSample]:
        out = self._samples[self._next : self._next + n]
        if band is not None:  # the live loop stopped where the PV left the band
            test = band.end_test()
            ends = [i for i, s in enumerate(out) if test(s.pv, s.op)]
            out = out[: ends[0] + 1] if ends else out
        self._next += len(out)
        return out

    def apply(self, demand: Demand, before: Demand) -> None:
        return None

    def hold_time(self) -> float:
        if not self._times:
            raise AutotuneError(f"{self.path}: the step's start time was not recorded")
        return self._times.pop(0)


def format_analysis(a: Analysis, rule: str | None) -> str:
    lines = [f"{a.path}: {a.method} test of {a.loop}, re-identified offline"]
    pv = unit(a.pv_units)  # the figures' units as the tune prints them
    if a.ident.ku is not None:
        lines.append(f"  K_u = {a.ident.ku:.6g} %/{pv}   P_u = {a.ident.pu:.6g} s")
    if isinstance(a.ident.step, IntegratingCurve):
        s = a.ident.step
        lines.append(
            f"  integrating: R = K' = {s.reaction_rate:.4g} {pv}/s per %  "
            f"L = {s.dead_time:.4g} s  a = R·L = {s.a:.4g} {pv}/%"
        )
    elif a.ident.step is not None:
        s = a.ident.step
        lines.append(
            f"  step curve: K = {s.gain:.4g} {pv}/%  L = {s.dead_time:.4g} s  "
            f"T = {s.time_constant_tangent:.4g} s  L/T = {s.l_over_t:.3f}"
        )
    lines += [f"  warning: {w}" for w in a.warnings]
    if a.missing:
        lines.append(
            f"  WARNING: {a.missing} samples missing from the record (the first gap after seq "
            f"{a.first_gap}): re-identified on a record with holes, not the live run's"
        )
    refusal = a.selection.refusal if a.selection is not None else None
    if a.selection is not None and a.selection.recommended is not None:
        rec = a.selection.recommended
        lines.append(f"  recommended: {rec.rule} ({rec.reason})")
    if refusal:  # this analysis's own: the table below is not to be applied as it stands
        lines.append(f"  refused: {refusal}")
    if a.live is not None:
        lines += _live_lines(a, refusal)
    lines.append(f"  {'rule':<15}{'Kc':>10}{'Ti (s)':>10}{'Td (s)':>10}")
    for name, g in a.gains.items():
        if rule and name != rule:
            continue
        isa = g.isa
        ti = "—" if isa.ti is None else f"{isa.ti:.4g}"
        lines.append(f"  {name:<15}{isa.kc:>10.4g}{ti:>10}{isa.td:>10.4g}")
    return "\n".join(lines)


def _live_lines(a: Analysis, refusal: str | None = None) -> list[str]:
    """The live run against this analysis. A run that ended before it reported its figures
    (aborted: cancelled, a lost peer, a budget; failed) has nothing to compare: said so, with
    its status and reason, not "DIFFERENT" (an hx1 relay cancelled at the sample that closed
    its last cycle read "live run: no K_u and P_u measured → DIFFERENT", and nowhere that it
    had been cancelled). ``refusal``: this analysis's own, printed above (a live reason that
    is the same words is not printed twice)."""
    live = a.live
    assert live is not None
    if live.reason and live.reason == refusal:
        how = f"{live.status} (refused as above)"
    else:
        how = live.status + (f" ({live.reason})" if live.reason else "")
    same = "identical" if a.matches_live() else "DIFFERENT"
    if live.step is None and live.ku is None and live.status in ("aborted", "failed"):
        if a.ident.ku is not None or a.ident.step is not None:
            return [
                f"  live run: {how} before it reported its figures; the record completes the "
                "test offline (figures the live run never gave)"
            ]
        return [f"  live run: {how}; no K_u and P_u measured → {same}"]
    out = [] if live.status in ("ok", "unverified", "proposed") else [f"  live run: {how}"]
    if live.step is not None:  # a step test's: its reaction curve, not K_u and P_u
        out.append(f"  live run: its step response's figures → {same}")
    elif live.ku is None or live.pu is None:  # none measured (said in its warnings)
        out.append(f"  live run: no K_u and P_u measured → {same}")
    else:
        out.append(f"  live run: K_u = {live.ku}, P_u = {live.pu} → {same}")
    return out


def dumps(a: Analysis, rule: str | None) -> str:
    return json_text.dumps(a.to_dict(rule), indent=2)
