"""The loop's PID block: anti-windup, bumpless mode switches and gain changes."""

import math

import numpy as np
import pytest

from services.plant_sim.simulation.models import FirstOrderPlusDeadTime
from shared.control.pid import PidBlock, PidSettings
from shared.messages import PidGains

TS = 0.1


def closed_loop(pid: PidBlock, plant, sp_profile, n: int):
    """Run the PID on the plant; return (pv, op, i_term) arrays."""
    pv = plant.reset()
    pid.track(pv, pid.op)
    pid.set_mode("auto", sp_profile(0), pv)
    out = []
    for k in range(n):
        pv = plant.step(pid.op)
        pid.update(sp_profile(k + 1), pv)
        out.append((pv, pid.op, pid.terms.i))
    return np.array(out).T


def test_anti_windup_recovers_after_saturation():
    """A setpoint step the output cannot follow at once saturates it; with anti-windup the
    integrator does not wind up meanwhile, so the output leaves the limit before the PV
    reaches the setpoint and the overshoot stays small. A plain integrator, run the same way,
    stays at the limit past the setpoint and overshoots far more."""
    gains = PidSettings(kc=2.0, ti=5.0)

    def plant():
        return FirstOrderPlusDeadTime(TS, gain=1.0, time_constant=5.0, delay=0.5, op0=50, pv0=50)

    sp = lambda k: 50.0 if k == 0 else 95.0  # noqa: E731 — auto at rest, then the step
    pid = PidBlock(gains, TS, (0.0, 100.0), op=50.0)
    pv, op, i_term = closed_loop(pid, plant(), sp, 1500)
    assert np.all(op[:20] == 100.0)  # saturated during the rise
    assert np.max(i_term) <= 100.0 + 1e-9  # the integrator never wound past the limit
    reached = int(np.argmax(pv >= 94.55))  # 99 % of the way
    assert reached > 0
    last_at_limit = int(np.nonzero(op == 100.0)[0][-1])
    assert last_at_limit < reached  # off the limit before the PV gets to the setpoint
    overshoot = max(np.max(pv) - 95.0, 0.0)
    assert np.max(np.abs(pv[1200:] - 95.0)) < 0.01  # settles at the setpoint

    naive_pv, naive_op = _naive_closed_loop(
        PidBlock(gains, TS, (0.0, 100.0), op=50.0), plant(), sp, 1500
    )
    naive_reached = int(np.argmax(naive_pv >= 95.0))
    assert naive_reached > 0
    assert naive_op[naive_reached + 5] == 100.0  # wound up: still at the limit after the SP
    assert np.max(naive_pv) - 95.0 > max(2.0 * overshoot, 1.0)


def _naive_closed_loop(pid: PidBlock, plant, sp, n):
    pv = plant.reset()
    i_term = pid.op - pid.gains.kc * (sp(0) - pv)
    out = []
    for k in range(n):
        pv = plant.step(pid.op)
        e = sp(k + 1) - pv
        pid.op = min(max(pid.gains.kc * e + i_term, 0.0), 100.0)
        i_term += pid.gains.kc * TS / pid.gains.ti * e
        out.append((pv, pid.op))
    return np.array(out).T


def test_manual_auto_switches_and_gain_changes_make_no_jump():
    plant = FirstOrderPlusDeadTime(TS, gain=1.5, time_constant=4.0, delay=0.3, op0=40, pv0=30)
    pid = PidBlock(PidSettings(kc=1.2, ti=3.0, td=0.5), TS, (0.0, 100.0), op=40.0)
    pv = plant.reset()
    sp = 45.0  # far from the PV: a naive switch would jump by Kc·15
    ops = []
    script = {
        50: ("auto",),
        150: ("gains", PidSettings(kc=4.0, ti=1.0, td=1.0)),
        250: ("manual",),
        300: ("output", 55.0),
        350: ("auto",),
        450: ("gains", PidSettings(kc=0.5, ti=None, td=0.0)),
        550: ("auto",),
    }
    checked = []
    for k in range(600):
        pv = plant.step(pid.op)
        if pid.mode == "auto":
            pid.update(sp, pv)
        else:
            pid.track(pv, pid.op)
        ops.append(pid.op)
        if k in script:
            before = pid.op
            action = script[k]
            if action[0] in ("auto", "manual"):
                pid.set_mode(action[0], sp, pv)
            elif action[0] == "gains":
                pid.set_gains(action[1], sp, pv)
            else:
                pid.set_output(action[1])
            if action[0] != "output":
                assert pid.op == before  # the switch itself moves nothing
                # and the next execution continues from there: the change in output is no
                # larger than the process's own motion over one period would cause
                pv_next = plant.step(pid.op)
                pid.update(sp, pv_next) if pid.mode == "auto" else pid.track(pv_next, pid.op)
                p_motion = pid.gains.kc * (abs(pv_next - pv) * (1 + pid.gains.td / TS * 2))
                i_motion = pid.gains.kc * TS / (pid.gains.ti or np.inf) * abs(sp - pv_next)
                assert abs(pid.op - before) <= p_motion + i_motion + 1e-9
                checked.append(k)
                pv = pv_next
    assert len(checked) == 6


@pytest.mark.parametrize(
    ("before", "after"),
    [((6.0, 0.0), (6.0, 5.0)), ((6.0, 2.0), (6.0, 5.0)), ((6.0, 5.0), (3.0, 5.0))],
)
def test_a_gain_change_does_not_fold_the_d_term_into_i(before, after):
    """Td 0 → 5 s on a loop at rest, a blip of noise on the sample before: the derivative
    was that of Td = 0 (the blip's raw difference over one sample), the rebase folded Kc·Td
    times it into I, and the output settled 12 % away as the new filter forgot it (`set
    --td` on hx1: up to 11.5 %); any change of Kc or Td folded a part of D in. Expected:
    where the same loop settles with no gain change but the blip (P, D and I from the blip
    alone are gone by then; the integral, Ti = 1000 s, barely moves), but for the change of
    P at the blip, which a bumpless change takes into I."""
    gains = PidSettings(kc=before[0], ti=1000.0, td=before[1])
    new = PidSettings(kc=after[0], ti=1000.0, td=after[1])

    def settled(change: bool) -> float:
        pid = PidBlock(gains, 0.25, (0.0, 100.0), mode="manual", op=40.0)
        pid.track(50.0, 40.0)
        pid.set_mode("auto", 50.0, 50.0)
        for _ in range(40):
            pid.update(50.0, 50.0)
        pid.update(50.0, 50.1)  # the noise's blip
        if change:
            pid.set_gains(new, 50.0, 50.1)
        for _ in range(400):  # 100 s: 20 of the new filter's time constants
            pid.update(50.0, 50.0)
        return pid.op

    # only the change of P at the blip (error −0.1) is taken into I, as a bumpless change of
    # Kc must: Kc·(sp − pv) before minus after
    p_change = -0.1 * (before[0] - after[0])
    assert settled(True) == pytest.approx(settled(False) + p_change, abs=0.01)


def test_p_only_keeps_its_manual_reset_and_direct_action_reverses_sign():
    pid = PidBlock(PidSettings(kc=2.0), TS, (0.0, 100.0), action="reverse", op=30.0)
    pid.track(50.0, 30.0)
    pid.set_mode("auto", 50.0, 50.0)
    assert pid.update(50.0, 50.0) == 30.0  # no error: the bias holds the output
    assert pid.update(50.0, 49.0) == pytest.approx(32.0)  # reverse: PV low → output up
    direct = PidBlock(PidSettings(kc=2.0), TS, (0.0, 100.0), action="direct", op=30.0)
    direct.track(50.0, 30.0)
    direct.set_mode("auto", 50.0, 50.0)
    assert direct.update(50.0, 49.0) == pytest.approx(28.0)


def test_derivative_acts_on_measurement_with_filter():
    pid = PidBlock(PidSettings(kc=1.0, td=2.0, n=10.0), TS, (0.0, 100.0), op=50.0)
    pid.track(10.0, 50.0)
    pid.set_mode("auto", 10.0, 10.0)
    assert pid.update(20.0, 10.0) == pytest.approx(60.0)  # SP step: P only, no derivative kick
    u = pid.update(20.0, 11.0)  # PV moves 1 unit: D = −Kc·Td/(Tf+T) with Tf = Td/N
    assert u == pytest.approx(50.0 + 9.0 - 1.0 * 2.0 / (0.2 + TS), rel=1e-12)


@pytest.mark.parametrize(
    "bad",
    [
        {"kc": -1.0},
        {"kc": math.inf},
        {"kc": 1.0, "ti": 0.0},
        {"kc": 1.0, "ti": math.nan},
        {"kc": 1.0, "td": -0.5},
        {"kc": 1.0, "n": 0.5},
        {"kc": 1.0, "n": 2000.0},
        {"kc": 1.0, "beta": 1.5},
    ],
)
def test_the_block_refuses_what_the_bus_refuses(bad):
    """The core's settings keep the bus message's bounds, so every conversion succeeds."""
    with pytest.raises(ValueError):
        PidSettings(**bad)
    with pytest.raises(ValueError):  # pydantic's ValidationError is a ValueError
        PidGains(**bad)


def test_bus_gains_convert_to_the_block_and_back_unchanged():
    msg = PidGains(kc=1.5, ti=12.0, td=0.75, n=8.0, beta=0.5)
    assert msg.to_core() == PidSettings(kc=1.5, ti=12.0, td=0.75, n=8.0, beta=0.5)
    assert PidGains.from_core(msg.to_core()) == msg
    assert PidGains.from_core(PidSettings(kc=2.0)) == PidGains(kc=2.0)  # the same defaults


@pytest.mark.parametrize("sign_action", ["reverse", "direct"])
def test_a_weighted_setpoint_integrates_to_the_setpoint(sign_action):
    """With β < 1 the P term at zero error is s·Kc·(β − 1)·sp, and I holds it off: at
    Kc 6, β 0.4 and a setpoint of 50, I sits at 230 % while the output rests at 50 %. Bounding
    I alone by the output limits froze the integral there, and the PV stopped at
    rest + β·step (52 after a step of 5 from 50) instead of the setpoint."""
    sign = 1.0 if sign_action == "reverse" else -1.0

    def plant():
        return FirstOrderPlusDeadTime(TS, gain=sign, time_constant=5.0, delay=0.5, op0=50, pv0=50)

    gains = PidSettings(kc=6.0, ti=8.0, beta=0.4)
    sp = lambda k: 50.0 if k < 10 else 55.0  # noqa: E731
    pid = PidBlock(gains, TS, (0.0, 100.0), op=50.0, action=sign_action)
    pv, op, i_term = closed_loop(pid, plant(), sp, 3000)
    assert abs(i_term[0] - 50.0) > 100.0  # I outside the output's range: β's offset
    assert pv[-1] == pytest.approx(55.0, abs=1e-6)  # at the setpoint, not 52
    assert np.all((op > 0.0) & (op < 100.0))
    # the output at zero error, I + s·Kc·(β − 1)·sp, is within the limits throughout
    at_zero = i_term + sign * 6.0 * (0.4 - 1.0) * 55.0
    assert np.all((at_zero[20:] >= 0.0) & (at_zero[20:] <= 100.0))
