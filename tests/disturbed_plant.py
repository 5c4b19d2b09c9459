"""A user's model class for the tests: a linear process with dead time whose measurement
carries a slow sinusoidal disturbance (an upset the tuner cannot see), from a helper's trial.

PV = G(s)·output, G = num/den·e^{−delay·s} held over each sample (exact zero-order hold), plus
``sin_amp``·sin(2πt/``sin_period``) from t = 0. ``settling``: the process starts that many %
of output away from its rest at op0 and ``age`` s into its settling toward it (a change an
operator made just before the test), as a self-regulating G leaves it."""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy.signal import cont2discrete, tf2ss


class SineDisturbed:
    pv_units = "u"
    pv_range = (0.0, 100.0)

    def __init__(
        self,
        sample_time: float,
        num: tuple[float, ...] = (1.0,),
        den: tuple[float, ...] = (20.0, 12.0, 1.0),
        delay: float = 3.0,
        sin_amp: float = 0.4,
        sin_period: float = 80.0,
        op0: float = 50.0,
        pv0: float = 50.0,
        settling: float = 0.0,
        age: float = 0.0,
    ):
        a, b, c, d = tf2ss(list(num), list(den))
        ad, bd, cd, dd, _ = cont2discrete((a, b, c, d), sample_time, method="zoh")
        self.ad, self.bd, self.cd, self.dd = ad, bd.ravel(), cd.ravel(), float(dd.ravel()[0])
        self.sample_time, self.ts, self.nd = sample_time, sample_time, round(delay / sample_time)
        self.amp, self.period, self.op0, self.pv0 = sin_amp, sin_period, op0, pv0
        self.settling, self.age = settling, age
        self.disturbances = {"load": 0.0}

    def reset(self) -> float:
        self.k = 0
        n = self.ad.shape[0]
        # at rest with the output ``settling`` % off op0, then op0 held for ``age`` s
        self.x = np.linalg.solve(np.eye(n) - self.ad, self.bd * self.settling)
        self.line = deque([0.0] * (self.nd + 1), maxlen=self.nd + 1)
        for _ in range(round(self.age / self.ts)):
            self.x = self.ad @ self.x
        return self.pv0 + float(self.cd @ self.x)

    def step(self, op: float) -> float:
        self.line.appendleft(op - self.op0 + self.disturbances["load"])
        u = self.line[self.nd]
        self.x = self.ad @ self.x + self.bd * u
        self.k += 1
        y = self.pv0 + float(self.cd @ self.x) + self.dd * u
        return y + self.amp * math.sin(2 * math.pi * self.k * self.ts / self.period)

    def disturbance_names(self) -> tuple[str, ...]:
        return tuple(self.disturbances)

    def set_disturbance(self, name: str, value: float) -> None:
        if name not in self.disturbances:
            raise KeyError(name)
        self.disturbances[name] = float(value)
