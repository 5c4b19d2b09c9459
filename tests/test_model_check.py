"""Model checks: healthy fits pass, the absurd models of issue 10 are refused with reasons.

Measured ultimate points of healthy plants are their exact ones (tests.exact); the bad models
are those users reported, and one a relay on a PV still moving fitted in reproduction.
"""

import math

import pytest

from services.autotuner.identify.model_check import ModelCheck, check_model
from services.autotuner.identify.model_fit import ProcessFit
from tests.exact import lag_ultimate

FOPDT = ProcessFit("fopdt", 1.0, (10.0,), 1.0, 0.03, noise_rms=0.025)
HX = ProcessFit("sopdt", 1.0, (60.0, 10.0), 5.0, 0.02, noise_rms=0.02)
IPDT = ProcessFit("ipdt", 0.5, (), 2.0, 0.03, noise_rms=0.03)


def ultimate_point(model: ProcessFit) -> tuple[float, float]:
    return lag_ultimate(model.gain, model.lags, model.delay)


def _measured(model: ProcessFit, spread: float = 0.01) -> dict:
    ku, pu = ultimate_point(model)
    return dict(ku=ku, pu=pu, ku_spread=spread, pu_spread=spread)


def _one_line(check: ModelCheck) -> None:
    assert check.reasons and all("\n" not in r for r in check.reasons)


@pytest.mark.parametrize("model", [FOPDT, HX, IPDT], ids=["fopdt", "sopdt", "ipdt"])
def test_a_healthy_fit_passes_every_check(model):
    check = check_model(model, **_measured(model))
    assert check.ok, check.reasons
    ku, pu = ultimate_point(model)
    assert check.ku_model == pytest.approx(ku, rel=1e-6)
    assert check.pu_model == pytest.approx(pu, rel=1e-6)


def test_ipdt_ultimate_point_closed_form_passes_with_evidence_of_integration():
    """K·e^{−Ls}/s: ω_u·L = π/2, K_u = ω_u/K, so K·L·K_u = π/2."""
    ku, pu = math.pi / (2 * IPDT.gain * IPDT.delay), 4 * IPDT.delay
    assert check_model(IPDT, ku, pu, 0.0, 0.0, integrating=True).ok
    refused = check_model(IPDT, ku, pu, 0.0, 0.0, integrating=False)
    assert not refused.ok and "settling" in refused.summary()


def test_step_test_model_is_checked_on_physics_only():
    assert check_model(FOPDT).ok
    bad = check_model(ProcessFit("fopdt", -0.4, (10.0,), 1.0, 0.0))
    _one_line(bad)
    assert "gain -0.4" in bad.reasons[0]
    assert not check_model(ProcessFit("fopdt", 1.0, (math.inf,), 1.0, 0.0)).ok
    assert not check_model(ProcessFit("fopdt", 1.0, (10.0,), math.nan, 0.0)).ok


def test_user_report_moving_pv_static_gain_too_small():
    """Issue 10: on the heat exchanger (K_u 15.29, P_u 43.56 s) the fit on a PV still moving
    gave K = 0.135 (true 1): a SOPDT that misses its own record and, made to pass near the
    measured phase, predicts K_u a fifth too high."""
    model = ProcessFit("sopdt", 0.135, (5.0, 2.0), 15.0, 0.66, noise_rms=0.04)
    check = check_model(model, 15.29, 43.56, 0.016, 0.0014)
    _one_line(check)
    assert any("misses the record" in r for r in check.reasons)
    assert any(r.startswith("SOPDT predicts K_u") for r in check.reasons)


def test_reproduced_moving_pv_fit_is_refused():
    """What a relay fitted here when started on the heat exchanger 30 s after a 5 % step."""
    model = ProcessFit("sopdt", 0.06266, (2.6239, 2.6238), 17.476, 0.6654, noise_rms=0.0369)
    check = check_model(model, 15.16, 43.565, 0.0164, 0.00139)
    assert not check.ok and any("misses the record" in r for r in check.reasons)


def test_user_report_integrator_with_huge_controller_gain():
    """Issue 10: IPDT K = 1.2e-5, L = 62.5 s beside a measured K_u of 9.4 (simc-pi-int then
    gave Kc = 1/(2KL) = 667, 71 × K_u): K·L·K_u is 0.007, not π/2, and the delay alone
    would lag past −180° long before P_u."""
    model = ProcessFit("ipdt", 1.2e-5, (), 62.5, 0.05, noise_rms=0.03)
    check = check_model(model, 9.4, 40.0, 0.01, 0.01)
    _one_line(check)
    text = check.summary()
    assert f"gain × delay × K_u = {1.2e-5 * 62.5 * 9.4:.3g}" in text  # 0.00705
    assert "delay 62.5 s beyond what P_u 40 s allows" in text
    assert "predicts K_u" in text and "predicts P_u" in text


def test_user_report_flow_loop_absurd_integrator():
    """Issue 10: a flow loop's IPDT with gain 6e-10 and delay 191 s (gain margin reported
    27,330,012)."""
    model = ProcessFit("ipdt", 6e-10, (), 191.0, 0.2, noise_rms=0.05)
    check = check_model(model, 0.8, 5.0, 0.02, 0.01)
    _one_line(check)
    assert len(check.reasons) >= 3


def test_dead_time_bounds_from_the_measured_phase():
    """A FOPDT's lag gives at most 90°: at ω_u the delay must supply the rest, L > P_u/4; no
    model's delay may exceed P_u/2 (it alone would lag 180°)."""
    ku, pu = ultimate_point(FOPDT)
    short = ProcessFit("fopdt", 1.0, (10.0,), 0.2 * pu, 0.03, 0.03)
    assert any("below" in r for r in check_model(short, ku, pu, 0.0, 0.0).reasons)
    long = ProcessFit("sopdt", 1.0, (1.0, 0.5), 0.6 * pu, 0.03, 0.03)
    assert any("beyond what P_u" in r for r in check_model(long, ku, pu, 0.0, 0.0).reasons)


def test_lag_model_gain_below_one_over_ku_is_impossible():
    """|K/(τjω+1)| ≤ K: a lag model reaching 1/K_u at ω_u needs K ≥ 1/K_u."""
    ku, pu = ultimate_point(FOPDT)
    small = ProcessFit("fopdt", 0.5 / ku, (10.0,), 1.0, 0.03, 0.03)
    assert any("below 1/K_u" in r for r in check_model(small, ku, pu, 0.0, 0.0).reasons)


def test_ultimate_point_tolerance_is_the_spread_plus_the_stated_margin():
    """A FOPDT whose gain is 10 % off predicts K_u 10 % off: within 15 % + spread it passes,
    at 20 % it does not."""
    ku, pu = ultimate_point(FOPDT)
    for factor, ok in ((1.1, True), (1.0 / 1.1, True), (1.25, False), (0.8, False)):
        m = ProcessFit("fopdt", factor, (10.0,), 1.0, 0.03, 0.03)
        assert check_model(m, ku, pu, 0.0, 0.0).ok is ok, factor
    assert check_model(ProcessFit("fopdt", 1.25, (10.0,), 1.0, 0.03, 0.03), ku, pu, 0.1).ok


def test_record_fit_residual_beyond_the_noise():
    """√(rms² − noise²) above 0.4 of the PV's spread: the model misses the record."""
    ku, pu = ultimate_point(FOPDT)
    noisy = ProcessFit("fopdt", 1.0, (10.0,), 1.0, 0.5, noise_rms=0.4)  # excess 0.3
    assert check_model(noisy, ku, pu, 0.0, 0.0).ok
    poor = ProcessFit("fopdt", 1.0, (10.0,), 1.0, 0.5, noise_rms=0.1)  # excess 0.49
    excess = math.sqrt(0.5**2 - 0.1**2)  # √(rms² − noise²) = 0.49
    assert f"excess {excess:.2g}" in check_model(poor, ku, pu, 0.0, 0.0).summary()
    unfitted = ProcessFit("fopdt", 1.0, (10.0,), 1.0, math.inf)
    assert not check_model(unfitted, ku, pu, 0.0, 0.0).ok


def test_noise_free_exact_models_of_the_benchmark_pass():
    """Second order plus dead time over a range of lag ratios, at their exact points."""
    for t1, t2, delay in ((1.0, 1.0, 1.0), (10.0, 0.1, 0.5), (100.0, 3.0, 0.2)):
        m = ProcessFit("sopdt", 2.0, (t1, t2), delay, 1e-6)
        ku, pu = ultimate_point(m)
        assert check_model(m, ku, pu, 0.0, 0.0).ok


def test_a_sound_model_that_disagrees_widens_the_stated_spread():
    """Measured K_u 7 % off the sound model's own (exact) point with a scatter of 0.65 %, as
    hx1 gave on the realtime clock under load: the stated spread is the 7 %, not the 0.65 %.
    A model that fails on physics or its record says nothing of the point's accuracy."""
    from services.autotuner.design.selection import stated_spreads
    from services.autotuner.identify.experiments import Identification

    ku, pu = ultimate_point(HX)
    ident = Identification(ku=1.07 * ku, pu=0.96 * pu, ku_spread=0.0065, pu_spread=0.004)
    check = check_model(HX, ident.ku, ident.pu, ident.ku_spread, ident.pu_spread)
    assert check.ok and check.sound  # within the check's allowance: used by the rules
    ku_s, pu_s = stated_spreads(ident, check)
    assert ku_s == pytest.approx(abs(ku / ident.ku - 1), rel=1e-6)
    assert ku_s >= 0.065 and pu_s == pytest.approx(abs(pu / ident.pu - 1), rel=1e-6)
    close = Identification(ku=1.001 * ku, pu=pu, ku_spread=0.02, pu_spread=None)
    assert stated_spreads(close, check_model(HX, close.ku, close.pu, 0.02, None)) == (
        0.02,  # the scatter, larger than the disagreement, stands
        pytest.approx(0.0, abs=1e-9),  # none stated (a ramp's P_u): the disagreement
    )
    # a ramp's K_u lies between two gains tried on the loop: its bracket stands, its P_u (no
    # scatter of its own) takes the disagreement
    ramp = Identification(ku=1.07 * ku, pu=0.96 * pu, ku_spread=0.006, ku_bracketed=True)
    ramp_check = check_model(HX, ramp.ku, ramp.pu, ramp.ku_spread, None)
    assert ramp_check.sound
    assert stated_spreads(ramp, ramp_check) == (
        0.006,
        pytest.approx(abs(pu / ramp.pu - 1), rel=1e-6),
    )
    bad = ProcessFit("sopdt", 1.0, (60.0, 10.0), 5.0, 0.9, noise_rms=0.02)  # misses its record
    worse = check_model(bad, ident.ku, ident.pu, ident.ku_spread, ident.pu_spread)
    assert not worse.sound
    assert stated_spreads(ident, worse) == (0.0065, 0.004)


def test_a_biased_relay_states_a_spread_that_covers_its_error():
    """hx1 (e^{−5s}/((10s+1)(60s+1)), its preset noise) with ``--relay-bias 0.3``: stage 2's
    point comes out about 6° off (kept as measured: its correction would have moved it by
    more than the cycles agreed) and K_u about 9 % high. The correction it was not given
    (8.6 % of G) is its stated uncertainty, so the experiment's own spread covers the error,
    and the model, whose own point lies near the exact one, is not refused for lying outside
    a spread that understated it (before: a cycle scatter of 2.9 %, the model refused)."""
    import tomllib
    from pathlib import Path

    from services.autotuner.tuning import TuningRun
    from services.offline.local_loop import LocalLoopClient
    from services.plant_sim.plant_file import build_plant
    from shared.messages import TuneRequest
    from tests.exact import ultimate_point as exact_point

    presets = Path(__file__).parents[1] / "services/plant_sim/plants/default.toml"
    loop = build_plant(tomllib.loads(presets.read_text()))["hx1"]
    req = TuneRequest(loop="hx1", method="relay", apply=False, relay_bias=0.3)
    r = TuningRun(LocalLoopClient(loop), req, "unit").run()
    ku, pu = exact_point([1.0], [600.0, 70.0, 1.0], 5.0)
    assert r.ku is not None and r.pu is not None and r.ku_spread and r.pu_spread
    # within the spread, give or take the model's own error (0.2 % here)
    assert abs(r.ku / ku - 1) <= r.ku_spread + 0.01
    assert abs(r.pu / pu - 1) <= r.pu_spread + 0.01
    assert abs(r.ku / ku - 1) > 0.05  # the case in point: a stage-2 point well off
    assert not any("was refused" in w for w in r.warnings), r.warnings
