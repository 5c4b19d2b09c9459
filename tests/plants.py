"""Plants the unit tests share, as (num, den, delay, sample time), and a relay run on them.

Sampled finely (≥ 400 samples per period) so that the sampled loop's ultimate point, which the
experiments measure, stays well inside the tolerances of the continuous plant's (tests.exact).
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from services.autotuner.identify.driver import drive
from services.autotuner.identify.relay import RelayConfig, RelayTest
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient, ModelPort, SimLoopPort
from services.plant_sim.plant_file import build_plant
from services.plant_sim.simulation.loop import SimLoop
from services.plant_sim.simulation.models import TransferFunctionModel
from shared.messages import TuneRequest

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


def transfer_function_loop(
    num,
    den,
    delay,
    ts,
    noise=0.0,
    seed=0,
    pv_range: tuple[float, float] | None = None,
    name: str = "x",
) -> SimLoop:
    """A plant_sim loop ``name`` of num/den·e^{−delay·s} sampled every ``ts`` s, seeded
    Gaussian noise of σ ``noise`` on its PV (its draws depend on the loop's name as well as
    the seed); ``pv_range``: its transmitter's (None: the default)."""
    spec = {
        "model": "transfer_function",
        "num": num,
        "den": den,
        "delay": delay,
        "sample_time": ts,
        "noise_std": noise,
    }
    if pv_range is not None:
        spec["pv_range"] = list(pv_range)
    return build_plant({"seed": seed, "loops": {name: spec}})[name]


def live_tune(
    plant: dict, loop: str, monkeypatch, one_at_a_time: tuple[type, ...] = (), **request
) -> tuple[dict, tuple]:
    """A whole live-path tune (``TuningRun`` on the loop in this process) of a fresh ``loop``
    of ``plant``: its result less its wall time, and the loop as left; the experiment classes
    in ``one_at_a_time`` fed a sample a batch (their horizon 1), as the batches are checked
    against."""
    sim = build_plant(plant, "default")[loop]
    with monkeypatch.context() as m:
        for cls in one_at_a_time:
            m.setattr(cls, "horizon", lambda self, cap: 1)
        result = TuningRun(LocalLoopClient(sim), TuneRequest(loop=loop, **request), "band").run()
    out = result.model_dump()
    out.pop("wall_time")
    return out, (sim.seq, sim.pv, sim.op, sim.sp, sim.mode)


def drive_in_batches(experiment, loop: SimLoop, cap: int, limit: float) -> Counter[str]:
    """``experiment`` driven on ``loop`` in lockstep (its present state the first sample, no
    samples after ``limit`` s) in batches of at most ``cap``; checks that every sample of a
    banded batch but its last is inside the band. Returns the count of batches."""
    port = SimLoopPort(loop, present_first=True, limit=limit)
    calls: Counter[str] = Counter()
    take = port.samples

    def counted(n, band=None):
        out = take(n, band)
        calls["batches"] += 1
        if band is not None:
            assert not any(band.ends(s.pv, s.op) for s in out[:-1])
        return out

    port.samples = counted
    drive(experiment, port, held=port.held_now(), max_chunk=cap)
    return calls
