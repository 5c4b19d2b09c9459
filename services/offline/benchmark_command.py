"""autotune benchmark: relay and ramp tunes of the benchmark suite, in-process, against the
exact ultimate points; then Iinoya & Hotta's table for first order plus dead time.

Table 1 gives, per plant, noise level and method, the K_u and P_u errors of our estimate
and of the describing function (the relay's stage 1, what classic relay tuners report),
the experiment's length in ultimate periods (classic stage 1 / whole test), the model chosen
and the recommended rule with its Ms on the true plant. Summary lines give the median and
worst |error| up to 1 % noise. Table 2 gives K₀·R·L and τ₀/L measured against the closed form
and the decay ratio that Ziegler–Nichols P (Kc = 0.5K_u) achieves against its 25 % aim.

With --iinoya-hotta, only Iinoya & Hotta's (1958) three figures for K·e^{−Ls}/(1 + sT), each
from the paper's equations (5, 7, 12, 15) and from the product's experiments on the plant
(relay, step test, and the settings where the dominant mode of a closed-loop setpoint step
decays by a quarter per period, or "none" where no setting gives such a response): Fig. 1, P
control's K₀/K₄ and K₄·R·L beside ZN's K₀/2 and 1/(R·L) rules; Fig. 2, K₀·R·L and τ₀/L; Fig. 3,
the integral time T_I4/L at ZN's PI gain 0.9/(R·L) against ZN's 3.33, and the derivative time
T_D4/L at the PD gain 1.2/(R·L), both branches, against the paper's 0.36–0.37. --plot DIR
writes the three figures as PNG: the curves, the rules and the measured points.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from services.offline import benchmark
from services.offline import iinoya_hotta as ih
from shared import json_text
from shared.cli import check_runs_dir

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

HELP = "benchmark identification on a suite of plants (in-process, no bus)"
MEASURE_RANGE = (0.05, 200.0)  # T/L: the step test's samples grow as L/T and T/L beyond


def _csv(values) -> str:
    return ",".join(f"{v:g}" for v in values)


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
        default=None,
        help="T/L values of the Iinoya–Hotta table (default 0.1,…,100; with --iinoya-hotta "
        f"{_csv(ih.FIGURE_RATIOS)}; empty: no table)",
    )
    parser.add_argument(
        "--iinoya-hotta",
        action="store_true",
        help="only Iinoya & Hotta's three figures, closed form and measured (no relay suite)",
    )
    parser.add_argument(
        "--measure",
        default=None,
        metavar="T/L,...",
        help="with --iinoya-hotta: the T/L values measured by simulated experiments, "
        f"{MEASURE_RANGE[0]:g}–{MEASURE_RANGE[1]:g} (default: every --ratios value; "
        "empty: closed forms only)",
    )
    parser.add_argument(
        "--plot",
        default=None,
        metavar="DIR",
        help="with --iinoya-hotta: write the three figures there as PNG",
    )
    parser.add_argument("--json", action="store_true", help="one JSON document on stdout")


def _numbers(flag: str, text: str) -> list[float]:
    """A comma-separated list of numbers; the one-line refusal naming ``flag`` otherwise."""
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(
            f"autotune benchmark: error: {flag} {text!r}: not a list of numbers"
        ) from None
    if not all(math.isfinite(v) for v in values):
        raise SystemExit(f"autotune benchmark: error: {flag} {text!r}: not a list of numbers")
    return values


def _parse(args: argparse.Namespace) -> tuple[list[float], list[str], list[float]]:
    try:
        noise = [float(x) for x in args.noise.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(
            f"autotune benchmark: error: --noise {args.noise!r}: not a list of numbers"
        ) from None
    if not noise or any(not (0.0 <= n < 0.5) for n in noise):
        raise SystemExit(
            f"autotune benchmark: error: --noise {args.noise!r}: each must be in [0, 0.5)"
        )
    ratios = _ratios(args)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in ("relay", "ramp")]
    if not methods or bad:
        raise SystemExit(
            f"autotune benchmark: error: --methods {args.methods!r}: use relay and/or ramp"
        )
    return noise, methods, ratios


def _ratios(args: argparse.Namespace) -> list[float]:
    """--ratios, or its default for the mode."""
    default = ih.FIGURE_RATIOS if args.iinoya_hotta else ih.IH_RATIOS
    text = _csv(default) if args.ratios is None else args.ratios
    ratios = _numbers("--ratios", text)
    if any(not (0.0 < r <= 1e4) for r in ratios):
        raise SystemExit(f"autotune benchmark: error: --ratios {text!r}: each in (0, 1e4]")
    return ratios


def _parse_iinoya_hotta(args: argparse.Namespace) -> tuple[list[float], list[float], Path | None]:
    """(table T/L, measured T/L, plot directory) of --iinoya-hotta; the flags that only it
    takes are refused without it."""
    if not args.iinoya_hotta:
        for flag, value in (("--measure", args.measure), ("--plot", args.plot)):
            if value is not None:
                raise SystemExit(f"autotune benchmark: error: {flag}: only with --iinoya-hotta")
        return [], [], None
    ratios = _ratios(args)
    measure = ratios if args.measure is None else _numbers("--measure", args.measure)
    lo, hi = MEASURE_RANGE
    if any(not (lo <= r <= hi) for r in measure):
        raise SystemExit(
            f"autotune benchmark: error: --measure {args.measure!r}: each in [{lo:g}, {hi:g}] "
            "(use --ratios for closed forms beyond)"
        )
    if not ratios and not measure:
        raise SystemExit("autotune benchmark: error: --ratios '': --iinoya-hotta needs a T/L")
    if args.plot is None:
        return ratios, measure, None
    if not args.plot.strip():
        raise SystemExit("autotune benchmark: error: --plot '': name a directory")
    check_runs_dir("--plot", args.plot)  # a directory, or one that can be made, writable
    return ratios, measure, Path(args.plot)


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
    if args.iinoya_hotta:
        return run_iinoya_hotta(*_parse_iinoya_hotta(args), as_json=args.json)
    _parse_iinoya_hotta(args)  # its flags are refused without it
    plants = [p for p in benchmark.suite() if args.plants in p.name]
    if not plants:
        raise SystemExit(f"autotune benchmark: error: --plants {args.plants!r}: no plant matches")
    started = time.perf_counter()
    outcomes = []
    for plant in plants:
        for level in noise:
            if "relay" in methods:
                outcomes.append(benchmark.run_relay(plant, level, args.seed))
            if "ramp" in methods:
                outcomes.append(benchmark.run_ramp(plant, level, args.seed))
    rows = [ih.iinoya_hotta_row(r) for r in ratios]
    elapsed = time.perf_counter() - started
    stats = summary(outcomes)
    if args.json:
        print(
            json_text.dumps(
                {
                    "tunes": [o.to_dict() for o in outcomes],
                    "summary_up_to_1pct_noise": stats,
                    "iinoya_hotta": [r.to_dict() for r in rows],
                    "seconds": elapsed,
                },
                indent=1,
            )
        )
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


# --- Iinoya & Hotta's three figures ---------------------------------------------------------


def _v(x: float | None, fmt: str = "7.4f") -> str:
    """A value in a table column, – for none."""
    width = int(fmt.split(".")[0]) if fmt[0].isdigit() else 7
    return f"{'–':>{width}}" if x is None or not math.isfinite(x) else format(x, fmt)


def _e(x: float | None) -> str:
    """A relative error in %, – for none."""
    return "      –" if x is None else f"{100 * x:+6.2f}%"


def _m(row: dict, key: str, status: str) -> str:
    """A measured value, or ``none`` where no setting gives a 25 %-damped response."""
    if row.get(status) in (ih.NOT_DOMINANT, ih.NO_CROSSING):
        return f"{'none':>7}"
    return _v(row.get(f"{key}_measured"))


def print_figures(figs: ih.Figures) -> None:
    """The three tables, their notes and the paper's turning points, as text."""
    print(
        "Iinoya & Hotta (1958), K·e^{-Ls}/(1+sT); eq. = the paper's closed form, meas. = the "
        "product's experiments\non K = 1, L = 1 s, T = T/L s (relay, step test, setpoint steps "
        "through the PID block): the setting where the response's\ndominant mode, read off its "
        "tail by a matrix pencil, decays by 0.25 per period (none: no setting gives a 25 %-damped"
        "\nresponse, the pair does not dominate); at the curve's own setting, DR = the whole "
        "response's first two crests (what a trend\nshows), mode = its dominant mode's decay "
        "ratio (the 25 % pair's is 0.25)\n"
    )
    print(
        "Fig. 1  P control: K₄ gives 25 % damping (eq. 7); ZN's rules K₀/2 and 1/(R·L) are "
        "K₀/K₄ = 2 and K₄·R·L = 1\n"
        f"{'T/L':>6} {'ω₄L':>6} | {'K₀/K₄ eq.':>9} {'meas.':>7} {'err':>7} | "
        f"{'K₄RL eq.':>9} {'meas.':>7} {'err':>7} | {'DR at K₄':>8} {'mode':>5} | "
        f"{'DR ZN K₀/2':>10} {'DR ZN 1/RL':>10}"
    )
    for r in figs.fig1:
        print(
            f"{r['t_over_l']:6g} {r['w4l']:6.3f} | {r['k0_over_k4']:9.4f} "
            f"{_m(r, 'k0_over_k4', 'k4_status')} {_e(r.get('k0_over_k4_error'))} | "
            f"{r['k4rl']:9.4f} {_m(r, 'k4rl', 'k4_status')} {_e(r.get('k4rl_error'))} | "
            f"{_v(r.get('decay_ratio_at_closed_form'), '8.3f')} "
            f"{_v(r.get('mode_decay_ratio_at_closed_form'), '5.3f')} | "
            f"{_v(r.get('decay_ratio_zn_ultimate'), '10.3f')} "
            f"{_v(r.get('decay_ratio_zn_reaction'), '10.3f')}"
        )
    print(
        "\nFig. 2  the ultimate point (eq. 5); ZN's two rules agree where K₀·R·L = 2 and "
        "τ₀/L = 4 (eq. 8; T/L → ∞: π/2 and 4)\n"
        f"{'T/L':>6} | {'K₀RL eq.':>9} {'meas.':>7} {'err':>7} | "
        f"{'τ₀/L eq.':>9} {'meas.':>7} {'err':>7}"
    )
    for r in figs.fig2:
        print(
            f"{r['t_over_l']:6g} | {r['k0rl']:9.4f} {_v(r.get('k0rl_measured'))} "
            f"{_e(r.get('k0rl_error'))} | {r['tau0']:9.4f} {_v(r.get('tau0_measured'))} "
            f"{_e(r.get('tau0_error'))}"
        )
    print(
        "\nFig. 3  T_I4/L at ZN's PI gain 0.9/(R·L) (eq. 12; ZN: 3.33) and T_D4/L at the PD "
        "gain 1.2/(R·L) (eq. 15; the paper: 0.36–0.37),\n        curve b (the higher ω) and "
        "b′ (the lower, above T/L ≈ 1.49)\n"
        f"{'T/L':>6} | {'T_I4/L eq.':>10} {'meas.':>7} {'err':>7} {'DR':>5} {'mode':>5} | "
        f"{'T_D4/L b eq.':>12} {'meas.':>7} {'err':>7} {'DR':>5} {'mode':>5} | "
        f"{'b′ eq.':>7} {'meas.':>7} {'err':>7} {'DR':>5} {'mode':>5}"
    )
    for r in figs.fig3:
        print(
            f"{r['t_over_l']:6g} | {r['ti4']:10.4f} {_m(r, 'ti4', 'ti4_status')} "
            f"{_e(r.get('ti4_error'))} {_v(r.get('decay_ratio_pi_at_closed_form'), '5.3f')} "
            f"{_v(r.get('mode_decay_ratio_pi_at_closed_form'), '5.3f')} | "
            f"{r['td4_upper']:12.4f} {_m(r, 'td4_upper', 'td4_upper_status')} "
            f"{_e(r.get('td4_upper_error'))} "
            f"{_v(r.get('decay_ratio_pd_upper_at_closed_form'), '5.3f')} "
            f"{_v(r.get('mode_decay_ratio_pd_upper_at_closed_form'), '5.3f')} | "
            f"{_v(r['td4_lower'])} {_m(r, 'td4_lower', 'td4_lower_status')} "
            f"{_e(r.get('td4_lower_error'))} "
            f"{_v(r.get('decay_ratio_pd_lower_at_closed_form'), '5.3f')} "
            f"{_v(r.get('mode_decay_ratio_pd_lower_at_closed_form'), '5.3f')}"
        )
    notes = [
        (row["t_over_l"], n)
        for rows in (figs.fig1, figs.fig2, figs.fig3)
        for row in rows
        for n in row["notes"]
    ]
    if notes:
        print("\nnotes:")
        for t_over_l, n in sorted(notes, key=lambda tn: tn[0]):
            print(f"  T/L = {t_over_l:g}: {n}")
    for failure in figs.failures:
        print(f"  not measured: {failure}")
    f = figs.findings
    print(
        "\nthe paper's turning points, solved:\n"
        f"  T_I4 = 3.33 L (ZN's) at T/L = {f['ti4_equals_zn_at_t_over_l']:.2f} (the paper: 60): "
        "below it ZN's integral time is longer than 25 % damping needs\n"
        f"  two PD settings above T/L = {f['pd_two_branches_above_t_over_l']:.3f} (the paper: "
        "1.43), where P alone at 1.2/(R·L) gives 25 %\n"
        "  the ideal PD's high-frequency roots decay slower than curve b's pair below T/L = "
        f"{f['pd_chain_slower_than_pair_below_t_over_l']:.3f}\n"
        f"  T/L → ∞: K₀/K₄ → {f['k0_over_k4_limit']:.4f}, K₄·R·L → {f['k4rl_limit']:.4f}, "
        f"T_I4/L → {f['ti4_limit']:.4f}, T_D4/L → {f['td4_upper_limit']:.4f} (b), "
        f"{f['td4_lower_limit']:.4f} (b′)"
    )


def _curve_grid(figs: ih.Figures) -> np.ndarray:
    """T/L of the plotted curves: 0.1–100 and every tabled T/L, log-spaced."""
    rows = [r["t_over_l"] for r in figs.fig1]
    return np.geomspace(min([0.1, *rows]), max([100.0, *rows]), 241)


PLANT = r"$K e^{-Ls}/(1+sT)$"
X_LABEL = "T/L (lag over dead time, dimensionless; log scale)"


def _log_t_over_l(ax: Axes) -> None:
    """A log T/L axis labelled 0.1, 1, 10, 100 (not 10⁻¹ …), with its grid."""
    from matplotlib.ticker import FuncFormatter

    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.grid(True, which="both", lw=0.4, alpha=0.5)


def _axes(fig: Figure, title: str, ylabel: str) -> Axes:
    ax = fig.subplots()
    _log_t_over_l(ax)
    ax.set_xlabel(X_LABEL)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    return ax


def _measured(
    ax: Axes, rows: list[dict], key: str, color: str, label: str, status: str | None = None
) -> None:
    """Measured points: filled on their curve (within the tolerance), open where off it; a
    cross on the curve where no setting gives a 25 %-damped response (``status``)."""
    on = [(r["t_over_l"], r[f"{key}_measured"]) for r in rows if _within(r, key)]
    off = [
        (r["t_over_l"], r[f"{key}_measured"])
        for r in rows
        if r.get(f"{key}_measured") is not None and not _within(r, key)
    ]
    none = [
        (r["t_over_l"], r[key])
        for r in rows
        if status and r.get(status) in (ih.NOT_DOMINANT, ih.NO_CROSSING)
    ]
    if on:
        ax.plot(*zip(*on, strict=True), "o", color=color, ms=6, label=f"{label}, measured")
    if off:
        ax.plot(
            *zip(*off, strict=True),
            "o",
            mfc="none",
            color=color,
            ms=8,
            mew=1.5,
            label=f"{label}, measured > {100 * ih.TOLERANCE:g} % off (see notes)",
        )
    if none:
        ax.plot(
            *zip(*none, strict=True),
            "x",
            color=color,
            ms=9,
            mew=2,
            label=f"{label}: no 25 %-damped response measured (the pair does not dominate)",
        )


def _within(row: dict, key: str) -> bool:
    err = row.get(f"{key}_error")
    return row.get(f"{key}_measured") is not None and err is not None and abs(err) <= ih.TOLERANCE


def _new_figure() -> Figure:
    # imported here: only --plot needs matplotlib (0.2 s of start-up)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 6), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def figure_1(figs: ih.Figures, c: dict[str, np.ndarray]) -> Figure:
    fig = _new_figure()
    ax = _axes(
        fig,
        f"Iinoya & Hotta (1958) Fig. 1 — P control of {PLANT}: the gain $K_4$ for 25 % damping",
        "ratio (dimensionless)",
    )
    x = c["t_over_l"]
    ax.plot(x, c["k0_over_k4"], color="tab:blue", label="(a) $K_0/K_4$, eqs. 5 and 7")
    ax.axhline(
        ih.ZN_P_ULTIMATE, color="tab:blue", ls="--", lw=1, label="ZN $K_1 = K_0/2$: $K_0/K_1$ = 2"
    )
    ax.plot(x, c["k4rl"], color="tab:red", label="(b) $K_4 M L/T = K_4 R L$, eq. 7")
    ax.axhline(
        ih.ZN_P_REACTION, color="tab:red", ls="--", lw=1, label="ZN $K_1 = 1/(RL)$: $K_1 RL$ = 1"
    )
    _measured(
        ax, figs.fig1, "k0_over_k4", "tab:blue", "$K_0/K_4$ (relay, closed loop)", "k4_status"
    )
    _measured(ax, figs.fig1, "k4rl", "tab:red", "$K_4 RL$ (closed loop, step test)", "k4_status")
    ax.set_ylim(0, min(6.0, float(np.nanmax(c["k4rl"])) * 1.05))
    ax.legend(fontsize=8, loc="upper right")
    ax.text(
        0.02,
        0.03,
        "$K_0/K_4$ < 2: ZN's $K_0/2$ damps more than 25 %; $K_4RL$ > 1: $1/(RL)$ is a smaller "
        "gain than 25 % needs",
        transform=ax.transAxes,
        fontsize=8,
    )
    return fig


def figure_2(figs: ih.Figures, c: dict[str, np.ndarray]) -> Figure:
    fig = _new_figure()
    ax = _axes(
        fig,
        f"Iinoya & Hotta (1958) Fig. 2 — the ultimate point of {PLANT} (eq. 5)",
        r"$K_0 RL$ and $\tau_0/L$ (dimensionless)",
    )
    x = c["t_over_l"]
    ax.plot(x, c["k0rl"], color="tab:blue", label="$K_0 RL$, eq. 5")
    ax.axhline(ih.ZN_K0RL, color="tab:blue", ls="--", lw=1, label="ZN (eq. 8): $K_0 RL$ = 2")
    ax.axhline(math.pi / 2, color="tab:blue", ls=":", lw=1, label=r"T/L → ∞: $\pi/2$")
    ax.plot(x, c["tau0"], color="tab:red", label=r"$\tau_0/L$, eq. 5")
    ax.axhline(
        ih.ZN_TAU0, color="tab:red", ls="--", lw=1, label=r"ZN (eq. 8), T/L → ∞: $\tau_0/L$ = 4"
    )
    _measured(ax, figs.fig2, "k0rl", "tab:blue", "$K_0 RL$ (relay $K_0$, step test $R$, $L$)")
    _measured(ax, figs.fig2, "tau0", "tab:red", r"$\tau_0/L$ (relay $\tau_0$, step test $L$)")
    ax.set_ylim(0, min(12.0, float(np.nanmax(c["k0rl"])) * 1.05))
    ax.legend(fontsize=8, loc="upper right")
    return fig


def figure_3(figs: ih.Figures, c: dict[str, np.ndarray]) -> Figure:
    fig = _new_figure()
    top, bottom = fig.subplots(2, 1, sharex=True)
    x = c["t_over_l"]
    for ax in (top, bottom):
        _log_t_over_l(ax)
    top.set_title(
        f"Iinoya & Hotta (1958) Fig. 3 — integral and derivative times for 25 % damping of {PLANT}",
        fontsize=10,
    )
    top.plot(x, c["ti4"], color="tab:blue", label="(a) $T_{I4}/L$ at $K = 0.9/(RL)$, eq. 12")
    top.axhline(ih.ZN_TI, color="tab:blue", ls="--", lw=1, label="ZN PI: $T_I/L$ = 3.33")
    meet = figs.findings["ti4_equals_zn_at_t_over_l"]
    top.axvline(meet, color="0.4", ls=":", lw=1)
    top.annotate(
        f"T/L = {meet:.1f}: below it ZN's $T_I$ is longer than needed",
        (meet, 1.0),
        xytext=(-8, 0),
        textcoords="offset points",
        ha="right",
        fontsize=8,
    )
    _measured(top, figs.fig3, "ti4", "tab:blue", "$T_{I4}/L$", "ti4_status")
    top.set_ylabel("$T_{I4}/L$ (dimensionless)")
    top.legend(fontsize=8, loc="upper left")
    ok = c["pd_dominated"]
    upper = c["td4_upper"]
    bottom.plot(x, np.where(ok, upper, np.nan), color="tab:red", label="(b) $T_{D4}/L$, eq. 15")
    bottom.plot(
        x,
        np.where(ok, np.nan, upper),
        color="tab:red",
        ls=":",
        label="(b) where the ideal PD's fast roots decay slower than the pair",
    )
    bottom.plot(x, c["td4_lower"], color="tab:purple", label="(b′) $T_{D4}/L$, eq. 15")
    bottom.axhspan(*ih.PAPER_TD, color="0.6", alpha=0.35, label="the paper's rule: 0.36–0.37")
    two = figs.findings["pd_two_branches_above_t_over_l"]
    bottom.axvline(two, color="tab:purple", ls=":", lw=1)
    bottom.annotate(
        f"b′ from T/L = {two:.2f}",
        (two, 0.03),
        xytext=(4, 0),
        textcoords="offset points",
        fontsize=8,
        color="tab:purple",
    )
    _measured(bottom, figs.fig3, "td4_upper", "tab:red", "$T_{D4}/L$ (b)", "td4_upper_status")
    _measured(bottom, figs.fig3, "td4_lower", "tab:purple", "$T_{D4}/L$ (b′)", "td4_lower_status")
    bottom.set_ylim(0, 1.0)
    bottom.set_ylabel("$T_{D4}/L$ at $K = 1.2/(RL)$ (dimensionless)")
    bottom.set_xlabel(X_LABEL)
    bottom.legend(fontsize=8, loc="upper right")
    return fig


def write_plots(figs: ih.Figures, directory: Path) -> list[Path]:
    """The three figures as PNG files in ``directory`` (made if missing)."""
    c = ih.curves(_curve_grid(figs))
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SystemExit(f"autotune benchmark: error: --plot {directory}: {err.strerror}") from None
    out = []
    for n, build in ((1, figure_1), (2, figure_2), (3, figure_3)):
        path = directory / f"iinoya_hotta_fig{n}.png"
        try:
            build(figs, c).savefig(path, dpi=110)
        except OSError as err:
            raise SystemExit(
                f"autotune benchmark: error: --plot {directory}: {err.strerror}"
            ) from None
        out.append(path)
    return out


def run_iinoya_hotta(
    ratios: list[float], measure: list[float], plot: Path | None, as_json: bool
) -> int:
    started = time.perf_counter()
    figs = ih.figures(ratios, measure)
    plots = write_plots(figs, plot) if plot is not None else []
    elapsed = time.perf_counter() - started
    if as_json:
        doc = figs.to_dict() | {"plots": [str(p) for p in plots], "seconds": elapsed}
        print(json_text.dumps(doc, indent=1, ensure_ascii=False))
        return 0
    print_figures(figs)
    for p in plots:
        print(f"wrote {p}")
    print(f"\n{len(figs.measured)} T/L measured in {elapsed:.1f} s")
    return 0
