"""An experiment's output a rounding error past a limit is sent at the limit, not refused.

The feed-tank preset (lvl2) with plant seed 2: the relay's amplitude grew to the bottom of its
room, and its low output, bias − d, came to −7.1e-15 %. The output command refused it (0 %
at least) and the run ended `failed` with the validation error as its reason.
"""

import tomllib
from pathlib import Path

from services.autotuner.identify.experiments import snapped
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

PRESETS = Path(__file__).resolve().parents[1] / "services/plant_sim/plants/default.toml"


def test_only_a_rounding_error_past_a_limit_is_snapped_to_it():
    assert snapped(-7.1e-15, (0.0, 100.0)) == 0.0
    assert snapped(100.0 + 5e-8, (0.0, 100.0)) == 100.0
    assert snapped(10.0 - 1e-9, (10.0, 90.0)) == 10.0
    # further out it is left as it is, for the command to refuse
    assert snapped(-1e-6, (0.0, 100.0)) == -1e-6
    assert snapped(100.001, (0.0, 100.0)) == 100.001
    assert snapped(42.0, (0.0, 100.0)) == 42.0


def test_the_feed_tank_relay_that_reached_the_bottom_of_its_room_runs_to_its_end():
    spec = tomllib.loads(PRESETS.read_text())["loops"]["lvl2"]
    sim = build_plant({"seed": 2, "loops": {"x": dict(spec)}}, "unit")["x"]
    before = sim.snapshot()
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method="relay"), "unit").run()
    assert r.status != "failed", r.reason
    assert "validation error" not in (r.reason or "")
    if r.status != "ok":  # rejected gains leave the loop as it was
        after = sim.snapshot()
        assert (after.mode, after.op, after.gains) == (before.mode, before.op, before.gains)
