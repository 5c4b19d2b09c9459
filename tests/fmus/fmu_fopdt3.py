"""First order plus dead time as an FMI 3.0 co-simulation FMU (built by pythonfmu3 in the
tests): the model of fmu_fopdt.py, integrated the same exact way."""

import math

from pythonfmu3 import Float64, Fmi3Causality, Fmi3Slave, Fmi3Variability


class Fopdt3(Fmi3Slave):
    author = "autotune tests"
    description = "First order plus dead time, exact (FMI 3.0)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.time = 0.0
        self.K = 2.0
        self.tau = 10.0
        self.L = 2.0
        self.u0 = 50.0
        self.y0 = 50.0
        self.u = 50.0
        self.y = 50.0
        self._x = 0.0
        self._changes = [(-math.inf, self.u)]
        self.register_variable(
            Float64(
                "time", causality=Fmi3Causality.independent, variability=Fmi3Variability.continuous
            )
        )
        for name in ("K", "tau", "L", "u0", "y0"):
            self.register_variable(
                Float64(name, causality=Fmi3Causality.parameter, variability=Fmi3Variability.fixed)
            )
        self.register_variable(Float64("u", causality=Fmi3Causality.input))
        self.register_variable(Float64("y", causality=Fmi3Causality.output))

    def exit_initialization_mode(self):
        self._x = self.K * (self.u - self.u0)
        self._changes = [(-math.inf, self.u)]
        self.y = self.y0 + self._x

    def do_step(self, current_time, step_size):
        if self.u != self._changes[-1][1]:
            self._changes.append((current_time, self.u))
        now, end = current_time, current_time + step_size
        while now < end:
            i = max(j for j, (t, _) in enumerate(self._changes) if t + self.L <= now)
            nxt = self._changes[i + 1][0] + self.L if i + 1 < len(self._changes) else math.inf
            stop = min(end, nxt)
            a = math.exp(-(stop - now) / self.tau)
            self._x = a * self._x + (1.0 - a) * self.K * (self._changes[i][1] - self.u0)
            now = stop
        while len(self._changes) > 1 and self._changes[1][0] + self.L <= end:
            self._changes.pop(0)
        self.y = self.y0 + self._x
        self.time = end
        return True
