"""The process-model protocol and the linear models: transfer function, FOPDT, IPDT.

Any class that satisfies ``ProcessModel`` can be named in a plant file as
``package.module:Class``; the service constructs it as ``Class(sample_time=T, **params)``
with the loop's remaining keys as ``params``.
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np

from shared.control.lti import (
    DelayedLinearSystem,
    DiscreteDelaySystem,
    discretize,
    split_delay,
    tf_to_ss,
)

# The longest dead time a plant model keeps, in sample periods: its delay line holds one
# float per sample (1e12 s at 0.25 s took all the memory there was).
MAX_DELAY_SAMPLES = 1_000_000
# a transfer function's num and den: at most this order. A process model has a few lags; the
# state-space form is order × order, so a den of 3,000 coefficients took 28 s to be refused
# (as unstable) and one of 100,000 tried to allocate 75 GiB (user trial)
MAX_ORDER = 100


class ModelParamError(ValueError):
    """A bad model parameter; ``field`` names it for the plant-file error message."""

    def __init__(self, field: str, reason: str):
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}")


@runtime_checkable
class ProcessModel(Protocol):
    """A process as its loop sees it: output held in (% of span), true PV out (PV units).

    Attributes: ``sample_time`` (s), ``pv_units``, ``pv_range`` (the transmitter's range, a
    default the plant file may override) and ``op0``, the output (%) at the operating point
    where ``reset`` leaves the process at rest.
    """

    sample_time: float
    pv_units: str
    pv_range: tuple[float, float]
    op0: float

    def reset(self) -> float:
        """Put the process at rest at its operating point; return the PV there."""
        ...

    def step(self, op: float) -> float:
        """Hold ``op`` (% of span) for one sample period; return the PV at its end."""
        ...

    def disturbance_names(self) -> tuple[str, ...]:
        """Names of the disturbance inputs ``set_disturbance`` accepts."""
        ...

    def set_disturbance(self, name: str, value: float) -> None:
        """Set one disturbance input; KeyError for an unknown name, ValueError for a bad value."""
        ...


def finite(
    field: str,
    value: float,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
) -> float:
    """Check a numeric parameter; raise ModelParamError naming ``field``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ModelParamError(field, f"expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ModelParamError(field, f"must be finite, got {value!r}")
    if low is not None and (v <= low if low_open else v < low):
        raise ModelParamError(field, f"must be {'>' if low_open else '≥'} {low}, got {v}")
    if high is not None and v > high:
        raise ModelParamError(field, f"must be ≤ {high}, got {v}")
    return v


def coefficients(field: str, values: list[float]) -> list[float]:
    if not isinstance(values, list | tuple) or not values:
        raise ModelParamError(field, f"expected a non-empty list of numbers, got {values!r}")
    if len(values) > MAX_ORDER + 1:
        raise ModelParamError(
            field,
            f"{len(values)} coefficients (order {len(values) - 1}); at most {MAX_ORDER + 1} "
            f"(order {MAX_ORDER})",
        )
    return [finite(f"{field}[{i}]", v) for i, v in enumerate(values)]


def check_delay(delay: float, sample_time: float) -> float:
    """The dead time (s), finite, ≥ 0 and at most MAX_DELAY_SAMPLES sample periods."""
    delay = finite("delay", delay, low=0.0)
    if delay / sample_time > MAX_DELAY_SAMPLES:
        raise ModelParamError(
            "delay",
            f"{delay:g} s is {delay / sample_time:.3g} sample periods of {sample_time:g} s; "
            f"at most {MAX_DELAY_SAMPLES} (the delay line keeps one value per sample)",
        )
    split_delay(delay, sample_time)
    return delay


def check_stable(den: np.ndarray) -> None:
    """ModelParamError("den") when a pole lies in the open right half-plane."""
    poles = np.roots(den)
    bad = [p for p in poles if p.real > 1e-9 * max(1.0, abs(p))]
    if bad:
        p = max(bad, key=lambda z: z.real)
        where = f"{p.real:.4g}" if abs(p.imag) <= 1e-12 * abs(p) else f"{p:.4g}"
        raise ModelParamError(
            "den",
            f"the process is open-loop unstable (a pole at s = {where}): plant_sim simulates "
            "stable and integrating processes",
        )


def check_discrete(sys: DiscreteDelaySystem, pv0: float) -> None:
    """ModelParamError when the sampled model overflows: its matrices, or the PV that a full
    swing of the output (and of the load) would give at steady state."""
    parts = [sys.phi, sys.gamma_new, sys.gamma_old, sys.c, np.array([sys.d])]
    if not all(np.all(np.isfinite(m)) for m in parts):
        raise ModelParamError(
            "den",
            "the model cannot be simulated in floating point at this sample time (its sampled "
            "matrices overflow: coefficients too large or too small, or sample_time too long)",
        )
    with np.errstate(all="ignore"):
        gain = sys.dc_gain()
    if math.isfinite(gain) and not abs(pv0) + abs(gain) * 200.0 < 1e300:
        raise ModelParamError(
            "num", f"the static gain {gain:.4g} PV units per % overflows the PV's arithmetic"
        )


class TransferFunctionModel:
    """PV = pv0 + G(s)·(op − op0 + load), G(s) = num(s)/den(s)·e^{−delay·s}.

    ``num`` and ``den`` in descending powers of s, PV units per % of output; ``delay`` in s,
    exact even when it is not a whole number of samples; ``sensor_lag`` (s) is a first-order
    transmitter lag folded into G exactly. Disturbance ``load``: a load in % of output,
    entering with the output (an input disturbance).
    """

    pv_units = "%"
    pv_range = (0.0, 100.0)

    def __init__(
        self,
        sample_time: float,
        num: list[float],
        den: list[float],
        delay: float = 0.0,
        op0: float = 50.0,
        pv0: float = 50.0,
        sensor_lag: float = 0.0,
        names: Mapping[str, str] | None = None,
    ):
        """``names``: the fields a model built on this one calls ``num`` and ``den`` (an FOPDT's
        ``gain`` and ``time_constant``), named in its errors instead: its plant file has no
        ``num`` to fix."""
        try:
            self._build(sample_time, num, den, delay, op0, pv0, sensor_lag)
        except ModelParamError as err:
            root = err.field.split("[", 1)[0]
            if names and root in names:
                raise ModelParamError(names[root], err.reason) from None
            raise

    def _build(
        self,
        sample_time: float,
        num: list[float],
        den: list[float],
        delay: float,
        op0: float,
        pv0: float,
        sensor_lag: float,
    ) -> None:
        self.sample_time = finite("sample_time", sample_time, low=0.0, low_open=True)
        self.num = coefficients("num", num)
        self.den = coefficients("den", den)
        self.delay = check_delay(delay, self.sample_time)
        self.op0 = finite("op0", op0, low=0.0, high=100.0)
        self.pv0 = finite("pv0", pv0)
        self.sensor_lag = finite("sensor_lag", sensor_lag, low=0.0)
        den_full = np.polymul(self.den, [self.sensor_lag, 1.0]) if self.sensor_lag else self.den
        with np.errstate(all="ignore"), warnings.catch_warnings():  # judged below, not printed
            warnings.simplefilter("ignore")
            try:
                a, b, c, d = tf_to_ss(self.num, list(den_full))
            except ValueError as err:
                field, _, reason = str(err).partition(": ")
                raise ModelParamError(field, reason) from None
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.isfinite(d)):
                raise ModelParamError(
                    "num", "the transfer function overflows (coefficients too large or too small)"
                )
            check_stable(np.trim_zeros(np.asarray(den_full, dtype=float), "f"))
            self.discrete = discretize(a, b, c, d, self.sample_time, self.delay)
        check_discrete(self.discrete, self.pv0)
        self._sys = DelayedLinearSystem(self.discrete)
        self.load = 0.0

    def reset(self) -> float:
        self._sys.reset()
        return self.pv0 + self._sys.output()

    def step(self, op: float) -> float:
        return self.pv0 + self._sys.step(op - self.op0 + self.load)

    def disturbance_names(self) -> tuple[str, ...]:
        return ("load",)

    def set_disturbance(self, name: str, value: float) -> None:
        if name != "load":
            raise KeyError(name)
        self.load = finite("load", value, low=-100.0, high=100.0)


class FirstOrderPlusDeadTime(TransferFunctionModel):
    """PV = pv0 + gain·e^{−delay·s}/(time_constant·s + 1)·(op − op0 + load)."""

    def __init__(
        self,
        sample_time: float,
        gain: float,
        time_constant: float,
        delay: float = 0.0,
        op0: float = 50.0,
        pv0: float = 50.0,
        sensor_lag: float = 0.0,
    ):
        gain = finite("gain", gain)
        time_constant = finite("time_constant", time_constant, low=0.0, low_open=True)
        super().__init__(
            sample_time,
            [gain],
            [time_constant, 1.0],
            delay,
            op0,
            pv0,
            sensor_lag,
            names={"num": "gain", "den": "time_constant"},
        )


class IntegratingPlusDeadTime(TransferFunctionModel):
    """PV = pv0 + gain·e^{−delay·s}/s·(op − op0 + load); ``gain`` in PV units/s per %.

    At rest only with the output at ``op0`` (the balance point).
    """

    def __init__(
        self,
        sample_time: float,
        gain: float,
        delay: float = 0.0,
        op0: float = 50.0,
        pv0: float = 50.0,
        sensor_lag: float = 0.0,
    ):
        gain = finite("gain", gain)
        super().__init__(
            sample_time,
            [gain],
            [1.0, 0.0],
            delay,
            op0,
            pv0,
            sensor_lag,
            names={"num": "gain", "den": "gain"},
        )
