"""A direct-acting loop (the PV falls as the output rises: a cooling valve, a level drained by
its valve) is tuned as its reverse-acting twin is: the relay works in the loop's own sense, so
its frequency points, model and K_u are those of the process as the controller acts on it
(−G), and the step test's findings are given the same way; the gains applied, with the PID
block's direct action, are stable on the true plant. Before, the relay's points came out of
its negative gain as a refused model, the step's as a refused reaction curve, and neither
loop could be tuned."""

from __future__ import annotations

import pytest

from services.autotuner.design.sampled_loop import sampled_loop_robustness
from services.autotuner.identify.experiments import DIRECT_NOTE
from services.autotuner.tuning import TuningRun
from services.logger import report
from services.logger.analysis import analyze_file
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.control.forms import IsaGains
from shared.control.transfer import DelayedTF
from shared.messages import TuneRequest
from tests.exact import ultimate_point
from tests.recorded_run import record_in_process

K, TAU, L, TS = 2.0, 20.0, 3.0, 0.5


def plant(gain: float, noise: float = 0.0) -> dict:
    action = "direct" if gain < 0 else "reverse"
    spec = {"model": "fopdt", "sample_time": TS, "gain": gain, "time_constant": TAU}
    return {"seed": 7, "loops": {"x": {**spec, "delay": L, "action": action, "noise_std": noise}}}


def tune(gain: float, method: str, noise: float = 0.0):
    sim = build_plant(plant(gain, noise))["x"]
    return TuningRun(LocalLoopClient(sim), TuneRequest(loop="x", method=method), "d").run()


def stable_on_the_true_loop(isa: dict) -> float:
    """Ms of the applied gains on the true plant as the direct-acting block closes it: the
    block turns the sign, so the loop is C·(−G) = C·K/(τs + 1)·e^{−Ls}."""
    rb = sampled_loop_robustness(
        IsaGains(isa["kc"], isa["ti"], isa["td"]), DelayedTF.of([K], [TAU, 1.0], L), TS
    )
    assert rb.stable
    return rb.ms


def test_the_relay_on_a_direct_acting_loop_is_its_reverse_acting_twin():
    ku, pu = ultimate_point([K], [TAU, 1.0], L)
    direct, twin = tune(-K, "relay"), tune(K, "relay")
    assert direct.status == twin.status == "ok", direct.reason
    assert direct.ku == pytest.approx(twin.ku, rel=1e-9)
    assert direct.pu == pytest.approx(twin.pu, rel=1e-9)
    assert direct.ku == pytest.approx(ku, rel=0.02) and direct.pu == pytest.approx(pu, rel=0.02)
    assert direct.experiment["model_gain"] > 0  # of −G, as the note says
    assert DIRECT_NOTE in direct.warnings
    assert direct.chosen == twin.chosen and direct.applied
    assert stable_on_the_true_loop(direct.chosen["isa"]) < 2.0


def test_the_step_test_of_a_direct_acting_loop_designs_for_its_action():
    r = tune(-K, "step", noise=0.02)
    assert r.status == "ok", r.reason
    assert r.step["gain"] == pytest.approx(-K, rel=0.02)  # the curve as measured
    assert r.experiment["model_gain"] == pytest.approx(K, rel=0.02)  # of −G, as the note says
    assert DIRECT_NOTE in r.warnings and r.chosen["isa"]["kc"] > 0 and r.applied
    assert stable_on_the_true_loop(r.chosen["isa"]) < 2.0


def test_the_ramp_on_a_direct_acting_loop_fits_its_model_as_the_twin_does():
    direct, twin = tune(-K, "ramp", noise=0.02), tune(K, "ramp", noise=0.02)
    assert direct.status == twin.status == "ok", direct.reason
    assert direct.ku == pytest.approx(twin.ku, rel=1e-6)
    assert direct.experiment["model_gain"] == pytest.approx(twin.experiment["model_gain"], 1e-6)
    assert direct.rule == twin.rule and DIRECT_NOTE in direct.warnings
    assert stable_on_the_true_loop(direct.chosen["isa"]) < 2.0


def test_a_direct_acting_relay_run_reanalyses_to_the_live_result(tmp_path):
    path, live = record_in_process(tmp_path, "p", plant(-K, 0.02), "x", "relay")
    assert live.status == "ok", live.reason
    a = analyze_file(path)
    assert a.matches_live() and a.ident.ku == live.ku
    # the report drives the stated model (of −G) by the output turned over: it fits the record
    overlay = report.load_report(path).overlay
    assert overlay is not None and overlay.fit_percent > 80.0
