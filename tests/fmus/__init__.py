"""The tests' FMUs: Python classes in this folder, packaged as real FMUs at test time.

pythonfmu builds the FMI 2.0 co-simulation ones (fmu_fopdt, fmu_heat_exchanger, fmu_tank,
fmu_faulty), pythonfmu3 the FMI 3.0 ones (fmu_fopdt3 co-simulation, fmu_lag_me model
exchange). Building is zipping the class beside a prebuilt binary (well under a second each).
No Python tool builds an FMI 2.0 model-exchange FMU, so lag_me2.c is compiled with the
machine's C compiler against FMPy's FMI headers (skipped where there is none). ``build_all``
does it all once per test process; ``damaged`` makes the bad-FMU corpus from them.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import zipfile
from pathlib import Path

import pytest

HERE = Path(__file__).parent
FMI2 = {
    "Fopdt": "fmu_fopdt.py",
    "HeatExchanger": "fmu_heat_exchanger.py",
    "Tank": "fmu_tank.py",
    "Faulty": "fmu_faulty.py",
}
FMI3 = {"Fopdt3": "fmu_fopdt3.py", "LagMe": "fmu_lag_me.py"}
_built: dict[str, Path] = {}


def build_all(dest: Path) -> dict[str, Path]:
    """Every test FMU by model name; built into ``dest`` on the first call of the process."""
    if _built:
        return dict(_built)
    builder2 = pytest.importorskip("pythonfmu.builder", reason="pythonfmu builds the test FMUs")
    builder3 = pytest.importorskip("pythonfmu3.builder", reason="pythonfmu3 builds FMI 3.0 FMUs")
    dest.mkdir(parents=True, exist_ok=True)
    for name, script in FMI2.items():
        _built[name] = builder2.FmuBuilder.build_FMU(HERE / script, dest=dest)
    for name, script in FMI3.items():
        _built[name] = builder3.FmuBuilder.build_FMU(HERE / script, dest=dest)
    # the same FOPDT, declared unable to vary its communication step
    _built["FopdtFixedStep"] = builder2.FmuBuilder.build_FMU(
        HERE / FMI2["Fopdt"],
        dest=dest / "FopdtFixedStep.fmu",
        canHandleVariableCommunicationStepSize=False,
    )
    me2 = compile_lag_me2(dest)
    if me2 is not None:
        _built["LagMe2"] = me2
    return dict(_built)


def compile_lag_me2(dest: Path) -> Path | None:
    """LagMe2.fmu: lag_me2.c compiled for linux64 beside lag_me2.xml; None without a C
    compiler (or off Linux x86-64)."""
    import fmpy

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None or fmpy.platform != "linux64":
        return None
    headers = Path(fmpy.__file__).parent / "c-code"
    library = dest / "LagMe2.so"
    built = subprocess.run(
        [
            cc,
            "-shared",
            "-fPIC",
            "-O2",
            f"-I{headers}",
            str(HERE / "lag_me2.c"),
            "-o",
            str(library),
            "-lm",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    if built.returncode != 0:
        return None
    fmu = dest / "LagMe2.fmu"
    with zipfile.ZipFile(fmu, "w") as z:
        z.write(HERE / "lag_me2.xml", "modelDescription.xml")
        z.write(library, "binaries/linux64/LagMe2.so")
    return fmu


def rewrite(src: Path, dest: Path, edit) -> Path:
    """A copy of the FMU ``src`` with each member passed through ``edit(name, data)``, which
    returns new bytes, or None to leave the member out."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dest, "w") as zout:
        for item in zin.infolist():
            data = edit(item.filename, zin.read(item.filename))
            if data is not None:
                zout.writestr(item.filename, data)
    return dest


def _md(edit_text):
    def edit(name: str, data: bytes) -> bytes:
        return edit_text(data.decode()).encode() if name == "modelDescription.xml" else data

    return edit


def with_output_range(src: Path, dest: Path, output: str, unit: str, lo: float, hi: float) -> Path:
    """The FMU with ``unit``, ``min`` and ``max`` declared on its output, as Modelica tools do."""

    def edit(text: str) -> str:
        pattern = rf'(<ScalarVariable name="{output}"[^>]*>\s*<Real)'
        text = re.sub(pattern, rf'\1 unit="{unit}" min="{lo}" max="{hi}"', text, count=1)
        units = f'<UnitDefinitions><Unit name="{unit}"/></UnitDefinitions>\n\t<LogCategories>'
        return text.replace("<LogCategories>", units, 1)

    return rewrite(src, dest, _md(edit))


def damaged(fmus: dict[str, Path], dest: Path) -> dict[str, Path]:
    """The bad-FMU corpus: files that are not FMUs or are broken FMUs."""
    dest.mkdir(parents=True, exist_ok=True)
    src = fmus["Fopdt"]
    out = {}
    text = dest / "text.fmu"
    text.write_text("not a zip archive\n")
    out["not a zip"] = text
    out["no model description"] = rewrite(
        src, dest / "nomd.fmu", lambda n, d: None if n == "modelDescription.xml" else d
    )
    out["xml not valid"] = rewrite(
        src, dest / "badxml.fmu", lambda n, d: b"<fmiModel" if n == "modelDescription.xml" else d
    )
    out["fmi 1.0"] = rewrite(
        src, dest / "fmi1.fmu", _md(lambda t: t.replace('fmiVersion="2.0"', 'fmiVersion="1.0"'))
    )
    out["no binary here"] = rewrite(
        src, dest / "nobin.fmu", lambda n, d: None if n.startswith("binaries/linux64") else d
    )
    out["binary broken"] = rewrite(
        src,
        dest / "badbin.fmu",
        lambda n, d: b"\x7fELF garbage" if n.startswith("binaries/linux64") else d,
    )
    folder = dest / "folder.fmu"
    folder.mkdir(exist_ok=True)
    out["a folder"] = folder
    copy = dest / "copy.fmu"
    shutil.copy(src, copy)
    out["fine"] = copy
    return out
