"""A ramp test whose bracket closes on trials without a period says what the trials showed.

Random field case: 1.18·e^{−132s}/(4.4s + 1), sampled every 6 s, noise σ 0.9. At 1.07–1.69
K_u the loop oscillated in a mode at P_u/3 (91–97 s; near a pure delay, the modes at 3ω_u,
5ω_u … go unstable just above K_u too); the trials near K_u, watched 3.5 of those periods,
showed none in the noise, and the bracket closed at Kc 0.98–0.99 on two of them. The run
said "the loop never oscillated", which three of its trials contradict.
"""

import math

from scipy.optimize import brentq

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

K, T, L = 1.1837175271574703, 4.3924319822794375, 131.7677909338731
SPEC = {
    "model": "transfer_function",
    "num": [K],
    "den": [T, 1.0],
    "delay": L,
    "sample_time": 6.010952483856114,
    "noise_std": 0.8996840813892261,
}


def tune(method: str):
    sim = build_plant({"seed": 174, "loops": {"x": dict(SPEC)}}, "unit")["x"]
    return TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method=method), "unit").run()


def test_the_ramp_names_the_trials_that_oscillated_away_from_its_bracket():
    r = tune("ramp")
    assert r.status == "aborted"
    assert "never oscillated" not in r.reason
    assert "no period to report" in r.reason
    assert "oscillated (period" in r.reason and "relay test" in r.reason


def test_the_relay_it_points_to_reads_the_ultimate_point():
    # the phase of K e^{-Ls}/(Ts + 1) crosses -180° where ωL + atan(ωT) = π
    w = brentq(lambda x: x * L + math.atan(x * T) - math.pi, 1e-6, math.pi / L)
    ku, pu = math.hypot(1.0, w * T) / K, 2 * math.pi / w
    r = tune("relay")
    assert r.status == "ok", r.reason
    # a noise of 6 % of the relay's swing: within 10 % of K_u, 5 % of P_u
    assert abs(r.ku / ku - 1) < 0.10
    assert abs(r.pu / pu - 1) < 0.05
