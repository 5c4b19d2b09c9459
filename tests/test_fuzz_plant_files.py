"""Plant files that are wrong in every way we could think of, and more chosen at random
(seeded): each is refused with one line naming the loop and field (the file, for what is not
TOML), or gives loops that run. User model classes that fail at load or mid-run: a loop whose
model fails is put to manual at its last output, marked faulted, and the others go on. One
subprocess per category proves ``autotune plant`` exits 2 with one line and no traceback."""

from __future__ import annotations

import dataclasses
import inspect
import logging
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from services.plant_sim.plant_file import build_plant, default_plant_path, load_plant_file
from services.plant_sim.simulation.loop import CommandRejected, SimLoop
from services.plant_sim.simulation.presets import MODELS
from shared.errors import ConfigError
from shared.messages import (
    DisturbanceCommand,
    GainsCommand,
    ModeCommand,
    OutputCommand,
    PidGains,
    SetpointCommand,
)

DATA = Path(__file__).parent / "data" / "fuzz"
USER = "fuzz_user_models"
PRESET_TEXT = default_plant_path().read_text()
# A loop with every key of a plant file set (the README's list).
FULL = {
    "model": "transfer_function",
    "num": [1.0],
    "den": [600.0, 70.0, 1.0],
    "delay": 5.0,
    "sample_time": 0.25,
    "noise_std": 0.01,
    "seed": 4,
    "mode": "auto",
    "setpoint": 55.0,
    "action": "reverse",
    "op_limits": [5.0, 95.0],
    "pv_range": [0.0, 120.0],
    "pv_units": "degC",
    "sp_track": False,
    "description": "every key",
    "pid": {"kc": 2.0, "ti": 60.0, "td": 1.0, "n": 10.0, "beta": 1.0},
}
NUMBERS = [-1.0, 0.0, 1e-308, 5e-324, 1e12, 1e308, -1e308, math.nan, math.inf, -math.inf]
WRONG_TYPES = ["five", True, [1.0, 2.0], {"x": 1.0}]


@pytest.fixture
def user_models(monkeypatch):
    """The misbehaving user classes of tests/data/fuzz, importable as a user's would be."""
    monkeypatch.syspath_prepend(str(DATA))
    yield
    for name in (USER, "fuzz_broken_module"):
        sys.modules.pop(name, None)


def toml_value(v: object) -> str:
    """``v`` as TOML (inf and nan included, which JSON cannot say)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return (
            "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        )
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    return str(v)


def toml_text(plant: dict) -> str:
    loops = plant.get("loops", {})
    tables = loops if isinstance(loops, dict) else {}
    plain = {k: v for k, v in plant.items() if k != "loops" or not isinstance(v, dict)}
    plain_loops = {k: v for k, v in tables.items() if not isinstance(v, dict)}
    lines = [f"{k} = {toml_value(v)}" for k, v in plain.items()]
    if plain_loops or (not tables and isinstance(loops, dict) and "loops" in plant):
        lines.append("[loops]")
        lines += [f"{k} = {toml_value(v)}" for k, v in plain_loops.items()]
    for loop, table in tables.items():
        if isinstance(table, dict):
            lines.append(f'[loops."{loop}"]')
            lines += [f"{k} = {toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def refused(err: ConfigError, *needles: str) -> str:
    """The refusal is one line, says it is the plant file, and holds every needle."""
    text = str(err)
    assert "\n" not in text and "\r" not in text, text
    assert text.startswith("plant file "), text
    for n in needles:
        assert n in text, (n, text)
    return text


def exercise(loops: dict[str, SimLoop], steps: int = 40) -> None:
    """Drive every loop through an output move (manual) or a setpoint move (auto) and back:
    nothing raises, every sample, status and info is a valid message (their models would
    refuse NaN or inf), and no built-in model faults."""
    for lid, loop in loops.items():
        lo, hi = loop.settings.op_limits
        plo, phi = loop.settings.pv_range
        for k in range(2):
            if loop.mode == "manual":
                loop.apply(OutputCommand(loop=lid, op=lo + (0.8 if k == 0 else 0.2) * (hi - lo)))
            else:
                loop.apply(
                    SetpointCommand(loop=lid, sp=plo + (0.7 if k == 0 else 0.3) * (phi - plo))
                )
            for _ in range(steps):
                loop.advance()
        loop.status("fuzz", "lockstep", "query")
        loop.info("fuzz", "lockstep", 1.0)
        if ":" not in loop.settings.model_name:
            assert loop.fault is None, (lid, loop.settings.model_params, loop.fault)


def judge(plant: dict, loop: str | None = None) -> str:
    """Build ``plant``: "refused" (one line, naming ``loop``) or "runs" (and it does)."""
    try:
        loops = build_plant(plant, source="fuzz.toml")
    except ConfigError as err:
        refused(err, "fuzz.toml", *([f"loops.{loop}"] if loop else []))
        return "refused"
    exercise(loops)
    return "runs"


# --- the cases found by hand (issue 11), and their kin --------------------------------------


def tf(num, den, **kw) -> dict:
    return {
        "loops": {
            "tf": {"model": "transfer_function", "num": num, "den": den, "sample_time": 0.1, **kw}
        }
    }


def user(cls: str, **kw) -> dict:
    return {"loops": {"u1": {"model": f"{USER}:{cls}", "sample_time": 0.5, **kw}}}


HAND = [
    # (id, plant, needles)
    (
        "init-raises",
        user("RaisesInInit"),
        ["loops.u1.model", "RuntimeError: the valve map file vmap.csv is missing"],
    ),
    (
        "init-multiline-message",
        user("MultilineError"),
        ["loops.u1.model", "first line second line third line"],
    ),
    ("init-exits", user("ExitsInInit"), ["loops.u1.model", "SystemExit: 3"]),
    (
        "reset-raises",
        user("ResetRaises"),
        ["loops.u1.model", "reset() raised ZeroDivisionError: no rest state at op0"],
    ),
    ("reset-exits", user("ResetExits"), ["loops.u1.model", "reset() raised SystemExit: 3"]),
    ("reset-nan", user("ResetNaN"), ["loops.u1.model", "reset() returned PV nan"]),
    (
        "reset-string",
        user("ResetString"),
        ["loops.u1.model", "reset() returned 'fifty', not a number"],
    ),
    ("reset-none", user("ResetNone"), ["loops.u1.model", "reset() returned None"]),
    ("property-raises", user("PropertyRaises"), ["loops.u1.model", ".pv_units raised KeyError"]),
    ("no-step", user("NoStep"), ["loops.u1.model", "missing: step"]),
    ("step-not-callable", user("StepNotCallable"), ["loops.u1.model", "step must be a method"]),
    (
        "names-not-names",
        user("NamesNotNames"),
        ["loops.u1.model", "disturbance_names() must return a tuple of names", "got 5"],
    ),
    (
        "names-raise",
        user("NamesRaise"),
        ["loops.u1.model", "disturbance_names() raised RuntimeError: no names today"],
    ),
    ("op0-string", user("Knobs", op0="fifty"), ["loops.u1.op0", "'fifty'"]),
    ("op0-bool", user("Knobs", set_op0=True), ["loops.u1.op0"]),
    ("op0-outside-limits", user("Knobs", op0=150.0), ["loops.u1.op_limits", "op0 = 150.0"]),
    ("pv-range-string", user("Knobs", set_pv_range="wide"), ["loops.u1.pv_range", "'wide'"]),
    ("pv-range-inf", user("Knobs", set_pv_range=[0.0, math.inf]), ["loops.u1.pv_range", "finite"]),
    (
        "pv-range-reversed",
        user("Knobs", set_pv_range=[5.0, 1.0]),
        ["loops.u1.pv_range", "low must be below high"],
    ),
    ("pv-units-number", user("Knobs", set_pv_units=5), ["loops.u1.pv_units", "must be a string"]),
    ("unknown-param", user("Good", nope=1), ["loops.u1.nope", "not a parameter"]),
    ("no-such-class", user("Missing"), ["loops.u1.model", "has no class 'Missing'"]),
    (
        "module-fails-import",
        {"loops": {"u1": {"model": "fuzz_broken_module:X", "sample_time": 1.0}}},
        ["loops.u1.model", "ImportError: this plant needs the package 'coolprop'"],
    ),
    (
        "no-such-module",
        {"loops": {"u1": {"model": "no_such_pkg.sub:X", "sample_time": 1.0}}},
        ["loops.u1.model", "No module named 'no_such_pkg'"],
    ),
    (
        "empty-module-name",
        {"loops": {"u1": {"model": ":X", "sample_time": 1.0}}},
        ["loops.u1.model", "cannot import"],
    ),
    (
        "builtins-int",
        {"loops": {"u1": {"model": "builtins:int", "sample_time": 1.0}}},
        ["loops.u1.model", "builtins:int"],
    ),
    (
        "builtins-dict",
        {"loops": {"u1": {"model": "builtins:dict", "sample_time": 1.0}}},
        ["loops.u1.model", "does not implement the ProcessModel protocol"],
    ),
    (
        "builtins-object",
        {"loops": {"u1": {"model": "builtins:object", "sample_time": 1.0}}},
        ["loops.u1.model"],
    ),
    (
        "os-system",
        {"loops": {"u1": {"model": "os:system", "sample_time": 1.0}}},
        ["loops.u1.model", "no class 'system'"],
    ),
    (
        "delay-1e12",
        {"loops": {"hx1": {"model": "heat_exchanger", "delay": 1e12}}},
        ["loops.hx1.delay", "at most 1000000"],
    ),
    (
        "delay-1e12-physical",
        {"loops": {"hx2": {"model": "heat_exchanger_physical", "delay": 1e12}}},
        ["loops.hx2.delay", "at most 1000000"],
    ),
    (
        "tiny-sample-time-long-delay",
        {"loops": {"hx1": {"model": "heat_exchanger", "sample_time": 1e-6}}},
        ["loops.hx1.delay"],
    ),
    (
        "sample-time-1e-300",
        {"loops": {"hx1": {"model": "heat_exchanger", "sample_time": 1e-300}}},
        ["loops.hx1.sample_time"],
    ),
    ("num-1e308-den-1e-308", tf([1e308], [1e-308]), ["loops.tf.", "overflow"]),
    ("num-1e308-den-1e-308-lag", tf([1e308], [1e-308, 1.0]), ["loops.tf.", "overflow"]),
    ("gain-1e307", tf([1e307], [1.0, 1.0]), ["loops.tf.num", "overflows"]),
    # a model with named parameters is told of by their names: its file has no num or den
    (
        "fopdt-gain-1e308",
        {
            "loops": {
                "f1": {"model": "fopdt", "gain": 1e308, "time_constant": 5.0, "sample_time": 0.1}
            }
        },
        ["loops.f1.gain:", "overflows"],
    ),
    (
        "fopdt-time-constant-1e-300",
        {
            "loops": {
                "f1": {"model": "fopdt", "gain": 1.0, "time_constant": 1e-300, "sample_time": 0.1}
            }
        },
        ["loops.f1.time_constant:", "floating point"],
    ),
    (
        "heat-exchanger-gain-1e308",
        {"loops": {"hx1": {"model": "heat_exchanger", "gain": 1e308}}},
        ["loops.hx1.gain:", "overflows"],
    ),
    ("unstable-pole", tf([1.0], [1.0, -1.0]), ["loops.tf.den", "unstable", "s = 1"]),
    ("unstable-pair", tf([1.0], [1.0, -0.2, 4.0]), ["loops.tf.den", "unstable"]),
    ("improper", tf([1.0, 2.0, 3.0], [1.0, 1.0]), ["loops.tf.num", "proper"]),
    ("zero-den", tf([1.0], [0.0, 0.0]), ["loops.tf.den"]),
    ("empty-num", tf([], [1.0, 1.0]), ["loops.tf.num"]),
    ("num-string", tf("1", [1.0, 1.0]), ["loops.tf.num"]),
    ("den-nan", tf([1.0], [1.0, math.nan]), ["loops.tf.den[1]"]),
    (
        "huge-sample-time",
        {"loops": {"hx1": {"model": "heat_exchanger", "sample_time": 1e300}}},
        ["loops.hx1.sample_time", "86400"],
    ),
    (
        "physical-stiff",
        {"loops": {"hx2": {"model": "heat_exchanger_physical", "ua": 1e300}}},
        ["loops.hx2."],
    ),
    (
        "tank-inflow-subnormal",
        {"loops": {"t1": {"model": "tank_level", "inflow_max": 5e-324}}},
        ["loops.t1."],
    ),
    (
        "flow-valve-subnormal",
        {"loops": {"f1": {"model": "flow", "valve_time_constant": 5e-324}}},
        ["loops.f1.sample_time", "fastest time constant"],
    ),
    (
        "seed-negative",
        {"seed": -1, "loops": {"hx1": {"model": "heat_exchanger"}}},
        ["seed", "greater than or equal to 0"],
    ),
    (
        "loop-seed-negative",
        {"loops": {"hx1": {"model": "heat_exchanger", "seed": -5}}},
        ["loops.hx1.seed"],
    ),
    ("loops-not-a-table", {"loops": 5}, ["loops:"]),
    ("loop-not-a-table", {"loops": {"hx1": 5}}, ["loops.hx1"]),
    ("no-loops", {"seed": 1}, ["loops: Field required"]),
    ("zero-loops", {"loops": {}}, ["loops"]),
    (
        "unknown-top-key",
        {"loops": {"hx1": {"model": "heat_exchanger"}}, "loop": {}},
        ["loop: Extra inputs"],
    ),
    (
        "model-missing",
        {"loops": {"hx1": {"modle": "heat_exchanger"}}},
        ["loops.hx1.model: Field required"],
    ),
    ("model-number", {"loops": {"hx1": {"model": 5}}}, ["loops.hx1.model"]),
    ("model-empty", {"loops": {"hx1": {"model": ""}}}, ["loops.hx1.model"]),
    (
        "mode-cascade",
        {"loops": {"hx1": {"model": "heat_exchanger", "mode": "cascade"}}},
        ["loops.hx1.mode"],
    ),
    (
        "action-sideways",
        {"loops": {"hx1": {"model": "heat_exchanger", "action": "sideways"}}},
        ["loops.hx1.action"],
    ),
    (
        "op-limits-three",
        {"loops": {"hx1": {"model": "heat_exchanger", "op_limits": [0, 50, 100]}}},
        ["loops.hx1.op_limits"],
    ),
    (
        "op-limits-outside",
        {"loops": {"hx1": {"model": "heat_exchanger", "op_limits": [-10, 150]}}},
        ["loops.hx1.op_limits"],
    ),
    (
        "pv-range-nan",
        {"loops": {"hx1": {"model": "heat_exchanger", "pv_range": [0, math.nan]}}},
        ["loops.hx1.pv_range"],
    ),
    (
        "setpoint-inf",
        {"loops": {"hx1": {"model": "heat_exchanger", "setpoint": math.inf}}},
        ["loops.hx1.setpoint"],
    ),
    (
        "noise-negative",
        {"loops": {"hx1": {"model": "heat_exchanger", "noise_std": -1.0}}},
        ["loops.hx1.noise_std"],
    ),
    (
        "pid-ti-zero",
        {"loops": {"hx1": {"model": "heat_exchanger", "pid": {"kc": 1.0, "ti": 0.0}}}},
        ["loops.hx1.pid.ti"],
    ),
    (
        "pid-unknown-key",
        {"loops": {"hx1": {"model": "heat_exchanger", "pid": {"kc": 1.0, "kd": 3.0}}}},
        ["loops.hx1.pid.kd"],
    ),
    (
        "pid-not-a-table",
        {"loops": {"hx1": {"model": "heat_exchanger", "pid": 2.0}}},
        ["loops.hx1.pid"],
    ),
    (
        "characteristic-number",
        {"loops": {"f1": {"model": "flow", "characteristic": 3}}},
        ["loops.f1.characteristic"],
    ),
    (
        "rangeability-one",
        {"loops": {"f1": {"model": "flow", "rangeability": 1.0}}},
        ["loops.f1.rangeability"],
    ),
    (
        "level0-above-height",
        {"loops": {"t1": {"model": "tank_level", "level0": 5.0}}},
        ["loops.t1.level0"],
    ),
    ("bad-loop-id", {"loops": {"a/b": {"model": "heat_exchanger"}}}, ["loops.a/b"]),
    (
        "description-number",
        {"loops": {"hx1": {"model": "heat_exchanger", "description": 5}}},
        ["loops.hx1.description"],
    ),
]


@pytest.mark.parametrize(("plant", "needles"), [c[1:] for c in HAND], ids=[c[0] for c in HAND])
def test_known_bad_plants_are_refused_in_one_line(user_models, tmp_path, plant, needles):
    path = tmp_path / "p.toml"
    path.write_text(toml_text(plant))
    with pytest.raises(ConfigError) as err:
        load_plant_file(path)
    refused(err.value, str(path), *needles)


FILES = [
    # (id, bytes, needles): what is not a TOML table of loops at all
    ("empty", b"", ["loops: Field required"]),
    ("binary", bytes(range(256)) * 4, ["not UTF-8", "offset"]),
    ("png", b"\x89PNG\r\n\x1a\n" + bytes(64), ["not UTF-8"]),
    ("utf16", PRESET_TEXT.encode("utf-16"), ["not UTF-8"]),
    (
        "latin1",
        '[loops.hx1]\nmodel = "heat_exchanger"\ndescription = "échangeur"\n'.encode("latin-1"),
        ["not UTF-8"],
    ),
    ("nul-bytes", b'[loops.hx1]\nmodel = "heat\x00exchanger"\n', ["not valid TOML"]),
    ("unclosed-table", b"[loops.hx1\n", ["not valid TOML"]),
    (
        "duplicate-table",
        b'[loops.hx1]\nmodel = "heat_exchanger"\n[loops.hx1]\nmodel = "flow"\n',
        ["not valid TOML"],
    ),
    ("json", b'{"loops": {"hx1": {"model": "heat_exchanger"}}}', ["not valid TOML"]),
    ("yaml", b"loops:\n  hx1:\n    model: heat_exchanger\n", ["not valid TOML"]),
    ("deep-nesting", b"x = " + b"[" * 5000 + b"]" * 5000 + b"\n", ["not valid TOML"]),
    (
        "date-value",
        b'[loops.hx1]\nmodel = "heat_exchanger"\ndelay = 1979-05-27\n',
        ["unsupported value"],
    ),
]


@pytest.mark.parametrize(("content", "needles"), [c[1:] for c in FILES], ids=[c[0] for c in FILES])
def test_files_that_are_not_plant_tomls_are_refused_in_one_line(tmp_path, content, needles):
    path = tmp_path / "p.toml"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as err:
        load_plant_file(path)
    refused(err.value, str(path), *needles)


def test_paths_that_are_not_files_and_harmless_oddities(tmp_path):
    with pytest.raises(ConfigError) as err:
        load_plant_file(tmp_path)  # a directory
    refused(err.value, "cannot read it")
    with pytest.raises(ConfigError) as err:
        load_plant_file(tmp_path / "missing.toml")
    refused(err.value, "cannot read it")
    # harmless: a UTF-8 byte-order mark, CRLF line ends, the noise override on a file whose
    # loops are not tables (refused for that, not crashed on)
    big = tmp_path / "big.toml"
    big.write_text('[loops.hx1]\nmodel = "heat_exchanger"\nseed = 99999999999999999999999\n')
    assert load_plant_file(big)["hx1"].advance().seq == 1
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + PRESET_TEXT.replace("\n", "\r\n").encode())
    assert set(load_plant_file(bom)) == {"hx1", "hx2", "lvl1", "lvl2", "flow1"}
    odd = tmp_path / "odd.toml"
    odd.write_text("loops = 5\n")
    with pytest.raises(ConfigError) as err:
        load_plant_file(odd, noise_std=0.1)
    refused(err.value, "loops")


def test_extreme_but_finite_plants_run_with_the_pv_at_its_transmitter_limit():
    """A process resting beyond its transmitter's range is a plant, not an error (the step
    test and the tuner say so when they meet it); it runs, clipped, and never faults."""
    for plant, at_top in (
        ({"loops": {"hx2": {"model": "heat_exchanger_physical", "steam_max": 1e300}}}, True),
        ({"loops": {"hx1": {"model": "heat_exchanger", "pv_range": [0.0, 55.0]}}}, True),
        ({"loops": {"hx1": {"model": "heat_exchanger", "gain": 1e12, "mode": "auto"}}}, False),
    ):
        assert judge(plant) == "runs"
        loop = next(iter(build_plant(plant).values()))
        assert (loop.advance().pv == loop.settings.pv_range[1]) == at_top
        if at_top and loop.settings.setpoint is None:  # not at the unreadable rest beyond it
            assert loop.sp == loop.settings.pv_range[1]


# --- systematic mutations of the presets and of a loop with every key ----------------------


def _params(model: str) -> dict[str, object]:
    sig = inspect.signature(MODELS[model])
    return {n: p.default for n, p in sig.parameters.items() if n != "sample_time"}


def preset_mutations() -> list[tuple[str, dict, str]]:
    """(id, plant, loop): each key of each preset loop and of FULL deleted, renamed, set to a
    wrong type or to each of NUMBERS (model parameters included)."""
    base = tomllib.loads(PRESET_TEXT)
    tables = {lid: dict(t) for lid, t in base["loops"].items()}
    tables["full"] = FULL
    cases = []
    for lid, table in tables.items():
        model = table["model"]
        keys = dict(table)
        for name, default in _params(model).items():
            keys.setdefault(name, default)
        for key, value in keys.items():

            def with_(v, key=key, lid=lid, table=table):
                return {"loops": {lid: {**table, key: v}}}

            if key in table:
                rest = {k: v for k, v in table.items() if k != key}
                cases.append((f"{lid}-del-{key}", {"loops": {lid: rest}}, lid))
                renamed = {**rest, key + "_x": table[key]}
                cases.append((f"{lid}-rename-{key}", {"loops": {lid: renamed}}, lid))
            for w in WRONG_TYPES:
                cases.append((f"{lid}-{key}={w!r}", with_(w), lid))
            if (isinstance(value, float | int) and not isinstance(value, bool)) or key in (
                "sample_time",
                "noise_std",
                "setpoint",
                "seed",
            ):
                for x in NUMBERS:
                    cases.append((f"{lid}-{key}={x!r}", with_(x), lid))
            if isinstance(value, list):
                for i in range(len(value)):
                    for x in NUMBERS:
                        cases.append(
                            (
                                f"{lid}-{key}[{i}]={x!r}",
                                with_([*value[:i], x, *value[i + 1 :]]),
                                lid,
                            )
                        )
            if isinstance(value, dict):
                for sub in value:
                    for x in NUMBERS:
                        cases.append((f"{lid}-{key}.{sub}={x!r}", with_({**value, sub: x}), lid))
    return cases


def test_every_preset_key_deleted_renamed_mistyped_or_extreme():
    cases = preset_mutations()
    outcomes = {"refused": 0, "runs": 0}
    for _id, plant, loop in cases:
        outcomes[judge(plant, loop)] += 1
    print(f"preset mutations: {len(cases)} cases, {outcomes}")
    assert len(cases) > 600 and outcomes["refused"] > 400 and outcomes["runs"] > 50


# --- seeded random damage to the preset file -----------------------------------------------


def damaged_texts(n: int, seed: int) -> list[bytes]:
    rng = np.random.default_rng(seed)
    lines = PRESET_TEXT.splitlines()
    tokens = [
        "1e308",
        "-1e308",
        "nan",
        "inf",
        "-1",
        "0",
        '"x"',
        "[]",
        "{}",
        "true",
        "1e-320",
        "5e12",
    ]
    out = []
    for _ in range(n):
        ls = list(lines)
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.integers(len(ls)))
            kind = int(rng.integers(6))
            if kind == 0:
                del ls[i]
            elif kind == 1:
                ls.insert(i, ls[i])
            elif kind == 2 and "=" in ls[i]:
                ls[i] = ls[i].split("=")[0] + "= " + str(rng.choice(tokens))
            elif kind == 3 and ls[i]:
                j = int(rng.integers(len(ls[i])))
                ls[i] = ls[i][:j] + ls[i][j + 1 :]
            elif kind == 4:
                key = rng.choice(["tau1", "gain", "delay", "sample_time", "op0", "area"])
                ls.insert(i, f"{key} = {rng.choice(tokens)}")
            else:
                ls[i] = ls[i][::-1]
        data = "\n".join(ls).encode()
        if rng.random() < 0.15:
            data = data[: int(rng.integers(len(data)))]
        if rng.random() < 0.1:
            k = int(rng.integers(len(data)))
            data = data[:k] + rng.bytes(3) + data[k:]
        out.append(data)
    return out


def test_seeded_random_damage_to_the_preset_file(tmp_path):
    outcomes = {"refused": 0, "runs": 0}
    path = tmp_path / "damaged.toml"
    for data in damaged_texts(150, seed=20261201):
        path.write_bytes(data)
        try:
            loops = load_plant_file(path)
        except ConfigError as err:
            refused(err, str(path))
            outcomes["refused"] += 1
            continue
        exercise(loops, steps=10)
        outcomes["runs"] += 1
    print(f"random damage: 150 cases, {outcomes}")
    assert outcomes["refused"] > 50 and outcomes["runs"] > 5


# --- user models that fail mid-run --------------------------------------------------------


HEALTHY = {
    "model": "transfer_function",
    "num": [2.0],
    "den": [5.0, 1.0],
    "sample_time": 0.5,
    "noise_std": 0.1,
}


@pytest.mark.parametrize(
    ("cls", "needle"),
    [
        ("StepRaisesAfter", "RuntimeError: sensor fault after 12 steps"),
        ("StepNaNAfter", "returned PV nan"),
        ("StepExitsAfter", "step() raised SystemExit: 4"),
        ("StepInfAfter", "returned PV inf"),
        ("StepOverflows", "OverflowError"),
        ("StepReturnsList", "not a number"),
        ("StepHugeInt", "not a finite number"),
    ],
)
def test_a_model_failing_mid_run_faults_its_loop_only(user_models, caplog, cls, needle):
    plant = {
        "seed": 2,
        "loops": {
            "bad": {"model": f"{USER}:{cls}", "sample_time": 0.5, "fail_after": 12},
            "ok": HEALTHY,
        },
    }
    if cls == "StepOverflows":
        del plant["loops"]["bad"]["fail_after"]
    loops = build_plant(plant)
    alone = build_plant({"seed": 2, "loops": {"ok": HEALTHY}})["ok"]
    bad, ok = loops["bad"], loops["ok"]
    bad.apply(OutputCommand(loop="bad", op=70.0))
    with caplog.at_level(logging.ERROR, logger="plant_sim"):
        samples = [bad.advance() for _ in range(40)]
        for _ in range(40):
            assert ok.advance() == alone.advance()  # the other loop is untouched, sample for sample
    assert bad.fault is not None and needle in bad.fault and "at t = " in bad.fault
    assert bad.mode == "manual" and bad.op == 70.0  # at the output it last held
    held = [s for s in samples if s.t > bad.fault_t]
    assert held and len({s.pv for s in held}) == 1  # the PV holds
    assert [s.seq for s in samples] == list(range(1, 41))  # time goes on: no driver waits
    faults = [r for r in caplog.records if "bad" in r.getMessage()]
    assert len(faults) == 1 and needle in faults[0].getMessage()  # logged once
    status = bad.status("plant", "lockstep", "query")
    assert status.fault == bad.fault and status.mode == "manual"
    for cmd in (
        ModeCommand(loop="bad", mode="auto"),
        OutputCommand(loop="bad", op=20.0),
        DisturbanceCommand(loop="bad", name="bias", value=1.0),
    ):
        with pytest.raises(CommandRejected) as err:
            bad.apply(cmd)
        assert err.value.category == "fault" and needle in err.value.reason
    bad.apply(SetpointCommand(loop="bad", sp=40.0))  # harmless ones are taken
    bad.apply(GainsCommand(loop="bad", gains=PidGains(kc=1.0, ti=10.0)))
    bad.apply(ModeCommand(loop="bad", mode="manual"))
    bad.restore(dataclasses.replace(bad.snapshot(), mode="auto", op=30.0))  # a lease expiring
    assert bad.mode == "manual" and bad.op == 70.0
    assert bad.info("plant", "lockstep", 1.0).disturbances == ["bias"]


def test_gains_that_are_no_control_at_all_are_refused_in_the_file_and_on_the_bus():
    """Kc 0 (in ideal form the factor of every term: a loop in auto holds its output whatever
    the PV does) was taken from a plant file's [pid] table and from a GainsCommand, which
    `autotune set --kc 0` refuses; so was 1e-320, whose proportional band, 100/(Kc·150/100)
    % of span, is no number. Both paths now refuse them, naming kc, and change nothing."""
    for kc in (0.0, 1e-320):
        plant = {"loops": {"hx1": {"model": "heat_exchanger", "pid": {"kc": kc, "ti": 60.0}}}}
        with pytest.raises(ConfigError) as err:
            build_plant(plant)
        refused(err.value, "loops.hx1.pid: kc ", "no control at all")
    loop = build_plant({"loops": {"hx1": {"model": "heat_exchanger", "mode": "auto"}}})["hx1"]
    before = loop.snapshot()
    for kc, said in ((0.0, "kc 0: "), (-0.0, "kc 0: "), (1e-320, ""), (5e-324, "")):
        with pytest.raises(CommandRejected, match="no control at all") as err:
            loop.apply(GainsCommand(loop="hx1", gains=PidGains(kc=kc, ti=60.0)))
        assert err.value.category == "range"
        assert err.value.reason.startswith("gains refused: " + (said or "kc "))
    after = loop.snapshot()
    assert (after.mode, after.op, after.gains) == (before.mode, before.op, before.gains)
    assert after.gains.kc == 2.0  # the preset's
    loop.apply(GainsCommand(loop="hx1", gains=PidGains(kc=1e-300, ti=60.0)))  # a number


def test_gains_beyond_floating_point_are_refused_and_the_pid_guard_holds():
    plant = {"loops": {"hx1": {"model": "heat_exchanger", "pid": {"kc": 1e308, "td": 5.0}}}}
    with pytest.raises(ConfigError) as err:
        build_plant(plant)
    refused(err.value, "loops.hx1.pid", "beyond floating-point range")
    loop = build_plant({"loops": {"hx1": {"model": "heat_exchanger", "noise_std": 0.5}}})["hx1"]
    with pytest.raises(CommandRejected, match="beyond floating-point range"):
        loop.apply(GainsCommand(loop="hx1", gains=PidGains(kc=1e300, ti=1.0, td=1e10)))
    # past the checks (as a bug might get): the loop faults rather than publish NaN
    loop.pid.set_gains(PidGains(kc=1e308, ti=1.0, td=5.0).to_core(), loop.sp, loop.pv)
    loop.apply(ModeCommand(loop="hx1", mode="auto"))
    loop.apply(SetpointCommand(loop="hx1", sp=120.0))
    for _ in range(50):
        s = loop.advance()
        assert math.isfinite(s.op) and 0.0 <= s.op <= 100.0
    assert loop.fault is not None and "PID block" in loop.fault and loop.mode == "manual"
    loop.status("plant", "lockstep", "query")


def test_user_disturbance_errors_are_refusals_not_crashes(user_models):
    loops = build_plant(
        {
            "loops": {
                "d1": {"model": f"{USER}:DisturbanceRaises", "sample_time": 1.0},
                "d2": {"model": f"{USER}:NamesRaiseLater", "sample_time": 1.0},
                "d3": {"model": f"{USER}:NamesJunkLater", "sample_time": 1.0},
            }
        }
    )
    with pytest.raises(CommandRejected) as err:
        loops["d1"].apply(DisturbanceCommand(loop="d1", name="bias", value=1.0))
    assert (
        err.value.category == "model"
        and "ZeroDivisionError: bias divides by zero" in err.value.reason
    )
    assert loops["d2"].status("p", "lockstep", "q").disturbances == {}
    assert loops["d3"].status("p", "lockstep", "q").disturbances == {"bias": 0.0}
    snap = loops["d1"].snapshot()
    loops["d1"].restore(snap)  # its set_disturbance raising: logged, the rest restored
    for lp in loops.values():
        lp.advance()
        assert lp.fault is None


# --- end to end: one subprocess per category, and a faulted loop in a running plant ---------


SUBPROCESS = [
    # (category, file bytes, needle)
    ("encoding", bytes(range(256)), "not UTF-8"),
    ("toml", b"[loops.hx1\n", "not valid TOML"),
    ("schema", b'[loops.hx1]\nmodle = "heat_exchanger"\n', "loops.hx1.model: Field required"),
    ("number", b'[loops.hx1]\nmodel = "heat_exchanger"\ndelay = 1e12\n', "loops.hx1.delay"),
    (
        "model",
        b'[loops.tf]\nmodel = "transfer_function"\nnum = [1e308]\nden = [1e-308]\n'
        b"sample_time = 1.0\n",
        "loops.tf.num",
    ),
    (
        "user-class",
        f'[loops.u1]\nmodel = "{USER}:RaisesInInit"\nsample_time = 1.0\n'.encode(),
        "vmap.csv is missing",
    ),
    (  # it held the plant at its load for good, silently
        "user-class-blocks",
        f'[loops.u1]\nmodel = "{USER}:ResetSleeps"\nsample_time = 1.0\n'.encode(),
        "reset() raised LoadTimeout: still loading after 2 s (--load-timeout)",
    ),
    (  # one that swallows the first stroke (except Exception) is struck again
        "user-class-retries",
        f'[loops.u1]\nmodel = "{USER}:ResetRetries"\nsample_time = 1.0\n'.encode(),
        "still loading after 2 s (--load-timeout)",
    ),
]


def test_autotune_plant_refuses_each_category_with_exit_2_and_one_line(tmp_path):
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(DATA), os.environ.get("PYTHONPATH", "")]),
    }
    procs = []
    for category, content, needle in SUBPROCESS:
        path = tmp_path / f"{category}.toml"
        path.write_bytes(content)
        cmd = [
            sys.executable,
            "-m",
            "services.cli",
            "plant",
            "--plant",
            str(path),
            "--no-multicast-scouting",
            "--load-timeout",
            "2",
        ]
        procs.append(
            (
                category,
                needle,
                subprocess.Popen(
                    cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
                ),
            )
        )
    for category, needle, proc in procs:  # all at once: each is an interpreter's start-up
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 2, (category, err)
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1, (category, err)
        assert err.startswith("autotune plant: error: plant file ") and needle in err, (
            category,
            err,
        )


FAULTY_PLANT = f"""
seed = 5
[loops.good]
model = "transfer_function"
num = [1.0]
den = [2.0, 1.0]
sample_time = 0.1
noise_std = 0.0

[loops.bad]
model = "{USER}:StepRaisesAfter"
sample_time = 0.1
fail_after = 20
"""


@pytest.mark.integration
def test_the_plant_service_stays_up_with_a_faulted_loop(start_plant, monkeypatch):
    from services.autotuner.loop_client import CommandRefused, LoopClient
    from shared import keys, wire
    from shared.messages import LoopStatus
    from shared.session import open_session

    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(DATA), os.environ.get("PYTHONPATH", "")]))
    plant = start_plant(FAULTY_PLANT, loops=("good", "bad"))
    with (
        open_session(plant.client_settings()) as s,
        LoopClient(s, plant.prefix, "good") as good,
        LoopClient(s, plant.prefix, "bad") as bad,
    ):
        bad.command(OutputCommand(loop="bad", op=60.0))
        held = bad.advance(40)  # fails at its 21st step; the samples keep coming, held
        assert [x.seq for x in held] == list(range(1, 41))
        assert len({x.pv for x in held[20:]}) == 1 and {x.op for x in held} == {60.0}
        before = good.last_status.seq
        assert [x.seq for x in good.advance(30)] == list(range(before + 1, before + 31))
        st = wire.query_one(s, keys.status(plant.prefix, "bad"), LoopStatus, 5.0)
        assert st is not None and st.mode == "manual" and st.op == 60.0
        assert st.fault is not None and "sensor fault after 20 steps" in st.fault
        with pytest.raises(CommandRefused, match="faulted"):
            bad.command(ModeCommand(loop="bad", mode="auto"))
        good.command(OutputCommand(loop="good", op=70.0))  # the other loop still obeys
        assert good.advance(5)[-1].op == 70.0
        ok = wire.query_one(s, keys.status(plant.prefix, "good"), LoopStatus, 5.0)
        assert ok is not None and ok.fault is None
    assert plant.proc.poll() is None, plant.stderr()
    log = plant.stderr()
    assert "Traceback" not in log
    assert log.count("model fuzz_user_models:StepRaisesAfter failed") == 1, log


def test_an_in_process_tune_ends_at_its_loops_fault(user_models):
    """In process (``LocalLoopClient``), the run heard of the fault only when a command was
    refused: a relay on a model failing at t = 150.1 s ran its verification's setpoint step
    on the held PV and ended "disturbance refused" (helper trial; here at 15 s, in the
    verification of a 22.5 s run). The advance ends at the
    fault and the client says so, as the bus's status does."""
    from services.autotuner.tuning import RunHooks, TuningRun
    from services.offline.local_loop import LocalLoopClient
    from shared.messages import TuneRequest

    spec = {"model": f"{USER}:StepRaisesAfter", "sample_time": 0.1, "fail_after": 150}
    loop = build_plant({"seed": 5, "loops": {"bad": spec}})["bad"]
    req = TuneRequest(loop="bad", method="relay")
    r = TuningRun(LocalLoopClient(loop), req, "fault", RunHooks()).run()
    assert r.status == "aborted" and r.reason.startswith("loop bad: the plant faulted it ("), (
        r.reason
    )
    assert "refused" not in r.reason
    assert loop.t == pytest.approx(loop.fault_t, abs=1e-9)  # not a sample past the fault


@pytest.mark.integration
def test_a_tune_ends_at_its_loops_fault_and_names_it(start_plant, monkeypatch):
    """The model fails 100 steps into a relay test: the run ended only when its next output
    command was refused (seen: 14,000 s of sim time later), and blamed "something other than this
    run" for the loop left in manual at the relay's output. It now aborts on the status that
    carries the fault, names it, and says why the loop is not as before."""
    from services.autotuner.loop_client import LoopClient
    from services.autotuner.tuning import TuningRun
    from shared.messages import TuneRequest
    from shared.session import open_session

    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(DATA), os.environ.get("PYTHONPATH", "")]))
    plant = start_plant(FAULTY_PLANT.replace("fail_after = 20", "fail_after = 100"), loops=("bad",))
    with open_session(plant.client_settings()) as s:
        with LoopClient(s, plant.prefix, "bad") as c:
            r = TuningRun(c, TuneRequest(loop="bad", method="relay"), "fault-test").run()
        with LoopClient(s, plant.prefix, "bad") as c:  # a held PV looks at rest: not started
            again = TuningRun(c, TuneRequest(loop="bad", method="relay"), "again").run()
    assert again.status == "aborted" and again.reason.startswith("not started: the loop is faulted")
    # its PV is held: "back where it was" said nothing of it (helper 52); the fault is said
    assert again.left is not None and again.left["fault"] is not None
    from services.autotuner.commands.tune import format_result

    assert "the loop is FAULTED (" in format_result(again)
    assert "back where it was" not in format_result(again)
    assert r.status == "aborted", r.reason
    assert "the plant faulted it (" in r.reason and "sensor fault" in r.reason
    assert "said in its status at t = " in r.reason
    assert "something other than this run" not in r.reason
    assert (
        "it faulted: a faulted loop stays in manual at its output; its setpoint and gains are "
        "as before (restart plant_sim to clear the fault)" in r.reason
    )
    assert r.sim_duration < 10.0 + 5.0  # within an advance of the fault, not 14,000 s on
    # said in the status the plant sent at the faulting sample (the advance ends there): a
    # 16,384-sample record ran 25 s of sim time on past a fault before it was said (helper)
    import re

    came, said = (float(x) for x in re.findall(r"at t = ([0-9.]+) s", r.reason)[:2])
    assert said == pytest.approx(came, abs=0.1 + 1e-9), r.reason


def test_model_check_of_a_class_with_its_own_num_and_den_and_a_huge_int(user_models):
    """`model check` ended "internal error", exit 70, on a class whose own ``num`` and
    ``den`` are not a transfer function, and on a step() that returned 10**400 (helper
    review): the first is checked from its steps, the second refused naming the model."""
    from services.plant_sim.model_check import check_loop

    loop = build_plant(user("OwnNumDen"))["u1"]
    r = check_loop("u1", loop)
    assert r.refused is None and r.ku_exact is None and r.behaviour == "self-regulating"
    loop = build_plant(user("StepHugeInt", fail_after=5))["u1"]
    r = check_loop("u1", loop)
    assert r.refused is not None and "not a finite number" in r.refused, r.refused


def test_model_check_json_stays_json_when_a_model_prints(user_models, tmp_path, capsys):
    """A model that prints in its __init__ and step() made `model check --json` start with
    its lines, and json.load failed (helper review): its prints go to stderr."""
    import json

    from tests.cli_run import run_cli

    path = tmp_path / "p.toml"
    path.write_text(toml_text(user("Chatty")))
    code, out, err = run_cli(capsys, "model", "check", str(path), "--json")
    assert code == 0 and json.loads(out)["loops"][0]["behaviour"] == "self-regulating"
    assert "hello from step" in err
