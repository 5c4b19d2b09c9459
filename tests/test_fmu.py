"""FMU plant models (issue 17, item 1): real FMUs, built from the classes in tests/fmus by
pythonfmu (FMI 2.0) and pythonfmu3 (FMI 3.0), loaded through the plant file.

Co-simulation: the FMU loop's PV equals the same model written as a transfer function to
1e-9 at every sample, with the dead time inside the FMU or the loop's own ``delay`` (whole or
fractional), op_scale, parameters, the heat exchanger's disturbance input (its closed form).
Model exchange: FMPy's CVode to its tolerance. ``reset`` re-instantiates. The bad-FMU corpus
gets one line naming the loop, the field and the FMU's own message; an FMU that fails
mid-run faults its loop only.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.plant_sim.plant_file import build_plant, load_plant_file
from services.plant_sim.simulation.loop import CommandRejected
from shared.errors import ConfigError
from shared.messages import DisturbanceCommand, ModeCommand, OutputCommand
from tests.fmus import build_all, damaged, with_output_range

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def fmus(tmp_path_factory) -> dict[str, Path]:
    return build_all(tmp_path_factory.mktemp("fmus"))


def fmu_loop(path: Path, **keys) -> dict:
    """A plant-file loop table for the FMU at ``path`` (noise off, a wide PV range)."""
    return {
        "model": "fmu",
        "path": str(path),
        "input": "u",
        "output": "y",
        "sample_time": 0.1,
        "noise_std": 0.0,
        "pv_range": [-1000.0, 1000.0],
        **keys,
    }


def tf_loop(num, den, delay, sample_time, op0=50.0, pv0=50.0, **keys) -> dict:
    return {
        "model": "transfer_function",
        "num": num,
        "den": den,
        "delay": delay,
        "op0": op0,
        "pv0": pv0,
        "sample_time": sample_time,
        "noise_std": 0.0,
        "pv_range": [-1000.0, 1000.0],
        **keys,
    }


def outputs(n: int, op0: float, seed: int = 7) -> list[float]:
    """A seeded output sequence: held for random stretches, steps of up to ±15 %."""
    rng = np.random.default_rng(seed)
    ops, op = [], op0
    while len(ops) < n:
        op = float(np.clip(op0 + rng.uniform(-15, 15), 0, 100))
        ops += [op] * int(rng.integers(1, 40))
    return ops[:n]


def drive(loops: dict, ops: list[float]) -> dict[str, np.ndarray]:
    """Every loop in manual through the same outputs; the PV of each sample."""
    pvs: dict[str, list[float]] = {k: [] for k in loops}
    for op in ops:
        for lid, loop in loops.items():
            loop.apply(OutputCommand(loop=lid, op=op))
            pvs[lid].append(loop.advance().pv)
    return {k: np.asarray(v) for k, v in pvs.items()}


@pytest.mark.parametrize(
    ("name", "fmu", "keys", "delay"),
    [
        ("fmi2, dead time inside the FMU", "Fopdt", {"parameters": {"L": 2.03}}, 2.03),
        ("fmi3, dead time inside the FMU", "Fopdt3", {"parameters": {"L": 2.03}}, 2.03),
        (
            "fmi2, the loop's fractional delay",
            "Fopdt",
            {"parameters": {"L": 0.0}, "delay": 2.03},
            2.03,
        ),
        ("fmi2, both, whole samples", "Fopdt", {"parameters": {"L": 1.0}, "delay": 0.5}, 1.5),
    ],
)
def test_cosimulation_pv_equals_the_transfer_function_to_1e9(fmus, name, fmu, keys, delay):
    """y = 50 + 2·e^{−Ls}/(10s + 1)·(u − 50), u in % (op_scale's default)."""
    loops = build_plant(
        {
            "loops": {
                "f": fmu_loop(fmus[fmu], **keys),
                "tf": tf_loop([2.0], [10.0, 1.0], delay, 0.1),
            }
        }
    )
    assert loops["f"].pv == loops["tf"].pv == 50.0
    pv = drive(loops, outputs(1500, 50.0))
    assert np.ptp(pv["tf"]) > 20  # the comparison spans real moves
    assert np.max(np.abs(pv["f"] - pv["tf"])) < 1e-9, name


def test_heat_exchanger_fmu_with_op_scale_and_loop_delay_is_the_preset(fmus):
    """Valve fraction (op_scale [0, 1]), Kv = 100 °C: 1 °C/% through 1/((10s+1)(60s+1)), and
    the loop's 5 s: the heat_exchanger preset, sample for sample."""
    loops = build_plant(
        {
            "loops": {
                "f": {
                    **fmu_loop(fmus["HeatExchanger"], input="valve", output="T_out"),
                    "op_scale": [0.0, 1.0],
                    "op0": 40.0,
                    "delay": 5.0,
                    "sample_time": 0.25,
                    "pv_range": [0.0, 150.0],
                    "disturbances": {"inlet_temp": "T_in"},
                },
                "tf": {"model": "heat_exchanger", "noise_std": 0.0},
            }
        }
    )
    pv = drive(loops, outputs(1200, 40.0, seed=3))
    assert np.max(np.abs(pv["f"] - pv["tf"])) < 1e-9
    assert loops["f"].settings.description.startswith("FMU HeatExchanger (FMI 2.0 co-simulation)")


def test_the_disturbance_input_moves_the_outlet_by_its_closed_form(fmus):
    """T_in → T_out is 1/(60s + 1): +5 °C on the inlet gives 5·(1 − e^{−t/60}) at the samples,
    without the valve's dead time; the status reports the disturbance's value."""
    loop = build_plant(
        {
            "loops": {
                "f": {
                    **fmu_loop(fmus["HeatExchanger"], input="valve", output="T_out"),
                    "op_scale": [0.0, 1.0],
                    "op0": 40.0,
                    "delay": 5.0,
                    "pv_range": [0.0, 150.0],
                    "disturbances": {"inlet_temp": "T_in"},
                }
            }
        }
    )["f"]
    assert loop.disturbances() == {"inlet_temp": 20.0}
    assert loop.info("n", "lockstep", 1.0).disturbances == ["inlet_temp"]
    loop.apply(DisturbanceCommand(loop="f", name="inlet_temp", value=25.0))
    pv = np.array([loop.advance().pv for _ in range(300)])
    t = 0.1 * np.arange(1, 301)
    assert np.max(np.abs(pv - (60.0 + 5.0 * (1.0 - np.exp(-t / 60.0))))) < 1e-9
    assert loop.status("n", "lockstep", "q").disturbances == {"inlet_temp": 25.0}
    with pytest.raises(CommandRejected, match="unknown disturbance 'nope'"):
        loop.apply(DisturbanceCommand(loop="f", name="nope", value=1.0))


def model_exchange(fmus: dict[str, Path], name: str) -> Path:
    if name not in fmus:
        pytest.skip("no C compiler here to build the FMI 2.0 model-exchange FMU")
    return fmus[name]


@pytest.mark.parametrize("name", ["LagMe", "LagMe2"], ids=["fmi3", "fmi2"])
def test_model_exchange_is_integrated_to_its_tolerance(fmus, name):
    """The model-exchange lag (FMI 3.0 from pythonfmu3, FMI 2.0 compiled from C) with the
    loop's fractional delay against its transfer function: CVode at relative tolerance 1e-8
    keeps within 1e-5 of a 30-unit swing."""
    loops = build_plant(
        {
            "loops": {
                "f": fmu_loop(model_exchange(fmus, name), delay=2.03),
                "tf": tf_loop([2.0], [10.0, 1.0], 2.03, 0.1),
            }
        }
    )
    assert loops["f"].process.interface == "model-exchange"
    pv = drive(loops, outputs(300, 50.0, seed=5))
    assert np.ptp(pv["tf"]) > 10
    assert np.max(np.abs(pv["f"] - pv["tf"])) < 1e-5


def test_sensor_lag_filters_the_fmu_output(fmus):
    """A 1 s transmitter lag on the FMU's output (taken as linear between samples) against the
    same lag folded exactly into the transfer function: within 1e-3 of a 30-unit swing."""
    loops = build_plant(
        {
            "loops": {
                "f": fmu_loop(fmus["Fopdt"], sensor_lag=1.0, parameters={"L": 2.0}),
                "tf": tf_loop([2.0], [10.0, 1.0], 2.0, 0.1, sensor_lag=1.0),
            }
        }
    )
    pv = drive(loops, outputs(600, 50.0))
    assert 0 < np.max(np.abs(pv["f"] - pv["tf"])) < 1e-3


def test_reset_instantiates_the_fmu_anew_at_rest(fmus):
    loop = build_plant({"loops": {"f": fmu_loop(fmus["Fopdt"], parameters={"K": 3.0})}})["f"]
    process = loop.process
    first = [process.step(60.0) for _ in range(100)]
    old = process._fmu
    assert process.reset() == 50.0 and process._fmu is not old
    assert [process.step(60.0) for _ in range(100)] == first
    # K = 3, 10 % up, seen 2 s late (L) through the 10 s lag: at t = 10 s
    assert first[-1] == pytest.approx(50.0 + 30.0 * (1 - math.exp(-(10.0 - 2.0) / 10.0)), abs=1e-9)


def test_settle_runs_the_fmu_at_op0_first_and_time_starts_after_it(fmus):
    """An FMU already at rest is unchanged by settling; its own clock starts at settle."""
    plain = build_plant({"loops": {"f": fmu_loop(fmus["Fopdt"])}})["f"].process
    settled = build_plant({"loops": {"f": fmu_loop(fmus["Fopdt"], settle=3.05)}})["f"].process
    assert settled._t0 == pytest.approx(3.1) and settled.reset() == plain.reset() == 50.0
    assert [settled.step(70.0) for _ in range(50)] == pytest.approx(
        [plain.step(70.0) for _ in range(50)], abs=1e-12
    )


def test_units_and_range_come_from_the_fmu_when_it_declares_them(fmus, tmp_path):
    src = with_output_range(fmus["Fopdt"], tmp_path / "ranged.fmu", "y", "degC", 0.0, 250.0)
    table = fmu_loop(src)
    del table["pv_range"]
    loop = build_plant({"loops": {"f": table}})["f"]
    assert loop.settings.pv_range == (0.0, 250.0) and loop.settings.pv_units == "degC"
    table = fmu_loop(fmus["Fopdt"])
    del table["pv_range"]
    with pytest.raises(ConfigError, match=r"loops\.f\.pv_range: required: the FMU's output 'y'"):
        build_plant({"loops": {"f": table}})


def test_the_path_is_relative_to_the_plant_file(fmus, tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "f.fmu").write_bytes(fmus["Fopdt"].read_bytes())
    plant = tmp_path / "plant.toml"
    plant.write_text(
        '[loops.f]\nmodel = "fmu"\npath = "models/f.fmu"\ninput = "u"\noutput = "y"\n'
        "sample_time = 0.5\npv_range = [0.0, 200.0]\n"
    )
    assert load_plant_file(plant)["f"].pv == 50.0


BAD = [  # (the loop's table, or a corpus name for path; the field; what the line says)
    ("not a zip", "path", "is not an FMU (not a zip archive)"),
    ("no model description", "path", "is not an FMU (no modelDescription.xml)"),
    ("xml not valid", "path", "its modelDescription.xml is not valid"),
    ("fmi 1.0", "path", "is an FMI 1.0 FMU; plant_sim runs FMI 2.0 and 3.0"),
    ("no binary here", "path", "has no binary for this platform (linux64)"),
    ("binary broken", "path", "the FMU failed to load its binary"),
    ("a folder", "path", "is not a file"),
    ("missing", "path", "no such file"),
    ({"input": "valve"}, "input", "no input 'valve' in the FMU (its real inputs: u)"),
    ({"input": "y"}, "input", "'y' is an output of the FMU, not an input"),
    ({"output": "T"}, "output", "no output 'T' in the FMU (its real outputs: y)"),
    ({"parameters": {"UA": 1.0}}, "parameters.UA", "no parameter 'UA' in the FMU"),
    ({"parameters": {"K": "two"}}, "parameters.K", "expected a number, got 'two'"),
    (
        {"parameters": {"u": 1.0}},
        "parameters.u",
        "'u' is a continuous input of the FMU, not a parameter",
    ),
    ({"parameters": 3}, "parameters", "expected a table"),
    ({"disturbances": {"q": "q_in"}}, "disturbances.q", "no input 'q_in' in the FMU"),
    ({"disturbances": {"q": "u"}}, "disturbances.q", "'u' is the loop's input already"),
    ({"op_scale": [1.0, 1.0]}, "op_scale", "the two ends must differ"),
    ({"op_scale": [0.0]}, "op_scale", "expected [at 0 %, at 100 %]"),
    ({"interface": "model-exchange"}, "interface", "offers co-simulation, not model-exchange"),
    ({"interface": "magic"}, "interface", "must be one of co-simulation, model-exchange"),
    ({"tolerance": 0.5}, "tolerance", "must be ≤ 0.01"),
    ({"delay": -1.0}, "delay", "must be ≥ 0.0"),
    ({"speed": 2}, "speed", "not a parameter of model 'fmu'"),
    ({"path": None}, "path", "required by model 'fmu'"),
]


@pytest.mark.parametrize(
    ("bad", "field", "needle"), BAD, ids=[f"{i}-{b[1]}" for i, b in enumerate(BAD)]
)
def test_bad_fmus_get_one_line_naming_loop_and_field(fmus, tmp_path, bad, field, needle):
    corpus = damaged(fmus, tmp_path / "bad")
    table = fmu_loop(fmus["Fopdt"])
    if isinstance(bad, str):
        table["path"] = str(corpus.get(bad, tmp_path / "missing.fmu"))
    else:
        table.update(bad)
        if table["path"] is None:
            del table["path"]
    with pytest.raises(ConfigError) as err:
        build_plant({"loops": {"f1": table}}, source="p.toml")
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"plant file p.toml: loops.f1.{field}: "), text
    assert needle in text, text


@pytest.mark.parametrize(
    ("params", "needle"),
    [
        ({"fail_init": 1}, "the FMU failed to initialise"),
        ({"fail_after": 1}, "RuntimeError('sensor fault after 0 steps')"),
    ],
)
def test_an_fmu_that_cannot_start_or_step_is_refused_in_its_own_words(fmus, params, needle):
    """Instantiated, initialised and stepped once at load: its failure is a load error."""
    with pytest.raises(ConfigError) as err:
        build_plant({"loops": {"f1": fmu_loop(fmus["Faulty"], parameters=params)}}, source="p")
    text = str(err.value)
    assert "\n" not in text and text.startswith("plant file p: loops.f1.path: "), text
    assert needle in text, text
    if "fail_init" in params:
        assert "the valve map file vmap.csv is missing" in text


def test_a_fractional_delay_needs_an_fmu_that_can_vary_its_step(fmus):
    fixed = fmu_loop(fmus["FopdtFixedStep"], parameters={"L": 0.0})
    build_plant({"loops": {"f": {**fixed, "delay": 0.5}}})  # whole samples: fine
    with pytest.raises(ConfigError, match=r"loops\.f\.delay: 0\.55 s is not a whole number"):
        build_plant({"loops": {"f": {**fixed, "delay": 0.55}}})


@pytest.mark.parametrize(
    ("params", "needle"),
    [
        ({"fail_after": 13}, "RuntimeError('sensor fault after 12 steps')"),
        ({"nan_after": 5}, "returned PV nan"),
    ],
)
def test_an_fmu_failing_mid_run_faults_its_loop_only(fmus, params, needle):
    plant = {
        "loops": {
            "bad": fmu_loop(fmus["Faulty"], parameters=params),
            "ok": tf_loop([2.0], [10.0, 1.0], 0.3, 0.1),
        }
    }
    loops = build_plant(plant)
    alone = build_plant({"loops": {"ok": plant["loops"]["ok"]}})["ok"]
    bad, ok = loops["bad"], loops["ok"]
    bad.apply(OutputCommand(loop="bad", op=70.0))
    samples = [bad.advance() for _ in range(40)]
    for _ in range(40):
        assert ok.advance() == alone.advance()
    assert bad.fault is not None and needle in bad.fault and "\n" not in bad.fault
    assert bad.mode == "manual" and bad.op == 70.0
    held = [s for s in samples if s.t > bad.fault_t]
    assert held and len({s.pv for s in held}) == 1
    with pytest.raises(CommandRejected) as err:
        bad.apply(ModeCommand(loop="bad", mode="auto"))
    assert err.value.category == "fault"


def test_a_model_exchange_fmu_failing_in_the_integrator_faults_its_loop(fmus, capfd):
    """Its derivatives fail from t = 1 s on: the loop faults with the FMU's own words, and
    nothing (SUNDIALS' own report included) is printed."""
    path = model_exchange(fmus, "LagMe2")
    loop = build_plant({"loops": {"m": fmu_loop(path, parameters={"fail_at": 1.0})}})["m"]
    for _ in range(30):
        loop.advance()
    assert loop.fault is not None and "the flow model diverged at t = 1.0" in loop.fault
    assert "the integrator failed" in loop.fault and loop.mode == "manual"
    assert capfd.readouterr().err == ""


def test_autotune_plant_refuses_a_bad_fmu_with_exit_2_and_one_line(fmus, tmp_path):
    plant = tmp_path / "p.toml"
    plant.write_text(
        f'[loops.hx3]\nmodel = "fmu"\npath = "{fmus["Faulty"]}"\ninput = "u"\noutput = "y"\n'
        "sample_time = 0.5\npv_range = [0.0, 100.0]\nparameters = { fail_init = 1 }\n"
    )
    run = subprocess.run(
        [sys.executable, "-m", "services.cli", "plant", "--plant", str(plant)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "loops.hx3.path: " in run.stderr and "vmap.csv is missing" in run.stderr
