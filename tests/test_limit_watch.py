"""Where the PV went past a run's PV limits (``limit_watch``): the abort's reason gives the PV
where it crossed (52.11), never where it went (53.02, outside for 7.5 s: helper trial on three
lags and a dead time). The watch sees every sample the run reads, once by its number."""

from __future__ import annotations

import re

import pytest

from services.autotuner.limit_watch import LimitWatch
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import ProcessSample, TuneRequest


def sample(seq: int, pv: float) -> ProcessSample:
    return ProcessSample(loop="x", seq=seq, t=0.5 * seq, pv=pv, sp=50.0, op=50.0, mode="manual")


def test_the_farthest_point_and_the_time_outside_each_sample_once() -> None:
    w = LimitWatch(49.5, 52.0)
    pvs = [50.0, 51.9, 52.11, 52.8, 53.02, 52.6, 51.0, 49.4, 50.0]
    w.see([sample(n, pv) for n, pv in enumerate(pvs)])
    w.see([sample(4, 53.02), sample(5, 52.6)])  # read again (held, then taken): once
    assert (w.peak, w.outside, w.first_t, w.last_t) == (53.02, 5, 1.0, 3.5)
    assert w.to_dict(0.5) == {
        "peak": 53.02,
        "samples": 5,
        "seconds": 2.5,
        "first_t": 1.0,
        "last_t": 3.5,
    }
    said = w.warning(0.5, "degC")
    assert said is not None and "to 53.02 degC, outside them for 2.5 s (5 samples" in said
    inside = LimitWatch(0.0, 100.0)
    inside.see([sample(n, 50.0) for n in range(5)])
    assert inside.to_dict(0.5) is None and inside.warning(0.5, "") is None


def test_a_relay_aborted_at_a_limit_says_where_the_pv_went() -> None:
    """Three lags and a dead time, limits 0.5 either side of the rest: the relay's abort at
    the crossing, and the PV on past it as the process carries on."""
    plant = {
        "model": "transfer_function",
        "num": [2.0],
        "den": [64.0, 56.0, 14.0, 1.0],
        "delay": 3.0,
        "sample_time": 0.5,
        "pv_range": [0.0, 100.0],
    }
    sim = build_plant({"seed": 3, "loops": {"x": plant}}, "lw")["x"]
    rest = sim.pv
    req = TuneRequest(loop="x", method="relay", pv_limits=(rest - 0.5, rest + 0.5))
    r = TuningRun(LocalLoopClient(sim), req, "lw").run()
    assert r.status == "aborted" and "left its limits" in r.reason, r.reason
    crossed = float(re.search(r"PV ([0-9.]+) left its limits", r.reason).group(1))
    out = r.pv_outside
    assert out is not None and out["samples"] >= 2
    assert abs(out["peak"] - rest) > abs(crossed - rest) > 0.5  # on past where it crossed
    assert out["seconds"] == pytest.approx(out["samples"] * 0.5)
    assert any(w.startswith("the PV went past its limits") for w in r.warnings)
