"""A noise-free loop whose relay switches lock to the sample grid runs a steady cycle that
repeats over a few cycles, not one: a square-root valve behind a 15 s lag and a 2 s dead
time at 0.1 s samples ran 7.565, 7.760 and 7.776 s over and over, identical to 7 digits for
30 cycles, 2.7 % apart, and the relay aborted ("the last 3 of 30 cycles still differ by
more than 2 %"; helper trial). Stage 1 now takes a repeating pattern of up to four cycles
as steady and counts its whole patterns.

Expected figures: the valve linearised at op0 = 50 %, dPV/dop = 0.5/√0.5, through
e^{−2s}/(15s + 1): its exact ultimate point (tests.exact).
"""

import math
from collections import deque

import pytest

from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest
from tests.exact import lag_ultimate

TAU, DELAY, TS = 15.0, 2.0, 0.1


class SqrtValve:
    """PV = 100·√(op/100) (% of span) through 1/(15s + 1) and a 2 s dead time."""

    pv_units = "%"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time: float, op0: float = 50.0):
        self.sample_time, self.op0 = sample_time, op0
        self.n = round(DELAY / sample_time)

    def reset(self) -> float:
        self.ops = deque([self.op0] * (self.n + 1), maxlen=self.n + 1)
        self.y = 100.0 * math.sqrt(self.op0 / 100.0)
        return self.y

    def step(self, op: float) -> float:
        self.ops.appendleft(min(max(op, 0.0), 100.0))
        a = math.exp(-self.sample_time / TAU)
        self.y = a * self.y + (1 - a) * 100.0 * math.sqrt(self.ops[self.n] / 100.0)
        return self.y

    def disturbance_names(self) -> tuple[str, ...]:
        return ()

    def set_disturbance(self, name: str, value: float) -> None:
        raise KeyError(name)


def test_a_cycle_locked_to_the_sample_grid_is_steady_over_its_pattern():
    spec = {"model": f"{__name__}:SqrtValve", "sample_time": TS, "noise_std": 0.0}
    loop = build_plant({"seed": 1, "loops": {"v": spec}})["v"]
    events = []
    hooks = RunHooks(event=events.append)
    r = TuningRun(LocalLoopClient(loop), TuneRequest(loop="v", method="relay"), "p", hooks).run()
    assert r.status == "ok", r.reason
    (pattern,) = [e.data for e in events if e.kind == "pattern"]
    assert pattern["cycles"] == 3 and pattern["pu_spread"] > 0.02  # beyond the 2 % asked
    ku, pu = lag_ultimate(0.5 / math.sqrt(0.5), (TAU,), DELAY)
    assert r.ku == pytest.approx(ku, rel=0.01)
    assert r.pu == pytest.approx(pu, rel=0.005)
    assert r.ku_spread >= abs(r.ku / ku - 1)  # the stated spread covers its error


def test_a_pattern_whose_cycles_differ_widely_is_not_one_cycle():
    """Cycles repeating with period 2 to the digit but alternating in amplitude by 30 % are
    not one cycle to average (review); by 5 % they are."""
    from services.autotuner.identify.relay import Cycle, RelayConfig, RelayTest

    def test_with(amplitudes: tuple[float, float]) -> RelayTest:
        test = RelayTest(RelayConfig(), 50.0, (0.0, 100.0), (0.0, 100.0), TS)
        start = Cycle(0.0, 3.0, 0.1, 0.5, 50.0)  # the start-up's, not counted
        test.cycles = [start] + [
            Cycle(10.0 * k, 10.0, amplitudes[k % 2], 0.5, 50.0) for k in range(1, 7)
        ]
        return test

    assert test_with((1.0, 1.3))._pattern() is None
    found = test_with((1.0, 1.05))._pattern()
    assert found is not None and [c.amplitude for c in found] == [1.05, 1.0, 1.05, 1.0]
