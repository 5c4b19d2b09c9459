"""A relay stopped at the PV limits says what relay would fit: its swing scales with its
amplitude d (a = 4d·|G(jω_u)|/π), so the swing it had when it crossed them gives the d that
keeps it within about half the room (``RelayTest._smaller_relay``). Helper trial: limits ±1
about the rest of e^{−3s}/((10s+1)(2s+1)), whose cycle at d 5 % is ±1.36, were left with
no figure to try next. That d, given, runs the test inside the limits and measures the
ultimate point (exact: the phase crossover of G)."""

from __future__ import annotations

import re

import pytest

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest
from tests.exact import ultimate_point

NUM, DEN, DELAY = [1.0], [20.0, 12.0, 1.0], 3.0  # e^{−3s}/((10s+1)(2s+1))


def _run(noise: float, half_width: float, amplitude: float | None = None):
    cfg = {
        "model": "transfer_function",
        "num": NUM,
        "den": DEN,
        "delay": DELAY,
        "sample_time": 0.1,
        "noise_std": noise,
        "pv_range": [0, 100],
        "op0": 50.0,
        "pv0": 50.0,
    }
    sim = build_plant({"seed": 3, "loops": {"x": cfg}})["x"]
    pv0 = sim.pv
    req = TuneRequest(
        loop="x",
        method="relay",
        pv_limits=(pv0 - half_width, pv0 + half_width),
        amplitude=amplitude,
    )
    return TuningRun(LocalLoopClient(sim), req, "unit").run()


@pytest.mark.parametrize("noise", [0.0, 0.02])
def test_the_relay_that_left_its_limits_names_one_that_keeps_to_them(noise: float) -> None:
    r = _run(noise, 1.0)
    assert r.status == "aborted" and "left its limits" in r.reason, r.reason
    said = re.search(r"--amplitude ([0-9.]+) would keep it within", r.reason)
    assert said is not None, r.reason
    d = float(said.group(1))
    # its cycle at 5 % is 4·5·|G(jω_u)|/π = 1.36 (|G| = 1/K_u); half the room is 0.5
    ku, pu = ultimate_point(NUM, DEN, DELAY)
    cycle = 4 * d / (3.141592653589793 * ku)
    assert 0.3 < cycle < 0.8, (d, cycle)
    again = _run(noise, 1.0, d)
    assert again.status == "ok", again.reason
    assert again.pv_outside is None  # never past the limits
    assert abs(again.ku / ku - 1) < 0.02 and abs(again.pu / pu - 1) < 0.02, (again.ku, ku)


def test_limits_too_close_for_the_noise_say_so_rather_than_a_relay() -> None:
    """A room under the cycle the noise's hysteresis needs (ε = 3σ = 0.9, a cycle of 2ε at
    least, against half of ±1): no amplitude would do."""
    r = _run(0.3, 1.0)
    assert r.status == "aborted" and "left its limits" in r.reason, r.reason
    assert "too little for a cycle clear of the noise" in r.reason, r.reason
    assert "--amplitude" not in r.reason, r.reason
