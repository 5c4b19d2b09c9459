"""An FMU that fails on request (FMI 2.0 co-simulation, built by pythonfmu in the tests).

y follows u through a first-order lag; ``fail_init`` = 1 makes initialisation raise,
``fail_after`` = n > 0 makes the n-th step after that raise, and ``nan_after`` = n makes the
output NaN from the n-th step on: the failures a plant must report in the FMU's own words.
"""

import math

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Integer, Real


class Faulty(Fmi2Slave):
    author = "autotune tests"
    description = "Fails on request"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.fail_init = 0
        self.fail_after = -1
        self.nan_after = -1
        self.u = 50.0
        self.y = 50.0
        self.n = 0
        for name in ("fail_init", "fail_after", "nan_after"):
            self.register_variable(
                Integer(name, causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed)
            )
        self.register_variable(Real("u", causality=Fmi2Causality.input))
        self.register_variable(Real("y", causality=Fmi2Causality.output))

    def exit_initialization_mode(self):
        if self.fail_init:
            raise RuntimeError("the valve map file vmap.csv is missing")
        self.y = self.u
        self.n = 0

    def do_step(self, current_time, step_size):
        self.n += 1
        if self.n == self.fail_after:
            raise RuntimeError(f"sensor fault after {self.n - 1} steps")
        a = math.exp(-step_size / 5.0)
        self.y = a * self.y + (1.0 - a) * self.u
        if 0 <= self.nan_after <= self.n:
            self.y = math.nan
        return True
