"""Relay and P-gain-ramp experiments in-process (no bus), against the exact ultimate point.

The sampled loop's own ultimate point differs from the continuous plant's by the zero-order
hold's lag (about ω·T/2 of phase); these plants are sampled finely enough (≥ 400 samples per
period) for that to stay well inside the tolerances.
"""

import math

import numpy as np
import pytest

from services.autotuner.identify.driver import drive
from services.autotuner.identify.oscillation import fit_oscillation
from services.autotuner.identify.ramp import RampConfig, RampTest
from services.autotuner.identify.relay import RelayConfig, RelayTest
from services.autotuner.identify.relay_estimate import KU_METHODS, MODEL_CROSSING
from services.offline.local_loop import ModelPort, SimLoopPort
from services.plant_sim.simulation.models import TransferFunctionModel
from shared.messages import GainsCommand, ModeCommand, PidGains
from tests.exact import ultimate_point
from tests.plants import HX, THIRD, run_relay, transfer_function_loop


@pytest.mark.parametrize("plant", [THIRD, HX], ids=["third-order", "heat-exchanger"])
def test_relay_within_the_describing_function_accuracy(plant):
    ku, pu = ultimate_point(*plant[:3])
    test = run_relay(*plant)
    r = test.result
    assert r is not None, test.reason
    assert r.ku_df == pytest.approx(ku, rel=0.08)  # stage 1: the describing function
    assert r.pu_df == pytest.approx(pu, rel=0.05)
    assert abs(r.ku_df / ku - 1) > 0.02  # … whose error is real on these plants
    assert r.ku == pytest.approx(ku, rel=0.01)  # both stages' exact points, at −180°
    assert r.pu == pytest.approx(pu, rel=0.005)
    assert r.ku_spread <= 0.02 and r.pu_spread <= 0.02
    assert r.hysteresis < 1e-9  # noise-free: no hysteresis needed
    assert r.cycles - r.stage_one_cycles == 2  # stage 2 adds two periods


@pytest.mark.parametrize("seed", range(6))
def test_relay_two_stages_within_two_percent_at_one_percent_noise(seed):
    ku, pu = ultimate_point(*HX[:3])
    sigma = 0.01 * 4 * 5.0 / (math.pi * ku)  # 1 % of the expected PV swing
    r = run_relay(*HX, noise=sigma, seed=seed).result
    assert r is not None
    assert r.ku == pytest.approx(ku, rel=0.02) and r.pu == pytest.approx(pu, rel=0.02)
    assert r.ku_df < 0.93 * ku  # the describing function with hysteresis: −8 to −11 %


def test_second_stage_lands_across_minus_180_degrees():
    """Stage 1 of a relay without hysteresis runs short of −180° on the third-order plant;
    stage 2's negative hysteresis (a phase lead) carries the cycle past it."""
    test = run_relay(*THIRD)
    r = test.result
    assert r.frequency[0].phase_deg > -180.0 > r.second[0].phase_deg > -186.0
    stage = next(e for e in test.events if e[1] == "stage")
    assert stage[2]["level"] < 0


def test_relay_with_noise_sets_hysteresis_from_it():
    ku, pu = ultimate_point(*HX[:3])
    sigma = 0.01 * 4 * 5.0 / (math.pi * ku)  # 1 % of the expected PV swing
    test = run_relay(*HX, noise=sigma, seed=4)
    r = test.result
    assert r is not None, test.reason
    assert r.noise_std == pytest.approx(sigma, rel=0.3)
    assert r.hysteresis == pytest.approx(3 * r.noise_std)
    assert r.ku == pytest.approx(ku, rel=0.02) and r.pu == pytest.approx(pu, rel=0.02)


class LoadAfter(ModelPort):
    """The plant, with an unmeasured load of 2 % appearing after 200 s."""

    def samples(self, n: int):
        if (self.k + 1) * self.ts > 200:
            self.model.set_disturbance("load", 2.0)
        return super().samples(n)


def test_relay_bias_adaptation_keeps_the_cycle_symmetric_under_a_load():
    num, den, delay, ts = HX
    model = TransferFunctionModel(ts, num=num, den=den, delay=delay)
    model.reset()
    test = RelayTest(RelayConfig(cycles=4, tolerance=0.01), 50.0, (0, 100), (-1e6, 1e6), ts)
    drive(test, LoadAfter(model, ts, 50.0))
    assert test.result is not None, test.reason
    assert test.result.bias == pytest.approx(48.0, abs=0.3)  # the relay moved to cancel it
    assert abs(test.cycles[-1].high_fraction - 0.5) < 0.02


def test_relay_aborts_at_the_pv_limit_and_refuses_a_too_wide_swing():
    num, den, delay, ts = HX
    model = TransferFunctionModel(ts, num=num, den=den, delay=delay, pv0=50.0)
    model.reset()
    test = RelayTest(RelayConfig(amplitude=20.0), 50.0, (0, 100), (49.0, 51.0), ts)
    assert drive(test, ModelPort(model, ts, 50.0)) is None
    assert test.phase == "aborted" and "left its limits" in test.reason
    assert test.demand.op == 50.0  # the output back at rest
    assert test.events[-1].kind == "aborted" and test.events[-1].data["reason"] == test.reason
    with pytest.raises(ValueError, match="beyond the loop's limits"):
        RelayTest(RelayConfig(amplitude=60.0), 50.0, (0, 100), (0, 100), ts)


def run_ramp(num, den, delay, ts, noise=0.0, seed=0, kc_start=1.0, bump=1.0, **kw):
    """A ramp test driven to its end in lockstep; ``kw``: RampConfig fields."""
    loop = transfer_function_loop(num, den, delay, ts, noise, seed, (-1e3, 1e3))
    test = RampTest(RampConfig(kc_start=kc_start, bump=bump, **kw), (-1e3, 1e3), ts)
    loop.apply(GainsCommand(loop="x", gains=PidGains(kc=kc_start)))
    loop.apply(ModeCommand(loop="x", mode="auto"))
    port = SimLoopPort(loop, present_first=True)
    drive(test, port, held=port.held_now())
    return test


@pytest.mark.parametrize(
    ("plant", "kc_start", "noise"),
    [(THIRD, 1.0, 0.0), (HX, 2.0, 0.0), (THIRD, 1.0, 0.01), (HX, 2.0, 0.01)],
    ids=["third-order", "heat-exchanger", "third-order-noisy", "heat-exchanger-noisy"],
)
def test_ramp_finds_the_ultimate_point(plant, kc_start, noise):
    ku, pu = ultimate_point(*plant[:3])
    test = run_ramp(*plant, noise=noise, kc_start=kc_start)
    r = test.result
    assert r is not None, test.reason
    tol = 0.01 if noise == 0 else 0.02
    assert r.ku == pytest.approx(ku, rel=tol)
    assert r.pu == pytest.approx(pu, rel=tol)
    assert r.kc_low < r.ku_loop < r.kc_high  # the sampled loop's, before the ZOH correction


def test_oscillation_fit_recovers_growth_and_period_under_noise():
    t = np.arange(0, 60, 0.05)
    rng = np.random.default_rng(2)
    for g in (-0.05, 0.0, 0.03):
        y = 3.0 + 2.0 * np.exp(g * t) * np.sin(2 * math.pi / 7.0 * t + 0.4)
        osc = fit_oscillation(t, y + 0.02 * rng.standard_normal(t.size), 0.02, 7.0)
        assert osc.growth == pytest.approx(g, abs=2e-3)
        assert osc.period == pytest.approx(7.0, rel=2e-3)


def test_biased_second_stage_gives_the_static_gain():
    """``--relay-bias 0.3``: stage 2's low output is b − 0.7·d; the model fitted on that record
    has the heat exchanger's static gain (1), and K_u stays within 1 %."""
    ku, _ = ultimate_point(*HX[:3])
    r = run_relay(*HX, low_ratio=0.7).result
    assert r.static_gain == pytest.approx(1.0, rel=0.02)
    assert r.ku == pytest.approx(ku, rel=0.01)
    assert run_relay(*HX).result.static_gain is None  # symmetric: no static gain claimed


def test_every_abort_goes_through_one_path_with_an_event():
    """Cycles that cannot agree within a tolerance of 1e-9 exhaust ``max_cycles``: the test
    aborts with its reason and an ``aborted`` event, as at the PV limit."""
    num, den, delay, ts = THIRD
    model = TransferFunctionModel(ts, num=num, den=den, delay=delay)
    model.reset()
    test = RelayTest(
        RelayConfig(cycles=3, max_cycles=4, tolerance=1e-9), 50.0, (0, 100), (-1e6, 1e6), ts
    )
    assert drive(test, ModelPort(model, ts, 50.0)) is None
    assert test.phase == "aborted" and len(test.cycles) == 4
    assert "still differ" in test.reason
    assert [e.kind for e in test.events].count("aborted") == 1
    assert test.events[-1].kind == "aborted" and test.events[-1].data == {"reason": test.reason}


def test_relay_says_which_path_gave_k_u():
    """Noise-free on the third-order plant both stages' points bracket −180°: K_u is the
    model's crossing between them, and the run's experiment object says so (a new key)."""
    test = run_relay(*THIRD)
    r = test.result
    assert r.crossing == "bracketed" and r.ku_method == MODEL_CROSSING
    fields = test.identification().experiment.to_dict()
    assert fields["ku_method"] == MODEL_CROSSING and fields["crossing"] == "bracketed"
    single = run_relay(*THIRD, refine=False).result  # no stage 2: stage 1's point alone
    assert single.ku_method in KU_METHODS and single.ku_method != "linear crossing"
    assert single.second == ()


def test_stage_two_is_an_explicit_phase():
    num, den, delay, ts = THIRD
    model = TransferFunctionModel(ts, num=num, den=den, delay=delay)
    model.reset()
    test = RelayTest(RelayConfig(), 50.0, (0.0, 100.0), (-1e6, 1e6), ts)
    phases = []
    port = ModelPort(model, ts, 50.0)
    drive(test, port, watch=lambda s: phases.append(test.phase))
    seen = [p for i, p in enumerate(phases) if i == 0 or phases[i - 1] != p]
    assert seen == ["quiet", "relay", "stage2", "concluding"]
    assert test.phase == "done"  # its findings computed by the driver's identification()


def test_the_output_is_back_at_rest_before_the_closing_fits():
    """The closing fits take up to seconds (1.7 s for a fast FOPDT here, more under load); a
    realtime loop runs on meanwhile. Computed inside the last sample's feed, they held the
    relay's last level: a ×10 realtime FOPDT (1/(5s+1)·e^{-1.5s}) sat at 45 % for 20 s of sim
    time and its PV went 4.7 off rest, against the relay's swing of 1.1."""
    num, den, delay, ts = THIRD
    model = TransferFunctionModel(ts, num=num, den=den, delay=delay)
    model.reset()
    test = RelayTest(RelayConfig(), 50.0, (0.0, 100.0), (-1e6, 1e6), ts)
    port = ModelPort(model, ts, 50.0)
    held_then: list[float] = []

    def compute(fn, *args):
        held_then.append(port.op)
        return fn(*args)

    test.compute = compute
    assert drive(test, port) is not None and test.phase == "done"
    assert held_then == [50.0]  # the output at rest, then the fits (once)
