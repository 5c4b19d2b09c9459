"""A user's model class as the README describes one: a 5 s lag of gain 1 about PV 50, for the
model-check tests to derive their faulty models from (``tests.test_model_check_*``)."""

from __future__ import annotations

import math


class Lag:
    """A 5 s lag of gain 1 about PV 50, stepped by its own ``sample_time``; ``n``: its steps."""

    pv_units = "%"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time, op0=50.0):
        self.sample_time, self.op0 = sample_time, op0
        self.n = 0

    def reset(self):
        self.x = 50.0
        return self.x

    def step(self, op):
        self.n += 1
        a = math.exp(-self.sample_time / 5.0)
        self.x = a * self.x + (1 - a) * (50.0 + op - self.op0)
        return self.x

    def disturbance_names(self):
        return ()

    def set_disturbance(self, name, value):
        raise KeyError(name)
