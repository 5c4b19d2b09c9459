"""A run whose gains ``--force`` let through outside the safety envelope ends ``forced``,
not ``ok``: ``ok`` says the gains were verified and are safe. flow1's ZN PI on its relay's
findings is predicted at Ms 2.21 on the sampled loop, above the bound 2; forced, it passes
its verification and was reported ``ok``, exit 0 (helper trial at x50: exact Ms 2.48)."""

from __future__ import annotations

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import default_plant_path, load_plant_file
from shared.messages import APPLIED_STATUSES, DONE_STATUSES, TuneRequest


def _flow1(**req):
    sim = load_plant_file(default_plant_path(), seed=0)["flow1"]
    return TuningRun(
        LocalLoopClient(sim), TuneRequest(loop="flow1", method="relay", **req), "f"
    ).run()


def test_gains_forced_outside_the_envelope_end_forced_not_ok():
    r = _flow1(rule="zn-pi", force=True)
    assert (r.status, r.applied) == ("forced", True), r.reason
    assert r.reason.startswith("applied because forced (--force), outside the safety envelope")
    assert "predicted Ms" in r.reason and "not known to be safe" in r.reason
    assert r.status in APPLIED_STATUSES and r.status in DONE_STATUSES  # exit 0: as asked


def test_force_that_overrides_nothing_is_ok():
    """The recommended rule needs no force: forced or not, the run is ``ok``."""
    r = _flow1(force=True)
    assert (r.status, r.applied) == ("ok", True), r.reason
