"""A ramp test whose trials bracket an ultimate point that the model fitted to their own record
contradicts is refused, not applied: one of the two is not the loop's.

Random field case: (2.43s² + 1.50s + 2.09)e^{−1.40s}/(6.73s² + 8.42s + 1), sampled every
0.043 s, noise σ 0.11: gain at high frequencies (0.36), so just above K_u the loop's faster
modes grow too. The trials read P_u 0.317 s (exact: 2.64 s); the model fitted to their record
put it at 2.70 s. TL PI from the trials (Ti 0.70 s) ended `ok`; after the run the loop swung
0–100 % (exact gain margin 0.50 on the sampled loop: unstable, growing by 0.1 % a sample,
slower than the verification's 24 s showed).
"""

import cmath
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from services.autotuner.commands.apply import choose
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.errors import ConfigError
from shared.messages import TuneRequest

NUM = [2.4329780886081447, 1.4964384519081175, 2.0874009859212674]
DEN = [6.728324728489864, 8.4210033222921, 1.0]
DELAY = 1.4040596789179467
SPEC = {
    "model": "transfer_function",
    "num": NUM,
    "den": DEN,
    "delay": DELAY,
    "sample_time": 0.04346150005056236,
    "noise_std": 0.110698177091245,
}


def ultimate_point() -> tuple[float, float]:
    """Where the phase of G(jω) first crosses −180° (unwrapped: the delay's −ωL added to
    the rational part's own phase, continuous from 0 at ω = 0)."""

    def phase(w: float) -> float:
        s = 1j * w
        rational = np.polyval(NUM, s) / np.polyval(DEN, s)
        # the rational part's phase stays within (−180°, 180°) here: no unwrapping needed
        return cmath.phase(rational) - w * DELAY

    w = brentq(lambda x: phase(x) + math.pi, 1e-6, math.pi / DELAY * 1.5)
    g = abs(np.polyval(NUM, 1j * w) / np.polyval(DEN, 1j * w))
    return 1.0 / g, 2 * math.pi / w


def tune(method: str):
    sim = build_plant({"seed": 224, "loops": {"x": dict(SPEC)}}, "unit")["x"]
    before = sim.snapshot()
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method=method), "unit").run()
    return r, before, sim


def test_the_contradicted_ramp_is_refused_and_the_loop_left_as_it_was():
    _, pu = ultimate_point()
    r, before, sim = tune("ramp")
    assert r.status == "rejected"
    assert r.reason.startswith("refused: the trials' ultimate point and the one of the model")
    assert "relay test" in r.reason and "force" in r.reason
    # the trials' period is the faster mode's, several times short of the exact P_u
    assert r.pu < pu / 2
    after = sim.snapshot()
    assert (after.mode, after.op, after.gains) == (before.mode, before.op, before.gains)


def test_the_relay_reads_the_same_loop_and_its_gains_are_applied():
    ku, pu = ultimate_point()
    r, _, sim = tune("relay")
    assert r.status == "ok", r.reason
    assert abs(r.ku / ku - 1) < 0.10
    assert abs(r.pu / pu - 1) < 0.05
    # TL's integral time from that period: Ti = 2.2 P_u, not a fraction of it
    assert sim.pid.gains.ti is not None and sim.pid.gains.ti > pu


def test_without_applying_the_run_says_its_gains_are_not_to_be_and_apply_refuses_it():
    sim = build_plant({"seed": 224, "loops": {"x": dict(SPEC)}}, "unit")["x"]
    req = TuneRequest(loop="x", method="ramp", apply=False)
    r = TuningRun(LocalLoopClient(sim), req, "unit").run()
    assert r.status == "proposed"
    assert "and not to be: the trials' ultimate point" in r.reason
    assert r.contradiction is not None and "times apart" in r.contradiction
    # `autotune apply` reads the run's record (history.jsonl: the rule's ISA gains): it
    # refuses the run, naming why; without the contradiction the same record applies
    gains = sim.pid.gains  # restored: the gains before the run, not the proposed ones
    isa = r.gains[r.rule]["isa"]
    run = {
        "run_id": r.run_id,
        "status": r.status,
        "rule": r.rule,
        "ku": r.ku,
        "gains": {r.rule: {"kc": isa["kc"], "ti": isa["ti"], "td": isa["td"]}},
        "contradiction": r.contradiction,
    }
    with pytest.raises(ConfigError, match="times apart"):
        choose(run, None)
    assert choose({**run, "contradiction": None}, None)[0] == r.rule
    assert gains.kc == 1.0 and gains.ti is None
