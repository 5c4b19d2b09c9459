"""A relay whose cycle rides on its hysteresis grows its amplitude (``RelayConfig.grow_times``).

On an integrating process the PV ramps between the switching levels r ± ε and runs past them
only for the dead time, by about k·d·θ; with d = 5 % and noise that asks for ε = 3σ, that run
(the only part of the cycle the process, not the hysteresis, decides) is within the noise:
lvl2 at d = 5 % ran its cycle at a = 1.1ε, and its model's dead time read 1.5 s against 2 s.
The plant here has the same shape, 0.01·e^{−2s}/s sampled every second, with noise σ 0.1
(ε ≈ 0.3 against k·d·θ = 0.1). Expected figures are the plant's own gain and dead time.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest

from services.autotuner.identify.driver import drive
from services.autotuner.identify.experiments import Settings, Setup
from services.autotuner.identify.fourier import FrequencyPoint
from services.autotuner.identify.relay import RelayConfig, RelayTest, build
from services.autotuner.identify.relay_estimate import linear_crossing, plausible
from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient, ModelPort
from services.plant_sim.simulation.models import TransferFunctionModel
from shared.messages import TuneRequest
from tests.plants import THIRD, run_relay, transfer_function_loop

K, DEAD = 0.01, 2.0  # PV units per % per s; s
IPDT = ([K], [1.0, 0.0], DEAD, 1.0)
NOISE = 0.1
SEEDS = range(6)


def _grown(test) -> list[dict]:
    return [e.data for e in test.events if e.kind == "amplitude"]


def _model(test) -> tuple[float, float]:
    """The fitted model's integrating gain (an FOPDT's K/T: the same at the cycle's
    frequencies) and dead time."""
    m = test.result.model.to_dict()
    gain = m["model_gain"] / m["model_lag_1"] if m["model"] == "fopdt" else m["model_gain"]
    return gain, m["model_delay"]


@pytest.mark.parametrize("seed", SEEDS)
def test_a_cycle_riding_on_the_hysteresis_grows_the_relay_and_reads_the_process(seed):
    test = run_relay(*IPDT, noise=NOISE, seed=seed)
    assert test.phase == "done", test.reason
    grown = _grown(test)
    assert grown and grown[0]["from"] == RelayConfig.amplitude
    assert all(g["hysteresis"] / g["amplitude"] > RelayConfig.grow_ratio for g in grown)
    assert len(grown) <= RelayConfig.grow_times
    r = test.result
    assert r.relay_amplitude_start == RelayConfig.amplitude
    assert r.relay_amplitude == pytest.approx(grown[-1]["relay_amplitude"])
    assert r.to_dict()["relay_amplitude_start"] == RelayConfig.amplitude
    # each growth by at most its factor, then the cycle clear of the hysteresis
    assert all(g["relay_amplitude"] <= RelayConfig.grow_factor * g["from"] for g in grown)
    assert r.hysteresis / r.amplitude <= RelayConfig.grow_ratio
    gain, delay = _model(test)
    assert gain == pytest.approx(K, rel=0.04)  # (its balance fitted too: one more free figure)
    assert delay == pytest.approx(DEAD, rel=0.06)


def test_kept_at_5_percent_the_same_plant_misreads_its_dead_time():
    """What a relay that never grew made of it (and a d the engineer gave still does)."""
    errors = []
    for seed in SEEDS:
        test = run_relay(*IPDT, noise=NOISE, seed=seed, grow_times=None)
        assert not _grown(test) and test.result.relay_amplitude == RelayConfig.amplitude
        assert test.result.hysteresis / test.result.amplitude > RelayConfig.grow_ratio
        errors.append(abs(_model(test)[1] / DEAD - 1.0))
    assert max(errors) > 0.06


def test_a_clean_cycle_does_not_grow_and_its_figures_are_unchanged():
    grows, kept = run_relay(*THIRD), run_relay(*THIRD, grow_times=None)
    assert not _grown(grows)
    assert grows.result.to_dict() == kept.result.to_dict()
    assert "relay_amplitude_start" not in grows.result.to_dict()


def _relay_within(pv_half_room: float, seed: int = 0, in_range: bool = False) -> RelayTest:
    """The relay on the plant with PV limits r ± ``pv_half_room`` (it rests at 50); with
    ``in_range`` those are the transmitter's range instead, the limits far wider."""
    model = TransferFunctionModel(1.0, num=IPDT[0], den=IPDT[1], delay=DEAD)
    model.reset()
    limits = (50.0 - pv_half_room, 50.0 + pv_half_room)
    if in_range:
        test = RelayTest(RelayConfig(), 50.0, (0.0, 100.0), (0.0, 100.0), 1.0, pv_range=limits)
    else:
        test = RelayTest(RelayConfig(), 50.0, (0.0, 100.0), limits, 1.0)
    drive(test, ModelPort(model, 1.0, 50.0, NOISE, np.random.default_rng(seed)))
    return test


@pytest.mark.parametrize("in_range", [False, True], ids=["pv limits", "transmitter range"])
def test_the_grown_cycle_keeps_within_half_the_room_to_the_pv_limits(in_range):
    """And to the ends of the transmitter's range, where the PV clips and the test aborts
    (limits wider than the range grew a cycle into its end: "PV 49 at an end of the
    transmitter's range")."""
    test = _relay_within(2.0, in_range=in_range)
    grown = _grown(test)
    assert grown, test.reason
    room = 2.0 - 4.0 * test.result.noise_std  # less the noise's peaks
    for g in grown:  # a ∝ d: the grown cycle's amplitude within half of that
        assert g["relay_amplitude"] / g["from"] * g["amplitude"] <= 0.5 * room * (1 + 1e-9)
    assert test.phase == "done", test.reason
    assert max(test.pv) < 52.0 and min(test.pv) > 48.0


def test_no_room_to_grow_by_half_again_keeps_the_relay_as_it_is():
    test = _relay_within(1.0, seed=2)  # (1 − 4σ)/2 = 0.3: under the cycle's own (0.33)
    assert not _grown(test)
    assert test.phase == "done", test.reason
    r = test.result
    assert r.relay_amplitude == RelayConfig.amplitude and r.relay_amplitude_start is None
    # what held it is said: in the result, and in the warning of a cycle short of −180°
    assert r.relay_growth_held.startswith("the room to the PV limits")
    assert r.to_dict()["relay_growth_held"] == r.relay_growth_held
    assert r._growth().startswith("d stayed at 5 %, held there by the room to the PV limits")


def test_a_grown_relay_judges_each_cycle_by_its_own_d_and_counts_stage_1_again():
    test = run_relay(*IPDT, noise=NOISE, seed=3)  # the seed that grew twice
    grown = _grown(test)
    assert len(grown) == 2
    last = grown[-1]
    # every cycle carries the d it ran under: the one closed at a growth the old one
    times = [e.t for e in test.events if e.kind == "amplitude"]
    for c in test.cycles:
        end = c.t_start + c.period
        expected = RelayConfig.amplitude
        for t, g in zip(times, grown, strict=True):
            if end > t:
                expected = g["relay_amplitude"]
        assert c.d == pytest.approx(expected)
    # stage 1 counted again after each growth: the next growth, or its agreeing cycles, all
    # after it (and the first after it, a transient, not among them)
    stage = next(e.t for e in test.events if e.kind == "stage")
    for since, until in zip(times, [*times[1:], stage], strict=True):
        after = [e for e in test.events if e.kind == "cycle" and since < e.t <= until]
        assert len(after) >= RelayConfig.cycles + 1
    # the describing function with the d the cycles ran under: 4d/(π√(a² − ε²))
    r = test.result
    assert r.relay_amplitude == pytest.approx(last["relay_amplitude"])
    a, eps = r.amplitude, r.hysteresis
    assert r.ku_df == pytest.approx(
        4 * r.relay_amplitude / (math.pi * math.sqrt(a * a - eps * eps)), rel=0.05
    )


def test_two_phases_a_hair_apart_give_no_crossing_rather_than_an_overflow():
    """Stage 2 measuring stage 1's cycle again: the straight line through them is carried
    past any float ("math range error" failed the run); now out of every plausible bound."""
    p1 = FrequencyPoint(0.5, cmath.rect(0.1, math.radians(-150.0)))
    p2 = FrequencyPoint(0.5001, cmath.rect(0.1, math.radians(-150.0 + 2e-9)))
    ku, pu = linear_crossing(p1, p2)
    assert not plausible((ku, pu), p1, p2)


def test_pv_limits_past_the_transmitters_range_are_kept_to_it():
    """Limits of 0-100 % on a range of 49-51 %: the verification stepped the setpoint to
    51.2, which the plant refuses (the run aborted); now it keeps to the range, says so, and
    refuses gains it cannot verify there before stepping anything."""
    sim = transfer_function_loop(*IPDT, noise=NOISE, seed=1, pv_range=(49.0, 51.0))
    req = TuneRequest(loop="x", method="relay", pv_limits=(0.0, 100.0))
    r = TuningRun(LocalLoopClient(sim), req, "range").run()
    assert any("reach past the transmitter's range [49.0, 51.0]" in w for w in r.warnings)
    assert r.status == "rejected", r.reason
    assert "the PV limits [49, 51]" in r.reason and r.restored


def test_the_output_never_leaves_its_limits_nor_d_the_room_about_the_bias():
    test = run_relay(*IPDT, noise=NOISE, seed=3)  # the seed that grew furthest
    assert min(test.op) >= 0.0 and max(test.op) <= 100.0
    r = test.result
    assert r.relay_amplitude <= min(r.bias, 100.0 - r.bias) + 1e-9


def _setup(**flags) -> Setup:
    return Setup(
        sample_time=1.0, op_lo=0.0, op_hi=100.0, pv_lo=0.0, pv_hi=100.0, op_start=50.0,
        direction=1.0, **flags,
    )  # fmt: skip


def test_only_a_new_run_with_the_default_amplitude_grows():
    new = _setup(relay_grow=True)
    assert build(Settings(), new).config.grow_times == RelayConfig.grow_times
    # a d the engineer asked for is kept, even the default's value
    given = Settings(amplitude=5.0, amplitude_given=True)
    assert build(given, new).config.grow_times is None
    # a run recorded before replays as it ran: d kept
    assert build(Settings(), _setup()).config.grow_times is None


def test_a_request_says_whether_the_amplitude_was_given():
    class Req:
        amplitude = None
        hysteresis = None
        cycles = 3
        tolerance = 0.02
        relay_bias = None
        step_size = None
        max_time = None
        repeat = None

    assert not Settings.of(Req()).amplitude_given
    Req.amplitude = 5.0
    assert Settings.of(Req()).amplitude_given
