"""An integral time under the sample time: what the rules give a loop whose dead time
dominates (nearly an integral controller), applied only where the verification judges it.

On e^{−0.2s}/(0.01s + 1) sampled at 0.1 s, SIMC PI is Kc = T/(K(τc + θ)), Ti = min(T,
4(τc + θ)) = T, the lag: Ti ≈ 0.01 s, a tenth of the sample time. A tune verified it `ok`,
and `autotune apply` of that run was then refused as "shorter than the loop's sample time",
a check made for hand-made requests applied unverified (``test_tuning_run``).
"""

import pytest

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import PidGains, TuneRequest

TS = 0.1
SPEC = {
    "model": "transfer_function",
    "num": [1.0],
    "den": [0.01, 1.0],
    "delay": 0.2,
    "sample_time": TS,
    "noise_std": 0.01,
    "pv_range": [0.0, 100.0],
}


def _loop(seed: int = 0) -> LocalLoopClient:
    return LocalLoopClient(build_plant({"seed": seed, "loops": {"a": dict(SPEC)}}, "t")["a"])


@pytest.fixture(scope="module")
def tuned():
    return TuningRun(_loop(), TuneRequest(loop="a", method="relay"), "t").run()


def test_the_rules_give_it_and_the_verification_passes_it(tuned):
    assert tuned.status == "ok", tuned.reason
    assert tuned.chosen["isa"]["ti"] < TS  # the case: an integral time under a sample
    assert tuned.after is not None and tuned.after.overshoot is not None


def _apply(client: LocalLoopClient, tuned, verify: bool):
    g = tuned.chosen["isa"]
    req = TuneRequest(
        loop="a",
        apply_from=tuned.run_id,
        apply_gains=PidGains(kc=g["kc"], ti=g["ti"], td=g["td"]),
        apply_timescale=tuned.timescale,
        apply_noise=tuned.noise,
        verify=verify,
    )
    return TuningRun(client, req, "t").run()


def test_apply_of_the_run_verifies_it_as_the_tune_did(tuned):
    client = _loop(1)
    r = _apply(client, tuned, verify=True)
    assert r.status == "ok", r.reason
    assert r.applied and client.sim.pid.gains.ti == pytest.approx(tuned.chosen["isa"]["ti"])


def test_unverified_it_is_refused_by_apply_and_by_tune(tuned):
    client = _loop(1)
    before = (client.sim.pid.gains, client.sim.mode)
    r = _apply(client, tuned, verify=False)
    assert r.status == "rejected" and r.reason.startswith("apply_gains.ti"), r.reason
    assert "nothing was applied" in r.reason and r.untouched
    assert (client.sim.pid.gains, client.sim.mode) == before
    r = TuningRun(client, TuneRequest(loop="a", method="relay", verify=False), "t").run()
    assert r.status == "rejected" and not r.applied and r.restored
    assert "shorter than the loop's sample time" in r.reason and "--no-verify" in r.reason
    assert (client.sim.pid.gains, client.sim.mode) == before
