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
    # crossed on its first swings (no whole cycle yet): a bound, said as one
    said = re.search(r"--amplitude ([0-9.]+) at most, less if its cycle is larger", r.reason)
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


def test_with_cycles_measured_the_amplitude_comes_from_them() -> None:
    """Where whole cycles were measured before the PV left the limits (a load, a growth of
    d), each cycle's amplitude per % of its d gives the d for half the room: a cycle of 1.2
    at d 4 % is 0.3 per %; half of a room of 1 is 0.5, so d 5/3 %."""
    from services.autotuner.identify.relay import Cycle, RelayConfig, RelayTest

    test = RelayTest(RelayConfig(), 50.0, (0.0, 100.0), (49.0, 51.0), 0.1)
    test.phase, test._r, test._d, test._relay_index = "relay", 50.0, 4.0, 0
    test.pv = [50.0, 50.9, 51.02]  # the swing that crossed: 1.02, 0.255 per %
    test.cycles = [Cycle(0.0, 16.0, 1.2, 0.5, 50.0, 4.0), Cycle(16.0, 16.0, 0.9, 0.5, 50.0, 4.0)]
    said = test._smaller_relay(49.0, 51.0)
    assert "its cycle, 1.2 from rest (50) with the relay at ±4 %" in said, said
    assert f"--amplitude {0.5 * 1.0 / 0.3:.2g} would keep it within" in said, said


def test_the_advice_is_not_the_machines_reason() -> None:
    """The abort's reason stays the machine's (a replay of a run recorded before the advice
    was said finds it in that run's own: ``analysis.EndedEarly``); the run's result says
    both."""
    r = _run(0.0, 1.0)
    head, _, advice = r.reason.partition("; it crossed them")
    assert head.startswith("relay test: PV ") and "left its limits [" in head, r.reason
    assert advice, r.reason
