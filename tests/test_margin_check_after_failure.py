"""The gain-margin check (Kc × 2) is never run on gains whose setpoint step has already failed
the acceptance limits: ZN PID forced on hx2 overshot its step by 64 % and was then run at
twice its gain, above the K_u the relay had measured, its output swinging 10–70 % for 186 s
of sim time before the rejection (helper trial). The gains are rejected as before; the loop
never holds more than the rule's Kc."""

from __future__ import annotations

import tomllib

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant, default_plant_path
from shared.messages import DisturbanceCommand, GainsCommand, PidGains, TuneRequest


class Watched(LocalLoopClient):
    """A local client that keeps every proportional gain the run writes to the loop."""

    def __init__(self, loop, **kw):
        super().__init__(loop, **kw)
        self.kcs: list[float] = []

    def _apply(self, cmd):
        if isinstance(cmd, GainsCommand):
            self.kcs.append(cmd.gains.kc)
        super()._apply(cmd)


def _preset(loop: str, seed: int):
    with open(default_plant_path(), "rb") as f:
        doc = tomllib.load(f)
    doc["seed"] = seed
    return build_plant(doc, "unit")[loop]


def test_gains_that_fail_their_step_are_not_run_at_twice_their_gain():
    sim = _preset("hx2", 11)
    before = sim.snapshot()
    client = Watched(sim)
    req = TuneRequest(loop="hx2", method="relay", rule="zn-pid", force=True)
    r = TuningRun(client, req, "unit").run()
    assert r.status == "rejected", r.reason
    assert "overshoot" in r.reason
    assert r.after.overshoot > r.acceptance["max_overshoot"]
    assert r.after.margin_factor is None  # not made
    kc = r.chosen["isa"]["kc"]
    # the loop held the rule's Kc at most (a doubled gain would be 2 × kc)
    assert max(client.kcs) <= kc * (1 + 1e-12), (max(client.kcs), kc)
    assert r.ku is not None and 2 * kc > r.ku  # what the check would have written: past K_u
    after = sim.snapshot()
    assert (after.mode, after.gains) == (before.mode, before.gains)


def test_gains_rejected_for_a_model_miss_are_not_run_at_twice_their_gain():
    """Any reason the acceptance gives from the steps, not only the overshoot and decay
    limits: AMIGO PID on flow1 told to allow its model no miss (``overshoot_miss`` 0.01
    points) overshoots a little more than predicted and is rejected for it, the loop never
    at Kc × 2 first (it was, before the rejection: review)."""
    sim = _preset("flow1", 0)
    before = sim.snapshot()
    client = Watched(sim)
    req = TuneRequest(loop="flow1", method="relay", rule="amigo-pid", overshoot_miss=0.01)
    r = TuningRun(client, req, "unit").run()
    assert r.status == "rejected", r.reason
    assert "the model is wrong" in r.reason
    assert r.after.overshoot - r.acceptance["predicted_overshoot"] > 0.01
    assert r.after.overshoot < r.acceptance["max_overshoot"]  # within the limits otherwise
    assert r.after.margin_factor is None  # not made
    kc = r.chosen["isa"]["kc"]
    assert max(client.kcs) <= kc * (1 + 1e-12), (max(client.kcs), kc)
    after = sim.snapshot()
    assert (after.mode, after.gains) == (before.mode, before.gains)


def test_gains_that_fail_their_setpoint_step_are_not_load_stepped():
    """Nor is a load step made, nor the return to the setpoint waited for, under gains their
    setpoint step already fails: the loop is restored at once. AMIGO PI from a model that
    missed e^{−0.5s}/(s² + 0.4s + 1) (Kc 0.2003, Ti 0.5989 s: Ms 26.6 on it), applied with
    ``autotune apply``, rang at a decay ratio of 0.97 through both steps, 124 s of sim time,
    before its rejection (helper trial)."""
    cfg = {
        "model": "transfer_function",
        "num": [1.0],
        "den": [1.0, 0.4, 1.0],
        "delay": 0.5,
        "sample_time": 0.02,
        "noise_std": 0.01,
    }
    sim = build_plant({"seed": 1, "loops": {"ud1": cfg}}, "unit")["ud1"]
    before = sim.snapshot()
    client = Watched(sim)
    req = TuneRequest(
        loop="ud1",
        apply_from="abcdef123456",
        rule="amigo-pi",
        apply_gains=PidGains(kc=0.2003, ti=0.5989),
        apply_timescale=3.0,
        apply_noise=0.01,
    )
    r = TuningRun(client, req, "unit").run()
    assert r.status == "rejected" and "decay ratio" in r.reason, r.reason
    assert r.after.load_step is None and r.after.iae_load is None
    loads = [c for c in client.commands if isinstance(c, DisturbanceCommand)]
    assert loads == [], loads
    after = sim.snapshot()
    assert (after.mode, after.gains, after.disturbances) == (
        before.mode,
        before.gains,
        before.disturbances,
    )
