"""A lockstep advance of a linear loop (``linear_steps``) gives the samples of
``SimLoop.advance`` one at a time, to the bit, and leaves the loop in the same state.

The reference is ``SimLoop.advance_slowly`` (the per-sample stepping every model has) on a
second copy of the same plant file and seed. Both copies get the same commands between
advances of uneven lengths; some advances carry stops (a band), which must end both at the
same sample and leave the noise generator where sample-by-sample stepping leaves it.
"""

from __future__ import annotations

from services.plant_sim.plant_file import build_plant
from services.plant_sim.simulation.linear_steps import steppable
from services.plant_sim.simulation.loop import SimLoop
from shared.messages import (
    DisturbanceCommand,
    GainsCommand,
    ModeCommand,
    OutputCommand,
    PidGains,
    SetpointCommand,
)
from tests.test_realtime_batch import PLANT as REALTIME

# the realtime batches' loops (PID forms, saturation, noise, whole and fractional dead times,
# direct action, sp tracking, third order, order 0), the physical one left out, and hx2 in
# auto with noise
PLANT = {
    "seed": 11,
    "loops": {lid: dict(cfg) for lid, cfg in REALTIME["loops"].items() if lid != "lvl"},
}
PLANT["loops"]["hx2"].update(noise_std=0.03, mode="auto", pid={"kc": 2.0, "ti": 20.0})

# (advance length, a band on the PV as (low, high) or None, commands after it)
SCRIPT = [
    (37, None, [SetpointCommand(loop="hx1", sp=58.0), OutputCommand(loop="i1", op=70.0)]),
    (1, None, [SetpointCommand(loop="g0", sp=52.0)]),
    (250, (40.0, 60.4), [DisturbanceCommand(loop="f1", name="load", value=-8)]),
    (300, None, [ModeCommand(loop="i1", mode="auto")]),  # i1's SP tracked its PV till now
    (3, None, [GainsCommand(loop="hx1", gains=PidGains(kc=1.2, ti=25.0, td=2.0, beta=0.6))]),
    (500, None, [ModeCommand(loop="f1", mode="manual"), ModeCommand(loop="g0", mode="auto")]),
    (64, (0.0, 49.9), [OutputCommand(loop="f1", op=20.0), SetpointCommand(loop="t3", sp=45.0)]),
    (1024, None, [ModeCommand(loop="f1", mode="auto")]),
    (700, (10.0, 90.0), []),
]


def _run(step) -> dict[str, list]:
    loops = build_plant(PLANT)
    out: dict[str, list] = {lid: [] for lid in loops}
    for steps, band, commands in SCRIPT:
        for lid, lp in loops.items():
            stops = (lambda pv, op, b=band: not b[0] <= pv <= b[1]) if band else None
            out[lid] += step(lp, steps, stops)
        for cmd in commands:
            loops[cmd.loop].apply(cmd)
    for lid, lp in loops.items():  # the state left behind: the next samples tell it
        out[lid] += step(lp, 40, None)
        out[lid].append(lp.status("n", "lockstep", "query"))
    return out


def test_every_loop_here_takes_the_fast_path():
    assert all(steppable(lp) for lp in build_plant(PLANT).values())


def test_fast_advances_equal_the_per_sample_stepping_to_the_bit():
    fast = _run(SimLoop.advance_many)
    slow = _run(SimLoop.advance_slowly)
    for lid in fast:
        assert len(fast[lid]) == len(slow[lid]), lid
        for a, b in zip(fast[lid], slow[lid], strict=True):
            assert a == b, (lid, a, b)
    # the bands did stop advances early (the test is of something)
    assert sum(len(v) for v in fast.values()) < len(PLANT["loops"]) * (
        sum(s for s, _, _ in SCRIPT) + 41
    )


def test_a_model_that_overflows_mid_advance_faults_as_it_always_did():
    """A state that overflows within the advance (its Φ scaled up past any stable model's, as
    a broken discretisation would leave it): the sample whose PV is not finite is stepped by
    the SimLoop, which faults the loop, and the rest are held."""
    plant = {"seed": 3, "loops": {"u1": {**PLANT["loops"]["hx1"], "model": "heat_exchanger"}}}
    fast, slow = build_plant(plant)["u1"], build_plant(plant)["u1"]
    for lp in (fast, slow):
        lp.process._sys._phi = lp.process._sys._phi * 1e30
        lp.apply(SetpointCommand(loop="u1", sp=70.0))
    a = fast.advance_many(300)
    b = slow.advance_slowly(300)
    assert a == b
    assert fast.fault is not None and fast.fault == slow.fault
    assert "returned PV" in fast.fault
    assert fast.status("n", "lockstep", "q") == slow.status("n", "lockstep", "q")
    # the advance ends at the faulting sample (its status says so at once), not 300 on
    assert len(a) < 300 and f"at t = {a[-1].t:g} s" in fast.fault
    assert fast.advance_many(5) == slow.advance_slowly(5)  # held, faulted: 5 more
    assert len(fast.advance_many(5)) == 5


def test_a_block_whose_output_stops_being_finite_faults_as_it_always_did():
    """The integral term not finite mid-run (as memory corrupted or a bug would leave it): the
    SimLoop steps that sample and faults the loop, naming the PID block's output."""
    fast, slow = build_plant(PLANT)["hx1"], build_plant(PLANT)["hx1"]
    assert fast.advance_many(50) == slow.advance_slowly(50)
    for lp in (fast, slow):
        lp.pid.terms.i = float("nan")
    assert fast.advance_many(30) == slow.advance_slowly(30)
    assert fast.fault is not None and fast.fault == slow.fault
    assert "PID block's output" in fast.fault
    assert fast.status("n", "lockstep", "q") == slow.status("n", "lockstep", "q")
