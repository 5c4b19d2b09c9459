"""autotune perf: speed and scale on this machine, measured side by side in one run.

Raw Zenoh ping-pong between two processes (the limit of any lockstep exchange), the relay tune
in this process (the numeric limit), lockstep tunes over the bus (one, then N at once through
one tuner and through N tuners), the CPU each service spends per lockstep sample, the realtime
plant's capacity (loops × rate kept at ≥ 99 % of real time), the logger's capacity with zero
drops against the raw MCAP writer, the wall time of `autotune demo`, and the wall time per
sample of the phases where the loop's PID is in charge (a ramp's trials, the verification)
over the bus against in this process (``perf_phases``; --source runs the services of another
source tree, for a before/after in one run). Ratios are printed beside the absolute figures:
machines differ. A benchmark, not a test; --size tiny takes seconds.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict
from pathlib import Path

from services.offline import perf, perf_phases
from shared import json_text

HELP = "measure speed and scale: bus limit, lockstep, CPU per sample, realtime, logger, demo"
KEEP = 0.99  # fraction of real time a realtime plant must keep
GIVE_UP = 0.9  # a realtime size below this: larger ones are not tried
PARTS = (*perf.PARTS, "phases")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="one JSON object on stdout")
    parser.add_argument(
        "--size",
        choices=tuple(perf.SIZES),
        default="normal",
        help="tiny: seconds, for the test suite; normal: about a minute (default)",
    )
    parser.add_argument(
        "--tunes", type=int, default=4, help="lockstep tunes at once, one tuner (default 4)"
    )
    parser.add_argument(
        "--tuners",
        type=int,
        default=None,
        help="the N tunes again on other loops, spread over this many tuner processes "
        "(default: as many as --tunes; 1: not measured)",
    )
    parser.add_argument(
        "--skip", default="", help=f"parts left out, comma-separated: {', '.join(PARTS)}"
    )
    parser.add_argument(
        "--source",
        type=Path,
        default=None,
        metavar="DIR",
        help="lockstep and phases: run the services from this source tree (an older "
        "checkout: its figures, measured the same way, beside this one's)",
    )


def _parse(args: argparse.Namespace) -> list[str]:
    if not 1 <= args.tunes <= 32:
        raise SystemExit(f"autotune perf: --tunes {args.tunes}: must be 1 to 32")
    if args.tuners is not None and not 1 <= args.tuners <= 32:
        raise SystemExit(f"autotune perf: --tuners {args.tuners}: must be 1 to 32")
    if args.source is not None and not (args.source / "services" / "cli.py").is_file():
        raise SystemExit(
            f"autotune perf: --source {args.source}: not a source tree (no services/cli.py)"
        )
    skip = [p.strip() for p in args.skip.split(",") if p.strip()]
    bad = [p for p in skip if p not in PARTS]
    if bad:
        raise SystemExit(
            f"autotune perf: --skip {args.skip!r}: unknown {', '.join(bad)} "
            f"(choose from {', '.join(PARTS)})"
        )
    return [p for p in PARTS if p not in skip]


def measure(
    parts: list[str],
    size: perf.Size,
    tunes: int,
    log=None,
    tuners: int | None = None,
    source: Path | None = None,
) -> dict:
    """Every part asked for, then the ratios between them: one JSON-ready dict."""
    out: dict = {}

    def note(text: str) -> None:
        if log is not None:
            print(text, file=log, flush=True)

    if "pingpong" in parts:
        note("raw zenoh ping-pong…")
        out["pingpong"] = asdict(perf.ping_pong(size.pingpong_count))
    if "inprocess" in parts:
        note("in-process relay tune…")
        out["inprocess"] = asdict(perf.in_process())
    if "lockstep" in parts:
        spread = tunes if tuners is None else tuners
        note(
            f"lockstep over the bus: one tune, then {tunes} at once"
            + (f", then {tunes} through {spread} tuners…" if spread > 1 else "…")
        )
        out["lockstep"] = asdict(perf.lockstep(tunes, spread, source=source))
    if "phases" in parts:
        note("closed-loop phases (ramp trials, verification), over the bus and in process…")
        out["phases"] = asdict(perf_phases.phases(source))
    if "realtime" in parts:
        rows = []
        for loops, rate in size.realtime:
            note(f"realtime plant, {loops} loops × {rate:g}/s…")
            r = perf.realtime(loops, rate, size.realtime_seconds)
            rows.append({**asdict(r), "samples_per_s": r.samples_per_s})
            if r.kept < GIVE_UP:
                break
        kept = [r for r in rows if r["kept"] >= KEEP]
        best = max(kept, key=lambda r: r["loops"] * r["rate"], default=None)
        out["realtime"] = {
            "sizes": rows,
            "capacity_samples_per_s": best["loops"] * best["rate"] if best else 0.0,
        }
    if "logger" in parts:
        note("logger capacity and the raw mcap writer…")
        out["logger"] = asdict(perf.logger_capacity(size.logger_rates, size.logger_seconds))
    if "demo" in parts:
        note("autotune demo…")
        out["demo"] = asdict(perf.demo())
    out["ratios"] = ratios(out)
    return out


def ratios(out: dict) -> dict[str, float]:
    """The figures against their limits, where both were measured."""
    r: dict[str, float] = {}
    ls, pp, ip = out.get("lockstep"), out.get("pingpong"), out.get("inprocess")
    if ls and pp:
        r["lockstep_one_over_pingpong"] = ls["one"]["rate"] / pp["rate"]
    if ls:
        r["lockstep_many_over_one"] = ls["many"]["rate"] / ls["one"]["rate"]
        if ls.get("many_tuners"):
            r["lockstep_many_tuners_over_one"] = ls["many_tuners"]["rate"] / ls["one"]["rate"]
    if ls and ip:
        r["lockstep_one_over_inprocess"] = ls["one"]["rate"] / ip["rate"]
    ph = out.get("phases")
    for name in ("trials", "verify"):  # wall per sample in process over that on the bus
        if ph and name in ph["bus"] and name in ph["inprocess"]:
            bus, local = ph["bus"][name], ph["inprocess"][name]
            r[f"{name}_bus_over_inprocess"] = bus["rate"] / local["rate"]
        if ph and name in (ph.get("bus_warm") or {}) and name in ph["inprocess"]:
            bus, local = ph["bus_warm"][name], ph["inprocess"][name]
            r[f"{name}_bus_warm_over_inprocess"] = bus["rate"] / local["rate"]
        for where in ("bus", "bus_warm") if ph else ():  # the same, while the samples flow
            bus, local = (ph.get(where) or {}).get(name), ph["inprocess"].get(name)
            if bus and local and bus.get("flow_us_per_sample") and local.get("flow_us_per_sample"):
                r[f"{name}_{where}_over_inprocess_flowing"] = (
                    local["flow_us_per_sample"] / bus["flow_us_per_sample"]
                )
    lg = out.get("logger")
    if lg and lg["raw_writer"] > 0:
        r["logger_over_raw_writer"] = lg["capacity"] / lg["raw_writer"]
    return r


def _print(out: dict, size: str, seconds: float) -> None:
    p = print
    p(f"autotune perf ({size}), {seconds:.0f} s on this machine")
    if "pingpong" in out:
        x = out["pingpong"]
        p(
            f"  raw zenoh ping-pong        {x['rate']:9.0f} round trips/s  "
            f"({x['payload_bytes']} B JSON, {x['round_trips']} round trips; {x['how']})"
        )
    if "inprocess" in out:
        x = out["inprocess"]
        p(
            f"  in-process relay tune      {x['rate']:9.0f} samples/s      "
            f"(hx1, {x['samples']:.0f} samples in {x['wall']:.2f} s, {x['status']}; no bus)"
        )
    if "lockstep" in out:
        x = out["lockstep"]
        rows = [("one", "one tune"), ("many", f"{x['many']['loops']} tunes at once")]
        if x.get("many_tuners"):
            rows.append(("many_tuners", f"{x['many_tuners']['loops']}, N tuners"))
        for k, what in rows:
            y = x[k]
            statuses = ", ".join(sorted(set(y["statuses"])))
            p(
                f"  lockstep, {what:<17}{y['rate']:9.0f} samples/s      "
                f"({y['samples']:.0f} samples in {y['wall']:.2f} s on the bus, first progress "
                f"to last result; submitted to last result {y['submit_wall']:.2f} s; {statuses})"
            )
        cpu = x["cpu_us_per_sample"]
        parts = ", ".join(f"{n} {v:.0f}" for n, v in cpu.items())
        p(f"  CPU per lockstep sample    {sum(cpu.values()):9.0f} µs in all     ({parts} µs)")
    if "phases" in out:
        x = out["phases"]
        where_label = (("bus", "bus"), ("bus_warm", "bus, warm"), ("inprocess", "in-process"))
        for where, label in where_label:
            for name, what in (("trials", "ramp trials"), ("verify", "verification")):
                y = (x.get(where) or {}).get(name)
                if y:
                    first = " (a fresh tuner's first tune)" if where == "bus" else ""
                    flow = y.get("flow_us_per_sample")
                    p(
                        f"  {what + ', ' + label:<27}{y['rate']:9.0f} samples/s      "
                        f"({y['us_per_sample']:.1f} µs per sample, {y['samples']:.0f} samples"
                        + (f"; {flow:.1f} µs while they flow" if flow else "")
                        + (
                            f"; services from {x['source']}, {x['status']}{first})"
                            if where != "inprocess"
                            else ")"
                        )
                    )
    if "realtime" in out:
        x = out["realtime"]
        for r in x["sizes"]:
            p(
                f"  realtime {r['loops']:>5} × {r['rate']:<4g}/s   keeps {100 * r['kept']:6.1f} % "
                f"of real time (slowest loop; mean {100 * r['kept_mean']:.1f} %), "
                f"{r['overruns']} overruns, {100 * r['cpu']:.0f} % of a core"
            )
        p(
            f"  realtime capacity          {x['capacity_samples_per_s']:9.0f} samples/s  "
            f"(largest loops × rate tried kept at ≥ {100 * KEEP:g} %)"
        )
    if "logger" in out:
        x = out["logger"]
        for t in x["trials"]:
            p(
                f"  logger at {t['rate']:>7.0f}/s         sent {t['sent']} at "
                f"{t['send_rate']:.0f}/s, wrote {t['written']}, dropped {t['dropped']}, "
                f"drained in {t['drain']:.2f} s: {'kept up' if t['kept_up'] else 'did not'}"
                + ("" if t["reached"] else " (the sender fell short of the rate)")
            )
        bound = "≥" if x["at_least"] else " "
        p(
            f"  logger capacity           {bound}{x['capacity']:9.0f} samples/s      "
            f"(highest rate kept up with, zero drops; ≥: the sender's or the sizes' limit; "
            f"raw mcap writer {x['raw_writer']:.0f}/s)"
        )
    if "demo" in out:
        x = out["demo"]
        p(f"  autotune demo              {x['wall']:9.1f} s              ({x['status']})")
    if out["ratios"]:
        p("ratios:")
        for k, v in out["ratios"].items():
            p(f"  {k:<32}{v:8.2f}")


def run(args: argparse.Namespace) -> int:
    parts = _parse(args)
    t0 = time.perf_counter()
    out = measure(parts, perf.SIZES[args.size], args.tunes, sys.stderr, args.tuners, args.source)
    seconds = time.perf_counter() - t0
    if args.json:
        print(json_text.dumps({"size": args.size, "seconds": seconds, **out}, indent=1))
        return 0
    _print(out, args.size, seconds)
    return 0
