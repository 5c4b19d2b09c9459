"""A ramp that cannot go on between trials hands the setpoint back before it aborts.

The trials bump the setpoint up and back in turn, so a test that stops after an odd one
leaves the PV a bump off its rest, and an integrating level, restored to its output before
the test, stays there (lvl2 was left 0.010 m off with a band of 0.008). The plant here is
lvl2's: 1e-4·e^{−2s}/s sampled every second, σ 0.002 m, whose K_u (about 7,900 % per m) no
bump the noise allows reaches: the test ends on the output's room, after putting the
setpoint back and calming the loop there.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_experiments import run_ramp

LEVEL = ([1e-4], [1.0, 0.0], 2.0, 1.0)
NOISE = 0.002


@pytest.fixture(scope="module")
def handed_back():
    return run_ramp(*LEVEL, noise=NOISE, seed=1, kc_start=10.0, bump=0.015)


def test_the_setpoint_is_put_back_and_the_pv_with_it(handed_back):
    test = handed_back
    assert test.phase == "aborted"
    assert "no bump the noise allows" in test.reason
    kinds = [e.kind for e in test.events]
    assert kinds[-2:] == ["hand_back", "aborted"]
    back = next(e for e in test.events if e.kind == "hand_back")
    first = next(e for e in test.events if e.kind == "trial")
    start = first.data["sp"] - first.data["bump"]  # where the test began
    assert back.data["sp"] == pytest.approx(start, abs=1e-12) and test.sp == back.data["sp"]
    # calmed there: the PV's mean over the last stretch is at the setpoint within its noise
    # (P-only on an integrator, the output at its balance: no offset)
    tail = np.asarray(test._y[-100:])
    assert abs(float(tail.mean()) - start) < 4 * NOISE


def test_recorded_before_the_test_aborted_a_bump_off():
    test = run_ramp(*LEVEL, noise=NOISE, seed=1, kc_start=10.0, bump=0.015, hand_back=False)
    assert test.phase == "aborted" and "hand_back" not in [e.kind for e in test.events]
    first = next(e for e in test.events if e.kind == "trial")
    start = first.data["sp"] - first.data["bump"]
    assert abs(test.sp - start) > 0.01  # stopped after an odd trial, a bump off


def test_an_abort_while_handing_back_says_why_the_test_was_ending(handed_back):
    test = handed_back
    first = test.reason
    test._abort("PV 9 left its limits [0, 3] at t = 1 s")  # as a limit crossed then would
    assert test.reason.startswith(first + "; putting the setpoint back where it began: PV 9")
