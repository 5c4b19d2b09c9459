"""A tank drained by gravity as an FMI 2.0 co-simulation FMU (built by pythonfmu in the tests).

area·dh/dt = inflow_max·valve/100 − cv·√h: inlet valve (%) → level h (m), nonlinear (the
square-root law): at rest h = (inflow_max·valve/(100·cv))², so the static gain and the time
constant grow with the level. RK4 over 20 sub-steps per communication step.
"""

import math

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real


class Tank(Fmi2Slave):
    author = "autotune tests"
    description = "Tank level, gravity drain (square-root law)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.area = 0.2  # m²
        self.inflow_max = 0.02  # m³/s at 100 % valve
        self.cv = 0.01 / math.sqrt(1.5)  # m^2.5/s: 1.5 m at 50 %
        self.valve = 50.0
        self.h = 1.5
        for name in ("area", "inflow_max", "cv"):
            self.register_variable(
                Real(name, causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed)
            )
        self.register_variable(Real("valve", causality=Fmi2Causality.input))
        self.register_variable(Real("h", causality=Fmi2Causality.output))

    def _dh(self, h):
        return (self.inflow_max * self.valve / 100.0 - self.cv * math.sqrt(max(h, 0.0))) / self.area

    def exit_initialization_mode(self):
        self.h = (self.inflow_max * self.valve / 100.0 / self.cv) ** 2

    def do_step(self, current_time, step_size):
        n = 20
        dt = step_size / n
        h = self.h
        for _ in range(n):
            k1 = self._dh(h)
            k2 = self._dh(h + 0.5 * dt * k1)
            k3 = self._dh(h + 0.5 * dt * k2)
            k4 = self._dh(h + dt * k3)
            h = max(h + dt * (k1 + 2 * k2 + 2 * k3 + k4) / 6.0, 0.0)
        self.h = h
        return True
