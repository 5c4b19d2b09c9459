"""A user's model class for the tests: a first-order lag with dead time whose process fails
high at a given sim time (a burst line, a stuck-open bypass): from then on its PV is far
above the transmitter's range, which reads it at the top of its span."""

from __future__ import annotations

import math

from tests.drifting_plant import Drifting


class FailsHigh(Drifting):
    """PV = K/(τs + 1)·e^{−Ls} of the output (no hidden load) until ``fail_at`` s of sim
    time, then 1e6."""

    def __init__(self, sample_time, op0=50.0, k=1.0, tau=10.0, delay=2.0, fail_at=math.inf):
        super().__init__(sample_time, op0, k, tau, delay, amp=0.0)
        self.fail_at = fail_at

    def step(self, op: float) -> float:
        if self.t + self.sample_time >= self.fail_at:
            self.t += self.sample_time
            return 1e6
        return super().step(op)
