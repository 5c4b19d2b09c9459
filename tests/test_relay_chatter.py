"""A relay that switches on the noise: many samples to a period (a fast-sampled loop) give a
3σ excursion of the noise every half-cycle, before the process has answered a switch; its
"cycles" are the noise's, of an amplitude far inside the hysteresis, and they agree only within
an agreement the noise has widened past meaning. Such a cycle (below half of ε; a process's
own never is: an integrating one ramps between the levels) widens ε (twice over, up to three
times) and stage 1 is counted again; a hysteresis the user gave is not widened: the test
aborts, saying why.

The plant is e^{−2s}/(3s + 1) sampled every millisecond (6,589 samples a period) with noise
σ 0.05: a tune of it never succeeded before (chatter, then "cycles differ", or a model read
from the noise). Expected figures are the closed-form ultimate point (``tests.exact``).
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
def test_a_relay_chattering_on_the_noise_widens_its_hysteresis_and_finds_the_ultimate_point(
    seed,
):
    ku, pu = ultimate_point(*LAG[:3])
    test = run_relay(*LAG, noise=NOISE, seed=seed)
    widened = _events(test, "hysteresis")
    assert widened and all(d["reason"] == "noise chatter" for d in widened)
    # each far inside the ε it had (half of it), the event's ε being twice that
    assert all(d["amplitude"] < 0.5 * d["hysteresis"] / 2 for d in widened)
    r = test.result
    assert r is not None, test.reason
    assert r.hysteresis == pytest.approx(3 * r.noise_std * 2 ** len(widened))
    assert r.amplitude > r.hysteresis  # a cycle of the process, clear of the hysteresis
    assert r.ku == pytest.approx(ku, rel=0.01)
    assert r.pu == pytest.approx(pu, rel=0.01)


def test_recorded_before_the_noises_cycles_were_taken_for_the_processs():
    """What such a run did (and its replay still does): no ultimate point of the process."""
    ku, _ = ultimate_point(*LAG[:3])
    test = run_relay(*LAG, noise=NOISE, seed=0, chatter_widenings=None)
    assert not _events(test, "hysteresis")
    assert test.result is None or test.result.ku != pytest.approx(ku, rel=0.1)


@pytest.mark.parametrize("sigmas", [3, 2, 1, 0])
def test_a_hysteresis_given_too_small_is_not_widened_the_test_aborts(sigmas):
    """However small: under a hysteresis of σ or less the noise's cycles are as tall as the
    noise, not far inside the hysteresis, and are judged against the 3σ the noise needs (a
    test that judged them against the one given ended done on them, K_u 10 to 14,000 times
    the process's)."""
    test = run_relay(*LAG, noise=NOISE, seed=0, hysteresis=sigmas * NOISE)
    assert test.phase == "aborted"
    assert "the relay switches on the noise, not on a limit cycle" in test.reason
    assert "as given (--hysteresis)" in test.reason
    assert not _events(test, "hysteresis")
