"""A user's model class for the tests: a first-order lag with dead time whose output carries
a hidden load, swinging sinusoidally (an unmeasured disturbance the tuner cannot see)."""

from __future__ import annotations

import math
from collections import deque


class Drifting:
    """PV = K/(τs + 1)·e^{−Ls} of (output + load), the load ``amp`` % swinging with period
    ``period`` s."""

    pv_units = "u"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time, op0=50.0, k=1.0, tau=10.0, delay=2.0, amp=0.5, period=40.0):
        self.sample_time, self.op0, self.k, self.tau = sample_time, op0, k, tau
        self.n = round(delay / sample_time)
        self.amp, self.period = amp, period
        self.disturbances = {"load": 0.0}

    def reset(self) -> float:
        self.t = 0.0
        self.y = self.k * self.op0
        self.ops = deque([self.op0] * (self.n + 1), maxlen=self.n + 1)
        return self.y

    def step(self, op: float) -> float:
        self.t += self.sample_time
        load = self.disturbances["load"] + self.amp * math.sin(2 * math.pi * self.t / self.period)
        self.ops.appendleft(op + load)
        a = math.exp(-self.sample_time / self.tau)
        self.y = a * self.y + (1 - a) * self.k * self.ops[self.n]
        return self.y

    def disturbance_names(self) -> tuple[str, ...]:
        return tuple(self.disturbances)

    def set_disturbance(self, name: str, value: float) -> None:
        if name not in self.disturbances:
            raise KeyError(name)
        self.disturbances[name] = float(value)
