"""A relay on a finely sampled noisy loop: many samples to a period give a 3σ excursion of the
noise every half-cycle, before the process has answered a switch, and the PV lingers near the
rest value, crossing it again and again on the noise. A cycle closes at one crossing per
switch up, none a quarter as soon after it as the last (``RelayConfig.early_crossing``), so
the noise's crossings make no cycles; where the relay still switches on the noise, its
"cycles" are as tall as the noise, far inside the hysteresis the noise needs (3σ): such cycles
(their mean below half of it; a process's own cycle never is: an integrating one ramps between
the levels) widen ε, twice over, up to three times, and stage 1 is counted again; a
hysteresis the user gave is not widened: the test aborts, saying why, however small it is.

The plant is e^{−2s}/(3s + 1) sampled every millisecond (6,589 samples a period) with noise
σ 0.05: a tune of it never succeeded before the widening (chatter, then "cycles differ", or a
model read from the noise), and with a given hysteresis of σ or less the relay ended done on
the noise's cycles, K_u 10 to 14,000 times the process's. Expected figures are the
closed-form ultimate point (``tests.exact``).
"""

from __future__ import annotations

import pytest

from tests.exact import ultimate_point
from tests.plants import run_relay

LAG = ([1.0], [3.0, 1.0], 2.0, 0.001)
NOISE = 0.05


def _events(test, kind: str) -> list[dict]:
    return [e.data for e in test.events if e.kind == kind]


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("widenings", [3, None])
def test_a_relay_on_a_finely_sampled_noisy_loop_finds_the_ultimate_point(seed, widenings):
    ku, pu = ultimate_point(*LAG[:3])
    test = run_relay(*LAG, noise=NOISE, seed=seed, chatter_widenings=widenings)
    r = test.result
    assert r is not None, test.reason
    # each widening (if the relay chattered at its start) on cycles far inside the ε it had
    widened = _events(test, "hysteresis")
    assert all(d["reason"] == "noise chatter" for d in widened)
    assert all(d["amplitude"] < 0.5 * d["hysteresis"] / 2 for d in widened)
    assert r.hysteresis == pytest.approx(3 * r.noise_std * 2 ** len(widened))
    assert r.amplitude > r.hysteresis  # a cycle of the process, clear of the hysteresis
    assert r.ku == pytest.approx(ku, rel=0.01)
    assert r.pu == pytest.approx(pu, rel=0.01)


def test_recorded_before_the_noises_cycles_were_taken_for_the_processs():
    """What such a run did (and its replay still does): no ultimate point of the process."""
    ku, _ = ultimate_point(*LAG[:3])
    test = run_relay(
        *LAG,
        noise=NOISE,
        seed=0,
        chatter_widenings=None,
        early_crossing=None,
        noise_chatter=False,
    )
    assert not _events(test, "hysteresis")
    assert test.result is None or test.result.ku != pytest.approx(ku, rel=0.1)


@pytest.mark.parametrize("sigmas", [2, 1, 0])
def test_a_hysteresis_given_too_small_is_not_widened_the_test_aborts(sigmas):
    """However small: under a hysteresis of σ or less the noise's cycles are as tall as the
    noise, not far inside the hysteresis, and are judged against the 3σ the noise needs (a
    test that judged them against the one given ended done on them, K_u 10 to 14,000 times
    the process's)."""
    test = run_relay(*LAG, noise=NOISE, seed=0, hysteresis=sigmas * NOISE)
    assert test.phase == "aborted"
    assert "the relay switches on the noise, not on a limit cycle" in test.reason
    assert "as given (--hysteresis)" in test.reason
    # judged against the 3σ the noise needs, and said so, with the least that would do
    r = test.result
    needs = 3 * test.events[0].data["noise_std"]
    assert f"within 3σ of the noise ({needs:.3g};" in test.reason
    assert f"a --hysteresis of {needs:.3g} or more lets the process answer" in test.reason
    assert r is None
    assert not _events(test, "hysteresis")
