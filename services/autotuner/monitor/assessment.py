"""A loop watched in normal operation: figures, Hägglund's detectors, and what they flag.

A ``Watcher`` is fed every sample (t, sp, pv, op, in auto or not) and, at the end of each
window, ``report()`` gives the window's ``Assessment``: the figures of ``performance``, the
oscillation detector's verdict (it and the idle index run on across windows: the detector's
supervision time is fifty ultimate periods), the idle index over the window's load
disturbances, and the flags, each with its reason:

- ``oscillating``: more than n_lim detections within T_sup (``oscillation``), with the period;
- ``sluggish``: the idle index above SLUGGISH_LIMIT over at least T_u of load disturbances;
- ``saturated``: the output at a limit SATURATION_LIMIT % of the time in auto or more;
- ``noisy``: the output's noise (σ of its sample-to-sample change over √2, % of output) above
  the limit a tune's verification holds gains to (``output_noise.DEFAULT_LIMIT``, 10 %): the
  PV's noise through the gains works the valve, tuned or not;
- ``degraded``: worse than the last tune (``Baseline``): an oscillation where its
  verification decayed; the output's noise more than DEGRADED_RATIO times what the
  verification measured with the tuned gains (the measurement got noisier, or the gains
  changed); the PV's noise more than DEGRADED_RATIO times what the tune measured at rest
  (the transmitter). The error's own spread is not judged against the tune: it grows with
  whatever disturbs the loop, which the tune did not see.

``watch`` feeds one window and reports once; the tuner's monitor reports every window; the
tests feed an in-process loop: one code path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.autotuner.monitor.idle_index import SLUGGISH_LIMIT, IdleIndex
from services.autotuner.monitor.oscillation import (
    AMPLITUDE_FRACTION,
    SUPERVISION_PERIODS,
    HalfPeriod,
    OscillationDetector,
)
from services.autotuner.monitor.performance import performance

SATURATION_LIMIT = 10.0  # % of the time in auto at an output limit: flagged saturated
# % of output (σ of the sample-to-sample change over √2): flagged noisy above it; the limit a
# tune's verification holds gains to (``design.output_noise.DEFAULT_LIMIT``: the monitor core
# does not load the design's scipy; a test holds them equal)
NOISY_LIMIT = 10.0
# a watch shorter than the detector's supervision time: an oscillation detected in this share
# of the half-periods watched, over this many of them at least, is flagged all the same
SUSTAINED_SHARE = 0.75
SUSTAINED_HALVES = 6.0
DEGRADED_RATIO = 3.0  # × the tune's figure: flagged degraded
DEFAULT_PERIOD_SAMPLES = 50  # T_u in sample times when nothing better is known
WINDOW_PERIODS = 10.0  # the tuner's report window, × T_u
MIN_WINDOW_SAMPLES = 100  # … and at least this many samples


def choose_period(
    given: float | None,
    tuned: float | None,
    ti: float | None,
    sample_time: float,
) -> tuple[float, str]:
    """T_u (s) for the detector, and where it came from: ``given`` (the user's), else the last
    tune's ultimate period ``tuned``, else the loop's integral time Ti (Hägglund 1995: without
    ω_u, 2π/Ti stands in for it), else DEFAULT_PERIOD_SAMPLES sample times."""
    for value, source in ((given, "given"), (tuned, "the last tune's P_u"), (ti, "Ti")):
        if value is not None and math.isfinite(value) and value > 0:
            return float(value), source
    return DEFAULT_PERIOD_SAMPLES * sample_time, (
        f"default: {DEFAULT_PERIOD_SAMPLES} sample times (no tune, no integral time)"
    )


def gains_note(
    gains: tuple[float, float | None, float] | None, baseline: Baseline | None
) -> str | None:
    """The note when the loop's gains (kc, ti, td) are no longer those the tune left: the
    comparison with it is then with other gains (None when they are, or nothing to say)."""
    if gains is None or baseline is None or baseline.gains is None or gains == baseline.gains:
        return None
    kc, ti, td = gains
    return (
        f"the loop's gains (Kc {kc:.4g}, Ti {'off' if ti is None else f'{ti:.4g} s'}, Td "
        f"{td:.4g} s) are no longer those of the tune {baseline.run_id}: the comparison is "
        "with other gains"
    )


@dataclass(frozen=True)
class Baseline:
    """What the last tune measured, to compare with: its run id, the output's noise σ at rest
    with the tuned gains (% of output), the PV's noise σ at rest before the test (PV units),
    the verification's decay ratio and overshoot (%), and the gains it left (kc, ti, td)."""

    run_id: str | None = None
    op_noise: float | None = None
    pv_noise: float | None = None
    decay_ratio: float | None = None
    overshoot: float | None = None
    stable: bool | None = None
    gains: tuple[float, float | None, float] | None = None

    @classmethod
    def from_result(cls, result: dict[str, Any] | None) -> Baseline | None:
        """From a TuneResult as a plain dict (``model_dump()``): None unless the run left its
        gains applied (nothing of it is then in the loop): ``ok``, or ``unverified`` (applied
        without verification: no verification figures to compare with)."""
        # ``shared.messages.APPLIED_STATUSES``, written out: the monitor core imports no pydantic
        if not result or result.get("status") not in ("ok", "forced", "unverified"):
            return None
        if not result.get("applied"):
            return None
        after = result.get("after") or {}
        rest = result.get("rest") or {}
        noise = result.get("noise", rest.get("noise_std"))
        g = after.get("gains") or result.get("chosen") or {}
        gains = (g["kc"], g.get("ti"), g.get("td", 0.0)) if "kc" in g else None
        return cls(
            run_id=result.get("run_id"),
            op_noise=after.get("op_noise"),
            pv_noise=noise if isinstance(noise, int | float) else None,
            decay_ratio=after.get("decay_ratio"),
            overshoot=after.get("overshoot"),
            stable=after.get("stable"),
            gains=gains,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id,
            "op_noise": self.op_noise,
            "pv_noise": self.pv_noise,
            "decay_ratio": self.decay_ratio,
            "overshoot": self.overshoot,
            "stable": self.stable,
            "gains": list(self.gains) if self.gains is not None else None,
        }


@dataclass(frozen=True)
class MonitorSettings:
    """The loop as the watcher needs it: ``period`` T_u (s) and where it came from, the
    sample time (s), the PV's range and the output's limits, and the controller's action
    (reverse: the output falls as the PV rises, a positive process gain), and whether it has
    integral action (without, its error keeps an offset the detector high-passes away)."""

    period: float
    period_source: str
    sample_time: float
    pv_range: tuple[float, float]
    op_limits: tuple[float, float]
    action: str = "reverse"
    integral: bool = True

    @property
    def amplitude(self) -> float:
        """a: the smallest oscillation worth flagging, AMPLITUDE_FRACTION of the PV's span
        (PV units)."""
        lo, hi = self.pv_range
        span = hi - lo if math.isfinite(hi - lo) and hi > lo else 1.0
        return AMPLITUDE_FRACTION * span

    @property
    def window(self) -> float:
        """The tuner's report window, s of sim time."""
        return max(WINDOW_PERIODS * self.period, MIN_WINDOW_SAMPLES * self.sample_time)


@dataclass
class Assessment:
    """One window's verdict; ``to_dict()`` is what ``LoopMonitor`` carries (less its loop and
    node) and what ``watch --json`` prints."""

    t: float
    t_start: float
    period: float
    period_source: str
    figures: dict[str, Any]
    oscillating: bool
    oscillation_period: float | None
    detections: int
    detection_limit: int
    supervision: float
    iae_limit: float
    amplitude: float
    pv_noise_estimate: float
    idle_index: float | None
    idle_seconds: float
    flags: dict[str, str]
    baseline: Baseline | None
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        f = self.figures
        return {
            "t": self.t,
            "t_start": self.t_start,
            "samples": f["samples"],
            "auto_fraction": f["auto_fraction"],
            "period": self.period,
            "period_source": self.period_source,
            "iae_rate": f["iae_rate"],
            "error_std": f["error_std"],
            "saturation": f["saturation"],
            "travel": f["travel"],
            "travel_rate": f["travel_rate"],
            "reversals": f["reversals"],
            "oscillating": self.oscillating,
            "oscillation_period": self.oscillation_period,
            "detections": self.detections,
            "detection_limit": self.detection_limit,
            "iae_limit": self.iae_limit,
            "idle_index": self.idle_index,
            "flags": dict(self.flags),
            "run_id": self.baseline.run_id if self.baseline else None,
            "figures": {
                **{k: f[k] for k in ("error_mean", "reversal_rate")},
                **{k: f[k] for k in ("reversal_deadband", "op_noise", "pv_noise", "duration")},
                "supervision": self.supervision,
                "amplitude": self.amplitude,
                "pv_noise_estimate": self.pv_noise_estimate,
                "idle_seconds": self.idle_seconds,
            },
            "baseline": self.baseline.to_dict() if self.baseline else None,
            "notes": list(self.notes),
        }


class Watcher:
    """Feed samples; ``report()`` at the end of each window (see the module)."""

    def __init__(self, settings: MonitorSettings, baseline: Baseline | None = None):
        self.settings = settings
        self.baseline = baseline
        s = settings
        self.detector = OscillationDetector(
            s.period, s.amplitude, s.sample_time, offset=not s.integral
        )
        self.idle = IdleIndex(s.period, s.sample_time, 1.0 if s.action == "reverse" else -1.0)
        self._rows: list[tuple[float, float, float, float, bool]] = []
        self._last_sp: float | None = None
        self._sp_changes: list[float] = []  # times of recent setpoint changes, s

    @property
    def window_start(self) -> float | None:
        """The time of the window's first sample, s (None before one)."""
        return self._rows[0][0] if self._rows else None

    def feed(self, t: float, sp: float, pv: float, op: float, auto: bool) -> None:
        """One sample: sim time t (s), setpoint and PV (PV units), output (%), in auto?"""
        s = self.settings
        if self._rows and t <= self._rows[-1][0]:  # time went back: a restarted plant
            self._rows = []
        self._rows.append((t, sp, pv, op, auto))
        if self._last_sp is not None and sp != self._last_sp:
            self._sp_changes.append(t)
        self._last_sp = sp
        if not auto:
            self.detector.interrupt()
            self.idle.interrupt()
            return
        self.idle.feed(t, op, pv)
        half = self.detector.feed(t, sp, pv)
        if half is not None:
            self._idle_close(half)
            self._sp_changes = [c for c in self._sp_changes if c >= half.end - s.period]

    def _idle_close(self, half: HalfPeriod) -> None:
        """The idle index reads ``half`` if it was a load disturbance clear of setpoint changes
        by T_u."""
        since = half.start - self.settings.period
        clear = not any(since <= c <= half.end for c in self._sp_changes)
        self.idle.close(half, half.detected and clear)

    def report(self) -> Assessment:
        """The window since the last report: its figures and flags; the next window starts."""
        s, det = self.settings, self.detector
        under_way = det.open_half_period()  # a sluggish loop's load response may be long
        if under_way is not None and under_way.detected:
            self._idle_close(under_way)
        rows = self._rows
        cols = np.array(rows, dtype=float).T if rows else np.zeros((5, 0))
        t, sp, pv, op, auto = cols
        quarter = round(0.25 * s.period / s.sample_time)  # the output averaged for reversals
        figures = performance(t, sp, pv, op, auto.astype(bool), s.op_limits, quarter)
        oscillating = det.max_count > det.detection_limit
        idle = self.idle.value()
        a = Assessment(
            t=float(t[-1]) if t.size else 0.0,
            t_start=float(t[0]) if t.size else 0.0,
            period=s.period,
            period_source=s.period_source,
            figures=figures,
            oscillating=oscillating,
            oscillation_period=det.peak_period if oscillating else None,
            detections=det.max_count,
            detection_limit=det.detection_limit,
            supervision=det.supervision,
            iae_limit=det.limit(),
            amplitude=s.amplitude,
            pv_noise_estimate=det.noise,
            idle_index=idle,
            idle_seconds=self.idle.seconds(),
            flags={},
            baseline=self.baseline,
        )
        a.flags, a.notes = judge(a, s, det.watched())
        if a.oscillating and a.oscillation_period is None:  # flagged on a short watch
            a.oscillation_period = det.period_estimate()
        self._rows = []
        det.clear_peak()
        self.idle.reset()
        return a


def judge(
    a: Assessment, s: MonitorSettings, watched: float | None = None
) -> tuple[dict[str, str], list[str]]:
    """The flags with their reasons, and notes (what could not be judged, and why).
    ``watched``: the seconds the oscillation detector has watched (None: its whole
    supervision time). Watched for less, it cannot count n_lim detections of an oscillation
    it sees in nearly every half-period (7 of 9 in 4.5 T_u was "not oscillating"): that is
    flagged as a sustained oscillation; fewer detections are a note, not a verdict."""
    f, b = a.figures, a.baseline
    flags: dict[str, str] = {}
    notes: list[str] = []
    if not f["samples"] or f["iae_rate"] is None:
        notes.append("the loop was not in auto: nothing to assess")
        return flags, notes
    short = watched is not None and watched < 0.999 * a.supervision
    halves = 2.0 * (watched or 0.0) / a.period
    if a.oscillating:
        period = (
            f", period {a.oscillation_period:.4g} s" if a.oscillation_period is not None else ""
        )
        seen = f" (of it, {watched:.4g} s watched)" if short else ""
        flags["oscillating"] = (
            f"{a.detections} half-periods with an IAE above {a.iae_limit:.3g} within the "
            f"{SUPERVISION_PERIODS:g} T_u supervision window{seen} (limit "
            f"{a.detection_limit}){period}, T_u {a.period:.4g} s"
        )
    elif short and halves >= SUSTAINED_HALVES and a.detections >= SUSTAINED_SHARE * halves:
        a.oscillating = True
        flags["oscillating"] = (
            f"{a.detections} half-periods with an IAE above {a.iae_limit:.3g} in the "
            f"{watched:.4g} s watched ({halves:.3g} half-periods of T_u {a.period:.4g} s): a "
            f"sustained oscillation, though the watch is shorter than the {SUPERVISION_PERIODS:g}"
            f" T_u ({a.supervision:.4g} s) over which {a.detection_limit} detections are asked"
        )
    elif short:
        notes.append(
            f"the oscillation detector watched {watched:.4g} s of its {SUPERVISION_PERIODS:g} "
            f"T_u ({a.supervision:.4g} s): {a.detections} detections, too short a watch to "
            f"tell an oscillation by its limit of {a.detection_limit} (--duration)"
        )
    if a.idle_index is not None and a.idle_index > SLUGGISH_LIMIT and not a.oscillating:
        flags["sluggish"] = (
            f"idle index {a.idle_index:.2f} over {a.idle_seconds:.4g} s of load disturbances "
            f"(above {SLUGGISH_LIMIT:g}: the output creeps after the PV)"
        )
    elif a.idle_index is None:
        notes.append("no load disturbance long enough to read the idle index")
    if f["saturation"] >= SATURATION_LIMIT:
        flags["saturated"] = (
            f"the output sat at a limit {f['saturation']:.3g} % of the time in auto "
            f"(limit {SATURATION_LIMIT:g} %)"
        )
    noise = f.get("op_noise")
    if noise is not None and noise > NOISY_LIMIT:
        flags["noisy"] = (
            f"the output's noise σ {noise:.3g} % sample to sample (above {NOISY_LIMIT:g} %, the "
            "limit a tune's verification holds gains to): the PV's noise through the gains "
            "works the valve; a lower gain or a filtered measurement spares it"
        )
    if b is None:
        notes.append("no applied tune to compare with")
        return flags, notes
    worse = []
    if a.oscillating and b.stable and (b.decay_ratio or 0.0) < 1.0:
        dr = f"decay ratio {b.decay_ratio:.2g}" if b.decay_ratio is not None else "no second peak"
        worse.append(f"it oscillates; the tune's verification decayed ({dr})")
    for name, now, then, unit in (
        ("output", f["op_noise"], b.op_noise, " %"),
        ("PV", f["pv_noise"], b.pv_noise, ""),
    ):
        if then is not None and now is not None and now > DEGRADED_RATIO * then and now > 0:
            worse.append(
                f"the {name}'s noise σ {now:.3g}{unit} against {then:.3g}{unit} at the tune "
                f"(limit × {DEGRADED_RATIO:g})"
            )
    if worse:
        flags["degraded"] = "; ".join(worse)
    return flags, notes


def loop_watcher(
    period: float, period_source: str, info: Any, status: Any, result: dict[str, Any] | None
) -> Watcher:
    """A Watcher of one loop: its sample time, PV range and output limits from ``info`` (a
    LoopInfo), its action and integral action from ``status`` (a LoopStatus; read by
    attribute: this layer imports no message model), the baseline from ``result`` (a
    TuneResult as a dict) when there is one."""
    settings = MonitorSettings(
        period,
        period_source,
        info.sample_time,
        tuple(info.pv_range),
        tuple(info.op_limits),
        status.action,
        integral=status.gains.ti is not None,
    )
    return Watcher(settings, Baseline.from_result(result))
