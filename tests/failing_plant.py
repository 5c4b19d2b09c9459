"""A user's model class for the tests: a first-order lag with dead time whose process fails
high at a given sim time (a burst line, a stuck-open bypass): from then on its PV is far
above the transmitter's range, which reads it at the top of its span."""

from __future__ import annotations

import math
from collections import deque


class FailsHigh:
    """PV = K/(τs + 1)·e^{−Ls} of the output until ``fail_at`` s of sim time, then 1e6."""

    pv_units = "u"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time, op0=50.0, k=1.0, tau=10.0, delay=2.0, fail_at=math.inf):
        self.sample_time, self.op0, self.k, self.tau = sample_time, op0, k, tau
        self.n = round(delay / sample_time)
        self.fail_at = fail_at
        self.disturbances = {"load": 0.0}

    def reset(self) -> float:
        self.t = 0.0
        self.y = self.k * self.op0
        self.ops = deque([self.op0] * (self.n + 1), maxlen=self.n + 1)
        return self.y

    def step(self, op: float) -> float:
        self.t += self.sample_time
        if self.t >= self.fail_at:
            return 1e6
        self.ops.appendleft(op + self.disturbances["load"])
        a = math.exp(-self.sample_time / self.tau)
        self.y = a * self.y + (1 - a) * self.k * self.ops[self.n]
        return self.y

    def disturbance_names(self) -> tuple[str, ...]:
        return tuple(self.disturbances)

    def set_disturbance(self, name: str, value: float) -> None:
        if name not in self.disturbances:
            raise KeyError(name)
        self.disturbances[name] = float(value)
