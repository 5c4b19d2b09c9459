"""``autotune watch LOOP``: a loop's performance in normal operation, no test signal.

Watches the loop for ``--duration`` seconds of sim time and prints, over its samples in auto:
the IAE per unit time and the error's s.d. (PV units), the time at an output limit (%), the
output's travel (% and % per hour) and reversals, Hägglund's oscillation detector (the IAE
between zero crossings of the error against a·T_u/π, a = 1 % of the PV's span; more than 10
detections within 50 T_u is an oscillation, whose period is given) and the idle index
(Hägglund's: near +1 a sluggish answer to load disturbances); compared with the last tune's
verification when the tuner has one; and the flags (oscillating, sluggish, saturated,
degraded), each with its reason. ``--json``: one object, the ``LoopMonitor`` the tuner
publishes for the loops it tuned.

T_u is ``--period``, else the P_u of the loop's last tune (asked of the running tuner; for an
``autotune apply`` run, the P_u of the run it applied, from the change history), else the
loop's integral time Ti (Hägglund's stand-in), else 50 sample times; the output says which.
A lockstep plant only moves when told: with nobody holding the loop's lease, ``watch`` advances
it itself (advancing is not a test signal: nothing else is written). A loop a test holds is not
in normal operation: it is refused, and a watch a test interrupts stops there. In realtime it
only listens.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import zenoh

from services.autotuner.loop_client import LoopClient, PlantLost, wait_for_loop, wait_for_token
from services.autotuner.monitor.assessment import (
    Watcher,
    choose_period,
    gains_note,
    loop_watcher,
)
from services.autotuner.monitor.oscillation import SUPERVISION_PERIODS
from shared import json_text, keys, wire
from shared.cli import MAX_SECONDS, add_common_arguments, check_ids
from shared.errors import AutotuneError, ConfigError
from shared.history_file import HISTORY_FILE, of_loop, read_history
from shared.identity import auth_user
from shared.messages import LoopMonitor, ProcessSample, TuneResult
from shared.session import open_session, settings_from_args

HELP = "watch a loop in normal operation: IAE, saturation, travel, oscillation, idle index, flags"
CHUNK = 256  # samples per lockstep round trip
MAX_SAMPLES = 500_000  # samples one watch holds in memory (about 100 MB)
RESULT_TIMEOUT = 2.0  # s of wall time to ask a running tuner for the loop's last result


def seconds(text: str) -> float:
    """An argparse type: a finite number of seconds, > 0 and at most MAX_SECONDS (argparse
    names the flag in its complaint)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: not a number of seconds") from None
    if not math.isfinite(value) or not 0 < value <= MAX_SECONDS:
        raise argparse.ArgumentTypeError(
            f"{text}: must be a finite number of seconds, > 0 and at most {MAX_SECONDS:g}"
        )
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("loop", metavar="LOOP", help="loop id, e.g. hx1")
    parser.add_argument(
        "--duration",
        type=seconds,
        metavar="S",
        help=f"seconds of sim time to watch (default: {SUPERVISION_PERIODS:g} × T_u, the "
        "oscillation detector's supervision time)",
    )
    parser.add_argument(
        "--period",
        type=seconds,
        metavar="S",
        help="T_u, s: the ultimate period the detector's limit is set from (default: the P_u "
        "of the loop's last tune, else its integral time Ti, else 50 sample times)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--runs",
        default="runs",
        metavar="DIR",
        help="the logger's runs directory, read for the loop's last applied tune where no "
        "tuner has it (restarted since): its P_u and verification (default: %(default)s)",
    )
    parser.add_argument(
        "--wait",
        type=seconds,
        default=10.0,
        metavar="S",
        help="seconds to wait for the loop to appear on the bus (default: %(default)s)",
    )
    add_common_arguments(parser)


def last_result(session: zenoh.Session, prefix: str, loop: str) -> TuneResult | None:
    """The loop's last tune result, from a running tuner (None when no tuner shows up within
    RESULT_TIMEOUT, or it has none for the loop). A session just opened learns of the other
    peers' tokens as they arrive: waited for, not asked once."""
    if not wait_for_token(session, keys.tuner_alive(prefix, keys.ANY), RESULT_TIMEOUT):
        return None
    return wire.query_one(session, keys.tune_result(prefix, loop), TuneResult, RESULT_TIMEOUT)


def recorded_tune(runs: Path, prefix: str, loop: str) -> dict[str, Any] | None:
    """The loop's last applied tune as the logger's change history holds it (its ``tune``
    record), as the fields of a TuneResult the watch reads; None where none is on record.
    Why: a tuner restarted since the tune has no result to give, and the watch fell back to
    Ti for T_u (1,000 s against a P_u of 43 s: its detector 23 times too slow to see a limit
    cycle) and said "no applied tune to compare with" (helper trial)."""
    try:
        records = list(read_history(runs / HISTORY_FILE))
    except ConfigError:  # not a regular file there: nothing read
        return None
    tunes = [
        r
        for r in records
        if r.get("record") == "tune" and r.get("applied") is True and of_loop(r, loop, prefix)
    ]
    if not tunes:
        return None
    r = tunes[-1]
    return {
        "run_id": r.get("run_id"),
        "status": r.get("status"),
        "applied": True,
        "applied_from": r.get("applied_from"),
        "after": r.get("verification_after"),
        "chosen": r.get("chosen"),
        "noise": r.get("noise"),
        "pu": _period(r.get("pu")),
    }


def tuned_pu(runs: Path, prefix: str, last: dict[str, Any] | None) -> float | None:
    """The P_u behind the last tune ``last``: its own, or, for an ``autotune apply`` run
    (which identifies nothing, its P_u None), that of the run whose gains it applied, from
    the change history. Why: after the console's Apply (or ``autotune apply``) the watch
    took Ti for T_u (96 s against the relay's P_u of 43.7 s on hx1: its detector and IAE
    limit sized on twice the loop's period; helper trial)."""
    if last is None:
        return None
    pu = _period(last.get("pu"))
    source = last.get("applied_from")
    if pu is not None or not isinstance(source, str):
        return pu
    try:
        records = list(read_history(runs / HISTORY_FILE))
    except ConfigError:
        return None
    found = [
        r
        for r in records
        if r.get("record") == "tune"
        and r.get("run_id") == source
        and r.get("prefix", prefix) == prefix
    ]
    return _period(found[-1].get("pu")) if found else None


def _period(pu: Any) -> float | None:
    return float(pu) if isinstance(pu, int | float) and math.isfinite(pu) and pu > 0 else None


def collect(client: LoopClient, watcher: Watcher, samples: int) -> str | None:
    """Feed ``samples`` samples of the loop to ``watcher`` (advancing a lockstep loop in
    chunks); stops early, saying why, when a test takes the loop's lease."""
    got = 0
    while got < samples:
        try:
            batch = client.samples(min(CHUNK, samples - got))
        except PlantLost:
            if client.last_status.leased_by is None:
                raise
            batch = []
        status = client.last_status
        for s in batch:
            if status.leased_by is not None and s.t > status.t:
                break
            feed(watcher, s)
        got += len(batch)
        if status.leased_by is not None:
            return (
                f"a test took the loop ({status.leased_by}) at t = {status.t:.6g} s: the watch "
                "stopped there"
            )
    return None


def feed(watcher: Watcher, s: ProcessSample) -> None:
    watcher.feed(s.t, s.sp, s.pv, s.op, s.mode == "auto")


def run(args: argparse.Namespace) -> int:
    check_ids(args.prefix, loop=args.loop)
    settings = settings_from_args(args)
    with open_session(settings, args.wait) as session:
        wait_for_loop(session, args.prefix, args.loop, args.wait)
        result = last_result(session, args.prefix, args.loop)
        with LoopClient(
            session, args.prefix, args.loop, source="autotune-watch", user=auth_user(settings)
        ) as client:
            info, status = client.info, client.last_status
            if status.leased_by is not None:
                raise AutotuneError(
                    f"loop {args.loop} is held by {status.leased_by!r} for a test, not in normal "
                    "operation: watch it once it is released"
                )
            last = result.model_dump() if result is not None else None
            if last is None or not last.get("applied"):
                # no tuner remembers an applied tune (restarted since): the logger's record
                last = recorded_tune(Path(args.runs), args.prefix, args.loop) or last
            pu = tuned_pu(Path(args.runs), args.prefix, last)
            period, source = choose_period(args.period, pu, status.gains.ti, info.sample_time)
            if source == "given":
                source = "--period"
            duration = args.duration or SUPERVISION_PERIODS * period
            n = max(2, round(duration / info.sample_time))
            if n > MAX_SAMPLES:
                raise ConfigError(
                    f"--duration {duration:g}: {n} samples at {info.sample_time:g} s; at most "
                    f"{MAX_SAMPLES * info.sample_time:g} s for this loop"
                )
            watcher = loop_watcher(period, source, info, status, last)
            baseline = watcher.baseline
            stopped = collect(client, watcher, n)
            gains = client.last_status.gains
    assessment = watcher.report()
    if stopped:
        assessment.notes.append(stopped)
    if (fault := client.last_status.fault) is not None:
        # held in manual with its PV held: "not in auto" alone hid why (helper review)
        assessment.notes.append(f"the loop is FAULTED ({fault}): held in manual, its PV held")
    if (note := gains_note((gains.kc, gains.ti, gains.td), baseline)) is not None:
        assessment.notes.append(note)
    msg = LoopMonitor(loop=args.loop, node="watch", pv_units=info.pv_units, **assessment.to_dict())
    print(
        json_text.dumps(msg.model_dump(mode="json"), indent=2) if args.json else format_monitor(msg)
    )
    return 0


def _num(v: float | None, unit: str = "", fmt: str = ".4g") -> str:
    return "–" if v is None else f"{v:{fmt}}{unit}"


def format_monitor(m: LoopMonitor) -> str:
    """The figures, the comparison with the tune and the flags, as a person reads them."""
    u = f" {m.pv_units}" if m.pv_units else ""
    f = m.figures
    # (t − t_start spans n − 1 sample periods: a default watch of 50 T_u counts as one)
    full = (m.t - m.t_start) * m.samples / (m.samples - 1) if m.samples > 1 else 0.0
    watched = full / m.period if m.period > 0 else 0.0
    # the detector counts over 50 T_u: a shorter watch says how long it had (it said "0
    # detections within 50 T_u" of a 1–2 T_u watch, and of one that assessed nothing:
    # helper review)
    within = (
        f"within {SUPERVISION_PERIODS:g} T_u"
        if watched >= SUPERVISION_PERIODS * (1.0 - 1e-9)
        else f"in the {watched:.2g} T_u watched (counted over {SUPERVISION_PERIODS:g})"
    )
    osc = (
        f"{m.detections} detections {within} (limit {m.detection_limit}), IAE limit "
        f"{m.iae_limit:.3g}{u}·s"
        if m.auto_fraction > 0
        else "– (not in auto)"
    )
    if m.oscillating:
        osc += f": OSCILLATING, period {_num(m.oscillation_period, ' s')}"
    idle = (
        f"{m.idle_index:.2f} over {f.get('idle_seconds', 0):.4g} s of load disturbances"
        if m.idle_index is not None
        else "– (no load disturbance long enough)"
    )
    deadband = _num(f.get("reversal_deadband"), " %", ".3g")
    rows = [
        ("IAE per unit time", _num(m.iae_rate, u)),
        ("error s.d.", _num(m.error_std, u)),
        ("output at a limit", _num(m.saturation, " % of the time", ".3g")),
        ("output travel", f"{_num(m.travel, ' %')} ({_num(m.travel_rate, ' % per hour')})"),
        ("output reversals", f"{_num(m.reversals, '', 'd')} (beyond {deadband})"),
        ("oscillation detector", osc),
        ("idle index", idle),
    ]
    width = max(len(k) for k, _ in rows)
    head = (
        f"Watch of {m.loop}: t = {m.t_start:.6g} → {m.t:.6g} s, {m.samples} samples "
        f"({100 * m.auto_fraction:.0f} % in auto); T_u = {m.period:.4g} s ({m.period_source})"
    )
    lines = [head, *(f"  {k:<{width}}  {v}" for k, v in rows)]
    b = m.baseline
    if b:
        lines.append(
            f"Compared with the tune {b.get('run_id')}: output noise σ "
            f"{_num(b.get('op_noise'), ' %', '.3g')} then, {_num(f.get('op_noise'), ' %', '.3g')} "
            f"now; PV noise σ {_num(b.get('pv_noise'), u, '.3g')} then, "
            f"{_num(f.get('pv_noise'), u, '.3g')} now; the verification's decay ratio "
            f"{_num(b.get('decay_ratio'), '', '.2g')}, overshoot "
            f"{_num(b.get('overshoot'), ' %', '.3g')}"
        )
    if m.flags:
        lines += [f"{flag.upper()}: {why}" for flag, why in m.flags.items()]
    elif m.auto_fraction == 0:
        # nothing in auto, nothing judged: it said "No flags: not oscillating, sluggish,
        # saturated or degraded." of lvl2 in manual (helper trial)
        lines.append("Not assessed: the loop was not in auto (no flag means nothing here)")
    else:
        short = any(n.startswith("the oscillation detector watched") for n in m.notes)
        lines.append(
            "No flags: not sluggish, saturated, noisy or degraded; oscillation not judged "
            "(see the note)"
            if short
            else "No flags: not oscillating, sluggish, saturated, noisy or degraded."
        )
    lines += [f"  note: {n}" for n in m.notes]
    return "\n".join(lines)
