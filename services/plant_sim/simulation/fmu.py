"""A Functional Mock-up Unit (FMI 2.0 or 3.0) as a plant_sim process model, through FMPy.

Engineers exchange plant models as FMUs (Modelica tools, Simulink, AMESim...); a plant-file loop
with ``model = "fmu"`` runs one::

    [loops.hx3]
    model = "fmu"
    path = "models/HeatExchanger.fmu"    # relative to the plant file
    input = "valve"                      # the FMU input the loop's output drives
    output = "T_out"                     # the FMU output that is the PV
    sample_time = 0.5
    parameters = { UA = 1200.0 }         # start values of FMU parameters
    disturbances = { inflow = "q_in" }   # loop disturbance name → FMU input
    op_scale = [0.0, 1.0]                # FMU input value at 0 % and 100 % output

Co-simulation FMUs advance with their own solver, one ``doStep`` per sample (two when the dead
time has a fraction of a sample); model-exchange FMUs are integrated by FMPy's CVode (BDF,
relative ``tolerance``), restarted wherever the input steps. The output (%) is held over each
sample (zero-order hold) and mapped linearly onto the FMU input by ``op_scale``. As for every
model, ``delay`` (s) is a dead time on the input — exact, also for a fraction of a sample — and
``sensor_lag`` (s) a first-order transmitter lag on the output; the loop adds the noise and the
transmitter's range. ``reset`` frees the instance and instantiates the FMU anew: the process
rests where the FMU's initialisation puts it with the input at ``op0`` (``settle`` s more at
``op0`` for an FMU that does not start at rest).

Whatever goes wrong is a ``ModelParamError`` naming the plant-file field at load (``path`` for
the FMU itself), or an ``FmuError`` carrying the FMU's own message at run time, which faults
the loop like any model's failure; an instance that failed is never called again. The FMU's
binary runs in this process (native code: one that crashes takes the process with it), and
FMPy is imported only when an FMU is loaded.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import math
import os
import shutil
import weakref
import zipfile
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

from services.plant_sim.simulation.models import (
    MAX_DELAY_SAMPLES,
    ModelParamError,
    check_delay,
    finite,
)
from services.plant_sim.simulation.physical import SensorLag
from shared.control.lti import split_delay
from shared.errors import one_line

INTERFACES = {"co-simulation": "CoSimulation", "model-exchange": "ModelExchange"}
REAL_TYPES = ("Real", "Float64", "Float32")
INTEGER_TYPES = (
    "Integer",
    "Enumeration",
    "Int8",
    "UInt8",
    "Int16",
    "UInt16",
    "Int32",
    "UInt32",
    "Int64",
    "UInt64",
)
MAX_EVENTS_PER_SAMPLE = 10_000  # model exchange: more events than this in one sample is a chatter
TIME_EPS = 1e-12  # relative: two instants this close are one (FMPy's isclose for events)


_INSTANCES: dict[int, Any] = {}  # every healthy FMU instance not yet freed, by id


def _terminate(fmu: Any) -> None:
    """Terminate and free an instance (and unload its library), whatever it says."""
    _INSTANCES.pop(id(fmu), None)
    with contextlib.suppress(Exception):
        fmu.terminate()
    with contextlib.suppress(Exception):
        fmu.freeInstance()


@atexit.register
def _free_all() -> None:
    """At exit, while Python still runs, free every healthy instance left (those of models
    the garbage collector took too): an FMU's library still loaded past the interpreter's end
    may run destructors that need it."""
    for fmu in list(_INSTANCES.values()):
        _terminate(fmu)


class FmuError(RuntimeError):
    """The FMU failed at run time; the message is the FMU's own, on one line."""


class _NoInput:
    """FMPy's CVode wrapper asks an input object to apply itself in the root function: our
    inputs are set by the step, piecewise constant, so there is nothing to do."""

    def apply(self, *_args: Any, **_kwargs: Any) -> None:
        return None


def _fmpy() -> Any:
    """FMPy, imported on first use (a plant without FMUs never loads it)."""
    try:
        import fmpy
        import fmpy.fmi1
        import fmpy.fmi2
        import fmpy.fmi3
        import fmpy.simulation
    except ImportError as err:  # an install without the dependency
        raise ModelParamError(
            "model", f"FMU models need the fmpy package, which cannot be imported: {err}"
        ) from None
    return fmpy


def _as_str(field: str, value: object) -> str:
    if not isinstance(value, str) or not value:
        raise ModelParamError(field, f"expected a non-empty string, got {one_line(repr(value))}")
    return value


def _scale(value: object) -> tuple[float, float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ModelParamError(
            "op_scale", f"expected [at 0 %, at 100 %], two numbers, got {one_line(repr(value))}"
        )
    lo = finite("op_scale[0]", value[0])
    hi = finite("op_scale[1]", value[1])
    if lo == hi or not math.isfinite(hi - lo):
        raise ModelParamError("op_scale", f"the two ends must differ (finitely), got {[lo, hi]}")
    return lo, hi


def _fmi_version(path: Path) -> str | None:
    """The ``fmiVersion`` of the FMU's modelDescription.xml root element, read before FMPy
    parses the rest (it cannot parse a version it does not expect); None if unreadable."""
    try:
        with zipfile.ZipFile(path) as z, z.open("modelDescription.xml") as f:
            for _, element in ElementTree.iterparse(f, events=("start",)):
                return element.get("fmiVersion")
    except (zipfile.BadZipFile, KeyError, OSError, ElementTree.ParseError):
        return None
    return None


def _number(text: object) -> float | None:
    """A finite float from an FMU's attribute text, else None."""
    try:
        value = float(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _a(words: str) -> str:
    """``words`` with its indefinite article."""
    return ("an " if words[:1].lower() in "aeiou" else "a ") + words


def _note(log: list[str], status: int, message: bytes | str | None) -> None:
    """Keep the FMU's warnings and errors (status ≥ 1), the last ten, one line each."""
    if status >= 1 and message:
        text = message.decode("utf-8", "replace") if isinstance(message, bytes) else str(message)
        log.append(one_line(text, 500))
        del log[:-10]


def _logger2(log: list[str]) -> Callable[..., None]:
    """An FMI 2.0 logger callback into ``log`` (not a bound method: the FMU holds it, and it
    must not keep its model alive)."""

    def logger(_env: Any, _name: Any, status: int, _category: Any, message: Any) -> None:
        _note(log, status, message)

    return logger


def _logger3(log: list[str]) -> Callable[..., None]:
    """An FMI 3.0 logMessage callback into ``log``."""

    def logger(_env: Any, status: int, _category: Any, message: Any) -> None:
        _note(log, status, message)

    return logger


def _quiet(solver: Any) -> None:
    """Keep only FMPy's error handler on the solver's SUNDIALS context: SUNDIALS' default one
    prints every failure to stderr, which the FmuError already carries."""
    with contextlib.suppress(Exception):
        from fmpy.sundials.libraries import sundials_core
        from fmpy.sundials.sundials_context import SUNContext_PushErrHandler

        clear = sundials_core.SUNContext_ClearErrHandlers
        clear.argtypes = [ctypes.c_void_p]
        clear.restype = ctypes.c_int
        if clear(solver.sunctx) == 0:
            SUNContext_PushErrHandler(solver.sunctx, solver.ehfun_, None)


def _listing(names: list[str]) -> str:
    shown = ", ".join(names[:12]) + (", ..." if len(names) > 12 else "")
    return shown or "none"


class FmuModel:
    """An FMU as a ``ProcessModel``: output (%) → FMU input, FMU output → PV (the FMU's units).

    ``parameters`` are start values set before initialisation; ``disturbances`` name FMU
    inputs the loop may set (in the FMU's units, held until changed, kept across ``reset``).
    ``interface`` is ``co-simulation`` or ``model-exchange`` (default: co-simulation when the
    FMU offers it); ``tolerance`` is the relative tolerance of the model-exchange integrator.
    """

    pv_units = ""
    pv_range: tuple[float, float] | None = None

    def __init__(
        self,
        sample_time: float,
        path: str,
        input: str,  # the plant file's key (shadows the builtin here only)
        output: str,
        parameters: Mapping[str, Any] | None = None,
        disturbances: Mapping[str, str] | None = None,
        op_scale: tuple[float, float] | list[float] = (0.0, 100.0),
        op0: float = 50.0,
        delay: float = 0.0,
        sensor_lag: float = 0.0,
        interface: str | None = None,
        tolerance: float = 1e-8,
        settle: float = 0.0,
    ):
        self.sample_time = finite("sample_time", sample_time, low=0.0, low_open=True)
        self.path = _as_str("path", path)
        self.input_name = _as_str("input", input)
        self.output_name = _as_str("output", output)
        self.op_scale = _scale(op_scale)
        self.op0 = finite("op0", op0, low=0.0, high=100.0)
        self.delay = check_delay(delay, self.sample_time)
        self._n, frac = split_delay(self.delay, self.sample_time)
        self._frac = frac / self.sample_time
        self.sensor_lag = finite("sensor_lag", sensor_lag, low=0.0)
        self.tolerance = finite("tolerance", tolerance, low=0.0, low_open=True, high=0.01)
        self.settle = finite("settle", settle, low=0.0)
        if self.settle / self.sample_time > MAX_DELAY_SAMPLES:
            raise ModelParamError(
                "settle", f"{self.settle:g} s is more than {MAX_DELAY_SAMPLES} sample periods"
            )
        if interface is not None and interface not in INTERFACES:
            raise ModelParamError(
                "interface",
                f"must be one of {', '.join(INTERFACES)}, got {one_line(repr(interface))}",
            )
        if parameters is not None and not isinstance(parameters, Mapping):
            raise ModelParamError("parameters", "expected a table of FMU parameter = start value")
        if disturbances is not None and not isinstance(disturbances, Mapping):
            raise ModelParamError("disturbances", 'expected a table of name = "FMU input"')
        self._fmpy = _fmpy()
        try:
            self.md = self._read(Path(self.path))
        except (OSError, ValueError) as err:  # a name too long, a NUL byte...
            if isinstance(err, ModelParamError):
                raise
            raise ModelParamError("path", f"cannot open {self.path!r}: {one_line(err)}") from None
        self.interface = self._choose_interface(interface)
        self._vars = {v.name: v for v in self.md.modelVariables}
        cs = self.md.coSimulation
        if self._cosim and self._frac > 0 and not cs.canHandleVariableCommunicationStepSize:
            raise ModelParamError(
                "delay",
                f"{self.delay:g} s is not a whole number of {self.sample_time:g} s samples, and "
                f"{self.path} cannot vary its communication step (its "
                "canHandleVariableCommunicationStepSize is false): give a whole number",
            )
        self._in = self._variable("input", self.input_name, ("input",))
        self._out = self._variable("output", self.output_name, ("output",))
        self.parameters = self._check_parameters(dict(parameters or {}))
        self._dist = self._check_disturbances(dict(disturbances or {}))
        self.disturbances = {name: self._start(v) for name, v in self._dist.items()}
        declared = _number(self._out.min), _number(self._out.max)
        if None not in declared and declared[0] < declared[1]:
            self.pv_range = (declared[0], declared[1])
        unit = self._out.unit or (self._out.declaredType and self._out.declaredType.unit)
        self.pv_units = unit or ""
        md = self.md
        self.description = one_line(
            f"FMU {md.modelName} (FMI {md.fmiVersion} {self.interface})"
            + (f": {md.description}" if md.description else ""),
            200,
        )
        self._dir = self._extract()
        self._fmu: Any = None
        self._solver: Any = None
        self._log: list[str] = []  # the FMU's warnings and errors, newest last
        self._failures: list[str] = []  # what failed inside the integrator's callbacks
        self._keep: list[Any] = []  # ctypes callbacks the FMU holds pointers to
        self._ops: deque[float] = deque(maxlen=self._n + 2)
        self._lag = SensorLag(self.sensor_lag, self.sample_time)
        self._k = 0
        self._t0 = 0.0
        self._t = 0.0
        self._u: float | None = None
        self._event_time: float | None = None
        self._failed = False  # an FMI call failed: the instance is never called again
        self._finalizer = weakref.finalize(self, shutil.rmtree, self._dir, True)
        self._probe()

    # --- loading -------------------------------------------------------------------------

    def _read(self, path: Path) -> Any:
        """The model description; ModelParamError("path") for anything that is not a usable
        FMI 2.0 or 3.0 FMU."""
        if not path.exists():
            raise ModelParamError("path", f"no such file: {path}")
        if not path.is_file():
            raise ModelParamError("path", f"{path} is not a file")
        if not zipfile.is_zipfile(path):
            raise ModelParamError("path", f"{path} is not an FMU (not a zip archive)")
        try:
            with zipfile.ZipFile(path) as z:
                if "modelDescription.xml" not in z.namelist():
                    raise ModelParamError("path", f"{path} is not an FMU (no modelDescription.xml)")
        except (zipfile.BadZipFile, OSError) as err:
            raise ModelParamError("path", f"{path} cannot be read as an FMU: {err}") from None
        version = _fmi_version(path)
        if version is not None and version != "2.0" and not version.startswith("3."):
            raise ModelParamError(
                "path", f"{path} is an FMI {version} FMU; plant_sim runs FMI 2.0 and 3.0"
            )
        try:
            md = self._fmpy.read_model_description(str(path), validate=True)
        except Exception as err:  # FMPy's parser and validation: the FMU's XML, its words
            raise ModelParamError(
                "path", f"{path}: its modelDescription.xml is not valid: {one_line(err)}"
            ) from None
        try:
            platforms = self._fmpy.supported_platforms(str(path))
        except Exception as err:
            raise ModelParamError("path", f"{path}: {one_line(err)}") from None
        here = self._fmpy.platform
        if here not in platforms:
            raise ModelParamError(
                "path",
                f"{path} has no binary for this platform ({here}); it has: "
                f"{_listing(sorted(platforms))}",
            )
        return md

    def _choose_interface(self, wanted: str | None) -> str:
        offered = [
            name
            for name, attr in INTERFACES.items()
            if getattr(self.md, attr[0].lower() + attr[1:], None) is not None
        ]
        if wanted is None:
            if not offered:
                raise ModelParamError(
                    "path", f"{self.path} offers neither co-simulation nor model exchange"
                )
            return offered[0]
        if wanted not in offered:
            raise ModelParamError(
                "interface", f"{self.path} offers {_listing(offered)}, not {wanted}"
            )
        return wanted

    @property
    def _cosim(self) -> bool:
        return self.interface == "co-simulation"

    def _variable(self, field: str, name: str, causalities: tuple[str, ...]) -> Any:
        """The FMU's scalar real variable ``name`` of one of ``causalities``."""
        var = self._vars.get(name)
        fitting = sorted(
            v.name
            for v in self.md.modelVariables
            if v.causality in causalities and v.type in REAL_TYPES and not v.shape
        )
        kind = "/".join(causalities)
        if var is None:
            raise ModelParamError(
                field, f"no {kind} {name!r} in the FMU (its real {kind}s: {_listing(fitting)})"
            )
        if var.causality not in causalities:
            raise ModelParamError(
                field,
                f"{name!r} is {_a(var.causality)} of the FMU, not {_a(kind)} (its real {kind}s: "
                f"{_listing(fitting)})",
            )
        if var.type not in REAL_TYPES or var.shape:
            shape = f"an array of {var.type}" if var.shape else var.type
            raise ModelParamError(field, f"{name!r} is {shape}; a real scalar is needed")
        return var

    def _check_parameters(self, params: dict[str, Any]) -> dict[str, Any]:
        """Each start value checked against its variable's type: ModelParamError naming
        ``parameters.NAME``."""
        known = sorted(v.name for v in self.md.modelVariables if v.causality in ("parameter",))
        out: dict[str, Any] = {}
        for name, value in params.items():
            field = f"parameters.{name}"
            var = self._vars.get(name)
            if var is None:
                raise ModelParamError(
                    field, f"no parameter {name!r} in the FMU (its parameters: {_listing(known)})"
                )
            if var.causality not in ("parameter", "structuralParameter") or (
                var.variability == "constant"
            ):
                raise ModelParamError(
                    field,
                    f"{name!r} is {_a(' '.join(filter(None, (var.variability, var.causality))))} "
                    "of the FMU, not a parameter whose start value can be set",
                )
            if var.shape:
                raise ModelParamError(field, f"{name!r} is an array; scalar parameters only")
            if var.type in REAL_TYPES:
                out[name] = finite(field, value)
            elif var.type in INTEGER_TYPES:
                if isinstance(value, bool) or not isinstance(value, int):
                    raise ModelParamError(
                        field, f"{name!r} is {var.type}: expected an integer, got {value!r}"
                    )
                out[name] = value
            elif var.type == "Boolean":
                if not isinstance(value, bool):
                    raise ModelParamError(
                        field, f"{name!r} is Boolean: expected true or false, got {value!r}"
                    )
                out[name] = value
            elif var.type == "String":
                if not isinstance(value, str):
                    raise ModelParamError(field, f"{name!r} is a String: got {value!r}")
                out[name] = value
            else:
                raise ModelParamError(field, f"{name!r} is {var.type}: not supported")
        return out

    def _check_disturbances(self, table: dict[str, Any]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, target in table.items():
            field = f"disturbances.{name}"
            if not name.isidentifier():
                raise ModelParamError(field, "a disturbance name must be a plain identifier")
            target = _as_str(field, target)
            var = self._variable(field, target, ("input",))
            if var.name == self._in.name:
                raise ModelParamError(field, f"{target!r} is the loop's input already")
            if any(v.name == var.name for v in out.values()):
                raise ModelParamError(field, f"{target!r} is mapped twice")
            out[name] = var
        return out

    @staticmethod
    def _start(var: Any) -> float:
        try:
            value = float(var.start) if var.start is not None else 0.0
        except (TypeError, ValueError):
            value = 0.0
        return value if math.isfinite(value) else 0.0

    def _extract(self) -> str:
        try:
            return str(self._fmpy.extract(self.path))
        except Exception as err:
            raise ModelParamError(
                "path", f"{self.path} cannot be extracted: {one_line(err)}"
            ) from None

    def _probe(self) -> None:
        """Instantiate, initialise and step once at ``op0``, so that an FMU that cannot is
        refused at load with its own message (``path``), not found out mid-run."""
        try:
            self.reset()
            self.step(self.op0)
            self.reset()
        except FmuError as err:
            raise ModelParamError("path", f"{self.path}: {err}") from None

    # --- the FMU's life --------------------------------------------------------------------

    def close(self) -> None:
        """Free the instance and the extracted files.

        A model dropped without ``close`` keeps its instance until the process ends (freed
        then, at exit): the garbage collector only removes the files, as an FMU's code is
        never called from it, at whatever moment it runs."""
        self._free()
        self._finalizer()

    def _free(self) -> None:
        """Terminate and free the instance; one that failed is only dropped (FMI allows no
        more than freeing it, and some FMUs crash even on that)."""
        self._solver = None
        fmu, self._fmu = self._fmu, None
        if fmu is None:
            return
        if self._failed:
            _INSTANCES.pop(id(fmu), None)  # left as it is, for good
            return
        _terminate(fmu)

    def _mark_failed(self) -> None:
        """The instance failed: it is never called again, nor freed (FMI allows only freeing
        it after an error, and some FMUs crash even on that)."""
        self._failed = True
        if self._fmu is not None:
            _INSTANCES.pop(id(self._fmu), None)

    def _call(self, what: str, fn: Callable[..., Any], *args: Any) -> Any:
        """An FMI call; FmuError with the FMU's own message when it fails."""
        self._log.clear()
        try:
            return fn(*args)
        except Exception as err:
            self._mark_failed()
            said = "; ".join(self._log[-3:])
            raise FmuError(
                f"the FMU failed to {what}: {one_line(err).rstrip('.')}"
                + (f": {said}" if said else "")
            ) from None

    def _instantiate(self) -> Any:
        fmpy = self._fmpy
        md = self.md
        fmi3 = not md.fmiVersion.startswith("2")
        cosim = self._cosim
        attr = "coSimulation" if cosim else "modelExchange"
        kwargs = dict(
            guid=md.guid,
            unzipDirectory=self._dir,
            modelIdentifier=getattr(md, attr).modelIdentifier,
            instanceName="plant",
        )
        if fmi3:
            cls = fmpy.fmi3.FMU3Slave if cosim else fmpy.fmi3.FMU3Model
        else:
            cls = fmpy.fmi2.FMU2Slave if cosim else fmpy.fmi2.FMU2Model
        try:
            cwd: str | None = os.getcwd()
        except OSError:  # a working directory that is gone: nothing to return to
            cwd = None
        try:
            fmu = self._call("load its binary", lambda: cls(**kwargs))
        finally:  # FMPy changes into the binary's folder to load it, and not back on failure
            if cwd is not None:
                with contextlib.suppress(OSError):
                    os.chdir(cwd)
        if fmi3:
            self._call(
                "instantiate",
                lambda: fmu.instantiate(loggingOn=True, logMessage=_logger3(self._log)),
            )
        else:
            cb = fmpy.fmi2.fmi2CallbackFunctions()
            cb.logger = fmpy.fmi2.fmi2CallbackLoggerTYPE(_logger2(self._log))
            cb.allocateMemory = fmpy.fmi2.fmi2CallbackAllocateMemoryTYPE(fmpy.fmi1.calloc)
            cb.freeMemory = fmpy.fmi2.fmi2CallbackFreeMemoryTYPE(fmpy.fmi1.free)
            with contextlib.suppress(Exception):  # formats the FMU's variadic messages
                from fmpy.logging import addLoggerProxy

                addLoggerProxy(ctypes.byref(cb))
            self._keep = [cb]
            self._call("instantiate", lambda: fmu.instantiate(callbacks=cb, loggingOn=True))
        _INSTANCES[id(fmu)] = fmu
        return fmu

    def _set_real(self, var: Any, value: float) -> None:
        fmu = self._fmu
        setter = fmu.setReal if self.md.fmiVersion.startswith("2") else fmu.setFloat64
        self._call(f"set {var.name}", setter, [var.valueReference], [value])

    def _get_real(self, var: Any) -> float:
        fmu = self._fmu
        getter = fmu.getReal if self.md.fmiVersion.startswith("2") else fmu.getFloat64
        return float(self._call(f"get {var.name}", getter, [var.valueReference])[0])

    def _to_input(self, op: float) -> float:
        lo, hi = self.op_scale
        return lo + (hi - lo) * op / 100.0

    def reset(self) -> float:
        """Free the instance, instantiate the FMU anew at ``op0`` and initialise it; the PV."""
        try:
            return self._reset()
        except FmuError:
            self._mark_failed()
            raise

    def _reset(self) -> float:
        self._free()
        fmpy = self._fmpy
        fmi2 = self.md.fmiVersion.startswith("2")
        self._failed = False
        self._fmu = fmu = self._instantiate()
        if self.parameters:
            left = self._call(
                "take the parameters' start values",
                fmpy.simulation.apply_start_values,
                fmu,
                self.md,
                dict(self.parameters),
            )
            if left:
                raise FmuError(f"the FMU did not take the start values of {', '.join(left)}")
        u = self._to_input(self.op0)
        self._set_real(self._in, u)
        for name, var in self._dist.items():
            self._set_real(var, self.disturbances[name])
        if fmi2:
            self._call("set up the experiment", fmu.setupExperiment, None, 0.0)
            self._call("enter initialisation", fmu.enterInitializationMode)
        else:
            self._call("enter initialisation", lambda: fmu.enterInitializationMode(startTime=0.0))
        self._call("initialise", fmu.exitInitializationMode)
        self._u = u
        self._t = 0.0
        self._event_time = None
        self._failures.clear()
        if not self._cosim:
            self._start_integrator()
        self._ops.clear()
        self._ops.extend([self.op0] * (self._n + 2))
        self._k = 0
        self._t0 = 0.0
        n_settle = math.ceil(self.settle / self.sample_time - 1e-9) if self.settle else 0
        for _ in range(n_settle):  # at op0 until at rest, for an FMU that starts elsewhere
            self._advance(self.sample_time * (self._k + 1), u)
            self._k += 1
        self._t0 = self._k * self.sample_time
        self._k = 0
        y = self._get_real(self._out)
        self._lag.fill(y)
        return y

    def _start_integrator(self) -> None:
        """Model exchange: the initial event iteration, continuous-time mode, and CVode."""
        fmu = self._fmu
        self._event_iteration()
        self._call("enter continuous-time mode", fmu.enterContinuousTimeMode)
        from fmpy.sundials import CVodeSolver

        fmi2 = self.md.fmiVersion.startswith("2")
        derivatives = fmu.getDerivatives if fmi2 else fmu.getContinuousStateDerivatives
        self._solver = self._call(
            "start the integrator",
            lambda: CVodeSolver(
                nx=self.md.numberOfContinuousStates,
                nz=self.md.numberOfEventIndicators,
                get_x=self._guard(fmu.getContinuousStates, fills=True),
                set_x=self._guard(fmu.setContinuousStates),
                get_dx=self._guard(derivatives, fills=True),
                get_z=self._guard(fmu.getEventIndicators, fills=True),
                get_nominals=self._guard(fmu.getNominalsOfContinuousStates, fills=True),
                set_time=self._guard(fmu.setTime),
                input=_NoInput(),
                startTime=self._t,
                maxStep=self.sample_time,
                relativeTolerance=self.tolerance,
                maxNumSteps=100_000,
            ),
        )
        _quiet(self._solver)

    def _guard(self, fn: Callable[..., Any], fills: bool = False) -> Callable[..., Any]:
        """A callback CVode calls through ctypes, where an exception cannot propagate (ctypes
        would print it): the first failure is kept and reported after the step, and a getter
        (``fills``) hands CVode NaN so that it stops."""
        log, failures = self._log, self._failures

        def call(*args: Any) -> Any:
            if failures:  # the FMU failed: never call it again (FMI allows only freeing it)
                if fills and len(args) >= 2:
                    for i in range(int(args[1])):
                        args[0][i] = math.nan
                return None
            try:
                return fn(*args)
            except Exception as err:
                if not failures:
                    said = "; ".join(log[-3:])
                    failures.append(one_line(err).rstrip(".") + (f": {said}" if said else ""))
                if fills and len(args) >= 2:
                    for i in range(int(args[1])):
                        args[0][i] = math.nan
                return None

        return call

    def _event_iteration(self) -> None:
        """Update the discrete states until they settle; note the next time event."""
        fmu = self._fmu
        fmi2 = self.md.fmiVersion.startswith("2")
        for _ in range(MAX_EVENTS_PER_SAMPLE):
            result = self._call(
                "update its discrete states",
                fmu.newDiscreteStates if fmi2 else fmu.updateDiscreteStates,
            )
            more, terminate, _, _, time_defined, next_time = result
            if terminate:
                raise FmuError(f"the FMU asked to stop the simulation at t = {self._t:g} s")
            self._event_time = float(next_time) if time_defined else None
            if not more:
                return
        raise FmuError("the FMU's discrete states never settle (event iteration)")

    def _advance(self, t_end: float, u: float) -> None:
        """Hold the FMU input at ``u`` from the present time to ``t_end`` (s, FMU time)."""
        if u != self._u:
            self._set_real(self._in, u)
            self._u = u
            if self._solver is not None:  # the input steps: restart the integrator here
                self._call("restart the integrator", self._solver.reset, self._t)
        if self._cosim:
            self._do_step(t_end)
        else:
            self._integrate(t_end)
        self._t = t_end

    def _do_step(self, t_end: float) -> None:
        fmu = self._fmu
        h = t_end - self._t
        result = self._call(f"step from t = {self._t:g} s", fmu.doStep, self._t, h)
        if not self.md.fmiVersion.startswith("2") and result is not None:
            _, terminate, early, last = result
            if terminate:
                raise FmuError(f"the FMU asked to stop the simulation at t = {self._t:g} s")
            if early and last < t_end - TIME_EPS * max(1.0, abs(t_end)):
                raise FmuError(f"the FMU returned early from its step, at t = {last:g} s")

    def _integrate(self, t_end: float) -> None:
        """Model exchange: CVode from the present time to ``t_end``, through the FMU's time
        and state events."""
        fmu = self._fmu
        needs_step = bool(self.md.modelExchange.needsCompletedIntegratorStep)
        t = self._t
        for _ in range(MAX_EVENTS_PER_SAMPLE):
            if t >= t_end - TIME_EPS * max(1.0, abs(t_end)):
                return
            target = t_end
            ev = self._event_time
            if ev is not None and t < ev < target:
                target = ev
            try:
                state_event, _, t = self._solver.step(t, target)
            except Exception as err:
                why = self._failures[0] if self._failures else one_line(err)
                raise FmuError(f"the integrator failed at t = {t:g} s: {why}") from None
            if self._failures:
                raise FmuError(
                    f"the FMU failed in the integrator at t = {t:g} s: {self._failures[0]}"
                )
            self._call("set the time", fmu.setTime, t)
            step_event = False
            if needs_step:
                step_event, terminate = self._call(
                    "complete an integrator step", fmu.completedIntegratorStep
                )
                if terminate:
                    raise FmuError(f"the FMU asked to stop the simulation at t = {t:g} s")
            time_event = ev is not None and abs(t - ev) <= TIME_EPS * max(1.0, abs(ev))
            if state_event or step_event or time_event:
                self._call("enter event mode", fmu.enterEventMode)
                self._t = t
                self._event_iteration()
                self._call("enter continuous-time mode", fmu.enterContinuousTimeMode)
                self._call("restart the integrator", self._solver.reset, t)
        raise FmuError(f"more than {MAX_EVENTS_PER_SAMPLE} events in one sample at t = {t:g} s")

    # --- the ProcessModel protocol --------------------------------------------------------

    def step(self, op: float) -> float:
        """Hold ``op`` (%) one sample (delayed by ``delay``); the PV at its end."""
        if self._fmu is None or self._failed:
            raise FmuError("the FMU is not running (it failed, or was never reset)")
        try:
            return self._step(op)
        except FmuError:
            self._mark_failed()
            raise

    def _step(self, op: float) -> float:
        self._ops.appendleft(float(op))
        start = self._t0 + self._k * self.sample_time
        end = self._t0 + (self._k + 1) * self.sample_time
        if self._frac > 0.0:  # the output of n+1 samples ago is still arriving for a while
            split = start + self._frac * self.sample_time
            self._advance(split, self._to_input(self._ops[self._n + 1]))
        self._advance(end, self._to_input(self._ops[self._n]))
        self._k += 1
        return self._lag.push(self._get_real(self._out))

    def disturbance_names(self) -> tuple[str, ...]:
        return tuple(self._dist)

    def set_disturbance(self, name: str, value: float) -> None:
        """Set the FMU input mapped to ``name`` (its own units), from now on."""
        if name not in self._dist:
            raise KeyError(name)
        value = finite(name, value)
        if self._fmu is not None:
            self._set_real(self._dist[name], value)
        self.disturbances[name] = value
