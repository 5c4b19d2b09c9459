"""Re-run a recorded tuning run's identification and rules offline, through the live code.

The run's ``experiment`` event holds the set-up the live tuner built its state machine from
and the first sample it fed; feeding the same recorded samples to a machine built the same
way (``autotuner.experiments``) reaches the same K_u, P_u or reaction curve, bit for bit,
and every rule's gains follow without a new experiment.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from services.autotuner import experiments
from services.autotuner.forms import all_forms
from services.autotuner.selection import Selection, assessments_dict, select
from services.autotuner.step_test import StepTest
from services.logger.mcap_io import read_run
from shared.errors import AutotuneError
from shared.messages import ProcessSample, TuneRequest, TuneResult


@dataclass
class Analysis:
    path: str
    loop: str
    method: str
    ident: experiments.Identification
    gains: dict[str, dict]
    live: TuneResult | None
    selection: Selection | None = None

    def to_dict(self, rule: str | None) -> dict:
        out = {
            "file": self.path,
            "loop": self.loop,
            "method": self.method,
            "ku": self.ident.ku,
            "pu": self.ident.pu,
            "ku_spread": self.ident.ku_spread,
            "pu_spread": self.ident.pu_spread,
            "step": self.ident.step,
            "l_over_t": self.selection.l_over_t if self.selection else None,
            "experiment": self.ident.experiment,
            "gains": self.gains,
        }
        if self.selection is not None:
            rec = self.selection.recommended
            out["robustness"] = assessments_dict(self.selection)
            out["recommended"] = (
                {"rule": rec.rule, "reason": rec.reason, "ms": rec.predicted_ms} if rec else None
            )
            out["warnings"] = self.selection.warnings
        if rule:
            out["rule"] = rule
            out["chosen"] = self.gains.get(rule)
        if self.live is not None:
            out["live"] = {
                "ku": self.live.ku,
                "pu": self.live.pu,
                "rule": self.live.rule,
                "chosen": self.live.chosen,
            }
            out["matches_live"] = self.matches_live()
        return out

    def matches_live(self) -> bool:
        live = self.live
        if live is None:
            return False
        if live.step is not None:
            return live.step == self.ident.step
        return bool(live.ku == self.ident.ku and live.pu == self.ident.pu)


def analyze_file(path: str | Path) -> Analysis:
    """Rebuild the run's experiment from the file and re-identify; AutotuneError if the file
    does not hold a complete experiment."""
    meta, records = read_run(path)
    events = [r.json() for r in records if r.topic.endswith("/event")]
    request = next((e for e in events if e["kind"] == "request"), None)
    setup = next((e for e in events if e["kind"] == "experiment"), None)
    if request is None or setup is None:
        raise AutotuneError(
            f"{path}: no experiment recorded in this run (it ended before the experiment started)"
        )
    req = TuneRequest.model_validate_json(request["data"]["request"])
    data = dict(setup["data"])
    first_seq = int(data.pop("first_seq"))
    step_times = [e["data"]["t"] for e in events if e["kind"] == "step_started"]
    samples = sorted(
        (ProcessSample.model_validate_json(r.data) for r in records if r.topic.endswith("/pv")),
        key=lambda s: s.seq,
    )
    machine = experiments.build(req.method, req, data)
    op = data.get("op_start")
    for s in samples:
        if s.seq < first_seq:
            continue
        want = experiments.feed(machine, s)
        if machine.finished:
            break
        if isinstance(machine, StepTest) and want != op:
            op = want
            if not step_times:
                raise AutotuneError(f"{path}: the step's start time was not recorded")
            machine.step_started(step_times.pop(0))
    ident = experiments.identification(machine)
    if ident is None:
        raise AutotuneError(
            f"{path}: the recorded samples do not complete the {req.method} "
            f"test ({machine.reason or 'the recording ends first'})"
        )
    sel = select(ident, req.rule, req.ms_bound, req.force, data.get("sample_time"))
    result = next((r for r in records if r.topic.endswith("/result")), None)
    live = TuneResult.model_validate_json(result.data) if result else None
    return Analysis(
        str(path),
        meta.get("loop", req.loop),
        req.method,
        ident,
        {name: all_forms(g) for name, g in sel.table.items()},
        live,
        sel,
    )


def format_analysis(a: Analysis, rule: str | None) -> str:
    lines = [f"{a.path}: {a.method} test of {a.loop}, re-identified offline"]
    if a.ident.ku is not None:
        lines.append(f"  K_u = {a.ident.ku:.6g}   P_u = {a.ident.pu:.6g} s")
    if a.ident.step:
        s = a.ident.step
        lines.append(
            f"  K = {s['gain']:.4g}  L = {s['dead_time']:.4g} s  "
            f"T = {s['time_constant_tangent']:.4g} s  L/T = {s['l_over_t']:.3f}"
        )
    if a.live is not None:
        lines.append(
            f"  live run: K_u = {a.live.ku}, P_u = {a.live.pu} → "
            f"{'identical' if a.matches_live() else 'DIFFERENT'}"
        )
    lines.append(f"  {'rule':<15}{'Kc':>10}{'Ti (s)':>10}{'Td (s)':>10}")
    for name, g in a.gains.items():
        if rule and name != rule:
            continue
        isa = g["isa"]
        ti = "—" if isa["ti"] is None else f"{isa['ti']:.4g}"
        lines.append(f"  {name:<15}{isa['kc']:>10.4g}{ti:>10}{isa['td']:>10.4g}")
    return "\n".join(lines)


def dumps(a: Analysis, rule: str | None) -> str:
    return json.dumps(a.to_dict(rule), indent=2)
