"""A relay on an integrating loop held off its balance: its whole-record model fits the held
output's offset (``RelayConfig.fit_offset``, ``model_fit.refine_on_record``).

A level re-tuned from auto is held, for the test, at its controller's mean output: a noisy
mean, a few tenths of a % off the output that balances its flows. The PV drifts from the
start, too slowly for the quiet period to see through the noise; the relay's bias adaptation
finds the balance, and the model, fitted from the held output, integrated that bias's move as
a ramp the PV never made: lvl2 re-tuned read "IPDT fit misses the record" with its dead time
exact, and no rule could be recommended. The plant here: 0.01·e^{−2s}/s sampled every second,
noise σ 0.1, held 0.2 and 0.4 % above its balance (50 %). Expected figures are its own gain
and dead time.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.autotuner.identify.driver import drive
from services.autotuner.identify.experiments import Settings, Setup
from services.autotuner.identify.relay import RelayConfig, RelayTest, build
from services.offline.local_loop import ModelPort
from services.plant_sim.simulation.models import TransferFunctionModel

K, DEAD, TS, NOISE = 0.01, 2.0, 1.0, 0.1
CASES = [(off, seed) for off in (0.2, 0.4) for seed in range(4)]


def _relay(off: float, seed: int, fit_offset: bool) -> RelayTest:
    model = TransferFunctionModel(TS, num=[K], den=[1.0, 0.0], delay=DEAD)
    model.reset()  # at rest at 50 %: the balance
    held = 50.0 + off
    test = RelayTest(RelayConfig(fit_offset=fit_offset), held, (0.0, 100.0), (-1e6, 1e6), TS)
    drive(test, ModelPort(model, TS, held, NOISE, np.random.default_rng(seed)))
    return test


@pytest.mark.parametrize(("off", "seed"), CASES)
def test_a_relay_held_off_the_balance_reads_the_integrator(off, seed):
    test = _relay(off, seed, fit_offset=True)
    assert test.phase == "done", test.reason
    m = test.result.model
    assert m is not None and m.kind == "ipdt"
    assert m.gain == pytest.approx(K, rel=0.06)
    assert m.delay == pytest.approx(DEAD, rel=0.03)
    # the balance is 50 %, `off` below the output held: the offset found, said in the result
    assert m.offset == pytest.approx(-off, abs=0.05)
    assert test.result.to_dict()["model_offset"] == m.offset


def test_without_the_offset_the_same_records_misread_it():
    """What a run recorded before made of them (and its replay still makes)."""
    worst = 0.0
    for off, seed in CASES:
        m = _relay(off, seed, fit_offset=False).result.model
        gain = m.gain if m.kind == "ipdt" else m.gain / m.lag  # an FOPDT's K/T at its cycle
        worst = max(worst, abs(gain / K - 1.0))
    assert worst > 0.5


def test_only_a_new_runs_set_up_fits_the_offset():
    common = dict(sample_time=1.0, op_lo=0.0, op_hi=100.0, pv_lo=0.0, pv_hi=100.0)
    new = Setup(**common, op_start=50.0, direction=1.0, relay_offset=True)
    old = Setup(**common, op_start=50.0, direction=1.0)
    assert build(Settings(), new).config.fit_offset
    assert not build(Settings(), old).config.fit_offset
