"""``autotune model check`` (issue 17, item 2): any model checked open loop before it is tuned.

Every preset, and the three test FMUs (first order plus dead time, heat exchanger, nonlinear
tank), against closed forms computed here: static gains (each step's, for the tank's
square-root law), dead time, time constants, the reaction curve's tangent, and the ultimate
point — exact from the transfer function where the model has one, and from the step response
for every model — within 1 %. Unstable, drifting, silent and failing models; the command's
text, JSON, plot and one-line refusals.
(tests/test_model_check.py is the autotuner's check of a fitted model: another module.)
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq

from services.plant_sim.model_check import check_loop, refine_step_point
from services.plant_sim.plant_file import build_plant, default_plant_path, load_plant_file
from tests.cli_run import run_cli
from tests.exact import lag_ultimate, sopdt_tangent, ultimate_point
from tests.fmus import build_all

ROOT = Path(__file__).resolve().parents[1]
HERE = "tests.test_plant_model_check"


@pytest.fixture(scope="session")
def fmus(tmp_path_factory) -> dict[str, Path]:
    return build_all(tmp_path_factory.mktemp("fmus"))


@pytest.fixture(scope="module")
def presets():
    loops = load_plant_file(default_plant_path())
    return {lid: check_loop(lid, loop) for lid, loop in loops.items()}


def check(table: dict, loop_id: str = "x"):
    return check_loop(loop_id, build_plant({"loops": {loop_id: table}})[loop_id])


def t63_sopdt(t1: float, t2: float) -> float:
    """Time after the dead time to 63.2 % of 1/((t1 s + 1)(t2 s + 1))'s step."""
    return brentq(
        lambda x: (
            1 - (t1 * math.exp(-x / t1) - t2 * math.exp(-x / t2)) / (t1 - t2) - (1 - 1 / math.e)
        ),
        1e-6,
        100 * (t1 + t2),
    )


def within(got: float | None, exact: float, rel: float = 0.01) -> None:
    assert got is not None and got == pytest.approx(exact, rel=rel), (got, exact)


def assert_fopdt_figures(r, k: float, tau: float, lag: float) -> None:
    within(r.gain, k, 1e-4)
    within(r.dead_time, lag)
    within(r.t63, tau)
    within(r.lag_sum, tau)
    within(r.apparent_dead_time, lag)
    within(r.apparent_lag, tau)
    ku, pu = lag_ultimate(k, (tau,), lag)
    within(r.ku_step, ku)
    within(r.pu_step, pu)


def assert_heat_exchanger_figures(r) -> None:
    """e^{−5s}/((10s + 1)(60s + 1)) °C per %."""
    within(r.gain, 1.0, 1e-4)
    within(r.dead_time, 5.0)
    within(r.lag_sum, 70.0)
    within(r.t63, t63_sopdt(10.0, 60.0))
    lag, slope = sopdt_tangent(1.0, 10.0, 60.0, 5.0)
    within(r.apparent_dead_time, lag)
    within(r.apparent_lag, 1.0 / slope)
    ku, pu = lag_ultimate(1.0, (10.0, 60.0), 5.0)
    within(r.ku_step, ku)
    within(r.pu_step, pu)
    assert r.samples_per_period == pytest.approx(pu / 0.25, rel=0.01)
    assert r.nonlinearity < 1e-6 and r.warnings == []


# --- the presets -------------------------------------------------------------------------


def test_heat_exchanger_preset(presets):
    r = presets["hx1"]
    assert r.behaviour == "self-regulating" and r.refused is None
    assert_heat_exchanger_figures(r)
    ku, pu = lag_ultimate(1.0, (10.0, 60.0), 5.0)
    assert r.ku_exact == pytest.approx(ku, rel=1e-9) and r.pu_exact == pytest.approx(pu, rel=1e-9)


def test_physical_heat_exchanger_preset(presets):
    """Linear in the valve (linear characteristic): the energy balances give
    G(s) = K_q·UA/((C_w s + UA)(C_f s + F c_p + UA) − UA²) · e^{−5s}/(s + 1)."""
    cp, h_fg, steam_max, flow, ua = 4186.0, 2.1e6, 0.4, 2.0, 12000.0
    c_f, c_w = 60.0 * cp, 250000.0
    k_q = steam_max * h_fg / 100.0  # W per % of valve
    den = np.polysub(np.polymul([c_w, ua], [c_f, flow * cp + ua]), [0.0, 0.0, ua**2])
    den = np.polymul(den, [1.0, 1.0])
    r = presets["hx2"]
    within(r.gain, k_q / (flow * cp), 1e-4)
    assert set(r.gains) == {"+2 %", "-2 %", "+10 %", "-10 %"}
    within(r.dead_time, 5.0)
    ku, pu = ultimate_point([k_q * ua], den, 5.0)
    within(r.ku_step, ku)
    within(r.pu_step, pu)
    assert r.ku_exact is None  # no transfer function of its own: the step response's


def test_tank_level_preset_is_nonlinear_and_sampled_too_slowly(presets):
    """At rest h = level0·(op/op0)²: each step's gain in closed form; linearised, a lag of
    2·area·level0/q0 = 600 s with 1 s dead time, whose P_u (4 s) is 4 samples."""
    r = presets["lvl1"]
    for label, gain in r.gains.items():
        d = float(label.split()[0])
        within(gain, 1.5 * ((50 + d) ** 2 - 50**2) / (50**2 * d), 1e-3)
    within(r.gain, 2 * 1.5 / 50, 1e-3)
    within(r.dead_time, 1.0)
    within(r.t63, 600.0)
    assert r.nonlinearity == pytest.approx(0.066 / 0.054 - 1, rel=1e-3)
    assert any(w.startswith("nonlinear: the gain varies by 22.2 %") for w in r.warnings)
    assert any("samples per ultimate period" in w and "below 20" in w for w in r.warnings)


def test_integrating_tank_preset(presets):
    """A·dh/dt = inflow_max·op/100 − q_pump: 1e-4 m/s per %, 2 s dead time."""
    r = presets["lvl2"]
    assert r.behaviour == "integrating"
    within(r.gain, 0.02 / (100 * 2.0), 1e-6)
    assert all(g == pytest.approx(1e-4, rel=1e-6) for g in r.gains.values())
    within(r.dead_time, 2.0)
    within(r.apparent_dead_time, 2.0)


def test_flow_preset(presets):
    """Linear valve: 1 m³/h per %, lags 1.5 s (actuator), 0.5 s (fluid), 0.3 s (transmitter),
    1 s dead time."""
    r = presets["flow1"]
    within(r.gain, 1.0, 1e-4)
    within(r.dead_time, 1.0)
    within(r.lag_sum, 2.3)
    ku, pu = lag_ultimate(1.0, (1.5, 0.5, 0.3), 1.0)
    within(r.ku_step, ku)
    within(r.pu_step, pu)


@pytest.mark.parametrize(
    ("den", "delay", "ts"),
    [
        ([35.0, 1.0], 10.0, 1.0),  # the power law read 10.046 s
        ([5.0, 1.0], 10.0, 1.0),  # 10.287 s
        ([1.0, 1.0], 10.0, 1.0),  # 10.859 s
        ([5.0, 1.0], 10.37, 1.0),  # within a sample: 10.54 s
        ([1.0, 3.0, 3.0, 1.0], 2.0, 0.5),  # (s + 1)³: 2.183 s
    ],
)
def test_the_dead_time_of_a_first_order_lag_or_a_chain_of_equal_lags_is_exact(den, delay, ts):
    """e^{−Ls}/(τs + 1)^n starts as the gamma distribution's P(n, (t − L)/τ): the onset read
    through the first three samples that moved is exact however few samples the lag spans,
    where the power law c·(t − L)^r bent over a first-order onset's curvature by moving L
    late by some 1.6·Ts²/τ (e^{−10s}/(35s + 1) at 1 s samples: 10.046 s, the order 0.95)."""
    r = check(
        {"model": "transfer_function", "num": [1.0], "den": den, "delay": delay, "sample_time": ts}
    )
    order = len(den) - 1
    assert r.dead_time == pytest.approx(delay, abs=1e-6 * ts)
    assert r.onset_order == pytest.approx(order, rel=1e-4)


def test_the_dead_time_of_unequal_lags_is_nearer_than_a_power_laws():
    """e^{−5s}/((10s + 1)(60s + 1)) (hx1) at 1 s samples: its onset is no gamma curve, and
    the one through its first three samples moves L by 0.021 s (the power law 0.061 s); at
    the preset's 0.25 s, 0.0012 s (0.004 s)."""
    table = {"model": "transfer_function", "num": [1.0], "den": [600.0, 70.0, 1.0], "delay": 5.0}
    assert abs(check({**table, "sample_time": 1.0}).dead_time - 5.0) < 0.025
    assert abs(check({**table, "sample_time": 0.25}).dead_time - 5.0) < 0.0015


@pytest.mark.parametrize(
    ("table", "exact"),
    [
        (
            {"model": "fopdt", "gain": 2.0, "time_constant": 10.0, "delay": 2.0},
            lag_ultimate(2.0, (10.0,), 2.0),
        ),
        ({"model": "ipdt", "gain": 0.02, "delay": 3.0}, (math.pi / (2 * 0.02 * 3.0), 12.0)),
        (
            {"model": "transfer_function", "num": [6.0], "den": [1.0, 6.0, 11.0, 6.0]},
            ultimate_point([6.0], [1.0, 6.0, 11.0, 6.0]),
        ),
    ],
    ids=["fopdt", "ipdt", "third-order"],
)
def test_linear_presets_exact_and_from_the_step(table, exact):
    r = check({**table, "sample_time": 0.01 if table["model"] == "transfer_function" else 0.1})
    assert r.ku_exact == pytest.approx(exact[0], rel=1e-9)
    assert r.pu_exact == pytest.approx(exact[1], rel=1e-9)
    within(r.ku_step, exact[0])
    within(r.pu_step, exact[1])
    if table["model"] == "fopdt":
        assert_fopdt_figures(r, 2.0, 10.0, 2.0)


@pytest.mark.parametrize(
    ("table", "exact"),
    [
        (
            {"model": "fopdt", "gain": -2.0, "time_constant": 10.0, "delay": 2.0},
            lag_ultimate(2.0, (10.0,), 2.0),
        ),
        ({"model": "ipdt", "gain": -0.02, "delay": 3.0}, (math.pi / (2 * 0.02 * 3.0), 12.0)),
        (
            {"model": "transfer_function", "num": [-1.5], "den": [10.0, 1.0], "delay": 2.0},
            lag_ultimate(1.5, (10.0,), 2.0),
        ),
    ],
    ids=["fopdt", "ipdt", "transfer-function"],
)
def test_a_direct_acting_loops_exact_point_is_that_of_minus_g(table, exact):
    """A process whose gain is negative is under a direct-acting controller, which closes the
    loop around −G: its exact ultimate point is −G's (G's phase starts at −180°, and no
    exact figure was given: only the step response's)."""
    r = check({**table, "sample_time": 0.1, "action": "direct"})
    assert r.ku_exact == pytest.approx(exact[0], rel=1e-9)
    assert r.pu_exact == pytest.approx(exact[1], rel=1e-9)
    within(r.ku_step, exact[0])
    within(r.pu_step, exact[1])


# --- the three test FMUs --------------------------------------------------------------------


def fmu_table(path: Path, **keys) -> dict:
    return {
        "model": "fmu",
        "path": str(path),
        "input": "u",
        "output": "y",
        "sample_time": 0.1,
        "pv_range": [0.0, 200.0],
        **keys,
    }


def test_fopdt_fmu(fmus):
    r = check(fmu_table(fmus["Fopdt"], parameters={"K": 2.0, "tau": 10.0, "L": 2.0}))
    assert r.behaviour == "self-regulating" and r.warnings == []
    assert_fopdt_figures(r, 2.0, 10.0, 2.0)


def test_fopdt_fmu_by_model_exchange(fmus):
    r = check(fmu_table(fmus["LagMe"], delay=2.0))
    assert_fopdt_figures(r, 2.0, 10.0, 2.0)


def test_heat_exchanger_fmu(fmus):
    r = check(
        fmu_table(
            fmus["HeatExchanger"],
            input="valve",
            output="T_out",
            op_scale=[0.0, 1.0],
            op0=40.0,
            delay=5.0,
            sample_time=0.25,
            disturbances={"inlet_temp": "T_in"},
        )
    )
    assert_heat_exchanger_figures(r)


def test_nonlinear_tank_fmu(fmus):
    """area·dh/dt = q_max·v/100 − cv·√h with the loop's 2 s: each step's gain from
    h = level0·(v/v0)², the linear part a 60 s lag of gain 0.06 m/% (1 % against it)."""
    r = check(fmu_table(fmus["Tank"], input="valve", output="h", delay=2.0, pv_range=[0, 6]))
    for label, gain in r.gains.items():
        d = float(label.split()[0])
        within(gain, 1.5 * ((50 + d) ** 2 - 50**2) / (50**2 * d), 1e-3)
    within(r.gain, 0.06, 1e-3)
    within(r.dead_time, 2.0)
    within(r.t63, 60.0)
    ku, pu = lag_ultimate(0.06, (60.0,), 2.0)
    within(r.ku_step, ku)
    within(r.pu_step, pu)
    assert r.nonlinearity > 0.2 and any(w.startswith("nonlinear") for w in r.warnings)


# --- models that must not be tuned as they are ---------------------------------------------


class _User:
    pv_units = "bar"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time: float, op0: float = 50.0):
        self.sample_time, self.op0 = sample_time, op0
        self.x, self.n = 0.0, 0

    def reset(self) -> float:
        self.x, self.n = 0.0, 0
        return 50.0

    def disturbance_names(self) -> tuple[str, ...]:
        return ()

    def set_disturbance(self, name: str, value: float) -> None:
        raise KeyError(name)


class Unstable(_User):
    """dx/dt = x/20 + 0.1·(op − op0), exactly sampled: doubles every 20·ln 2 s."""

    def step(self, op: float) -> float:
        a = math.exp(self.sample_time / 20.0)
        self.x = a * self.x + (a - 1.0) * 2.0 * (op - self.op0)
        return 50.0 + self.x


class Ignores(_User):
    def step(self, op: float) -> float:
        return 50.0


class NaNAfter(_User):
    def step(self, op: float) -> float:
        self.n += 1
        return math.nan if self.n > 30 else 50.0 + 0.1 * (op - self.op0)


class Raises(_User):
    def step(self, op: float) -> float:
        self.n += 1
        if self.n > 5:
            raise RuntimeError("valve stuck")
        return 50.0


class Drifts(_User):
    """An integrator not balanced at op0: 0.002 bar/s at rest, 0.01 bar/s per %."""

    def step(self, op: float) -> float:
        self.x += (0.002 + 0.01 * (op - self.op0)) * self.sample_time
        return 50.0 + self.x


class Deadband(_User):
    """A valve with a ±3 % deadband about op0 before a first-order lag of 5 s, gain 1: steps
    of 2 % move nothing, steps of 10 % move the PV by 7."""

    def step(self, op: float) -> float:
        d = op - self.op0
        u = math.copysign(max(abs(d) - 3.0, 0.0), d)
        a = math.exp(-self.sample_time / 5.0)
        self.x = a * self.x + (1.0 - a) * u
        return 50.0 + self.x


def test_a_deadband_is_said_not_called_linear():
    """A valve with 4 % of backlash was called "linear, spread < 0.001 %, ok": its ±2 % steps
    moved nothing and were dropped unsaid (helper trial F)."""
    r = check({"model": f"{HERE}:Deadband", "sample_time": 0.1})
    assert r.unmoved == ["+2 %", "-2 %"], r.unmoved
    assert r.nonlinearity == math.inf
    assert any(w.startswith("no response to the steps of +2 %, -2 %") for w in r.warnings)
    # its gain at op0 is the ±10 % steps' (7/10), and the report says so: it said "small
    # steps" beside "no response to +2 %, -2 %" (helper trial)
    assert r.linear_step == 10.0 and r.gain == pytest.approx(0.7, rel=1e-3)
    from services.plant_sim.commands.model_check import format_report

    (line,) = [x for x in format_report(r).splitlines() if "gain at op0" in x]
    assert "(the ±10 % steps: the smaller moved nothing, up and down averaged)" in line


def test_a_process_that_settles_within_a_sample_is_said_unresolved():
    """1/(0.1s + 1) sampled every 5 s: e^{−50} of the step is left after one sample. It was
    given T63 3.16 s and "ok" (helper trial F); now its lags are said not resolved. 1/(5s + 1)
    at 0.1 s is resolved: no such warning."""
    fast = {"model": "transfer_function", "num": [1.0], "den": [0.1, 1.0]}
    r = check({**fast, "sample_time": 5.0})
    assert any(w.startswith("settles within one sample (5 s)") for w in r.warnings), r.warnings
    r = check({"model": "transfer_function", "num": [1.0], "den": [5.0, 1.0], "sample_time": 0.1})
    assert not any(w.startswith("settles within one sample") for w in r.warnings)


def test_a_process_that_reaches_63_percent_in_its_first_sample_is_said_unresolved():
    """e^{−2s}/(10s + 1) sampled every 15 s: 1 − e^{−1.3} (73 %) of the change by the first
    sample that moves, so its onset fit read a dead time near the sample time and T63 came
    out below zero (the physical heat exchanger at 100 s: dead time 95.3 s, T63 −1.50 s, "ok");
    now no negative time constant is given and the figures are said to be the sampling's.
    At 1 s it is resolved: its T63 is 10 s after the dead time, as 1/(10s + 1)'s."""
    lag = {"model": "transfer_function", "num": [1.0], "den": [10.0, 1.0], "delay": 2.0}
    r = check({**lag, "sample_time": 15.0})
    assert any(w.startswith("reaches 63 % of its change by the first sample") for w in r.warnings)
    assert r.t63 is None or r.t63 >= 0
    assert r.lag_sum is None or r.lag_sum >= 0
    r = check({**lag, "sample_time": 1.0})
    assert not any(w.startswith("reaches 63 %") for w in r.warnings), r.warnings
    assert r.t63 == pytest.approx(10.0, rel=0.02)


class VaryingLag(_User):
    """Gain 1 everywhere, but a lag that grows with the PV, τ = 5·e^{x/4} s (x the PV's move
    from rest): a step of +10 % rises on a lag e^{2.5} times a −10 % step's falls on. Stepped
    at 0.1 s by 100 Euler steps a sample."""

    def step(self, op: float) -> float:
        h = self.sample_time / 100.0
        for _ in range(100):
            self.x += h * ((op - self.op0) - self.x) / (5.0 * math.exp(self.x / 4.0))
        return 50.0 + self.x


def test_dynamics_that_vary_more_than_the_gain_are_said():
    """A conical tank's gain varied 22 % over ±10 % of output, its K_u 3.7 times, and only the
    gain was said (helper trial F): K/T63 per step is compared too."""
    r = check({"model": f"{HERE}:VaryingLag", "sample_time": 0.1})
    assert r.nonlinearity is not None and r.nonlinearity < 0.01  # the gains agree
    (w,) = [w for w in r.warnings if w.startswith("the dynamics vary more than the gain")]
    assert "K/T63" in w


def test_an_unstable_model_is_said_to_run_away():
    r = check({"model": f"{HERE}:Unstable", "sample_time": 0.5})
    assert r.behaviour == "unstable" and r.refused is None and r.ku is None
    within(r.doubling_time, 20.0 * math.log(2.0))
    assert any(w.startswith("unstable: the PV runs away") for w in r.warnings)


def test_a_double_integrator_runs_away_without_a_doubling_time():
    # 1/s²: t² after a step, accelerating without bound but not exponentially
    r = check(
        {"model": "transfer_function", "num": [1.0], "den": [1.0, 0.0, 0.0], "sample_time": 0.5}
    )
    assert r.behaviour == "unstable" and r.doubling_time is None
    assert any("accelerating, but not exponentially" in w for w in r.warnings), r.warnings


def test_a_stable_model_of_an_absurd_gain_is_out_of_range_not_unstable():
    r = check(
        {"model": "fopdt", "gain": 1e200, "time_constant": 10.0, "delay": 1.0, "sample_time": 0.5}
    )
    assert r.behaviour == "out of range" and r.doubling_time is None
    assert any(w.startswith("out of range: the +2 % step moved the PV by") for w in r.warnings)
    assert not any(w.startswith("unstable") for w in r.warnings)


def test_a_model_not_at_rest_is_corrected_for_its_drift_and_said_so():
    r = check({"model": f"{HERE}:Drifts", "sample_time": 0.5})
    assert r.behaviour == "integrating"
    assert all(g == pytest.approx(0.01, rel=1e-9) for g in r.gains.values())
    assert r.rest_drift == pytest.approx(0.002, rel=1e-9)
    assert any(w.startswith("not at rest at op0 = 50 %: the PV drifts 0.002") for w in r.warnings)
    # noise-free, its drift over the tuner's rest window (40 samples, 20 s: 0.04) is beyond
    # what the tuner takes as rest (1e-5 of the 0–100 span): no tune would start; with a σ
    # of 0.02 (3σ = 0.06) one would
    (said,) = [w for w in r.warnings if w.startswith("a tune will not start")]
    assert "moves 0.04 bar over the 20 s" in said and "beyond the 0.001 it takes" in said
    noisy = check({"model": f"{HERE}:Drifts", "sample_time": 0.5, "noise_std": 0.02})
    assert not any(w.startswith("a tune will not start") for w in noisy.warnings)
    # in auto under a PI, its PID takes the drift out: the tuner finds rest as it is (review)
    held = check(
        {
            "model": f"{HERE}:Drifts",
            "sample_time": 0.5,
            "mode": "auto",
            "pid": {"kc": 2.0, "ti": 20.0},
        }
    )
    assert not any(w.startswith("a tune will not start") for w in held.warnings)


@pytest.mark.parametrize(
    ("cls", "needle"),
    [
        ("Ignores", "it ignores its input: the PV did not move in"),
        ("NaNAfter", "the model's step() returned PV nan (at t = 15.5 s of the run held at op0)"),
        ("Raises", "the model's step() raised RuntimeError: valve stuck"),
    ],
)
def test_models_that_cannot_be_tuned_are_refused(cls, needle):
    r = check({"model": f"{HERE}:{cls}", "sample_time": 0.5})
    assert r.refused is not None and needle in r.refused and "\n" not in r.refused


# --- the command ----------------------------------------------------------------------------


def plant_with(tmp_path: Path, fmus: dict[str, Path], extra: str = "") -> Path:
    path = tmp_path / "plant.toml"
    path.write_text(
        f'[loops.fo1]\nmodel = "fmu"\npath = "{fmus["Fopdt"]}"\ninput = "u"\noutput = "y"\n'
        'sample_time = 0.1\npv_range = [0.0, 200.0]\npv_units = "degC"\n\n'
        '[loops.ip]\nmodel = "ipdt"\ngain = 0.02\ndelay = 3.0\nsample_time = 0.1\n' + extra
    )
    return path


def test_a_coarse_loops_step_point_is_read_at_a_finer_sample_time(capsys):
    """lvl1 and lvl2 at 1 s samples are 4 and 8 samples a period: read from those samples
    their step-response points were 19 % and 5 % low (the hold divided out of a spectrum
    that aliases near Nyquist). Read again at 40 samples a period, they are their
    linearised closed forms: lvl1 0.06·e^{−s}/(600s + 1) m per % (2·level0/op0 over a lag of
    2·area·level0/q0), lvl2 1e-4·e^{−2s}/s (K_u = π/(2·1e-4·2), P_u = 4·2 s)."""
    code, out, err = run_cli(capsys, "model", "check", str(default_plant_path()), "--json")
    assert code == 0, err
    loops = {x["loop"]: x for x in json.loads(out)["loops"]}
    lvl1, lvl2 = loops["lvl1"], loops["lvl2"]
    ku1, pu1 = lag_ultimate(0.06, (600.0,), 1.0)
    within(lvl1["ku"], ku1, 0.005)
    within(lvl1["pu"], pu1, 0.005)
    within(lvl2["ku"], math.pi / (2 * 1e-4 * 2.0), 0.005)
    within(lvl2["pu"], 8.0, 0.005)
    assert 0 < lvl1["step_sample_time"] <= pu1 / 40 and lvl2["step_sample_time"] <= 8.0 / 40
    # a loop sampled finely enough is read at its own samples
    assert loops["hx2"]["step_sample_time"] == 0.25


def test_a_coarse_point_that_cannot_be_read_again_is_said_blurred():
    """Where the loop cannot be stepped at the finer sample time (its model refuses it, or
    loads too slowly), its step-response point is the one its own samples blur: said so, with
    the reason, not printed as if sound (lvl1 at 4 samples a period reads 19 % low)."""
    r = check_loop("lvl1", load_plant_file(default_plant_path())["lvl1"])
    ku, pu, asked = r.ku_step, r.pu_step, []

    def cannot(t: float) -> str:
        asked.append(t)
        return "loops.lvl1.model: takes a fixed step"

    refine_step_point(r, cannot)
    assert (r.ku_step, r.pu_step, r.step_sample_time) == (ku, pu, r.sample_time)
    said = [w for w in r.warnings if w.startswith("the step response's K_u and P_u")]
    assert len(said) == 1, r.warnings
    assert "1 s samples" in said[0] and "takes a fixed step" in said[0]
    assert f"again at {asked[0]:.4g} s" in said[0] and asked[0] <= pu / 40


def test_the_command_prints_json_and_a_plot(fmus, tmp_path, capsys):
    plant = plant_with(tmp_path, fmus)
    png = tmp_path / "check.png"
    code, out, err = run_cli(capsys, "model", "check", str(plant), "--json", "--plot", str(png))
    assert code == 0, err
    loops = {x["loop"]: x for x in json.loads(out)["loops"]}
    assert set(loops) == {"fo1", "ip"} and loops["fo1"]["status"] == "ok"
    within(loops["fo1"]["ku"], lag_ultimate(2.0, (10.0,), 2.0)[0])
    assert loops["ip"]["ku_exact"] == pytest.approx(math.pi / (2 * 0.02 * 3.0), rel=1e-9)
    assert loops["ip"]["behaviour"] == "integrating"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, out, err = run_cli(capsys, "model", "check", str(plant), "--loop", "ip")
    assert code == 0 and out.startswith("loop ip: model ipdt") and "loop fo1" not in out
    assert "ultimate point: K_u 26.18 % per %, P_u 12 s (exact, from the transfer function" in out


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--loop", "nope"], "--loop nope: no such loop in"),
        (["--plot", "x.jpg"], "--plot x.jpg: must name a .png file"),
        (["--plot", "/no/such/dir/x.png"], "the directory /no/such/dir does not exist"),
    ],
)
def test_bad_flags_are_one_line(fmus, tmp_path, capsys, args, needle):
    code, _, err = run_cli(capsys, "model", "check", str(plant_with(tmp_path, fmus)), *args)
    assert code == 2 and len(err.strip().splitlines()) == 1 and needle in err, err
    # named by the command given, `model check` (it read "autotune model: error:")
    assert err.startswith("autotune model check: error: "), err


def test_a_refused_model_is_reported_and_exits_2_in_one_line(fmus, tmp_path, capsys):
    extra = f'\n[loops.bad]\nmodel = "{HERE}:NaNAfter"\nsample_time = 0.5\n'
    code, out, err = run_cli(capsys, "model", "check", str(plant_with(tmp_path, fmus, extra)))
    assert code == 2 and "loop fo1" in out and "REFUSED" in out
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "loops.bad.model: refused: the model's step() returned PV nan" in err


def test_through_a_real_interpreter(fmus, tmp_path):
    plant = plant_with(tmp_path, fmus)
    run = subprocess.run(
        [sys.executable, "-m", "services.cli", "model", "check", str(plant), "--loop", "fo1"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr
    assert "loop fo1: model fmu" in run.stdout and "behaviour: self-regulating" in run.stdout
    # e^{−2s}·2/(10s + 1): the onset of a first-order lag, read exactly (the power law it
    # was read with before moved it to 2.0016 s, 1.6·Ts²/τ late)
    assert "dead time: 2 s (first movement, onset like t^1)" in run.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "services.cli", "model", "chek", str(plant)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


def test_a_process_resting_beyond_its_transmitter_says_so():
    """pv0 50 on a 0–10 transmitter: the file runs (clipped at 10), and the check says why no
    test will see the PV move."""
    r = check(
        {
            "model": "fopdt",
            "gain": 1.0,
            "time_constant": 10.0,
            "sample_time": 0.1,
            "pv_range": [0.0, 10.0],
            "pv0": 50.0,
        }
    )
    assert r.pv0 == pytest.approx(50.0)
    assert any(w.startswith("the process rests at PV 50, out of pv_range") for w in r.warnings)
    inside = check({"model": "fopdt", "gain": 1.0, "time_constant": 10.0, "sample_time": 0.1})
    assert not any("rests at" in w for w in inside.warnings)


def test_a_process_gain_against_the_loops_action_is_warned_of():
    text = "the process gain is -2 (its PV falls as the output rises) but the loop's PID is "
    wrong = check({"model": "fopdt", "gain": -2.0, "time_constant": 10.0, "sample_time": 0.1})
    assert any(w.startswith(text + "reverse-acting") for w in wrong.warnings), wrong.warnings
    right = check(
        {
            "model": "fopdt",
            "gain": -2.0,
            "time_constant": 10.0,
            "sample_time": 0.1,
            "action": "direct",
        }
    )
    assert not any("the process gain is" in w for w in right.warnings)


def test_an_inverse_response_is_warned_of_and_the_lags_are_not_misnamed():
    """(1 − 10s)/(5s + 1)³: its step first dips 31.8 % of its change the other way (the
    minimum of its step response, by scipy on a fine grid), and the check said "ok: nothing
    stands in the way". Its mean residence time less the dead time is 15 + 10 = 25 s (the
    lags' sum less the zero's −10 s), which was called "sum of lags"; its lags sum to 15 s."""
    from scipy.signal import step

    loop = build_plant(
        {
            "seed": 1,
            "loops": {
                "nmp": {
                    "model": "transfer_function",
                    "num": [-10.0, 1.0],
                    "den": [125.0, 75.0, 15.0, 1.0],
                    "sample_time": 0.5,
                    "noise_std": 0.0,
                }
            },
        }
    )["nmp"]
    r = check_loop("nmp", loop)
    _, y = step(([-10.0, 1.0], [125.0, 75.0, 15.0, 1.0]), T=np.linspace(0, 60, 60001))
    dip = float(-np.min(y))
    said = [w for w in r.warnings if w.startswith("inverse response")]
    assert said and f"{100 * dip:.3g} % of its change" in said[0], (r.warnings, dip)
    assert r.lag_sum == pytest.approx(25.0, rel=0.01)


def test_a_lightly_damped_mode_above_the_ultimate_frequency_is_named():
    """100·e^{−s}/((5s + 1)(s² + 0.2s + 100)): "nothing stands in the way", then AMIGO PID at
    a gain margin of 1.05 on its resonance (helper review, den 5s³ + 2s² + 501s + 100). Its
    poles: −0.2 and −0.1 ± j√99.99, ω_n 10 rad/s, ζ 0.01. A well-damped pair (ζ 0.5) or a
    lightly damped one near ω_u (the tuner's relay and models see it) is not named."""
    table = {"model": "transfer_function", "num": [100.0], "delay": 1.0, "sample_time": 0.01}
    r = check({**table, "den": [5.0, 2.0, 500.2, 100.0]})
    (said,) = [w for w in r.warnings if w.startswith("a lightly damped mode")]
    assert "at 10 rad/s (ζ 0.01, period 0.628 s)" in said, said
    # (5s + 1)(s² + 10s + 100): ζ 0.5
    assert not any(
        "lightly damped" in w for w in check({**table, "den": [5.0, 51.0, 510.0, 100.0]}).warnings
    )
    # e^{−0.5s}/(s² + 0.3s + 1): ζ 0.15 at ω_n 1, below 2·ω_u
    near = check(
        {
            "model": "transfer_function",
            "num": [1.0],
            "den": [1.0, 0.3, 1.0],
            "delay": 0.5,
            "sample_time": 0.05,
        }
    )
    assert near.pu is not None and 2 * (2 * math.pi / near.pu) > 1.0
    assert not any("lightly damped" in w for w in near.warnings)


def test_a_lag_sampled_too_finely_to_see_it_settle_is_not_called_integrating_unsaid():
    """10/(10s + 1) sampled at 1e-4 s: its first 64 samples rise as a ramp, and the check
    said "integrating … nothing stands in the way" (helper review). Its transfer function
    has no pole at 0: a warning says so, with its 10 s lag; an integrator is not warned of."""
    r = check({"model": "fopdt", "gain": 1.0, "time_constant": 10.0, "delay": 0.0,
               "sample_time": 1e-4})  # fmt: skip
    (said,) = [w for w in r.warnings if w.startswith("read as integrating")]
    assert "has no integrator and a slowest time constant of 10 s" in said, said
    ipdt = check({"model": "transfer_function", "num": [0.1], "den": [1.0, 0.0], "delay": 2.0,
                  "sample_time": 0.1})  # fmt: skip
    assert ipdt.behaviour == "integrating"
    assert not any(w.startswith("read as integrating") for w in ipdt.warnings)
