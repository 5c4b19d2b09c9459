"""Open-loop step test (process reaction curve), as a state machine fed one sample at a time.

In manual at the present output: a quiet baseline (noise and rest value), a step of ``size``
% in the output, samples until the PV is at rest again (``reaction_curve.settled``), then the
reaction-curve figures. It aborts when the PV leaves its limits or no rest comes in
``timeout`` seconds. ``run_step_test`` drives a live loop with it and always restores the
loop's mode and output, whatever happens.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from services.autotuner.loop_client import LoopClient
from services.autotuner.reaction_curve import (
    ReactionCurve,
    analyze_step,
    at_rest,
    noise_level,
    settled,
)
from shared.errors import AutotuneError
from shared.messages import ModeCommand, OutputCommand, ProcessSample

SETTLE_CHECK_EVERY = 8  # samples between rest checks (each is a regression over a window)


class StepTestAborted(AutotuneError):
    """The step test stopped before a result; the loop has been restored."""


@dataclass(frozen=True)
class StepTestConfig:
    size: float = 5.0  # % of output; negative steps down
    baseline: float | None = None  # s of quiet before the step; None: 40 samples
    timeout: float = 7200.0  # s after the step to wait for rest
    pv_limits: tuple[float, float] | None = None  # abort outside; None: the loop's PV range


@dataclass
class StepTest:
    """The experiment; ``feed`` each sample, hold the output it returns."""

    config: StepTestConfig
    op_start: float
    op_limits: tuple[float, float]
    pv_limits: tuple[float, float]
    sample_time: float
    phase: str = "baseline"  # baseline → step → done | aborted
    reason: str = ""
    t_step: float | None = None
    result: ReactionCurve | None = None
    t: list[float] = field(default_factory=list)
    pv: list[float] = field(default_factory=list)
    events: list[tuple[float, str, dict]] = field(default_factory=list)
    _baseline_samples: int = 0
    _pv_before: float = math.nan
    _noise: float = 0.0

    def __post_init__(self) -> None:
        cfg = self.config
        if not math.isfinite(cfg.size) or cfg.size == 0:
            raise ValueError(f"size {cfg.size}: must be a non-zero number of %")
        target = self.op_start + cfg.size
        lo, hi = self.op_limits
        if not lo <= target <= hi:
            raise ValueError(
                f"size {cfg.size:+g} %: the output would go from {self.op_start:g} "
                f"to {target:g} %, outside the loop's limits [{lo:g}, {hi:g}] %"
            )
        base = cfg.baseline if cfg.baseline is not None else 40 * self.sample_time
        if not base >= 0:
            raise ValueError(f"baseline {base}: must be ≥ 0 s")
        self._baseline_samples = max(10, math.ceil(base / self.sample_time))

    @property
    def finished(self) -> bool:
        return self.phase in ("done", "aborted")

    @property
    def op_target(self) -> float:
        return self.op_start + self.config.size

    def _abort(self, reason: str) -> float:
        self.phase, self.reason = "aborted", reason
        self.events.append((self.t[-1] if self.t else 0.0, "aborted", {"reason": reason}))
        return self.op_start

    def feed(self, s: ProcessSample) -> float:
        """Take the sample at ``s.t``; return the output to hold from ``s.t`` on."""
        if self.finished:
            return self.op_start
        self.t.append(s.t)
        self.pv.append(s.pv)
        lo, hi = self.pv_limits
        if not lo <= s.pv <= hi:
            return self._abort(f"PV {s.pv:.4g} left its limits [{lo:g}, {hi:g}] at t = {s.t:g} s")
        if self.phase == "baseline":  # at rest first: no trend beyond the noise
            n = self._baseline_samples
            if len(self.pv) < n:
                return self.op_start
            base = np.asarray(self.pv[-n:])
            if not at_rest(base):
                if len(self.pv) >= 20 * n:
                    return self._abort("the PV is not at rest before the step (it keeps drifting)")
                return self.op_start
            self._pv_before = float(base.mean())
            self._noise = noise_level(base)
            self.phase = "step"
            self.events.append(
                (
                    s.t,
                    "step",
                    {"op": self.op_target, "pv_before": self._pv_before, "noise_std": self._noise},
                )
            )
            return self.op_target
        if self.t_step is None:
            return self.op_target
        if s.t - self.t_step > self.config.timeout:
            return self._abort(
                f"no steady state within {self.config.timeout:g} s of the step "
                "(an integrating process never settles: see the README)"
            )
        t, y = np.asarray(self.t), np.asarray(self.pv)
        if (len(self.pv) % SETTLE_CHECK_EVERY) == 0:
            done, rest = settled(t, y, self.t_step, self._pv_before, self._noise)
            if done:
                try:
                    self.result = analyze_step(
                        t, y, self.t_step, self.config.size, self._pv_before, rest, self._noise
                    )
                except ValueError as err:
                    return self._abort(str(err))
                self.phase = "done"
                self.events.append(
                    (s.t, "done", {"gain": self.result.gain, "dead_time": self.result.dead_time})
                )
                return self.op_start
        return self.op_target

    def step_started(self, t: float) -> None:
        """The driver reports the sim time from which the stepped output is held."""
        self.t_step = t


@dataclass(frozen=True)
class StepTestReport:
    loop: str
    model: str
    pv_units: str
    mode_before: str
    op_before: float
    t_step: float
    t_end: float
    samples: int
    curve: ReactionCurve
    restored: bool

    def to_dict(self) -> dict:
        return {
            "loop": self.loop,
            "model": self.model,
            "pv_units": self.pv_units,
            "mode_before": self.mode_before,
            "op_before": self.op_before,
            "op_step": self.op_before + self.curve.step_size,
            "t_step": self.t_step,
            "t_end": self.t_end,
            "samples": self.samples,
            "restored": self.restored,
            **self.curve.to_dict(),
        }


def run_step_test(
    client: LoopClient,
    config: StepTestConfig,
    progress: Callable[[StepTest, ProcessSample], None] | None = None,
) -> StepTestReport:
    """Run the step test on a live loop; restore its mode and output afterwards, always."""
    before = client.sync()
    info = client.info
    pv_limits = config.pv_limits or tuple(info.pv_range)
    try:
        test = StepTest(config, before.op, tuple(info.op_limits), pv_limits, info.sample_time)
    except ValueError as err:
        raise StepTestAborted(f"loop {client.loop}: {err}") from None
    restored = False
    try:
        if before.mode != "manual":
            client.command(ModeCommand(loop=client.loop, mode="manual", source=client.source))
        op = before.op
        while not test.finished:
            s = client.next_sample()
            want = test.feed(s)
            if progress:
                progress(test, s)
            if want != op and not test.finished:
                status = client.command(
                    OutputCommand(loop=client.loop, op=want, t=s.t, source=client.source)
                )
                # Lockstep: applied at the present sample. Realtime: latched at the next one.
                test.step_started(
                    status.t if info.clock == "lockstep" else status.t + info.sample_time
                )
                op = want
    finally:
        restored = _restore(client, before.mode, before.op)
    if test.phase == "aborted" or test.result is None:
        raise StepTestAborted(
            f"loop {client.loop}: step test aborted: {test.reason}; "
            f"{'loop restored' if restored else 'LOOP NOT RESTORED'} "
            f"({before.mode}, {before.op:g} %)"
        )
    return StepTestReport(
        client.loop,
        info.model,
        info.pv_units,
        before.mode,
        before.op,
        test.t_step or 0.0,
        test.t[-1],
        len(test.t),
        test.result,
        restored,
    )


def _restore(client: LoopClient, mode: str, op: float) -> bool:
    """Put the loop back to ``mode`` at output ``op`` (bumpless into auto)."""
    try:
        status = client.sync()
        if status.mode == "manual" and status.op != op:
            client.command(OutputCommand(loop=client.loop, op=op, source=client.source))
        if mode != status.mode:
            client.command(ModeCommand(loop=client.loop, mode=mode, source=client.source))
        return True
    except AutotuneError:
        return False
