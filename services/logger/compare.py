"""``autotune runs --compare RUN RUN``: two runs' figures side by side — what was identified
(K_u, P_u, the model), the gains chosen (Kc with units, as %/% and PB), their predicted
robustness and the verification measured after — with the change from the first to the
second. ``compare(path_a, path_b)`` is the dict ``--json`` prints (the console shows it too);
``format_compare`` its text."""

from __future__ import annotations

import math
from pathlib import Path

from services.logger.gain_text import kc_forms, number, span_of
from services.logger.mcap_io import decode, one_result, read_run
from shared import keys
from shared.messages import TuneResult, TunerEvent

# (key, label, unit; "PV" stands for the PV's units)
ROWS = (
    ("ku", "K_u", "%/PV"),
    ("ku_percent", "K_u", "%/%"),
    ("pu", "P_u", "s"),
    ("ku_spread", "K_u spread", "%"),
    ("pu_spread", "P_u spread", "%"),
    ("model", "model", ""),
    ("model_gain", "model K", "PV/%"),
    ("model_lag_1", "model T1", "s"),
    ("model_lag_2", "model T2", "s"),
    ("model_delay", "model L", "s"),
    ("l_over_t", "L/T", ""),
    ("rule", "rule", ""),
    ("kc", "Kc", "%/PV"),
    ("kc_percent", "Kc", "%/%"),
    ("pb", "PB", "% of span"),
    ("ti", "Ti", "s"),
    ("td", "Td", "s"),
    ("beta", "setpoint weight β", ""),
    ("ms", "Ms (predicted)", ""),
    ("gain_margin", "gain margin", ""),
    ("phase_margin_deg", "phase margin", "deg"),
    ("overshoot_pct", "overshoot (predicted)", "%"),
    ("overshoot", "overshoot (measured)", "%"),
    ("decay_ratio", "decay ratio", ""),
    ("rise_time", "rise time", "s"),
    ("settling_time", "settling time", "s"),
    ("settling_band", "settling band", "% of step"),
    ("iae_sp", "IAE, setpoint", "PV·s"),
    ("iae_load", "IAE, load", "PV·s"),
    ("max_deviation_load", "max deviation, load", "PV"),
    ("recovery_time", "recovery time, load", "s"),
    ("status", "status", ""),
    ("sim_duration", "run length, sim time", "s"),
)
PERCENT_KEYS = ("ku_spread", "pu_spread")  # fractions on the result, given in % (JSON too)
# figures in %: their change is told in percentage points (an overshoot from 0.0001 % to 10 %
# is not a change of +10,000,000 %)
POINT_KEYS = (*PERCENT_KEYS, "overshoot_pct", "overshoot", "settling_band")
# where a run's L/T comes from: a step test's reaction curve (its tangent) or, else, the
# model's first-order equivalent (``selection.l_over_t``): the two are not the same figure
L_OVER_T_FROM = {True: "step tangent", False: "model FOPDT"}
# a gain in %/% and the row of the same gain in %/PV unit (equal when the PV's span is 100 %)
SAME_IN_PERCENT = {"ku_percent": "ku", "kc_percent": "kc"}


def _result(path: Path) -> tuple[dict[str, str], TuneResult | None, float | None]:
    """The run's metadata, its result (None: none recorded) and the PV's span."""
    meta, records = read_run(path)
    run_id = meta.get("run_id")
    results = [(r, decode(path, r, TuneResult)) for r in records if keys.leaf(r.topic) == "result"]
    result = one_result(path, [(r, x) for r, x in results if not run_id or x.run_id == run_id])
    span = span_of(result.pv_range) if result is not None else None
    if span is None:  # files from before the result carried it: the experiment's set-up
        for r in records:
            if keys.leaf(r.topic) == "event":
                e = decode(path, r, TunerEvent)
                if e.kind == "experiment" and (not run_id or e.run_id == run_id):
                    span = span_of((e.data.get("pv_range_lo"), e.data.get("pv_range_hi")))
    return meta, result, span


def figures(meta: dict[str, str], r: TuneResult | None, span: float | None) -> dict:
    """The run's figures by ``ROWS`` key (None where it has none)."""
    out: dict = {k: None for k, _, _ in ROWS} | {"l_over_t_from": None}
    out["status"] = meta.get("status")
    if r is None:
        return out
    e = r.experiment or {}
    chosen = r.chosen if isinstance(r.chosen, dict) else {}
    isa = chosen.get("isa") if isinstance(chosen.get("isa"), dict) else {}
    rob = r.robustness.get(r.rule, {}) if isinstance(r.robustness, dict) else {}
    kc_pct, pb = kc_forms(isa.get("kc"), span)
    ku_pct = kc_forms(r.ku, span)[0]
    out.update(
        ku=r.ku,
        ku_percent=r.ku_percent if r.ku_percent is not None else ku_pct,
        pu=r.pu,
        ku_spread=r.ku_spread,
        pu_spread=r.pu_spread,
        model=e.get("model"),
        model_gain=e.get("model_gain"),
        model_lag_1=e.get("model_lag_1"),
        model_lag_2=e.get("model_lag_2"),
        model_delay=e.get("model_delay"),
        l_over_t=r.l_over_t,
        l_over_t_from=L_OVER_T_FROM[r.step is not None] if r.l_over_t is not None else None,
        rule=r.rule,
        kc=isa.get("kc"),
        kc_percent=kc_pct,
        pb=pb,
        ti=isa.get("ti"),
        td=isa.get("td"),
        status=r.status,
        sim_duration=r.sim_duration,
    )
    for k in ("ms", "gain_margin", "phase_margin_deg", "overshoot_pct"):
        out[k] = rob.get(k)
    if r.after is not None:
        out["beta"] = r.after.gains.beta  # the verified gains' (``design.setpoint_weight``)
        for k in (
            "overshoot",
            "decay_ratio",
            "rise_time",
            "settling_time",
            "settling_band",
            "iae_sp",
            "iae_load",
            "max_deviation_load",
            "recovery_time",
        ):
            out[k] = getattr(r.after, k)
    return out


def _number(v: object) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def compare(path_a: str | Path, path_b: str | Path) -> dict:
    """Both runs' figures, row by row, with the relative change from a to b (numbers only);
    AutotuneError (one line naming the file) for a file that cannot be read."""
    runs, values, units = [], [], []
    for path in (Path(path_a), Path(path_b)):
        meta, result, span = _result(path)
        if result is not None:  # a file without its metadata record (a killed logger's):
            # who and what from its result, as `analyze` reads it (a header of Nones: helper)
            meta = {"run_id": result.run_id, "loop": result.loop, "method": result.method,
                    "status": result.status} | {k: v for k, v in meta.items() if v}  # fmt: skip
        runs.append(
            {
                "file": str(path),
                "run_id": meta.get("run_id"),
                "loop": meta.get("loop"),
                "method": meta.get("method"),
                "started": meta.get("started"),
                "pv_units": result.pv_units if result else "",
                "span": span,
            }
        )
        values.append(figures(meta, result, span))
        units.append(result.pv_units if result else None)
    if None in units:  # a run without its result (a recovered one): its units not known,
        # not "PV units differ (A degC, B —)" (helper trial); it has no figure to compare
        units = [next((u for u in units if u is not None), "")] * 2
    mixed = units[0] != units[1]  # a figure in PV units then has no change from a to b
    rows = []
    for key, label, unit in ROWS:
        a, b = values[0][key], values[1][key]
        if a is None and b is None:
            continue
        if key in PERCENT_KEYS:  # fractions on the result, in % here as the unit says
            a, b = (100.0 * v if _number(v) is not None else v for v in (a, b))
        base = SAME_IN_PERCENT.get(key)
        if base is not None and _same(a, values[0][base]) and _same(b, values[1][base]):
            continue  # a PV in % over 0–100: the %/% row would repeat the row above it
        na, nb = _number(a), _number(b)
        change = (nb - na) / abs(na) if na is not None and nb is not None and na != 0 else None
        in_pv = "PV" in unit
        if in_pv and mixed:  # 2 %/degC against 3 %/(m3/h) is no change of 50 %
            change = None
        if base is not None and units == ["%", "%"]:  # PVs in %: "%/%" would name both rows
            unit = "%/% of span"
        if key == "l_over_t":
            froms = [v.get("l_over_t_from") for v in values]
            unit = " | ".join(f for f in froms if f) if froms[0] != froms[1] else froms[0] or ""
            if froms[0] != froms[1]:
                change = None  # a tangent's L/T against a model's: not one figure
        shown = _unit(unit, units) if in_pv else unit
        if key == "model_gain":  # an integrator's K is a rate, K' of K'·e^{−Ls}/s: PV/s per %
            per = [_gain_unit(v.get("model")) for v in values if v.get("model")]
            if len(set(per)) == 2:  # a rate against a static gain: not one figure
                change = None
                shown = " | ".join(_unit(u, [pv, pv]) for u, pv in zip(per, units, strict=True))
            elif per:
                shown = _unit(per[0], units)
        row = {
            "key": key,
            "label": label,
            "unit": shown,
            "a": a,
            "b": b,
            "change": change,
        }
        if key in POINT_KEYS and na is not None and nb is not None:
            # percentage points; none between figures equal to their last bits (37.5 and
            # 37.5 read "-2.2e-13 pt": helper trial)
            row["points"] = 0.0 if _same(na, nb) else nb - na
        rows.append(row)
    return {"runs": runs, "rows": rows, "pv_units_differ": mixed}


def _gain_unit(model: str | None) -> str:
    """The unit of a model's gain K: PV/s per % for an integrator (IPDT), else PV/%."""
    return "PV/s per %" if model == "ipdt" else "PV/%"


def _same(x: object, y: object) -> bool:
    """The same figure, to the last few bits (×100/span by a span of 100 may round)."""
    nx, ny = _number(x), _number(y)
    if nx is None or ny is None:
        return x == y
    return math.isclose(nx, ny, rel_tol=1e-12, abs_tol=0.0)


def _unit(unit: str, units: list[str]) -> str:
    """``unit`` with "PV" as the runs' PV units: one unit, or A's and B's where they differ
    (a PV without units: "PV unit")."""
    a, b = (u or "PV unit" for u in units)
    return unit.replace("PV", a) if a == b else f"{unit.replace('PV', a)} | {unit.replace('PV', b)}"


def _cell(key: str, v: object) -> str:
    if v is None:
        return "—"
    if key in PERCENT_KEYS and _number(v) is not None:
        return number(float(v), ".3g")  # type: ignore[arg-type]
    if isinstance(v, int | float) and not isinstance(v, bool):
        return number(v, ".5g")
    return str(v)


def format_compare(c: dict) -> str:
    """The comparison as a table: one row per figure, the runs in two columns."""
    a, b = c["runs"]
    head = []
    for name, run in (("A", a), ("B", b)):
        started = (run.get("started") or "")[:19]
        when = f"  ({started} UTC)" if started else "  (start not recorded)"
        head += [
            f"{name}  {run['file']}",
            f"   {run.get('loop') or '—'} {run.get('method') or '—'} run "
            f"{run.get('run_id') or '—'}{when}",
        ]
    if c.get("pv_units_differ"):
        head += [
            "",
            f"PV units differ (A {a.get('pv_units') or '—'}, B {b.get('pv_units') or '—'}): "
            "figures in PV units are shown, not compared",
        ]
    labels = [f"{r['label']} ({r['unit']})" if r["unit"] else r["label"] for r in c["rows"]]
    width = max([32, *map(len, labels)])
    head += [
        "",
        f"{'':<{width}} {'A':>14} {'B':>14} {'B vs A':>10}",
    ]
    for label, r in zip(labels, c["rows"], strict=True):
        ch = r["change"]
        change = (
            f"{r['points']:+.3g} pt"
            if r.get("points") is not None
            else ""
            if ch is None
            else f"{100 * ch:+.1f} %"
        )
        head.append(
            f"{label:<{width}} {_cell(r['key'], r['a']):>14} {_cell(r['key'], r['b']):>14} "
            f"{change:>10}"
        )
    return "\n".join(head)
