"""The recorded runs for the page: the list, each run's report figure as SVG, two compared.

The figures are the logger's own (``services.logger.report``: the same as ``autotune
report``), drawn as SVG; two runs compared are the logger's comparison (``compare``) where it
exists, else the two runs' rows of ``autotune runs`` side by side. The calls into the logger
are here only.
"""

from __future__ import annotations

import importlib
import io
from pathlib import Path
from typing import Any

from services.logger import report
from services.logger.commands.runs import summarize
from shared.errors import AutotuneError, ConfigError, one_line


def run_rows(runs: Path) -> list[dict[str, Any]]:
    """Every run file in ``runs`` as ``autotune runs --json`` lists it, newest last."""
    if not runs.is_dir():
        return []
    return [summarize(p) for p in sorted(runs.glob("*.mcap"))]


def run_file(runs: Path, name: str) -> Path:
    """The run file ``name`` in ``runs``: a plain ``.mcap`` file name, nothing outside."""
    if not name or Path(name).name != name or not name.endswith(".mcap"):
        raise ConfigError(f"file {name!r}: not the name of a run file (NAME.mcap in --runs)")
    path = runs / name
    if not path.is_file():
        raise ConfigError(f"file {name}: no such run in {runs}")
    return path


def report_svg(path: Path) -> bytes:
    """The run's report figure as SVG; AutotuneError with one line when it cannot be drawn."""
    render = getattr(report, "render", None)
    try:
        if render is not None:
            return render(path, "svg")
        fig = report.build_figure(report.load_series(path))
        out = io.BytesIO()
        fig.savefig(out, format="svg")
        return out.getvalue()
    except (ValueError, OverflowError) as err:
        why = one_line(err)
        raise AutotuneError(f"{path.name}: cannot plot the recorded series: {why}") from None


def compare_runs(a: Path, b: Path) -> dict[str, Any]:
    """Two runs' figures side by side: the logger's ``compare(a, b)`` where it has one, else
    their rows of ``autotune runs``."""
    try:
        logger_compare = importlib.import_module("services.logger.compare").compare
    except (ImportError, AttributeError):
        logger_compare = None
    if logger_compare is not None:
        return {"kind": "compare", "compare": logger_compare(a, b)}
    return {"kind": "rows", "rows": [summarize(a), summarize(b)]}
