"""``autotune set LOOP [--mode auto|manual] [--sp V] [--op V] [--kc X] [--ti S|none] [--td S]
[--beta B]``: the faceplate's writes to a running loop, each confirmed by the plant.

Values (checked before anything is sent; a bad one is refused in one line naming the flag,
exit 2, and nothing moves):

  --sp V     setpoint, PV units, within the loop's PV range
  --op V     manual output, %, within the loop's output limits; only in manual: with the loop
             in auto give --mode manual too (the plant refuses a manual output in auto)
  --kc X     controller gain, % of output per PV unit, > 0, and at most 1000 % of output per
             % of span (Kc·span/100 ≤ 1000, a proportional band of at least 0.1 % of span):
             above that a 0.1 % error drives the output across its whole range, the valve
             bangs between its limits on the noise, and it is a slip of the keyboard or of the
             units (% per % for % per PV unit) rather than a tuning. (A check of this
             command's: the plant itself refuses only a Kc that is no control at all, 0 or
             one whose proportional band is no number, and gains beyond floating-point range)
  --ti S     integral time, s, at least the loop's sample time (shorter, each sample's
             integral step is more than Kc times the error: the output slams); `--ti none`
             turns integral action off (P or PD with a manual reset). 0 is refused: Ti → 0 is
             not "off" but infinite integral action
  --td S     derivative time, s, ≥ 0 (0: no derivative action)
  --beta B   setpoint weight on proportional action, 0–1
  Gains not given are kept from the loop's present ones (its status), so `--kc 3` changes Kc
  only; the derivative filter N is always kept. NaN and infinities are refused everywhere.

Order of the writes, each sent and confirmed (a sync) before the next:

  1. --mode manual   the output stays where it is
  2. --op            in manual: moves the output to V
  3. gains           the plant's PID block rebases its integral term so that the output does
                     not move; a setpoint written next is then answered by the new gains
                     (with --beta 0 there is no proportional kick)
  4. --sp            in auto the output moves at once by Kc·β·ΔSP (proportional action on the
                     setpoint; derivative acts on the PV only); in manual it does not move
  5. --mode auto     last: the switch is bumpless (the integral term is rebased at the present
                     output), so `--mode auto --sp 60` on a loop in manual writes the setpoint
                     first and the loop starts from where it is, integral action taking the PV
                     to 60 without a proportional kick. If the loop tracked its PV with its
                     setpoint in manual meanwhile, the setpoint is written once more in auto.

The plant refuses any write while a tuning run or step test holds the loop's lease (naming
the holder), an output or auto on a faulted loop, a Kc of 0 (no control at all) and gains
beyond floating-point range. At the first refusal nothing more is sent; what was applied
before it stays applied, and the
report says which writes were applied, which was refused with the plant's reason, and which
were not sent. The commands' source label is `autotune-set` (the plant's status names it in
`by_source`, and the session's Zenoh user, if any, in `by_user`).

Exit codes: 0 every write confirmed by the plant; 1 the plant refused one (the report says
what was applied); 2 a bad value, an unknown loop, or a plant that does not answer.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field
from typing import Literal

from services.autotuner.commands.loops import seconds
from services.autotuner.loop_client import (
    CommandRefused,
    LoopClient,
    PlantLost,
    wait_for_loop,
)
from services.autotuner.recorder_watch import unrecorded_change
from shared.cli import add_common_arguments, check_ids
from shared.control.forms import MAX_KC_PERCENT, kc_percent, kc_problem
from shared.errors import ConfigError, one_line
from shared.identity import auth_user
from shared.messages import (
    Command,
    GainsCommand,
    LoopStatus,
    ModeCommand,
    OutputCommand,
    PidGains,
    SetpointCommand,
)
from shared.session import open_session, settings_from_args

HELP = "write a loop's mode, setpoint, output or gains, bumplessly, confirmed by the plant"

SOURCE = "autotune-set"  # the source label of every command `set` sends
DEFAULT_TIMEOUT = 5.0  # s: for the loop to appear, and for each write's confirmation
NO_INTEGRAL = "none"  # `--ti none`: no integral action (PidGains.ti = None)
EXIT_REFUSED = 1


# --- values -----------------------------------------------------------------------------------


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text}: must be a finite number")
    return value + 0.0  # -0 is 0 (it was sent, and shown, as "-0")


def finite(text: str) -> float:
    """--sp, --op: any finite number (the loop's ranges are checked once it is read)."""
    return _number(text)


def gain(text: str) -> float:
    """--kc: a finite number > 0, % of output per PV unit."""
    value = _number(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text}: must be > 0 % per PV unit")
    return value


def integral_time(text: str) -> float | str:
    """--ti: a finite number of seconds > 0, or ``none`` (no integral action)."""
    if text.strip().lower() == NO_INTEGRAL:
        return NO_INTEGRAL
    try:
        value = _number(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: must be a finite number of seconds > 0, or none (no integral action)"
        ) from None
    if not value > 0:
        raise argparse.ArgumentTypeError(
            f"{text}: must be > 0 s (use --ti none for no integral action)"
        )
    return value


def derivative_time(text: str) -> float:
    """--td: a finite number of seconds ≥ 0."""
    value = _number(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"{text}: must be ≥ 0 s")
    return value


def weight(text: str) -> float:
    """--beta: a finite number 0–1."""
    value = _number(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"{text}: must lie in 0–1")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("loop", metavar="LOOP", help="loop id, e.g. hx1")
    # --mode is the loop's here, as on a faceplate: the Zenoh session's mode keeps -m only
    # (this group resolves the clash by taking --mode from the Zenoh flag added before it)
    writes = parser.add_argument_group(
        "writes (in the order above, each confirmed by the plant)", conflict_handler="resolve"
    )
    writes.add_argument("--sp", type=finite, metavar="V", help="setpoint, PV units")
    writes.add_argument("--op", type=finite, metavar="V", help="manual output, %% (manual only)")
    writes.add_argument("--kc", type=gain, metavar="X", help="controller gain, %% per PV unit")
    writes.add_argument(
        "--ti",
        type=integral_time,
        metavar="S|none",
        help="integral time, s; none: no integral action",
    )
    writes.add_argument("--td", type=derivative_time, metavar="S", help="derivative time, s")
    writes.add_argument("--beta", type=weight, metavar="B", help="setpoint weight, 0–1")
    parser.add_argument(
        "--timeout",
        type=seconds,
        default=DEFAULT_TIMEOUT,
        metavar="S",
        help="seconds to wait for the loop to appear and for each write's confirmation "
        "(default: %(default)s)",
    )
    add_common_arguments(parser)
    writes.add_argument(
        "--mode",
        dest="loop_mode",
        choices=("auto", "manual"),
        help="switch the loop to auto or manual (the Zenoh session's mode is -m here)",
    )


@dataclass(frozen=True)
class Asked:
    """What the user asked for; None: not given. ``ti`` is NO_INTEGRAL for ``--ti none``."""

    mode: Literal["auto", "manual"] | None = None
    sp: float | None = None
    op: float | None = None
    kc: float | None = None
    ti: float | str | None = None
    td: float | None = None
    beta: float | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Asked:
        return cls(args.loop_mode, args.sp, args.op, args.kc, args.ti, args.td, args.beta)

    @property
    def gains_given(self) -> bool:
        return any(v is not None for v in (self.kc, self.ti, self.td, self.beta))

    def check(self) -> None:
        """ConfigError if nothing is asked; the values themselves were checked on parsing."""
        if self.mode is None and self.sp is None and self.op is None and not self.gains_given:
            raise ConfigError("nothing to set: give --mode, --sp, --op, --kc, --ti, --td or --beta")


@dataclass(frozen=True)
class Write:
    """One write: what it is (``mode``, ``output``, ``gains``, ``setpoint``), the change in
    words, and the command."""

    what: str
    change: str
    cmd: Command


def _ti(ti: float | None) -> str:
    return "none" if ti is None else f"{ti:.6g} s"


def new_gains(asked: Asked, present: PidGains) -> PidGains:
    """The present gains with those asked for replaced (``--ti none``: no integral)."""
    update = {
        name: value
        for name, value in (("kc", asked.kc), ("td", asked.td), ("beta", asked.beta))
        if value is not None
    }
    if asked.ti is not None:
        update["ti"] = None if asked.ti == NO_INTEGRAL else float(asked.ti)
    return PidGains(**{**present.model_dump(), **update})


def _mode_change(now: str, asked: str) -> str:
    """``manual → auto``, or ``auto (already)`` where the loop is in that mode (it read
    "auto → auto applied")."""
    return f"{now} → {asked}" if now != asked else f"{asked} (already)"


def gains_change(asked: Asked, old: PidGains, new: PidGains) -> str:
    """``Kc 6.973 → 3, Ti 96.09 s → none (Td 6.933 s, β 1 kept)``."""
    items = [
        ("Kc", asked.kc is not None, f"{old.kc:.6g}", f"{new.kc:.6g}"),
        ("Ti", asked.ti is not None, _ti(old.ti), _ti(new.ti)),
        ("Td", asked.td is not None, f"{old.td:.6g} s", f"{new.td:.6g} s"),
        ("β", asked.beta is not None, f"{old.beta:.6g}", f"{new.beta:.6g}"),
    ]
    changed = ", ".join(f"{n} {a} → {b}" for n, given, a, b in items if given)
    kept = ", ".join(f"{n} {a}" for n, given, a, _ in items if not given)
    return changed + (f" ({kept} kept)" if kept else "")


def plan(
    asked: Asked, status: LoopStatus, pv_units: str, sample_time: float | None = None
) -> list[Write]:
    """The writes in the order they are sent (see the module doc), or ConfigError naming the
    flag whose value the loop cannot take: an output outside its limits or while it stays in
    auto, a setpoint outside its PV range, an integral time shorter than the loop's
    ``sample_time`` (s)."""
    asked.check()
    loop, u = status.loop, f" {pv_units}" if pv_units else ""
    if asked.op is not None:
        lo, hi = status.op_limits
        if not lo <= asked.op <= hi:
            raise ConfigError(
                f"--op {asked.op:g}: outside the loop's output limits [{lo:g}, {hi:g}] %"
            )
        if status.mode == "auto" and asked.mode != "manual":  # --op is written in manual
            # a loop a run holds takes neither (following "add --mode manual" was refused
            # for the lease: helper trial): said first
            held = (
                f", and {status.leased_by!r} holds its lease (a run): nothing is written to it "
                "until that ends; then add --mode manual"
                if status.leased_by
                else ": add --mode manual"
            )
            raise ConfigError(
                f"--op {asked.op:g}: {loop} is in auto, where the plant takes no manual "
                f"output{held}"
            )
    if asked.sp is not None:
        lo, hi = status.pv_range
        if not lo <= asked.sp <= hi:
            raise ConfigError(f"--sp {asked.sp:g}: outside the loop's PV range [{lo:g}, {hi:g}]{u}")
    if asked.kc is not None:
        check_kc(asked.kc, status.pv_range, u)
    ti = asked.ti if isinstance(asked.ti, float | int) else None  # not `none`
    if ti is not None and sample_time and ti < sample_time:
        # each sample's integral step, Kc·T/Ti of the error, is then more than Kc times it:
        # `--ti 0.001` took hx1's output from 40 % to 0 % in three samples
        raise ConfigError(
            f"--ti {ti:g}: shorter than the loop's sample time ({sample_time:g} s): each "
            "sample's integral step would be more than Kc times the error and slam the "
            f"output; at least {sample_time:g} s (or --ti none)"
        )
    writes: list[Write] = []
    if asked.mode == "manual":
        writes.append(
            Write(
                "mode", _mode_change(status.mode, "manual"), ModeCommand(loop=loop, mode="manual")
            )
        )
    if asked.op is not None:
        writes.append(
            Write(
                "output",
                f"{status.op:.6g} → {asked.op:.6g} %",
                OutputCommand(loop=loop, op=asked.op),
            )
        )
    if asked.gains_given:
        gains = new_gains(asked, status.gains)
        writes.append(
            Write(
                "gains",
                gains_change(asked, status.gains, gains),
                GainsCommand(loop=loop, gains=gains),
            )
        )
    if asked.sp is not None:
        writes.append(
            Write(
                "setpoint",
                f"{status.sp:.6g} → {asked.sp:.6g}{u}",
                SetpointCommand(loop=loop, sp=asked.sp),
            )
        )
    if asked.mode == "auto":
        writes.append(
            Write("mode", _mode_change(status.mode, "auto"), ModeCommand(loop=loop, mode="auto"))
        )
    return [
        Write(w.what, w.change, w.cmd.model_copy(update={"source": SOURCE, "t": status.t}))
        for w in writes
    ]


def check_kc(kc: float, pv_range: tuple[float, float], units: str, what: str = "--kc") -> None:
    """ConfigError for a gain that is no control at all (``kc_problem``: 0, or a proportional
    band that is no number) or above ``MAX_KC_PERCENT`` % per % of the loop's span (``what``:
    where the gain comes from, as the message names it)."""
    span = pv_range[1] - pv_range[0]
    # 1e-320 was taken, shown as "PB inf %": a gain whose proportional band is no number;
    # the plant refuses these too (and Kc 0), in the same words
    problem = kc_problem(kc, span)
    if problem:
        raise ConfigError(f"{what} {kc:g}: {problem}")
    pct = kc_percent(kc, span)
    if pct is not None and pct > MAX_KC_PERCENT:
        raise ConfigError(
            f"{what} {kc:g}: {pct:.8g} % of output per % of span (a proportional band of "
            f"{100.0 / pct:.2g} % of the {span:g}{units} span), above the {MAX_KC_PERCENT:g} "
            f"% per % `set` takes: Kc is in % of output per PV unit, at most "
            f"{rounded_down(100.0 * MAX_KC_PERCENT / span)} here"
        )


def rounded_down(x: float, digits: int = 4) -> str:
    """``x`` to ``digits`` significant figures, rounded down: a most that the check itself
    takes (666.67 printed "at most 666.7", which it refused: helper trial)."""
    if not (x > 0 and math.isfinite(x)):
        return f"{x:g}"
    unit = 10.0 ** (math.floor(math.log10(x)) - digits + 1)
    return f"{math.floor(x / unit) * unit:.{digits}g}"


# --- running them -----------------------------------------------------------------------------


@dataclass
class Outcome:
    """What became of the writes: applied (in order); the one refused with the plant's reason,
    or the one in flight when the plant was lost (``lost``: why), unconfirmed; those not
    sent; the loop's last confirmed status; notes."""

    applied: list[Write]
    status: LoopStatus
    refused: tuple[Write, str] | None = None
    unconfirmed: Write | None = None
    lost: str | None = None
    not_sent: list[Write] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _send(client: LoopClient, w: Write, out: Outcome, rest: list[Write]) -> bool:
    """Send ``w`` and wait for the plant's confirmation; False (``out`` says why) if it was
    refused or the plant stopped answering, ``rest`` then not sent."""
    try:
        out.status = client.command(w.cmd)
    except CommandRefused as err:
        out.refused = (w, str(err).removeprefix(f"loop {client.loop}: "))
    except PlantLost as err:
        out.unconfirmed, out.lost = w, str(err)
    else:
        out.applied.append(w)
        return True
    out.not_sent = list(rest)
    return False


def execute(client: LoopClient, writes: list[Write]) -> Outcome:
    """Send the writes in order, each confirmed by a sync; stop at the first refusal, or
    when the plant stops answering. A setpoint written before a switch to auto that the
    loop's setpoint tracking overwrote meanwhile (a realtime clock ran a sample between the
    two) is written once more, in auto."""
    out = Outcome([], client.last_status)
    for i, w in enumerate(writes):
        if not _send(client, w, out, writes[i + 1 :]):
            return out
    sp = next((w.cmd.sp for w in writes if isinstance(w.cmd, SetpointCommand)), None)
    if sp is None or out.status.sp == sp:
        return out
    if out.status.mode == "auto" and writes[-1].what == "mode":
        again = SetpointCommand(loop=client.loop, sp=sp, source=SOURCE, t=out.status.t)
        if _send(client, Write("setpoint", f"→ {sp:.6g} once more, in auto", again), out, []):
            out.notes.append("the loop's setpoint tracked its PV in manual before the switch")
    else:
        out.notes.append(
            f"the loop tracks its PV with its setpoint in manual: SP now {out.status.sp:.6g}"
        )
    return out


def state_line(status: LoopStatus, pv_units: str, label: str = "now") -> str:
    """``hx1 now: auto, SP 60 degC, PV 59.91 degC, OP 40.67 %; Kc 6.973, Ti 96.09 s, …``."""
    u = f" {pv_units}" if pv_units else ""
    g = status.gains
    return (
        f"{status.loop} {label}: {status.mode}, SP {status.sp:.6g}{u}, PV {status.pv:.6g}{u}, "
        f"OP {status.op:.6g} %; Kc {g.kc:.6g}, Ti {_ti(g.ti)}, Td {g.td:.6g} s, β {g.beta:.6g}"
        f" (t = {status.t:.6g} s)"
    )


def format_outcome(out: Outcome, pv_units: str) -> str:
    """The report: every write with what became of it, then the loop as it now is."""
    rows = [(w.what, w.change, "applied") for w in out.applied]
    if out.refused is not None:
        w, reason = out.refused
        # the plant's reason names the command's kind once ("mode refused: the loop is
        # faulted …"); its "kind: " before it said it twice (helper review)
        kind, sep, rest = reason.partition(": ")
        if sep and rest.startswith(f"{kind} refused"):
            reason = rest
        rows.append((w.what, w.change, f"REFUSED by the plant: {reason}"))
    if out.unconfirmed is not None:
        rows.append((out.unconfirmed.what, out.unconfirmed.change, "sent, not confirmed"))
    rows += [(w.what, w.change, "not sent") for w in out.not_sent]
    width = max(len(c) for _, c, _ in rows)
    lines = [f"{out.status.loop}: writes from {SOURCE}"]
    lines += [f"  {what:<9} {change:<{width}}  {result}" for what, change, result in rows]
    lines += [f"  note: {n}" for n in out.notes]
    lines.append(state_line(out.status, pv_units, "last confirmed" if out.lost else "now"))
    return "\n".join(lines)


def refusal_line(out: Outcome) -> str:
    """The one line for stderr when the plant refused a write."""
    assert out.refused is not None
    w, reason = out.refused
    applied = ", ".join(a.what for a in out.applied) or "nothing"
    tail = f"; not sent: {', '.join(n.what for n in out.not_sent)}" if out.not_sent else ""
    return (
        f"autotune set: {out.status.loop}: {w.what} refused by the plant: {one_line(reason)} "
        f"(applied before it: {applied}{tail})"
    )


def run(args: argparse.Namespace) -> int:
    asked = Asked.from_args(args)
    asked.check()
    check_ids(args.prefix, loop=args.loop)
    settings = settings_from_args(args)
    with open_session(settings, args.timeout) as session:
        wait_for_loop(session, args.prefix, args.loop, args.timeout)
        with LoopClient(
            session,
            args.prefix,
            args.loop,
            source=SOURCE,
            timeout=args.timeout,
            user=auth_user(settings),
        ) as client:
            units = client.info.pv_units
            out = execute(client, plan(asked, client.last_status, units, client.info.sample_time))
            gains = any(isinstance(w.cmd, GainsCommand) for w in out.applied)
            unrecorded = unrecorded_change(session, args.prefix, args.loop) if gains else None
    print(format_outcome(out, units))
    if unrecorded:
        print(unrecorded, file=sys.stderr)
    if out.lost is not None:
        raise PlantLost(out.lost)
    if out.refused is not None:
        print(refusal_line(out), file=sys.stderr)
        return EXIT_REFUSED
    return 0
