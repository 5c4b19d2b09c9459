"""Step tests back to back within the engineer's limits: e^{−4s}/(30s + 1) at 0.2 s, σ 0.05,
in manual, --pv-limits 48.5 51.5 about its rest at 50, the default 5 % step (its answer
would end at 55). Each test stops on the PV's trend and restores the output; the next
begins once the rest check passes on its short window, the PV still some 0.45 up and on its
way down. Read at 2 standard errors less and checked every 8 samples, with the baseline's
drift against the step left in the trend, two of six went past 51.5 (helper trial); over 10
seeds, 14 of 60 runs, up to 0.475 past. The limits are the engineer's: the fitted trend,
without that drift, over the samples to the next check."""

from __future__ import annotations

import pytest

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

SPEC = {
    "model": "fopdt",
    "gain": 1.0,
    "time_constant": 30.0,
    "delay": 4.0,
    "sample_time": 0.2,
    "noise_std": 0.05,
    "pid": {"kc": 1.0},
}
LIMITS = (48.5, 51.5)


def test_back_to_back_steps_stay_within_the_limits():
    sim = build_plant({"seed": 0, "loops": {"fo1": SPEC}}, "t")["fo1"]
    client = LocalLoopClient(sim)
    for i in range(6):
        req = TuneRequest(loop="fo1", method="step", pv_limits=LIMITS)
        r = TuningRun(client, req, f"r{i}").run()
        assert r.status == "aborted" and "would leave its limits [48.5, 51.5]" in r.reason
        assert r.pv_outside is None, (i, r.pv_outside)


def test_a_step_whose_answer_ends_inside_the_limits_is_not_stopped():
    """From rest, a 1 % step of the same process ends 1 up, inside ±1.5: the test runs to its
    end. Read on the fitted trend from rest too, 9 of 24 such steps were stopped (a small
    step's slow start, read with its noise over a long horizon)."""
    for seed in (0, 3, 6):  # three the fitted reading stopped
        spec = {k: v for k, v in SPEC.items() if k != "pid"}
        sim = build_plant({"seed": seed, "loops": {"f": spec}}, "t")["f"]
        req = TuneRequest(loop="f", method="step", pv_limits=LIMITS, step_size=1.0)
        r = TuningRun(LocalLoopClient(sim), req, "r").run()
        assert r.status == "ok", (seed, r.reason)
        assert r.step["gain"] == pytest.approx(1.0, rel=0.1), r.step
