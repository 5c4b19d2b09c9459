"""First order plus dead time as an FMI 2.0 co-simulation FMU (built by pythonfmu in the tests).

y = y0 + K·e^{−L·s}/(tau·s + 1)·(u − u0). The input is held over each communication step (the
master's zero-order hold) and delayed by L exactly: the lag is integrated in closed form over
every piece of constant delayed input, so its samples are the continuous response to rounding.
"""

import math

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real


class Fopdt(Fmi2Slave):
    author = "autotune tests"
    description = "First order plus dead time, exact"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.K = 2.0  # output units per input unit
        self.tau = 10.0  # s
        self.L = 2.0  # s, dead time on the input
        self.u0 = 50.0  # input at the operating point
        self.y0 = 50.0  # output there
        self.u = 50.0
        self.y = 50.0
        self._x = 0.0
        self._changes = [(-math.inf, self.u)]  # (from time, input value), oldest first
        for name in ("K", "tau", "L", "u0", "y0"):
            self.register_variable(
                Real(name, causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed)
            )
        self.register_variable(Real("u", causality=Fmi2Causality.input))
        self.register_variable(Real("y", causality=Fmi2Causality.output))

    def exit_initialization_mode(self):
        if not self.tau > 0 or not self.L >= 0:
            raise ValueError(f"tau must be > 0 and L >= 0, got tau={self.tau}, L={self.L}")
        self._x = self.K * (self.u - self.u0)  # at rest with the input it starts with
        self._changes = [(-math.inf, self.u)]
        self.y = self.y0 + self._x

    def do_step(self, current_time, step_size):
        if self.u != self._changes[-1][1]:
            self._changes.append((current_time, self.u))
        now, end = current_time, current_time + step_size
        while now < end:
            # the delayed input at `now` and the time it next changes
            i = max(j for j, (t, _) in enumerate(self._changes) if t + self.L <= now)
            nxt = self._changes[i + 1][0] + self.L if i + 1 < len(self._changes) else math.inf
            stop = min(end, nxt)
            a = math.exp(-(stop - now) / self.tau)
            self._x = a * self._x + (1.0 - a) * self.K * (self._changes[i][1] - self.u0)
            now = stop
        while len(self._changes) > 1 and self._changes[1][0] + self.L <= end:
            self._changes.pop(0)
        self.y = self.y0 + self._x
        return True
