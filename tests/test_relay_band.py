"""The relay's half-cycles in one lockstep round trip: a batch ends at the sample where the PV
leaves the relay's band (``RelayTest.band``), so the run is the run fed sample by sample —
the same samples, the same switches, the same result to the bit — in a tenth of the round
trips. Checked on whole in-process runs of the preset loops, noise and a biased stage 2
included, and on the band's edges."""

from __future__ import annotations

import math
import tomllib
from collections import Counter
from importlib.resources import files

import pytest

from services.autotuner.identify.experiments import Band
from services.autotuner.identify.relay import RelayTest
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import AdvanceCommand, TuneRequest

PLANT = tomllib.loads(files("services.plant_sim").joinpath("plants/default.toml").read_text())


# a direct-acting loop (the PV falls as the output rises), a fractional dead time, noise
DIRECT = {
    "seed": 7,
    "loops": {
        "d1": {
            "model": "fopdt",
            "sample_time": 0.25,
            "gain": -2.0,
            "time_constant": 8.0,
            "delay": 1.3,
            "action": "direct",
            "noise_std": 0.05,
        }
    },
}


def tune(
    loop: str, per_sample: bool, monkeypatch, plant: dict = PLANT, **request
) -> tuple[dict, tuple, Counter]:
    """A whole relay run on a fresh loop (a preset's by default): its result (less its wall
    time), the loop as left, and how the run asked for its samples."""
    sim = build_plant(plant, "default")[loop]
    calls: Counter[str] = Counter()
    take = LocalLoopClient.samples

    def counted(self, steps, band=None, record=None):
        out = take(self, steps, band, record)
        calls["batches"] += 1
        calls["banded"] += band is not None
        calls["samples"] += len(out)
        if band is not None:  # every sample but the last inside the band
            assert not any(band.ends(s.pv, s.op) for s in out[:-1])
        return out

    with monkeypatch.context() as m:
        m.setattr(LocalLoopClient, "samples", counted)
        if per_sample:
            m.setattr(RelayTest, "horizon", lambda self, cap: 1)
        req = TuneRequest(loop=loop, method="relay", **request)
        result = TuningRun(LocalLoopClient(sim), req, "band").run().model_dump()
    result.pop("wall_time")
    return result, (sim.seq, sim.pv, sim.op, sim.sp, sim.mode), calls


@pytest.mark.parametrize(
    ("loop", "request_"),
    [
        ("hx1", {}),
        ("hx2", {}),
        ("lvl1", {}),
        ("flow1", {}),
        ("hx1", {"relay_bias": 0.3}),
        ("d1", {"plant": DIRECT}),
    ],
)
def test_banded_runs_are_the_runs_fed_sample_by_sample(loop, request_, monkeypatch):
    one, left_one, by_one = tune(loop, True, monkeypatch, **request_)
    banded, left, by_band = tune(loop, False, monkeypatch, **request_)
    assert one["status"] == "ok", one["reason"]
    assert banded == one and left == left_one
    assert by_band["samples"] == by_one["samples"]
    # the relay's bands on top of the verification's (banded by the PV limits in both)
    assert by_band["banded"] > by_one["banded"] and by_band["batches"] < 0.25 * by_one["batches"]


def test_a_band_ends_at_or_past_its_bounds_and_on_a_pv_that_is_no_number():
    band = Band(1.0, 2.0)
    inside, edges = 1.5, (1.0, 2.0, 0.5, 2.5, math.nan)  # at, past, not a number
    assert not band.ends(inside) and all(band.ends(x) for x in edges)
    assert not Band(-math.inf, math.inf).ends(1e300)
    assert Band(-math.inf, 3.0).stops() == (None, 3.0)
    cmd = AdvanceCommand(loop="x", steps=9, stop_below=1.0, stop_above=2.0)
    assert [cmd.stops_at(x) for x in (1.5, 1.0, 2.0, math.nan)] == [False, True, True, True]
    assert not AdvanceCommand(loop="x", steps=9).stops_at(math.nan)


def test_a_band_with_output_bounds_ends_on_the_output_too():
    """A ramp's band: the output (%) at or past its bounds ends a batch as the PV does; no
    output given (a caller that reads the PV alone) or no output bounds: the PV decides."""
    band = Band(1.0, 2.0, 10.0, 90.0)
    edges = (10.0, 90.0, 5.0, 95.0, math.nan)  # at, past, not a number
    assert not band.ends(1.5, 50.0) and all(band.ends(1.5, op) for op in edges)
    assert band.ends(2.0, 50.0) and not band.ends(1.5) and not Band(1.0, 2.0).ends(1.5, 100.0)
    assert band.op_stops() == (10.0, 90.0) and Band(1.0, 2.0).op_stops() == (None, None)
    cmd = AdvanceCommand(loop="x", steps=9, stop_op_below=10.0, stop_op_above=90.0)
    assert cmd.banded and not AdvanceCommand(loop="x", steps=9).banded
    assert not cmd.stops_at(1.5, 50.0) and all(cmd.stops_at(1.5, op) for op in edges)
    assert not cmd.stops_at(1.5) and not AdvanceCommand(loop="x", steps=9).stops_at(1.5, 100.0)


def test_an_advance_refuses_stops_that_are_not_numbers():
    import pydantic

    for bad in (
        '{"loop":"x","steps":3,"stop_above":"NaN"}',
        '{"loop":"x","stop_below":"a"}',
        '{"loop":"x","stop_op_above":"NaN"}',
    ):
        with pytest.raises(pydantic.ValidationError):
            AdvanceCommand.model_validate_json(bad)


# the transmitter's range ends just above the rest (60 °C): a relay's swing reaches it
CLIPPED = {
    "seed": 3,
    "loops": {"c1": {"model": "heat_exchanger", "pv_range": [0.0, 60.15], "noise_std": 0.02}},
}


def test_a_pv_clipped_inside_wider_limits_ends_the_batch_where_it_aborts(monkeypatch):
    """PV limits wider than the transmitter's range leave its ends inside them: the band
    ends a batch there too, where the test aborts (``clipped``); a batch that ran on stepped
    the loop past the abort, under the relay's output."""
    wide = {"plant": CLIPPED, "pv_limits": (-100.0, 200.0)}
    one, left_one, _ = tune("c1", True, monkeypatch, **wide)
    banded, left, _ = tune("c1", False, monkeypatch, **wide)
    assert one["status"] == "aborted" and "transmitter's range" in one["reason"]
    assert banded == one and left == left_one
