"""Plant files (TOML): which loops a plant_sim process serves and how each is modelled.

Minimum form::

    [loops.hx1]
    model = "transfer_function"   # or a preset name, or "package.module:Class"
    num = [1.0]
    den = [600.0, 70.0, 1.0]
    delay = 5.0
    sample_time = 0.25
    noise_std = 0.0               # PV units

Loop keys (all optional but ``model``): sample_time (s), noise_std (PV units), seed, mode
("manual"/"auto"), setpoint (PV units), action ("reverse"/"direct"), op_limits ([lo, hi] %),
pv_range ([lo, hi] PV units), pv_units, sp_track (bool), description, and a ``pid`` table
(kc, ti, td, n, beta). Every other key is a parameter of the model. A top-level ``seed``
seeds every loop's noise (each loop also mixes in its own id). ``model = "fmu"`` runs a
Functional Mock-up Unit (simulation/fmu.py): its ``path`` is relative to the plant file.

Whatever the file holds, loading it either gives loops that run or raises one ConfigError:
one line naming the loop and field (or the file) and the reason — for a user's model class,
its own error message. Every loop is built and probed (reset, its status and info messages)
before the service starts, so nothing the file says can fail later at publish time.
"""

from __future__ import annotations

import importlib
import inspect
import json
import math
import numbers
import tomllib
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pydantic
from pydantic import BaseModel, ConfigDict, Field

from services.plant_sim.load_bound import models_own
from services.plant_sim.simulation.fmu import FmuModel
from services.plant_sim.simulation.loop import LoopSettings, ModelFailure, SimLoop, gains_problem
from services.plant_sim.simulation.models import ModelParamError
from services.plant_sim.simulation.presets import CUSTOM_DEFAULTS, DEFAULTS, MODELS, LoopDefaults
from shared.errors import ConfigError
from shared.errors import one_line as brief
from shared.keys import check_id
from shared.messages import Action, Mode, PidGains

MAX_SAMPLE_TIME = 86400.0  # s: a day between samples is a loop no PID block runs
# s: a microsecond; below it no PID block samples, and a model's change in a sample is lost in
# rounding (1e-300 s was checked as "ignores its input … in 1.31072e-295 s": user trial)
MIN_SAMPLE_TIME = 1e-6
PROTOCOL = (
    "sample_time",
    "pv_units",
    "pv_range",
    "op0",
    "reset",
    "step",
    "disturbance_names",
    "set_disturbance",
)


class LoopConfig(BaseModel):
    """One ``[loops.<id>]`` table; keys not listed here go to the model."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False, strict=True)

    model: str = Field(min_length=1)
    sample_time: float | None = Field(default=None, gt=0.0, le=MAX_SAMPLE_TIME)
    noise_std: float | None = Field(default=None, ge=0.0)
    seed: int | None = Field(default=None, ge=0)
    mode: Mode = "manual"
    setpoint: float | None = None
    action: Action | None = None
    op_limits: tuple[float, float] = (0.0, 100.0)
    pv_range: tuple[float, float] | None = None
    pv_units: str | None = None
    sp_track: bool = False
    description: str = ""
    pid: PidGains | None = None


class PlantConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    seed: int = Field(default=0, ge=0)
    loops: dict[str, LoopConfig] = Field(min_length=1)


def _error(text: str) -> ConfigError:
    """A ConfigError on one line (a file's key, a path or a user's message may hold breaks)."""
    return ConfigError(brief(text, 2000))


def default_plant_path() -> Path:
    """The plant served when none is given: one loop of every preset."""
    return Path(str(resources.files("services.plant_sim") / "plants" / "default.toml"))


def load_plant_file(
    path: str | Path,
    seed: int | None = None,
    noise_std: float | None = None,
    select: Callable[[list[str]], list[str]] | None = None,
    sample_times: dict[str, float] | None = None,
) -> dict[str, SimLoop]:
    """Read a plant file and build its loops; ConfigError names the loop and field at fault.

    ``select``: given the file's loop ids in file order, the ids to build (a shard of the
    file); its ConfigError is raised as it is. ``sample_times``: loops built with another
    sample time than the file's (s; ``autotune model check`` reads a coarse loop finer)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise _error(f"plant file {path}: cannot read it: {err.strerror}") from None
    try:
        text = raw.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as err:
        raise _error(
            f"plant file {path}: not UTF-8 text, as TOML must be (byte 0x{raw[err.start]:02x} "
            f"at offset {err.start})"
        ) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise _error(f"plant file {path}: not valid TOML: {brief(err)}") from None
    except RecursionError:
        raise _error(f"plant file {path}: not valid TOML: nested too deeply") from None
    if noise_std is not None and isinstance(data.get("loops"), dict):
        for table in data["loops"].values():
            if isinstance(table, dict):
                table["noise_std"] = noise_std
    for loop_id, sample_time in (sample_times or {}).items():
        table = data.get("loops", {}).get(loop_id) if isinstance(data.get("loops"), dict) else None
        if isinstance(table, dict):
            table["sample_time"] = sample_time
    return build_plant(data, source=str(path), seed=seed, base_dir=path.parent, select=select)


def build_plant(
    data: dict[str, Any],
    source: str = "plant",
    seed: int | None = None,
    base_dir: Path | None = None,
    select: Callable[[list[str]], list[str]] | None = None,
) -> dict[str, SimLoop]:
    """Build every loop of a parsed plant file (``seed`` overrides the file's; an FMU's
    relative ``path`` is taken from ``base_dir``, the plant file's folder)."""
    try:
        # JSON mode: arrays are accepted for tuples, numbers stay strict ("5" is not 5).
        plant = PlantConfig.model_validate_json(json.dumps(data))
    except pydantic.ValidationError as err:
        raise _error(f"plant file {source}: {_first_error(err)}") from None
    except (TypeError, ValueError) as err:  # a TOML date, a value nested beyond recursion
        raise _error(f"plant file {source}: unsupported value ({brief(err)})") from None
    if seed is not None and seed < 0:
        raise _error(f"plant file {source}: seed: must be ≥ 0, got {seed}")
    plant_seed = plant.seed if seed is None else seed
    chosen = list(plant.loops) if select is None else select(list(plant.loops))
    loops = {}
    for loop_id in chosen:
        loops[loop_id] = build_loop(loop_id, plant.loops[loop_id], plant_seed, source, base_dir)
    return loops


def _first_error(err: pydantic.ValidationError) -> str:
    """``where: what`` of a validation error's first complaint, with the value if short."""
    e = err.errors()[0]
    where = ".".join(str(p) for p in e["loc"])
    value = e.get("input")
    shown = ""
    if isinstance(value, bool | int | float | str) and len(repr(value)) <= 40:
        shown = f", got {value!r}"
    return f"{where or 'top level'}: {e['msg']}{shown}"


def _resolve_model(name: str) -> tuple[type, LoopDefaults]:
    if name in MODELS:
        return MODELS[name], DEFAULTS[name]
    if name == "fmu":
        return FmuModel, CUSTOM_DEFAULTS
    if ":" not in name:
        raise ValueError(
            f"unknown model {name!r}: use one of {', '.join(MODELS)}, 'fmu' or "
            "'package.module:Class'"
        )
    module_name, _, class_name = name.partition(":")
    try:
        module = importlib.import_module(module_name)
    except BaseException as err:  # the user's module runs here: anything can happen
        if not models_own(err):
            raise
        raise ValueError(
            f"cannot import {module_name!r}: {type(err).__name__}: {brief(err)}"
        ) from None
    cls = getattr(module, class_name, None)
    if not isinstance(cls, type):
        raise ValueError(f"module {module_name!r} has no class {class_name!r}")
    return cls, CUSTOM_DEFAULTS


def _check_params(cls: type, params: dict[str, Any], model: str) -> str | None:
    """Name the first unknown or missing parameter of ``cls``, or None when all is well (or
    when its signature cannot be read: its constructor then judges)."""
    try:
        sig = inspect.signature(cls)
    except (TypeError, ValueError):
        return None
    accepted = {n for n, p in sig.parameters.items() if n != "sample_time"}
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values()):
        return None
    for key in params:
        if key not in accepted:
            return (
                f"{key}: not a parameter of model {model!r} (it takes: "
                f"{', '.join(sorted(accepted)) or 'nothing'})"
            )
    for n, p in sig.parameters.items():
        if (
            n != "sample_time"
            and p.default is inspect.Parameter.empty
            and n not in params
            and p.kind not in (inspect.Parameter.VAR_POSITIONAL,)
        ):
            return f"{n}: required by model {model!r}"
    return None


def build_loop(
    loop_id: str,
    cfg: LoopConfig,
    plant_seed: int,
    source: str = "plant",
    base_dir: Path | None = None,
) -> SimLoop:
    """Construct the process model and the loop around it."""

    def fail(field: str, reason: str) -> ConfigError:
        return _error(f"plant file {source}: loops.{loop_id}.{field}: {reason}")

    try:
        check_id(loop_id)
    except ValueError as err:
        raise _error(f"plant file {source}: loops.{loop_id}: {err}") from None
    try:
        cls, defaults = _resolve_model(cfg.model)
    except ValueError as err:
        raise fail("model", str(err)) from None
    sample_time = cfg.sample_time if cfg.sample_time is not None else defaults.sample_time
    if sample_time is None:
        raise fail("sample_time", f"required for model {cfg.model!r} (seconds, > 0)")
    if sample_time < MIN_SAMPLE_TIME:
        raise fail(
            "sample_time",
            f"{sample_time:g} s is under {MIN_SAMPLE_TIME:g} s (a microsecond): no PID block "
            "samples faster, and a model's change in one sample is lost in rounding",
        )
    params = dict(cfg.model_extra or {})
    problem = _check_params(cls, params, cfg.model)
    if problem:
        field, _, reason = problem.partition(": ")
        raise fail(field, reason)
    if cls is FmuModel and isinstance(params.get("path"), str) and base_dir is not None:
        params["path"] = str(base_dir / params["path"])  # an absolute path stays as it is
    try:
        with np.errstate(all="ignore"):  # overflow is judged by the model, not printed
            process = cls(sample_time=sample_time, **params)
    except ModelParamError as err:
        raise fail(err.field, brief(err.reason)) from None
    except (TypeError, ValueError) as err:
        raise fail("model", f"{cfg.model} rejected its parameters: {brief(err)}") from None
    except BaseException as err:  # a user's class: its own words, on one line
        if not models_own(err):
            raise
        raise fail("model", f"{cfg.model}() raised {type(err).__name__}: {brief(err)}") from None
    if cls is FmuModel and cfg.pv_range is None and process.pv_range is None:
        raise fail(
            "pv_range",
            f"required: the FMU's output {process.output_name!r} declares no min and max "
            "(give the transmitter's range, [lo, hi] in PV units)",
        )
    try:
        got = _read_protocol(process, cfg)
    except ModelParamError as err:
        raise fail(err.field, err.reason) from None
    pv_range = cfg.pv_range if cfg.pv_range is not None else tuple(got["pv_range"])
    if not pv_range[0] < pv_range[1]:
        raise fail("pv_range", f"low must be below high, got {list(pv_range)}")
    lo, hi = cfg.op_limits
    if not 0.0 <= lo < hi <= 100.0:
        raise fail("op_limits", f"must satisfy 0 ≤ low < high ≤ 100 %, got {[lo, hi]}")
    if not lo <= got["op0"] <= hi:
        raise fail("op_limits", f"the operating point op0 = {got['op0']} % lies outside them")
    if not math.isfinite(pv_range[1] - pv_range[0]):
        raise fail("pv_range", f"its width overflows floating point, got {list(pv_range)}")
    gains = cfg.pid or defaults.gains
    problem = gains_problem(gains, float(sample_time), (pv_range[0], pv_range[1]))
    if problem:
        raise fail("pid", problem)
    if cfg.setpoint is not None and not pv_range[0] <= cfg.setpoint <= pv_range[1]:
        raise fail("setpoint", f"{cfg.setpoint} is outside pv_range {list(pv_range)}")
    settings = LoopSettings(
        loop_id=loop_id,
        model_name=cfg.model,
        model_params={"sample_time": sample_time, **params},
        sample_time=float(sample_time),
        noise_std=cfg.noise_std if cfg.noise_std is not None else defaults.noise_std,
        seed=cfg.seed if cfg.seed is not None else plant_seed,
        mode=cfg.mode,
        setpoint=cfg.setpoint,
        action=cfg.action or defaults.action,
        op_limits=(float(lo), float(hi)),
        pv_range=(float(pv_range[0]), float(pv_range[1])),
        pv_units=cfg.pv_units if cfg.pv_units is not None else got["pv_units"],
        gains=gains,
        sp_track=cfg.sp_track,
        description=cfg.description
        or (process.description if cls is FmuModel else (inspect.getdoc(cls) or "").split("\n")[0]),
    )
    try:
        loop = SimLoop(settings, process)
    except ModelFailure as err:
        raise fail("model", f"{cfg.model}: {err.reason}") from None
    except BaseException as err:  # the user's attributes, read again by the loop
        if not models_own(err):
            raise
        raise fail("model", f"{cfg.model}: {type(err).__name__}: {brief(err)}") from None
    try:  # what the service will publish: any field that could not be is named now
        loop.status("check", "lockstep", "start")
        loop.info("check", "lockstep", 1.0)
    except pydantic.ValidationError as err:
        raise fail("model", f"{cfg.model}: {_first_error(err)}") from None
    return loop


def _read_protocol(process: object, cfg: LoopConfig) -> dict[str, Any]:
    """The ProcessModel protocol's members of ``process``; ModelParamError (field, reason)
    when one is missing or unusable (attributes the plant file overrides are not judged)."""
    values: dict[str, Any] = {}
    missing = []
    overridden = {"pv_range": cfg.pv_range is not None, "pv_units": cfg.pv_units is not None}
    for name in PROTOCOL:
        try:
            values[name] = getattr(process, name)
        except AttributeError:
            if not overridden.get(name, False):  # the plant file gives it: not needed
                missing.append(name)
        except BaseException as err:  # a property of the user's that raises
            if not models_own(err):
                raise
            raise ModelParamError(
                "model", f"{cfg.model}: .{name} raised {type(err).__name__}: {brief(err)}"
            ) from None
    if missing:
        raise ModelParamError(
            "model",
            f"{cfg.model} does not implement the ProcessModel protocol "
            f"(missing: {', '.join(missing)})",
        )
    methods = ("reset", "step", "disturbance_names", "set_disturbance")
    not_callable = [m for m in methods if not callable(values[m])]
    if not_callable:
        raise ModelParamError(
            "model",
            f"{cfg.model} does not implement the ProcessModel protocol "
            f"({', '.join(not_callable)} must be "
            f"{'a method' if len(not_callable) == 1 else 'methods'})",
        )
    try:  # the disturbances its status shows and a command may set: names, or a refusal
        names = values["disturbance_names"]()
    except BaseException as err:
        if not models_own(err):
            raise
        raise ModelParamError(
            "model", f"{cfg.model}.disturbance_names() raised {type(err).__name__}: {brief(err)}"
        ) from None
    if not isinstance(names, tuple | list) or not all(isinstance(n, str) for n in names):
        # (5 was taken, and the loop's status showed no disturbance: helper trial)
        raise ModelParamError(
            "model",
            f"{cfg.model}.disturbance_names() must return a tuple of names (strings), got "
            f"{brief(repr(names))}",
        )
    try:  # optional: the disturbances' present values, read for every status it publishes
        # (a class's own __getattr__ raising for any name it lacks has none)
        if inspect.getattr_static(process, "disturbances", None) is not None:
            getattr(process, "disturbances")  # noqa: B009 (a property of the user's runs here)
    except BaseException as err:  # a property of the user's that raises (it was accepted, and
        if not models_own(err):  # the loop's status then showed stale values: user trial)
            raise
        raise ModelParamError(
            "model", f"{cfg.model}: .disturbances raised {type(err).__name__}: {brief(err)}"
        ) from None
    op0 = values["op0"]
    if isinstance(op0, bool) or not isinstance(op0, numbers.Real) or not math.isfinite(op0):
        raise ModelParamError(
            "op0", f"{cfg.model}.op0 must be a finite number of %, got {brief(repr(op0))}"
        )
    values["op0"] = float(op0)
    if cfg.pv_range is None:
        pv_range = _as_range(values["pv_range"])
        if pv_range is None:
            raise ModelParamError(
                "pv_range",
                f"{cfg.model}.pv_range must be two finite numbers, "
                f"got {brief(repr(values['pv_range']))}",
            )
        values["pv_range"] = pv_range
    if cfg.pv_units is None and not isinstance(values["pv_units"], str):
        raise ModelParamError(
            "pv_units",
            f"{cfg.model}.pv_units must be a string, got {brief(repr(values['pv_units']))}",
        )
    return values


def _as_range(value: object) -> tuple[float, float] | None:
    """``(lo, hi)`` of two finite real numbers, or None."""
    try:
        lo, hi = value  # type: ignore[misc]
    except (TypeError, ValueError):
        return None
    ok = all(
        isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)
        for v in (lo, hi)
    )
    return (float(lo), float(hi)) if ok else None
