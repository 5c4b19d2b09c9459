"""A step test's gains are held below the K_u its record implies, as a relay's are below the
one it measures.

(10s + 1)e^{−s}/((20s + 1)(s + 1)) answers a step at once with half its gain, after its dead
time: an FOPDT fitted to the record starts rising early to follow that jump, its dead time
unresolved (floored), and AMIGO PI on it was Kc 15 — 3.4 times the K_u of 4.4 that the
record implies by itself (``step_frequency``). It was recommended at Ms 1.38 predicted, and
its verification saturated the output for 81 % of its window and rejected it. The expected
figures are the plant's exact ultimate point (``tests.exact``) and its Ms computed with numpy.
"""

from __future__ import annotations

from services.autotuner.design.recommend import Assessment, envelope_problem
from services.autotuner.design.rules import UltimatePoint
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from shared.control.forms import IsaGains
from shared.messages import TuneRequest
from tests.exact import isa_ms, ultimate_point
from tests.plants import transfer_function_loop

NUM, DEN, DELAY, TS = [10.0, 1.0], [20.0, 21.0, 1.0], 1.0, 0.05


def test_a_lead_lags_step_tune_keeps_kc_below_the_implied_k_u():
    ku, _ = ultimate_point(NUM, DEN, DELAY)
    for seed in (0, 1):
        sim = transfer_function_loop(NUM, DEN, DELAY, TS, 0.005, seed=seed, name="b")
        req = TuneRequest(loop="b", method="step")
        r = TuningRun(LocalLoopClient(sim), req, "t", RunHooks()).run()
        assert r.status == "ok", r.reason
        assert r.chosen["isa"]["kc"] < ku
        assert isa_ms(NUM, DEN, DELAY, TS, r.chosen["isa"]) < 2.0
        assert r.gains["amigo-pi"]["isa"]["kc"] > ku  # still offered, no longer recommended
        assert r.rule != "amigo-pi"


def test_the_envelope_names_the_implied_k_u_only_without_a_measured_one():
    a = Assessment("amigo-pi", IsaGains(kc=15.0, ti=2.2), None)
    said = envelope_problem(a, None, 2.0, implied=(4.4, 0.05))
    assert said is not None and "the K_u 4.4 the step's record implies by itself" in said
    assert envelope_problem(a, None, 2.0, implied=(15.0, 0.05)) is None  # within its ± 5 %
    assert "measured K_u" in envelope_problem(a, UltimatePoint(10.0, 3.0), 2.0, (20.0, 0.0))
