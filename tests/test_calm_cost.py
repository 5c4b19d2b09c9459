"""The recommendation's preference for a calm predicted step does not cost the load's answer.

On e^{−0.5s}/((100s + 1)(s + 1)) by step (noise seed 1 of a loop named "twosc"), AMIGO PI
predicted 25.001 % of setpoint overshoot, just past the calm preference's 25 %; the only
candidate left calm within the Ms margin was lambda PID (Ti = T = 100 s, λ = T), at 0.0016 of
the integral gain of AMIGO PID (31 % predicted, inside the verification's 35 %). Lambda PID
was applied: Ms 1.01, a load step's integrated error some 500 against 2.1 for AMIGO PI on
another seed. The calm preference now keeps at least a quarter of the best integral gain of
the candidates predicted within the verification's limits. The expected figures: Ms of the
applied gains computed with numpy on the exact plant (``tests.exact``).
"""

from __future__ import annotations

from services.autotuner.design.predicted_response import StepFigures
from services.autotuner.design.recommend import (
    CALM_KI_SHARE,
    PASSABLE_DECAY,
    PASSABLE_OVERSHOOT,
    Assessment,
    recommend,
)
from services.autotuner.design.robustness import Robustness
from services.autotuner.identify.model_fit import ProcessFit
from services.autotuner.tuning import RunHooks, TuningRun
from services.offline.local_loop import LocalLoopClient
from shared.control.forms import IsaGains
from shared.messages import TuneRequest
from tests.exact import isa_ms
from tests.plants import transfer_function_loop

NUM, DEN, DELAY, TS = [1.0], [100.0, 101.0, 1.0], 0.5, 0.02
MODEL = ProcessFit("sopdt", 1.0, (100.0, 1.0), 0.5, 0.0)


def _cand(rule: str, kc: float, ti: float, ms: float, overshoot: float) -> Assessment:
    rb = Robustness(ms, 5.0, 60.0, 1.0, 0.5, stable=True, sample_time=TS)
    return Assessment(rule, IsaGains(kc=kc, ti=ti), rb, StepFigures(overshoot, 0.0, True))


def test_a_calm_candidate_far_weaker_than_a_passable_one_is_passed_over():
    lam = _cand("lambda-pi", 1.0, 100.0, 1.01, 2.4)  # Ki 0.01
    fair = _cand("amigo-pi", 34.0, 12.0, 1.52, 25.001)  # Ki 2.8, inside 35 %
    wild = _cand("simc-pi", 50.0, 2.0, 1.75, 60.0)  # Ki 25, outside the verification's limit
    rec = recommend(None, MODEL, candidates={c.rule: c for c in (lam, fair, wild)})
    assert rec is not None and rec.rule == "amigo-pi", rec
    assert "within the verification's limits (overshoot ≤ 35 %" in rec.reason, rec.reason
    assert "lambda-pi, has 0.0035 of its integral gain" in rec.reason, rec.reason


def test_a_calm_candidate_within_the_share_is_still_preferred():
    ki_fair = 34.0 / 12.0
    calm = _cand("amigo-pi", CALM_KI_SHARE * ki_fair * 1.01 * 20.0, 20.0, 1.5, 20.0)
    fair = _cand("amigo-pid", 34.0, 12.0, 1.4, 31.0)
    rec = recommend(None, MODEL, candidates={c.rule: c for c in (calm, fair)})
    assert rec is not None and rec.rule == "amigo-pi", rec
    assert "and a predicted overshoot ≤ 25 %" in rec.reason, rec.reason
    # just below the share: the passable one, and the reason says why
    calm = _cand("amigo-pi", CALM_KI_SHARE * ki_fair * 0.99 * 20.0, 20.0, 1.5, 20.0)
    rec = recommend(None, MODEL, candidates={c.rule: c for c in (calm, fair)})
    assert rec is not None and rec.rule == "amigo-pid", rec


def test_the_two_time_scale_loop_by_step_is_not_tuned_to_a_crawl():
    sim = transfer_function_loop(NUM, DEN, DELAY, TS, 0.002, seed=1, name="twosc")
    r = TuningRun(LocalLoopClient(sim), TuneRequest(loop="twosc", method="step"), "t", RunHooks())
    res = r.run()
    assert res.status == "ok", res.reason
    assert not res.rule.startswith("lambda"), res.recommended
    # the case above: AMIGO PI's 25.001 % sits on the calm 25 %, and which side it falls depends
    # on the last bits of the CPU's floating point (an AMD EPYC reads it within: AMIGO PI calm,
    # chosen as such); either way the choice is not lambda's crawl
    reason = res.recommended["reason"]
    assert "lambda-pid, has" in reason or "predicted overshoot ≤ 25 %" in reason, reason
    ms = isa_ms(NUM, DEN, DELAY, TS, res.chosen["isa"])
    assert 1.2 < ms < 1.8, ms  # robust, and not the Ms 1.01 of a loop left to crawl
    isa = res.chosen["isa"]
    assert isa["kc"] / isa["ti"] > 1.0  # lambda PID's was 0.0099 % per PV unit per s


def test_the_passable_limits_are_the_verifications_defaults():
    fields = TuneRequest.model_fields
    assert fields["max_overshoot"].default == PASSABLE_OVERSHOOT
    assert fields["max_decay_ratio"].default == PASSABLE_DECAY


def test_equal_integral_gains_go_to_the_lower_ms_whatever_the_last_bits():
    """lvl2: SIMC PI and lambda PI both at Ki 100.4117916127567x, the pick was the rounding's
    (helper trial): a tie within SAME_KI is the more robust candidate's, either way round."""
    ki = 100.41179161275672
    for bump in (1.0 + 2e-16, 1.0 - 2e-16):
        stiff = _cand("simc-pi-int", 3422.0, 3422.0 / ki, 1.62, 20.0)
        soft = _cand("lambda-pi", 1745.0, 1745.0 / (ki * bump), 1.31, 20.0)
        rec = recommend(None, MODEL, candidates={c.rule: c for c in (stiff, soft)})
        assert rec is not None and rec.rule == "lambda-pi", (bump, rec)
    # a real difference in integral gain still wins over Ms
    stiff = _cand("simc-pi-int", 3422.0, 3422.0 / (ki * 1.001), 1.62, 20.0)
    soft = _cand("lambda-pi", 1745.0, 1745.0 / ki, 1.31, 20.0)
    rec = recommend(None, MODEL, candidates={c.rule: c for c in (stiff, soft)})
    assert rec is not None and rec.rule == "simc-pi-int", rec


def test_the_calm_test_reads_the_decay_ratio_the_table_prints():
    """TL PI's predicted step overshoots 7.1 % and creeps back from above with a ripple on the
    way: no second overshoot, its decay ratio "—" in the table, but its crests read 0.90, and
    the calm and passable tests, reading the crests, passed it over for a candidate fifty
    times weaker that the table showed no better."""
    rb = Robustness(1.5, 5.0, 60.0, 1.0, 0.5, stable=True, sample_time=TS)
    tl = Assessment("tl-pi", IsaGains(kc=5.0, ti=10.0), rb, StepFigures(7.1, 0.90, True, None))
    lam = _cand("lambda-pi", 1.0, 100.0, 1.01, 0.0)
    rec = recommend(None, MODEL, candidates={c.rule: c for c in (tl, lam)})
    assert rec is not None and rec.rule == "tl-pi", rec
    # a second overshoot of the table's, past the calm 0.25: passed over, as it was
    rough = Assessment("tl-pi", tl.gains, rb, StepFigures(7.1, 0.90, True, 0.4))
    rec = recommend(None, MODEL, candidates={c.rule: c for c in (rough, lam)})
    assert rec is not None and rec.rule == "lambda-pi", rec
