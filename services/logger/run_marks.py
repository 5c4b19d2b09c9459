"""The marks of a recorded run on its sim-time axis, each with the label its legend shows:
relay switches, relay cycles, the relay's amplitude growing, the start of its stage 2, ramp
trials with their Kc, the step test's output steps, and per verification the gains applied,
the setpoint step and the load step. Pure: from the decoded messages' own sim time ``t``
(never the file's log time, which may be wall-clock)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from shared.control.forms import unit
from shared.messages import (
    DisturbanceCommand,
    GainsCommand,
    PidGains,
    SetpointCommand,
    TuneProgress,
    TunerEvent,
    verify_message,
)

LOAD = "load"  # the disturbance input the verification steps (tuning._verify)


@dataclass(frozen=True)
class Mark:
    t: float  # s, sim time
    # "switch", "cycle", "relay amplitude", "stage 2", "stage 2 again", "trial", "output step"
    kind: str
    label: str


def _num(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def experiment_marks(events: Sequence[TunerEvent], units: str) -> list[Mark]:
    """The experiment's marks in time order: each relay switch (to its output), each cycle
    closed (its number), stage 2's start (and its setting again, when it got stuck: never
    its end, abandoned or out of patience), each ramp trial (its number and Kc, % per PV
    unit), each output step of a step test (to its output, %)."""
    out = []
    for e in events:
        d = e.data
        if e.kind == "switch":
            op = _num(d.get("op"))
            out.append(Mark(e.t, "switch", f"relay to {op:.4g} %" if op is not None else "relay"))
        elif e.kind == "cycle":
            out.append(Mark(e.t, "cycle", f"cycle {d.get('n')}"))
        elif e.kind == "stage" and d.get("stage") == 2 and d.get("rearmed"):
            out.append(Mark(e.t, "stage 2 again", "stage 2 set again"))
        elif e.kind == "stage" and d.get("stage") == 2 and "level" in d:  # its start
            out.append(Mark(e.t, "stage 2", "stage 2"))
        elif e.kind == "amplitude":  # the relay's d grew (its cycle rode on the hysteresis)
            old, new = _num(d.get("from")), _num(d.get("relay_amplitude"))
            text = (
                f"relay amplitude {old:.3g} → {new:.3g} %"
                if old is not None and new is not None
                else "relay amplitude grew"
            )
            out.append(Mark(e.t, "relay amplitude", text))
        elif e.kind == "step":
            op = _num(d.get("op"))
            text = f"output step to {op:.4g} %" if op is not None else "output step"
            out.append(Mark(e.t, "output step", text))
        elif e.kind == "trial":
            kc = _num(d.get("kc"))
            kc_s = f"Kc {kc:.4g} %/{unit(units)}" if kc is not None else "Kc ?"
            out.append(Mark(e.t, "trial", f"trial {d.get('n')}: {kc_s}"))
    return sorted(out, key=lambda m: m.t)


@dataclass(frozen=True)
class VerifyWindow:
    """One verification of a set of gains: from the gains applied to the next verification
    (or the run's end); the setpoint step and the load step in it (None: not made)."""

    label: str  # "before" (the loop's own gains) or "after" (the new gains)
    start: float  # s
    end: float  # s
    gains: str  # as the run's progress said them
    sp0: float | None = None  # the setpoint the step started from
    step_t: float | None = None
    sp: float | None = None  # the stepped setpoint
    load_t: float | None = None
    load: float | None = None  # the load's change, its units
    load_off_t: float | None = None


def verify_windows(
    progress: Sequence[TuneProgress],
    setpoints: Sequence[SetpointCommand],
    disturbances: Sequence[DisturbanceCommand],
    t_end: float,
    with_before: bool,
    gains: Sequence[GainsCommand] = (),
    cut_short: PidGains | None = None,
) -> list[VerifyWindow]:
    """Each ``verify`` phase of the run as a window; the last is "after", one before it
    "before" when the result has a before-verification. A window ends where the gains it
    verified were replaced (``gains``: the run's gains commands; one at its start is its
    own): a rejected run's restore comes before its phase ends, and the old gains' response
    after it was drawn as the new gains' (hx1's "after" ran 144 s past the restore).

    ``cut_short``: the loop's gains before a run that ended within its verifications (its
    result has neither): a first window of those gains is "before", however many followed
    (a run cancelled in it had its one window drawn as "after", titled with the old gains)."""
    starts = [p for p in progress if p.phase == "verify"]
    # the last made again with a setpoint weight (its message the gains' and ", β b"): the
    # one before it is the same gains at full weight, and a before-verification one earlier
    again = len(starts) >= 2 and starts[-1].message.startswith(starts[-2].message + ", β ")
    changed = [c.t for c in gains_changes(gains) if c.t is not None]
    out = []
    for i, p in enumerate(starts):
        later = [q.t for q in progress if q.t > p.t and q.phase not in ("verify",)]
        later += [t for t in changed if t > p.t]
        end = min([*later, *(q.t for q in starts[i + 1 :]), t_end])
        sps = [c for c in setpoints if c.t is not None and p.t <= c.t < end]
        sp0 = sps[0].sp if sps else None
        step = next((c for c in sps if sp0 is not None and c.sp != sp0), None)
        loads = [
            c for c in disturbances if c.name == LOAD and c.t is not None and p.t <= c.t <= end
        ]
        # on: base + size, then off: base (the size is the difference)
        load = loads[0].value - loads[1].value if len(loads) >= 2 else None
        last = i == len(starts) - 1
        first_after = len(starts) - (2 if again else 1)
        label = "after" if last else ("before" if with_before and i == first_after - 1 else "")
        if again and i == first_after:
            label = "after, β 1"
        if cut_short is not None and i == 0:
            own = p.message == verify_message(cut_short)
            label = "before" if own else ("after" if last else "")
        out.append(
            VerifyWindow(
                label or f"verification {i + 1}",
                p.t,
                end,
                p.message,
                sp0,
                step.t if step else None,
                step.sp if step else None,
                loads[0].t if loads else None,
                load,
                loads[1].t if len(loads) >= 2 else None,
            )
        )
    return out


def _isa(g: PidGains) -> tuple[float, float | None, float, float]:
    return (g.kc, g.ti, g.td, g.beta)


def gains_changes(gains: Sequence[GainsCommand]) -> list[GainsCommand]:
    """The gains commands at a sim time that change the gains the one before set (a run
    sets its chosen gains again as it ends: no change)."""
    out: list[GainsCommand] = []
    last = None
    for c in sorted((c for c in gains if c.t is not None), key=lambda c: c.t or 0.0):
        if last is None or _isa(c.gains) != _isa(last.gains):
            out.append(c)
        last = c
    return out


def _gains_text(g: PidGains, units: str) -> str:
    ti = "off" if g.ti is None else f"{g.ti:.4g} s"
    weight = "" if g.beta == 1.0 else f", β {g.beta:g}"
    return f"Kc {g.kc:.4g} %/{unit(units)}, Ti {ti}, Td {g.td:.4g} s{weight}"


def gains_marks(
    gains: Sequence[GainsCommand],
    windows: Sequence[VerifyWindow],
    previous: PidGains | None,
    units: str,
    factor: float = 2.0,
) -> list[Mark]:
    """The run's gains changes from its first verification on that no verification window
    begins with: the loop's own gains given back (``previous``: "gains restored"), or others
    set ("gains set"), the gain-margin check's Kc × ``factor`` (the run's: 2, or less under a
    --ms-bound past 2) and the window's gains back after it.
    A window's start already says its gains (and a ramp's trials, before the verifications,
    their Kc); a restore, mid-window or after, was unmarked."""
    if not windows:
        return []
    starts = {w.start for w in windows}
    changes = gains_changes(gains)
    tried = {_isa(c.gains) for c in changes if c.t in starts}  # the gains each window tried
    doubled = {(factor * kc, ti, td, beta) for kc, ti, td, beta in tried}
    out = []
    checking = False  # the last change was a gain-margin check's
    for c in changes:
        if c.t is None or c.t < windows[0].start or c.t in starts:
            continue
        g = c.gains
        same = previous is not None and _isa(g) == _isa(previous)
        back = checking and _isa(g) in tried
        checking = _isa(g) in doubled  # the verification's gain-margin check (margin_check)
        if checking:
            what = f"gain-margin check, Kc × {factor:.3g}"
        elif back:
            what = "gains back after the check"
        elif same:
            what = "gains restored"
        else:
            what = "gains set"
        out.append(Mark(c.t, "gains", f"{what}: {_gains_text(g, units)}"))
    return out
