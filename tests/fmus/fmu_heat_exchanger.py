"""A heat exchanger as an FMI 2.0 co-simulation FMU (built by pythonfmu in the tests).

Steam valve (fraction 0–1) → outlet temperature T_out (°C), with the inlet temperature T_in
(°C) a disturbance input::

    tau1·dT_w/dt = −T_w + Kv·valve          (wall, heated by the steam)
    tau2·dT/dt   = −T + T_w + T_in           (water)

so T_out = T_in + Kv·valve at rest, valve → T_out is Kv/((tau1·s + 1)(tau2·s + 1)) and
T_in → T_out is 1/(tau2·s + 1). Both are integrated in closed form over each step (inputs
held), so the samples are the continuous response to rounding.
"""

import math

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real


class HeatExchanger(Fmi2Slave):
    author = "autotune tests"
    description = "Heat exchanger, two lags, inlet temperature disturbance"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.Kv = 100.0  # °C per unit valve opening
        self.tau1 = 10.0  # s
        self.tau2 = 60.0  # s
        self.valve = 0.4
        self.T_in = 20.0
        self.T_out = 60.0
        self._w = 40.0  # wall state, °C above the inlet's contribution
        for name in ("Kv", "tau1", "tau2"):
            self.register_variable(
                Real(name, causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed)
            )
        self.register_variable(Real("valve", causality=Fmi2Causality.input))
        self.register_variable(Real("T_in", causality=Fmi2Causality.input))
        self.register_variable(Real("T_out", causality=Fmi2Causality.output))

    def exit_initialization_mode(self):
        if not (self.tau1 > 0 and self.tau2 > 0 and self.tau1 != self.tau2):
            raise ValueError(f"tau1 and tau2 must be > 0 and differ, got {self.tau1}, {self.tau2}")
        self._w = self.Kv * self.valve
        self.T_out = self._w + self.T_in

    def do_step(self, current_time, step_size):
        a1 = math.exp(-step_size / self.tau1)
        a2 = math.exp(-step_size / self.tau2)
        w_ss = self.Kv * self.valve
        e0 = self._w - w_ss  # the wall's distance from its rest, decaying with tau1
        c = e0 * self.tau1 / (self.tau1 - self.tau2)
        t_ss = w_ss + self.T_in
        self.T_out = t_ss + c * a1 + (self.T_out - t_ss - c) * a2
        self._w = w_ss + e0 * a1
        return True
