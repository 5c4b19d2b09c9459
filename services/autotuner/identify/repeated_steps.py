"""Repeated step tests (seed 001: "do two or three more step tests … and use the average").

Up and down steps of the same size alternate, each from rest at the same output: a step test
(``StepTest``), then the output back at its start and the PV watched until it is at rest
again (``ReturnWatch``; an integrating loop's test gives its level back itself). Every test's
figures are kept; the identification is their mean, and each figure's spread is reported:
the sample standard deviation over the tests, relative to the mean, and the precision of the
mean, two standard errors (2·s/√n) relative to it.

``repeat`` tests, or with ``auto`` from ``AUTO_FIRST`` tests on one more at a time until
every figure's mean is known to ``tolerance`` (two standard errors, relative), at most
``AUTO_LIMIT``. A mean less precise than ``tolerance`` at the end is said in the findings'
``notes``. Up and down steps read differently on a nonlinear plant (a valve's
characteristic, a tank's square-root outflow): that shows as spread, and is said as such.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, ClassVar

from services.autotuner.identify import step_test
from services.autotuner.identify.experiments import (
    Band,
    Demand,
    Event,
    Identification,
    Progress,
    Settings,
    Setup,
    as_controlled,
)
from services.autotuner.identify.model_fit import ProcessFit, StepModel, model_of
from services.autotuner.identify.reaction_curve import IntegratingCurve, ReactionCurve
from services.autotuner.identify.step_test import (
    ReturnWatch,
    StepTest,
    StepTestConfig,
    return_timeout,
)
from shared.control.signals import Sample

AUTO_FIRST = 2  # tests before ``auto`` judges the spread (an up and a down step)
AUTO_LIMIT = 6  # at most this many tests with ``auto``
MAX_REPEAT = 20  # at most this many tests asked for
REST_DRIFT = 0.001  # of the last test's change: a drift the next baseline counts as rest
DEFAULT_TOLERANCE = 0.05  # the mean of each figure known to ± 5 % (two standard errors)

# the figures averaged and judged, by kind of response
SELF_REGULATING = ("gain", "dead_time", "time_constant_tangent", "time_constant_63")
INTEGRATING = ("reaction_rate", "dead_time")


@dataclass(frozen=True)
class Spread:
    """One figure over the tests: mean, sample standard deviation, and the mean's precision
    (two standard errors), both relative to the mean."""

    mean: float
    std: float
    spread: float  # std / |mean|
    precision: float  # 2·std/√n / |mean|

    @classmethod
    def of(cls, values: list[float]) -> Spread:
        mean = statistics.fmean(values)
        std = statistics.stdev(values) if len(values) > 1 else 0.0
        scale = abs(mean) if mean else math.inf
        return cls(mean, std, std / scale, 2.0 * std / math.sqrt(len(values)) / scale)


@dataclass(frozen=True)
class RepeatFindings:
    """The run's ``experiment`` object for repeated step tests (flat: numbers and words)."""

    step_size: float  # % of output, the first test's (the others alternate in sign)
    tests: int
    spreads: dict[str, Spread]
    tolerance: float
    model: ProcessFit | None
    integrating: bool

    @property
    def settled(self) -> bool:
        return all(s.precision <= self.tolerance for s in self.spreads.values())

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "step_size": self.step_size,
            "method": "repeated steps",
            "tests": self.tests,
            "tolerance": self.tolerance,
            "settled": self.settled,
        }
        for name, s in self.spreads.items():
            out[f"{name}_mean"] = s.mean
            out[f"{name}_spread"] = s.spread
            out[f"{name}_precision"] = s.precision
        return {**out, **(self.model.to_dict() if self.model else {})}


@dataclass
class RepeatedSteps:
    """The experiment; ``feed`` each sample, hold the output it returns."""

    config: StepTestConfig
    op_start: float
    op_limits: tuple[float, float]
    pv_limits: tuple[float, float]
    sample_time: float
    pv_range: tuple[float, float] | None = None
    pv_units: str = ""
    repeat: int = 3  # tests to run (with ``auto``: the most it may run)
    auto: bool = False
    tolerance: float = DEFAULT_TOLERANCE
    direction: float = 1.0  # −1: a direct-acting loop (the findings ``as_controlled``)
    phase: str = "test"  # test → return → test … → done | aborted
    reason: str = ""
    done: list[StepTest] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    result: ReactionCurve | IntegratingCurve | None = None  # the mean curve once done
    _test: StepTest | None = None
    _watch: ReturnWatch | None = None
    _t_end: float = math.nan  # the last test's end, from which its return is watched
    _forwarded: int = 0  # events of the running test already in ``events``

    needs_hold_time: ClassVar[bool] = True

    def __post_init__(self) -> None:
        if not 1 <= self.repeat <= MAX_REPEAT or (self.auto and self.repeat < AUTO_FIRST):
            raise ValueError(
                f"repeat {self.repeat}: must be 1–{MAX_REPEAT} (≥ {AUTO_FIRST} with auto)"
            )
        if not 0 < self.tolerance < 1:
            raise ValueError(f"tolerance {self.tolerance}: must be between 0 and 1")
        self._test = self._new_test()  # ValueError here if the step cannot be made
        if self.repeat > 1:  # and the down step, before anything moves
            down = dataclasses.replace(self.config, size=-self.config.size)
            StepTest(down, self.op_start, self.op_limits, self.pv_limits, self.sample_time)

    @classmethod
    def like(cls, single: StepTest, **kw: Any) -> RepeatedSteps:
        """Repeated tests of ``single``'s step on its loop (``kw``: ``repeat``, ``auto``…)."""
        return cls(
            single.config,
            single.op_start,
            single.op_limits,
            single.pv_limits,
            single.sample_time,
            pv_range=single.pv_range,
            pv_units=single.pv_units,
            direction=single.direction,
            **kw,
        )

    # --- the experiment protocol ---------------------------------------------------------

    @property
    def finished(self) -> bool:
        return self.phase in ("done", "aborted")

    @property
    def closing(self) -> Demand | None:
        """Finished: the output back at rest."""
        return Demand(op=self.op_start) if self.finished else None

    @property
    def demand(self) -> Demand:
        if self.phase == "test" and self._test is not None:
            return self._test.demand
        return Demand(op=self.op_start)

    def feed(self, s: Sample) -> Demand:
        if self.finished:
            return Demand(op=self.op_start)
        if self.phase == "return":
            if not self._watch.feed(s.t, s.pv):
                return Demand(op=self.op_start)
            self._next_or_end(s.t)
            return self.demand
        test = self._test
        want = test.feed(s)
        self._take_events(test)
        if not test.finished:
            return want
        if test.phase == "aborted":
            return self._abort(f"test {len(self.done) + 1} of {self._planned()}: {test.reason}")
        self.done.append(test)
        # the last test's return is the caller's (as after one test); an integrating loop's
        # test gave its level back itself
        if isinstance(test.result, IntegratingCurve) or self._enough():
            self._next_or_end(s.t)
            return self.demand
        rc = test.result
        self._t_end = s.t
        self._watch = ReturnWatch(
            s.t,  # until the driver says when the restored output holds
            rc.pv_after,
            rc.noise_std,
            return_timeout(self.config, test.t_step, s.t),
            self.pv_range,
            pv_back=rc.pv_before,
            swing=self.config.swing_check,  # off in a run recorded before (its replay)
        )
        self.phase = "return"
        self.events.append(Event(s.t, "return", {"test": len(self.done)}))
        return Demand(op=self.op_start)

    def held(self, t: float) -> None:
        """The sim time from which the last changed output holds: the test's step (or pulse),
        or the output back at its start, from which the return is watched."""
        if self.phase == "test" and self._test is not None:
            self._test.held(t)
            self._take_events(self._test)
        else:
            if self._watch is not None:
                self._watch.t_restore = t
            self.events.append(Event(t, "output_held", {"t": t}))

    step_started = held  # what ``step_run`` calls (it drives without the driver)

    def horizon(self, cap: int) -> int:
        """The running test's (``StepTest.horizon``); watching a return to rest, up to its
        next rest check (every ``SETTLE_CHECK_EVERY`` samples) or its timeout, whichever
        may come first: a batch fed one by one leaves the tests where one sample a batch
        would."""
        if self.finished:
            return 1
        if self.phase == "test" and self._test is not None:
            return self._test.horizon(cap)
        if self.phase != "return" or self._watch is None:
            return 1
        return self._watch.horizon(cap, self.sample_time)

    def band(self) -> Band | None:
        """The running test's; none while a return is watched (it aborts on no PV)."""
        if self.phase == "test" and self._test is not None:
            return self._test.band()
        return None

    def progress(self) -> Progress:
        n = len(self.done) + (1 if self.phase == "test" else 0)
        return Progress("step", max(n, 1), message=f"step test {max(n, 1)} of {self._planned()}")

    def identification(self) -> Identification | None:
        found = self._identification()
        return None if found is None else as_controlled(found, self.direction)

    def _identification(self) -> Identification | None:
        if self.phase != "done" or not self.done:
            return None
        idents = [t.identification() for t in self.done]
        integrating = isinstance(self.result, IntegratingCurve)
        spreads = self.spreads()
        model = _mean_model([i.model for i in idents if i is not None and i.model is not None])
        rc = self.result
        if integrating:
            step_model = StepModel.integrating(rc.reaction_rate, rc.dead_time)
        else:
            step_model = StepModel(rc.gain, rc.dead_time, rc.time_constant_tangent)
        # where the steps' models took a dead time the record did not resolve (``StepTest.
        # _design_delay``, asked by the set-up: a run recorded before replays as it was), the
        # open-loop rules take the mean model's too, and it is said with the L designed on
        bounded = self.done[0].config.bound_delay
        unresolved = [
            n
            for i in idents
            if i is not None and bounded
            for n in i.notes
            if n.startswith(step_test.UNRESOLVED) and step_test.DESIGN_TAKES in n
        ]
        said: list[str] = []
        if unresolved and model is not None and model.kind in ("fopdt", "ipdt"):
            step_model = dataclasses.replace(
                step_model, dead_time=max(step_model.dead_time, model.delay)
            )
            said = [
                f"{step_test.UNRESOLVED} in {len(unresolved)} of {len(idents)} steps; "
                f"{step_test.DESIGN_TAKES} {model.delay:.4g} s, the mean of the steps' models "
                f"(the last such step: {unresolved[-1].split(': ', 1)[1]})"
            ]
        findings = RepeatFindings(
            self.done[0].config.size, len(self.done), spreads, self.tolerance, model, integrating
        )
        return Identification(
            step=rc,
            step_model=step_model,
            model=model or model_of(step_model),
            integrating=integrating,
            experiment=findings,
            timescale=statistics.fmean(i.timescale for i in idents),
            noise=statistics.fmean(i.noise for i in idents),
            rest_pv=idents[0].rest_pv,
            notes=self.notes(spreads) + said,
            repeats=self.curves(),
        )

    # --- what the tests gave -------------------------------------------------------------

    def curves(self) -> list[ReactionCurve | IntegratingCurve]:
        return [t.result for t in self.done]

    def spreads(self) -> dict[str, Spread]:
        curves = self.curves()
        names = INTEGRATING if isinstance(curves[0], IntegratingCurve) else SELF_REGULATING
        return {n: Spread.of([getattr(c, n) for c in curves]) for n in names}

    def notes(self, spreads: dict[str, Spread] | None = None) -> list[str]:
        """What the engineer must know: a mean less precise than the tolerance."""
        spreads = spreads if spreads is not None else self.spreads()
        loose = [
            f"{name} ± {100 * s.precision:.2g} % (spread {100 * s.spread:.2g} %)"
            for name, s in spreads.items()
            if s.precision > self.tolerance
        ]
        if not loose or len(self.done) < 2:
            return []
        return [
            f"{len(self.done)} step tests disagree beyond the tolerance (the mean within ± "
            f"{100 * self.tolerance:.2g} %): {', '.join(loose)}; noise, a disturbance during "
            "a test, or a nonlinear plant (up and down steps read differently): "
            + (
                f"the {AUTO_LIMIT} tests auto allows did not settle it; a larger step may"
                if self.auto
                else "more tests (--repeat auto) or a larger step"
            )
        ]

    # --- the state machine ---------------------------------------------------------------

    def _planned(self) -> str:
        return f"up to {self.repeat}" if self.auto else str(self.repeat)

    def _new_test(self) -> StepTest:
        size = self.config.size * (1 if len(self.done) % 2 == 0 else -1)
        # rest before the next test: a drift of 0.1 % of the last test's change over the
        # baseline, as well as the noise (a noise-free PV's return never stops moving at all)
        last = self.done[-1].result if self.done else None
        change = abs(last.pv_after - last.pv_before) if isinstance(last, ReactionCurve) else 0.0
        return StepTest(
            dataclasses.replace(self.config, size=size),
            self.op_start,
            self.op_limits,
            self.pv_limits,
            self.sample_time,
            pv_range=self.pv_range,
            pv_units=self.pv_units,
            rest_drift=REST_DRIFT * change,
        )

    def _enough(self) -> bool:
        n = len(self.done)
        if n >= self.repeat:
            return True
        if not self.auto or n < AUTO_FIRST:
            return False
        return all(s.precision <= self.tolerance for s in self.spreads().values())

    def _next_or_end(self, t: float) -> None:
        kinds = {isinstance(c, IntegratingCurve) for c in self.curves()}
        if len(kinds) > 1:
            self._abort(
                "the step tests disagree on the kind of process: some ramp (integrating), "
                "some settle; the loop is not the same from one test to the next"
            )
            return
        if self._enough():
            self.result = _mean_curve(self.curves(), self.spreads())
            self.phase = "done"
            self.events.append(Event(t, "done", {"tests": len(self.done)}))
            return
        try:
            self._test = self._new_test()
        except ValueError as err:  # a down step below the output's limits
            self._abort(f"test {len(self.done) + 1}: {err}")
            return
        self._watch, self._forwarded = None, 0
        self.phase = "test"
        self.events.append(Event(t, "repeat", {"test": len(self.done) + 1}))

    def _abort(self, reason: str) -> Demand:
        self.phase, self.reason = "aborted", reason
        self.events.append(Event(self._t_end, "aborted", {"reason": reason}))
        return Demand(op=self.op_start)

    def _take_events(self, test: StepTest) -> None:
        """The running test's new events, numbered (1, 2, …): one list for the whole run.
        Called before a finished test joins ``done``."""
        n = len(self.done) + 1
        for e in test.events[self._forwarded :]:
            self.events.append(Event(e.t, e.kind, {**e.data, "test": n}))
        self._forwarded = len(test.events)


def _mean_curve(
    curves: list[ReactionCurve | IntegratingCurve], spreads: dict[str, Spread]
) -> ReactionCurve | IntegratingCurve:
    """The tests' mean, in the first test's form: the averaged figures, and those derived
    from them (R = K/T, a = R·L, L/T) recomputed from the means."""
    first = curves[0]
    mean = {name: s.mean for name, s in spreads.items()}
    if isinstance(first, IntegratingCurve):
        rate, lag = mean["reaction_rate"], mean["dead_time"]
        return dataclasses.replace(
            first,
            reaction_rate=rate,
            dead_time=lag,
            a=rate * lag,
            slope=rate * first.step_size,
        )
    k, lag, t = mean["gain"], mean["dead_time"], mean["time_constant_tangent"]
    rate = k / t
    return dataclasses.replace(
        first,
        gain=k,
        dead_time=lag,
        time_constant_tangent=t,
        time_constant_63=mean["time_constant_63"],
        reaction_rate=rate,
        slope=rate * first.step_size,
        a=rate * lag,
        l_over_t=lag / t,
        pv_after=first.pv_before + k * first.step_size,
        method="mean",
    )


def _mean_model(models: list[ProcessFit]) -> ProcessFit | None:
    """The tests' fitted models averaged, of the kind most of them have (ties: the first's);
    None without any."""
    if not models:
        return None
    kind = Counter(m.kind for m in models).most_common(1)[0][0]
    same = [m for m in models if m.kind == kind]
    lags = tuple(statistics.fmean(m.lags[i] for m in same) for i in range(len(same[0].lags)))
    return ProcessFit(
        kind,
        statistics.fmean(m.gain for m in same),
        lags,
        statistics.fmean(m.delay for m in same),
        statistics.fmean(m.rms for m in same),
        noise_rms=statistics.fmean(m.noise_rms for m in same),
        source="fit" if all(m.source == "fit" for m in same) else "reaction curve",
    )


def build(settings: Settings, setup: Setup) -> StepTest | RepeatedSteps:
    """The step test a request asks for: one (``repeat`` unset or 1), else repeated; ValueError
    naming the setting that cannot work."""
    single = step_test.build(settings, setup)
    if not settings.repeat_auto and (settings.repeat or 1) == 1:
        return single
    return RepeatedSteps.like(
        single, repeat=settings.repeat or AUTO_LIMIT, auto=settings.repeat_auto
    )
