"""A user's model whose step() takes 20 ms of wall time: slower than its period on a realtime
clock at ×20 with a 0.1 s sample time (5 ms allowed)."""

from __future__ import annotations

import time

from tests.lag_model import Lag


class SlowStep(Lag):
    def step(self, op):
        time.sleep(0.02)  # the model's own cost, what the test is about (not a wait)
        return super().step(op)
