"""The layers hold: the control core and the autotuner's identification and design code are pure
(no bus, no schema library, no file formats, no plotting, no CLI parsing), and no service package
imports another's, except the logger using the autotuner's pure code for offline analysis.

Modules are discovered by globbing the directories, so a new module is covered without editing
this file. Two checks: what a fresh interpreter has loaded after importing them (catches a heavy
dependency pulled in transitively), and each module's own import statements (catches a forbidden
import even when the dependency happens to be loaded by something else, such as scipy loading
argparse itself).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

PURE_DIRS = (
    "shared/control",
    "services/autotuner/identify",
    "services/autotuner/design",
    "services/autotuner/monitor",
)
HEAVY = ("zenoh", "pydantic", "mcap", "matplotlib")
SERVICE_PACKAGES = ("plant_sim", "autotuner", "logger", "offline")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules_in(directory: str) -> list[Path]:
    return sorted((ROOT / directory).rglob("*.py"))


def imported_names(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path``, relative ones resolved."""
    return imports_in(path.read_text(), module_name(path), path.name == "__init__.py")


def imports_in(source: str, module: str, is_package: bool) -> list[tuple[int, str]]:
    tree = ast.parse(source)
    package = module.split(".") if is_package else module.split(".")[:-1]
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            name = ".".join([*base, *([node.module] if node.module else [])])
            # ``from pkg import x`` as pkg.x: x may be a module, and an allowed submodule of a
            # package (services.autotuner.identify) must not pass for the whole package
            found += [(node.lineno, f"{name}.{alias.name}") for alias in node.names]
    return found


def under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def top(name: str) -> str:
    return name.split(".")[0]


def test_the_directories_hold_modules():
    """Guards the globbing: a moved directory must not make the checks below vacuous."""
    for directory in PURE_DIRS:
        names = [p.name for p in modules_in(directory)]
        assert "__init__.py" in names and len(names) >= 4, (directory, names)


def test_the_pure_layers_load_no_bus_schema_file_or_plot_library():
    names = [module_name(p) for d in PURE_DIRS for p in modules_in(d)]
    code = (
        "import importlib, json, sys\n"
        "first = {}\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        "    for m in list(sys.modules):\n"
        f"        if m.split('.')[0] in {HEAVY!r}:\n"
        "            first.setdefault(m.split('.')[0], name)\n"
        "print(json.dumps(first))\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout) == {}, "library: the first module after which it was loaded"


# the standard library's CLI parsing, processes, threads, files, sockets and logging: the pure
# layers compute; what they find travels back as return values and events, not I/O
NO_IO = (
    "argparse", "asyncio", "http", "logging", "multiprocessing", "os", "pathlib", "selectors",
    "shutil", "signal", "socket", "sqlite3", "subprocess", "sys", "tempfile", "threading",
    "urllib",
)  # fmt: skip


def allowed_in_control(name: str) -> bool:
    """shared/control/ imports numpy, scipy, the standard library (its I/O aside) and itself."""
    if top(name) in ("numpy", "scipy", "__future__") or under(name, "shared.control"):
        return True
    return top(name) in sys.stdlib_module_names and top(name) not in NO_IO


def allowed_in_autotuner_core(name: str) -> bool:
    """identify/, design/ and monitor/ add the project's plain error types, each other, and
    ``services.autotuner.parts`` (how a step's independent parts are computed: a type and a
    function of the standard library's, checked below)."""
    return (
        allowed_in_control(name)
        or under(name, "shared.errors")
        or under(name, "services.autotuner.parts")
        or under(name, "services.autotuner.identify")
        or under(name, "services.autotuner.design")
        or under(name, "services.autotuner.monitor")
    )


def bad_imports(directory: str, allowed) -> list[str]:
    return [
        f"{p.relative_to(ROOT)}:{line}: {name}"
        for p in modules_in(directory)
        for line, name in imported_names(p)
        if not allowed(name)
    ]


def test_the_control_core_imports_only_numpy_scipy_and_the_standard_library():
    assert bad_imports("shared/control", allowed_in_control) == []


@pytest.mark.parametrize(
    "directory",
    ["services/autotuner/identify", "services/autotuner/design", "services/autotuner/monitor"],
)
def test_identification_and_design_import_only_the_core(directory):
    assert bad_imports(directory, allowed_in_autotuner_core) == []


def test_the_parts_module_imports_only_the_standard_library():
    path = ROOT / "services/autotuner/parts.py"
    assert [name for _, name in imported_names(path) if not allowed_in_control(name)] == []


def test_shared_imports_no_service():
    found = [
        f"{p.relative_to(ROOT)}:{line}: {name}"
        for p in modules_in("shared")
        for line, name in imported_names(p)
        if under(name, "services")
    ]
    assert found == []


# What each service package may import of the others. services/offline composes plant_sim's
# core with the autotuner (benchmark, in-process loop) and is exempt, as are the top-level
# composition modules (services/cli.py, demo.py, up.py, stack.py...). The logger replays runs
# offline with the autotuner's pure code (identification and design, the request check
# included), and nothing else of it.
MAY_IMPORT = {
    "plant_sim": (),
    "autotuner": (),
    "logger": ("services.autotuner.identify", "services.autotuner.design"),
}


def test_identification_does_not_import_design():
    """Layers go one way: design builds on what identification found, never the reverse."""
    found = [
        f"{p.relative_to(ROOT)}:{line}: {name}"
        for p in modules_in("services/autotuner/identify")
        for line, name in imported_names(p)
        if under(name, "services.autotuner.design")
    ]
    assert found == []


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_no_service_imports_another_services_package(package):
    others = [f"services.{p}" for p in SERVICE_PACKAGES if p != package]
    found = [
        f"{p.relative_to(ROOT)}:{line}: {name}"
        for p in modules_in(f"services/{package}")
        for line, name in imported_names(p)
        if any(under(name, o) for o in others)
        and not any(under(name, a) for a in MAY_IMPORT[package])
    ]
    assert found == []


def test_the_import_walker_sees_every_form():
    """The checks above are only as good as imports_in: pin it on each import form."""
    source = (
        "import zenoh\nimport numpy.linalg as la\nfrom . import runs\n"
        "from ..analysis import f\nfrom services.autotuner import tuning\n"
        "def g():\n    import pydantic\n"
    )
    names = {n for _, n in imports_in(source, "services.logger.commands.x", is_package=False)}
    assert names == {
        "zenoh",
        "numpy.linalg",
        "services.logger.commands.runs",
        "services.logger.analysis.f",
        "services.autotuner.tuning",
        "pydantic",
    }


def test_the_rules_refuse_what_the_issue_names():
    """Pin the allow-lists on the imports the layers must never make."""
    for name in ("zenoh", "pydantic.fields", "mcap.reader", "matplotlib", "argparse"):
        assert not allowed_in_autotuner_core(name), name
    for name in ("shared.messages", "shared.wire", "services.autotuner.tuning", "services.cli"):
        assert not allowed_in_autotuner_core(name), name
    assert not allowed_in_control("shared.errors") and not allowed_in_control("threading")
    for name in ("numpy.linalg", "scipy.signal", "math", "shared.control.lti.discretize"):
        assert allowed_in_control(name), name


def test_the_commands_that_check_a_request_load_no_optimiser():
    """`autotune tune` and `apply` check their request against the methods' registry before
    sending it, and fit nothing: scipy (its optimisers, half a second of a command's start)
    is loaded by the experiments that fit, when one is built."""
    code = (
        "import sys\n"
        "import services.autotuner.commands.tune, services.autotuner.commands.apply\n"
        "from services.autotuner.identify import methods\n"
        "assert 'scipy' not in sys.modules, 'scipy loaded'\n"
        "methods.method('ramp')\n"
        "assert 'scipy' not in sys.modules, 'scipy loaded by the registry'\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 0, run.stderr
