"""Plants the unit tests share, as (num, den, delay, sample time), and a relay run on them.

Sampled finely (≥ 400 samples per period) so that the sampled loop's ultimate point, which the
experiments measure, stays well inside the tolerances of the continuous plant's (tests.exact).
"""

from __future__ import annotations

import numpy as np

from services.autotuner.identify.driver import drive
from services.autotuner.identify.relay import RelayConfig, RelayTest
from services.offline.local_loop import ModelPort
from services.plant_sim.simulation.models import TransferFunctionModel

THIRD = ([6.0], [1.0, 6.0, 11.0, 6.0], 0.0, 0.002)  # 6/((s+1)(s+2)(s+3)): K_u = 10, ω_u = √11
HX = ([1.0], [600.0, 70.0, 1.0], 5.0, 0.05)  # the heat exchanger e^{−5s}/((10s+1)(60s+1))


def run_relay(num, den, delay, ts, noise=0.0, seed=0, **kw) -> RelayTest:
    """A relay test driven to its end in lockstep on the plant, with seeded Gaussian noise of
    standard deviation ``noise`` on the PV; ``kw``: RelayConfig fields."""
    model = TransferFunctionModel(ts, num=num, den=den, delay=delay)
    model.reset()
    test = RelayTest(RelayConfig(**kw), 50.0, (0.0, 100.0), (-1e6, 1e6), ts)
    drive(test, ModelPort(model, ts, 50.0, noise, np.random.default_rng(seed)))
    return test
