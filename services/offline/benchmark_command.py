"""autotune benchmark: relay and ramp tunes of the benchmark suite, in-process, against the
exact ultimate points; then Iinoya & Hotta's table for first order plus dead time.

Table 1 gives, per plant, noise level and method, the K_u and P_u errors of our estimate
and of the describing function (the relay's stage 1, what classic relay tuners report),
the experiment's length in ultimate periods (classic stage 1 / whole test), the model chosen
and the recommended rule with its Ms on the true plant. Summary lines give the median and
worst |error| up to 1 % noise. Table 2 gives K₀·R·L and τ₀/L measured against the closed form
and the decay ratio that Ziegler–Nichols P (Kc = 0.5K_u) achieves against its 25 % aim.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from services.offline import benchmark

HELP = "benchmark identification on a suite of plants (in-process, no bus)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--noise",
        default=",".join(f"{n:g}" for n in benchmark.NOISE_LEVELS),
        help="noise levels as fractions of the PV's peak-to-peak swing (default 0,0.01,0.03)",
    )
    parser.add_argument(
        "--methods", default="relay,ramp", help="relay, ramp or both (default relay,ramp)"
    )
    parser.add_argument("--plants", default="", help="only plants whose name contains this")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    parser.add_argument(
        "--ratios",
        default=",".join(f"{r:g}" for r in benchmark.IH_RATIOS),
        help="T/L values of the Iinoya–Hotta table (default 0.1,…,100; empty: no table)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON document on stdout")


def _parse(args: argparse.Namespace) -> tuple[list[float], list[str], list[float]]:
    try:
        noise = [float(x) for x in args.noise.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(
            f"autotune benchmark: --noise {args.noise!r}: not a list of numbers"
        ) from None
    if not noise or any(not (0.0 <= n < 0.5) for n in noise):
        raise SystemExit(f"autotune benchmark: --noise {args.noise!r}: each must be in [0, 0.5)")
    try:
        ratios = [float(x) for x in args.ratios.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(
            f"autotune benchmark: --ratios {args.ratios!r}: not a list of numbers"
        ) from None
    if any(not (0.0 < r <= 1e4) for r in ratios):
        raise SystemExit(f"autotune benchmark: --ratios {args.ratios!r}: each in (0, 1e4]")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in ("relay", "ramp")]
    if not methods or bad:
        raise SystemExit(f"autotune benchmark: --methods {args.methods!r}: use relay and/or ramp")
    return noise, methods, ratios


def summary(outcomes: list[benchmark.TuneOutcome], max_noise: float = 0.01) -> dict:
    """Median and worst |error| per method up to ``max_noise``, ours and describing function."""
    out: dict[str, dict] = {}
    for method in sorted({o.method for o in outcomes}):
        sel = [o for o in outcomes if o.method == method and o.noise <= max_noise + 1e-12]
        ok = [o for o in sel if o.ok]
        row: dict[str, float | int] = {"runs": len(sel), "failed": len(sel) - len(ok)}
        for key in ("ku_error", "pu_error", "ku_df_error", "pu_df_error"):
            vals = np.abs([getattr(o, key) for o in ok])
            vals = vals[np.isfinite(vals)]
            if vals.size:
                row[f"{key}_median"] = float(np.median(vals))
                row[f"{key}_worst"] = float(np.max(vals))
        extra = [o.periods - o.periods_classic for o in ok if math.isfinite(o.periods_classic)]
        if extra:
            row["extra_periods_worst"] = max(extra)  # stage 2, in P_u
        recs = [o for o in ok if o.recommended]
        row["recommended_unstable"] = sum(not o.recommended_stable for o in recs)
        row["recommended_ms_worst"] = max((o.recommended_ms for o in recs), default=math.nan)
        out[method] = row
    return out


def _pct(x: float) -> str:
    return "     –" if not math.isfinite(x) else f"{100 * x:+6.2f}"


def run(args: argparse.Namespace) -> int:
    noise, methods, ratios = _parse(args)
    plants = [p for p in benchmark.suite() if args.plants in p.name]
    if not plants:
        raise SystemExit(f"autotune benchmark: --plants {args.plants!r}: no plant matches")
    started = time.perf_counter()
    outcomes = []
    for plant in plants:
        for level in noise:
            if "relay" in methods:
                outcomes.append(benchmark.run_relay(plant, level, args.seed))
            if "ramp" in methods:
                outcomes.append(benchmark.run_ramp(plant, level, args.seed))
    rows = [benchmark.iinoya_hotta_row(r) for r in ratios]
    elapsed = time.perf_counter() - started
    stats = summary(outcomes)
    if args.json:
        json.dump(
            {
                "tunes": [o.to_dict() for o in outcomes],
                "summary_up_to_1pct_noise": stats,
                "iinoya_hotta": [r.to_dict() for r in rows],
                "seconds": elapsed,
            },
            sys.stdout,
            indent=1,
        )
        print()
        return 0
    print(
        f"{'plant':22} {'noise':>5} {'method':6} | {'Ku ours':>7} {'Pu ours':>7} | "
        f"{'Ku DF':>7} {'Pu DF':>7} | {'periods':>9} | model  recommended   Ms"
    )
    for o in outcomes:
        if not o.ok:
            print(f"{o.plant:22} {o.noise:5.2f} {o.method:6} | failed: {o.reason}")
            continue
        periods = (
            f"{o.periods_classic:4.1f}/{o.periods:4.1f}"
            if math.isfinite(o.periods_classic)
            else f"{o.periods:9.1f}"
        )
        print(
            f"{o.plant:22} {o.noise:5.2f} {o.method:6} | {_pct(o.ku_error)}% {_pct(o.pu_error)}% | "
            f"{_pct(o.ku_df_error)}% {_pct(o.pu_df_error)}% | {periods:>9} | "
            f"{o.model or '-':6} {o.recommended:12} {o.recommended_ms:4.2f}"
            + ("" if o.recommended_stable else " UNSTABLE")
        )
    print("\nup to 1 % noise, |error| median / worst:")
    for method, s in stats.items():
        line = f"  {method:6} {s['runs']} runs, {s['failed']} failed"
        for key, label in (("ku_error", "Ku"), ("pu_error", "Pu"), ("ku_df_error", "Ku DF")):
            if f"{key}_median" in s:
                line += (
                    f"; {label} {100 * s[f'{key}_median']:.2f} % / {100 * s[f'{key}_worst']:.2f} %"
                )
        if "extra_periods_worst" in s:
            line += f"; stage 2 adds at most {s['extra_periods_worst']:.2f} P_u"
        line += (
            f"; recommended gains unstable on {s['recommended_unstable']}, "
            f"worst Ms {s['recommended_ms_worst']:.2f}"
        )
        print(line)
    print(
        "\nIinoya & Hotta, K·e^{-Ls}/(Ts+1), relay without noise:\n"
        f"{'T/L':>6} | {'K0·R·L exact':>12} {'measured':>9} {'err':>7} | "
        f"{'τ0/L exact':>10} {'measured':>9} {'err':>7} | decay ratio of ZN P (aim 25 %)"
    )
    for r in rows:
        print(
            f"{r.t_over_l:6g} | {r.krl_exact:12.4f} {r.krl_measured:9.4f} {_pct(r.krl_error)}% | "
            f"{r.tau_exact:10.4f} {r.tau_measured:9.4f} {_pct(r.tau_error)}% | "
            f"{100 * r.decay_ratio_zn_p:5.1f} %"
        )
    print(f"\n{len(outcomes)} tunes and {len(rows)} Iinoya–Hotta runs in {elapsed:.1f} s")
    return 0
