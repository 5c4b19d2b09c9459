"""P-only gains on a self-regulating process leave a steady offset of 1/(1 + Kc·K) of any
setpoint change, and the verification judges a loop on its setpoint: ZN P (half) on
1/(s + 1)⁴, stable with Ms 1.5, was switched in, stepped and rejected "the loop did not
settle at its setpoint … (it rests +0.0707 off it)", its stable flag False (helper trial).
Such gains are now refused before anything is switched, saying why; --no-verify still
applies them; on an integrating process P-only has no offset and is tried as any gains."""

from __future__ import annotations

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

LAG4 = {"model": "transfer_function", "num": [1.0], "den": [1.0, 4.0, 6.0, 4.0, 1.0],
        "sample_time": 0.1, "noise_std": 0.01, "pv_range": [0.0, 100.0]}  # fmt: skip


def _run(**request):
    sim = build_plant({"seed": 0, "loops": {"a": LAG4}}, "t")["a"]
    before = (sim.mode, sim.op, sim.sp, sim.pid.gains)
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="a", **request), "t").run()
    return r, sim, before


def test_p_only_on_a_self_regulating_loop_is_refused_before_anything_is_switched():
    r, sim, before = _run(method="relay", rule="zn-p-half")
    assert r.status == "rejected" and not r.applied and r.restored
    assert r.reason.startswith("zn-p-half: P-only gains leave a steady offset of 1/(1 + Kc·K)")
    assert r.after is None  # no verification was made
    assert (sim.mode, sim.op, sim.sp, sim.pid.gains) == before


def test_with_a_bias_the_relay_pins_the_gain_and_the_offset_is_said():
    """With --relay-bias the relay measures the static gain (K = 1 here): the offset is
    1/(1 + Kc·K), Kc = K_u/4 and K_u = 4 for 1/(s + 1)⁴, about 50 %."""
    r, _, _ = _run(method="relay", rule="zn-p-half", relay_bias=0.5)
    assert r.status == "rejected"
    share = float(r.reason.split("(about ")[1].split(" %")[0])
    assert 45.0 < share < 55.0


def test_no_verify_still_applies_them_untried():
    r, sim, _ = _run(method="relay", rule="zn-p-half", verify=False)
    assert r.status == "unverified" and r.applied and sim.pid.gains.ti is None
