"""Nonlinear physical processes: heat exchanger, tanks and a flow loop.

They are ODEs in physical units integrated with classical Runge–Kutta (RK4) over fixed
sub-steps of each sample period, with the output held (zero-order hold). The sub-step is at
most a twentieth of the fastest time constant, so the integration error is far below any
measurement noise. A transport delay on the measurement is kept as a line of past samples
(exact for whole samples, linear interpolation for a fraction of a sample); a transmitter
lag is a first-order filter discretised exactly for an input linear between samples.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np

from services.plant_sim.simulation.models import ModelParamError, check_delay, finite
from shared.control.lti import split_delay

# RK4 sub-steps per sample at most: a sample time far beyond the fastest time constant (or a
# time constant driven towards zero by its parameters) would otherwise stall the loop.
MAX_SUBSTEPS = 1000

CHARACTERISTICS = ("linear", "equal_percentage", "quick_opening")


def valve_fraction(position: float, characteristic: str, rangeability: float) -> float:
    """Flow fraction (0–1) of a valve at ``position`` % under its inherent characteristic."""
    x = min(max(position / 100.0, 0.0), 1.0)
    if characteristic == "linear":
        return x
    if characteristic == "equal_percentage":
        return (rangeability**x - 1.0) / (rangeability - 1.0)
    return math.sqrt(x)


def check_characteristic(characteristic: str, rangeability: float) -> tuple[str, float]:
    if characteristic not in CHARACTERISTICS:
        raise ModelParamError(
            "characteristic", f"must be one of {', '.join(CHARACTERISTICS)}, got {characteristic!r}"
        )
    return characteristic, finite("rangeability", rangeability, low=1.0, low_open=True)


class TransportDelay:
    """PV seen ``delay`` seconds late: whole samples exact, the fraction interpolated."""

    def __init__(self, delay: float, sample_time: float):
        self.n, f = split_delay(delay, sample_time)
        self.frac = f / sample_time
        self._past: deque[float] = deque(maxlen=self.n + 2)

    def fill(self, value: float) -> None:
        self._past.clear()
        self._past.extend([value] * (self.n + 2))

    def push(self, value: float) -> float:
        self._past.appendleft(value)
        return (1.0 - self.frac) * self._past[self.n] + self.frac * self._past[self.n + 1]


class SensorLag:
    """First-order lag τ; exact when the input moves linearly between samples."""

    def __init__(self, tau: float, sample_time: float):
        self.tau = tau
        if tau > 0:
            a = math.exp(-sample_time / tau)
            self._a, self._b = a, 1.0 - tau * (1.0 - a) / sample_time
        self._y = 0.0
        self._u = 0.0

    def fill(self, value: float) -> None:
        self._y = self._u = value

    def push(self, u: float) -> float:
        if self.tau <= 0:
            self._y = u
        else:
            self._y = self._a * self._y + (1.0 - self._a) * self._u + (u - self._u) * self._b
        self._u = u
        return self._y


def rk4(
    f: Callable[[np.ndarray, float], np.ndarray], x: np.ndarray, op: float, h: float, n: int
) -> np.ndarray:
    """Integrate ẋ = f(x, op) over n steps of h with op held."""
    for _ in range(n):
        k1 = f(x, op)
        k2 = f(x + 0.5 * h * k1, op)
        k3 = f(x + 0.5 * h * k2, op)
        k4 = f(x + h * k3, op)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


class OdeProcess:
    """Common shell of the physical models: sub-stepped RK4, state limits, delay, sensor lag.

    Subclasses set ``disturbances`` (name → value), ``_limits`` (name → (low, high)) and
    implement ``_derivatives``, ``_rest_state``, ``_pv`` and optionally ``_clip``.
    """

    pv_units = ""
    pv_range = (0.0, 100.0)

    def __init__(
        self,
        sample_time: float,
        op0: float,
        delay: float,
        sensor_lag: float,
        fastest_time_constant: float,
    ):
        self.sample_time = finite("sample_time", sample_time, low=0.0, low_open=True)
        self.op0 = finite("op0", op0, low=0.0, high=100.0)
        self.delay = check_delay(delay, self.sample_time)
        self.sensor_lag = finite("sensor_lag", sensor_lag, low=0.0)
        ratio = self.sample_time / fastest_time_constant if fastest_time_constant > 0 else math.inf
        substeps = 20.0 * ratio
        if not substeps <= MAX_SUBSTEPS:
            raise ModelParamError(
                "sample_time",
                f"{self.sample_time:g} s is {ratio:.3g} times this model's fastest time constant "
                f"({fastest_time_constant:.3g} s, from its parameters); at most "
                f"{MAX_SUBSTEPS // 20} (the integration would take {substeps:.3g} sub-steps "
                "per sample)",
            )
        self._substeps = max(1, math.ceil(substeps))
        self._h = self.sample_time / self._substeps
        self._delay_line = TransportDelay(self.delay, self.sample_time)
        self._lag = SensorLag(self.sensor_lag, self.sample_time)
        self.disturbances: dict[str, float] = {}
        self._limits: dict[str, tuple[float, float]] = {}
        self._x = np.zeros(0)

    def _derivatives(self, x: np.ndarray, op: float) -> np.ndarray:
        raise NotImplementedError

    def _rest_state(self, op: float) -> np.ndarray:
        raise NotImplementedError

    def _pv(self, x: np.ndarray) -> float:
        raise NotImplementedError

    def _clip(self, x: np.ndarray) -> np.ndarray:
        return x

    def _check_scale(self) -> None:
        """ModelParamError when the parameters put the model beyond floating-point range: its
        state at rest, or one sample from rest at 0 % or 100 % output, is not finite (a
        subclass calls this last in its constructor)."""
        try:
            with np.errstate(all="ignore"):
                x = self._rest_state(self.op0)
                ok = bool(np.all(np.isfinite(x))) and math.isfinite(self._pv(x))
                for op in (0.0, 100.0):
                    y = self._clip(rk4(self._derivatives, x, op, self._h, self._substeps))
                    ok = ok and bool(np.all(np.isfinite(y)))
        except (ArithmeticError, ValueError):
            ok = False
        if not ok:
            raise ModelParamError(
                "model",
                "its parameters are out of floating-point range (the state at rest, or one "
                "sample from it at 0 % or 100 % output, is not a finite number)",
            )

    def reset(self) -> float:
        self._x = self._rest_state(self.op0)
        pv = self._pv(self._x)
        self._delay_line.fill(pv)
        self._lag.fill(pv)
        return pv

    def step(self, op: float) -> float:
        op = min(max(op, 0.0), 100.0)
        self._x = self._clip(rk4(self._derivatives, self._x, op, self._h, self._substeps))
        return self._lag.push(self._delay_line.push(self._pv(self._x)))

    def disturbance_names(self) -> tuple[str, ...]:
        return tuple(self.disturbances)

    def set_disturbance(self, name: str, value: float) -> None:
        if name not in self.disturbances:
            raise KeyError(name)
        low, high = self._limits[name]
        self.disturbances[name] = finite(name, value, low=low, high=high)


class HeatExchangerPhysical(OdeProcess):
    """Steam-heated water heater: steam valve % → outlet water temperature, °C.

    Energy balances of the tube wall and the water hold-up (lumped)::

        C_w·dT_w/dt = ṁ_s·h_fg − UA·(T_w − T)
        C_f·dT/dt   = F·c_p·(T_in − T) + UA·(T_w − T)

    ṁ_s = steam_max·f(valve) with the valve's inherent characteristic. The outlet is measured
    after the pipe's transport ``delay`` and the thermowell's ``sensor_lag``. Disturbances:
    ``inlet_temp`` (°C) and ``flow`` (water, kg/s): the gain and time constants vary with flow.
    Defaults: 60 °C at 40 % valve, about 1 °C/%, time constants ≈ 9 s and ≈ 75 s.
    """

    pv_units = "degC"
    pv_range = (0.0, 150.0)
    CP = 4186.0  # J/(kg·K), water
    H_FG = 2.1e6  # J/kg, latent heat of steam at about 3 bar

    def __init__(
        self,
        sample_time: float,
        op0: float = 40.0,
        steam_max: float = 0.4,
        flow: float = 2.0,
        inlet_temp: float = 20.0,
        ua: float = 12000.0,
        water_mass: float = 60.0,
        wall_capacity: float = 250000.0,
        delay: float = 5.0,
        sensor_lag: float = 1.0,
        characteristic: str = "linear",
        rangeability: float = 30.0,
    ):
        self.steam_max = finite("steam_max", steam_max, low=0.0, low_open=True)
        self.ua = finite("ua", ua, low=0.0, low_open=True)
        self.c_f = finite("water_mass", water_mass, low=0.0, low_open=True) * self.CP
        self.c_w = finite("wall_capacity", wall_capacity, low=0.0, low_open=True)
        self.characteristic, self.rangeability = check_characteristic(characteristic, rangeability)
        flow = finite("flow", flow, low=0.0, low_open=True)
        fastest = min(self.c_w / self.ua, self.c_f / (self.ua + 2.0 * flow * self.CP))
        super().__init__(sample_time, op0, delay, sensor_lag, fastest)
        self.disturbances = {
            "inlet_temp": finite("inlet_temp", inlet_temp, low=-20, high=100),
            "flow": flow,
        }
        self._limits = {"inlet_temp": (-20.0, 100.0), "flow": (0.05 * flow, 2.0 * flow)}
        self._check_scale()

    def _heat(self, op: float) -> float:
        return (
            self.steam_max * valve_fraction(op, self.characteristic, self.rangeability) * self.H_FG
        )

    def _derivatives(self, x: np.ndarray, op: float) -> np.ndarray:
        t_wall, t = x
        q_wall = self.ua * (t_wall - t)
        fcp = self.disturbances["flow"] * self.CP
        return np.array(
            [
                (self._heat(op) - q_wall) / self.c_w,
                (fcp * (self.disturbances["inlet_temp"] - t) + q_wall) / self.c_f,
            ]
        )

    def _rest_state(self, op: float) -> np.ndarray:
        q = self._heat(op)
        t = self.disturbances["inlet_temp"] + q / (self.disturbances["flow"] * self.CP)
        return np.array([t + q / self.ua, t])

    def _pv(self, x: np.ndarray) -> float:
        return float(x[1])


class TankLevel(OdeProcess):
    """Tank filled through a valve, drained by gravity: A·dh/dt = q_in − c_v·(v/100)·√h.

    Inlet valve % → level, m. Self-regulating with a gain and time constant that grow with the
    level (the square-root law). The outlet is a hand valve (disturbance ``outlet_valve``, % open);
    ``inflow`` adds an unmeasured inflow (m³/s). The level stays between 0 and ``height``
    (the tank overflows at the top). Defaults: 1.5 m at 50 %, τ ≈ 600 s, gain ≈ 0.06 m/%.
    """

    pv_units = "m"

    def __init__(
        self,
        sample_time: float,
        op0: float = 50.0,
        area: float = 2.0,
        height: float = 3.0,
        inflow_max: float = 0.02,
        level0: float = 1.5,
        delay: float = 1.0,
        sensor_lag: float = 0.0,
    ):
        self.area = finite("area", area, low=0.0, low_open=True)
        self.height = finite("height", height, low=0.0, low_open=True)
        self.inflow_max = finite("inflow_max", inflow_max, low=0.0, low_open=True)
        level0 = finite("level0", level0, low=0.0, low_open=True, high=self.height)
        op0 = finite("op0", op0, low=0.0, high=100.0)
        if op0 <= 0:
            raise ModelParamError("op0", "must be > 0 for the tank to be at rest at level0")
        self.cv = self.inflow_max * op0 / 100.0 / math.sqrt(level0)
        self.pv_range = (0.0, self.height)
        tau = 2.0 * self.area * math.sqrt(level0) / self.cv
        super().__init__(sample_time, op0, delay, sensor_lag, tau)
        self.disturbances = {"outlet_valve": 100.0, "inflow": 0.0}
        self._limits = {"outlet_valve": (0.0, 100.0), "inflow": (-self.inflow_max, self.inflow_max)}
        self._check_scale()

    def _derivatives(self, x: np.ndarray, op: float) -> np.ndarray:
        h = max(x[0], 0.0)
        q_out = self.cv * self.disturbances["outlet_valve"] / 100.0 * math.sqrt(h)
        q_in = self.inflow_max * op / 100.0 + self.disturbances["inflow"]
        return np.array([(q_in - q_out) / self.area])

    def _rest_state(self, op: float) -> np.ndarray:
        q_in = self.inflow_max * op / 100.0 + self.disturbances["inflow"]
        open_cv = self.cv * self.disturbances["outlet_valve"] / 100.0
        h = (q_in / open_cv) ** 2 if open_cv > 0 else self.height
        return np.array([min(max(h, 0.0), self.height)])

    def _clip(self, x: np.ndarray) -> np.ndarray:
        return np.clip(x, 0.0, self.height)

    def _pv(self, x: np.ndarray) -> float:
        return float(x[0])


class TankLevelPumped(OdeProcess):
    """Tank filled through a valve, emptied by a pump: A·dh/dt = q_in + inflow − q_pump.

    Inlet valve % → level, m. Integrating: at rest only where the valve's flow balances the
    pump (``op0``). Disturbances ``outflow`` (pump flow, m³/s) and ``inflow`` (m³/s). The level
    stays between 0 and ``height``. Default gain 0.0001 m/s per % (≈ 0.36 m/h per %).
    """

    pv_units = "m"

    def __init__(
        self,
        sample_time: float,
        op0: float = 50.0,
        area: float = 2.0,
        height: float = 3.0,
        inflow_max: float = 0.02,
        level0: float = 1.5,
        delay: float = 2.0,
        sensor_lag: float = 0.0,
    ):
        self.area = finite("area", area, low=0.0, low_open=True)
        self.height = finite("height", height, low=0.0, low_open=True)
        self.inflow_max = finite("inflow_max", inflow_max, low=0.0, low_open=True)
        self.level0 = finite("level0", level0, low=0.0, high=self.height)
        self.pv_range = (0.0, self.height)
        super().__init__(sample_time, op0, delay, sensor_lag, math.inf)
        self.disturbances = {"outflow": self.inflow_max * self.op0 / 100.0, "inflow": 0.0}
        self._limits = {
            "outflow": (0.0, self.inflow_max),
            "inflow": (-self.inflow_max, self.inflow_max),
        }
        self._check_scale()

    def _derivatives(self, x: np.ndarray, op: float) -> np.ndarray:
        q_in = self.inflow_max * op / 100.0 + self.disturbances["inflow"]
        q_out = (
            self.disturbances["outflow"]
            if x[0] > 0
            else min(self.disturbances["outflow"], max(q_in, 0.0))
        )
        return np.array([(q_in - q_out) / self.area])

    def _rest_state(self, op: float) -> np.ndarray:
        return np.array([self.level0])

    def _clip(self, x: np.ndarray) -> np.ndarray:
        return np.clip(x, 0.0, self.height)

    def _pv(self, x: np.ndarray) -> float:
        return float(x[0])


class FlowLoop(OdeProcess):
    """Flow through a control valve: valve % → flow, m³/h.

    The actuator follows the output with a first-order lag (``valve_time_constant``), the flow
    follows the installed valve with the fluid's inertia (``flow_time_constant``)::

        τ_v·dx/dt = op − x,   τ_f·dq/dt = q_max·f(x)·√(Δp/Δp₀) − q

    then transport ``delay`` and transmitter damping ``sensor_lag``: a fast loop whose dead time
    is comparable to its time constant. Disturbance ``supply_pressure`` (% of nominal Δp).
    """

    pv_units = "m3/h"

    def __init__(
        self,
        sample_time: float,
        op0: float = 50.0,
        flow_max: float = 100.0,
        valve_time_constant: float = 1.5,
        flow_time_constant: float = 0.5,
        delay: float = 1.0,
        sensor_lag: float = 0.3,
        characteristic: str = "linear",
        rangeability: float = 30.0,
    ):
        self.flow_max = finite("flow_max", flow_max, low=0.0, low_open=True)
        self.tau_v = finite("valve_time_constant", valve_time_constant, low=0.0, low_open=True)
        self.tau_f = finite("flow_time_constant", flow_time_constant, low=0.0, low_open=True)
        self.characteristic, self.rangeability = check_characteristic(characteristic, rangeability)
        self.pv_range = (0.0, self.flow_max)
        super().__init__(sample_time, op0, delay, sensor_lag, min(self.tau_v, self.tau_f))
        self.disturbances = {"supply_pressure": 100.0}
        self._limits = {"supply_pressure": (0.0, 200.0)}
        self._check_scale()

    def _target(self, x: float) -> float:
        return (
            self.flow_max
            * valve_fraction(x, self.characteristic, self.rangeability)
            * math.sqrt(self.disturbances["supply_pressure"] / 100.0)
        )

    def _derivatives(self, x: np.ndarray, op: float) -> np.ndarray:
        pos, q = x
        return np.array([(op - pos) / self.tau_v, (self._target(pos) - q) / self.tau_f])

    def _rest_state(self, op: float) -> np.ndarray:
        return np.array([op, self._target(op)])

    def _pv(self, x: np.ndarray) -> float:
        return float(x[1])
