"""The console page's number format (``fmt`` in console.js), run by node: d significant digits,
only the zeros after a decimal point dropped. The old pattern also dropped an integer's own
zeros: lvl2's Ti of 4000 s showed as "4 s" on its card."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from importlib.resources import files

import pytest

VALUES = [4000, 600, 10, 6.973, 15000, 0.1, 96.09, 1e-7, 120, 1000.5, -2500, None]
EXPECTED = [
    "4000",
    "600",
    "10",
    "6.973",
    "1.5e+4",
    "0.1",
    "96.09",
    "1e-7",
    "120",
    "1001",
    "-2500",
    "—",
]


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")
def test_numbers_keep_their_digits_and_lose_only_trailing_decimal_zeros():
    script = files("services.console").joinpath("static/console.js").read_text()
    (line,) = re.findall(r"^const fmt = .*$", script, flags=re.MULTILINE)
    out = subprocess.run(
        [
            "node",
            "-e",
            f"{line}\nconsole.log(JSON.stringify({json.dumps(VALUES)}.map((v) => fmt(v))))",
        ],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    assert json.loads(out.stdout) == EXPECTED


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")
def test_an_apply_run_is_listed_as_an_apply_not_as_a_test():
    """The console's runs table listed an ``autotune apply`` run (the page's Apply) as a relay
    run with no K_u or P_u; ``autotune runs`` says "apply"."""
    script = files("services.console").joinpath("static/console.js").read_text()
    (line,) = re.findall(r"^const runMethod = .*$", script, flags=re.MULTILINE)
    rows = [{"method": "relay", "applied_from": "04e4a18e25fa"}, {"method": "relay"}]
    out = subprocess.run(
        ["node", "-e", f"{line}\nconsole.log(JSON.stringify({json.dumps(rows)}.map(runMethod)))"],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    assert json.loads(out.stdout) == ["apply of 04e4a18e25fa", "relay"]


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")
def test_a_rule_unstable_on_the_model_shows_no_margins_or_overshoot():
    """The page showed cc-pid on lvl1 (unstable on the sampled model) with GM 0.92, PM -7.57°,
    an overshoot of 3404.4 % and a decay ratio of 1.22 as if they were figures; `autotune
    tune` says "UNSTABLE on the model"."""
    script = files("services.console").joinpath("static/console.js").read_text()
    lines = [
        re.findall(rf"^const {name} = .*$", script, flags=re.MULTILINE)[0]
        for name in ("fmt", "fixed", "robustCells")
    ]
    rows = [
        {"ms": None, "gain_margin": 0.92, "phase_margin_deg": -7.57, "overshoot_pct": 3404.4,
         "decay_ratio": 1.22, "stable": False},
        {"ms": 1.39, "gain_margin": 4.72, "phase_margin_deg": 57.8, "overshoot_pct": 16.9,
         "decay_ratio": 0.0, "stable": True},
        {"ms": 1.01, "gain_margin": 83.6, "phase_margin_deg": 89.0, "overshoot_pct": 0.0,
         "decay_ratio": None, "stable": True, "op_noise_pct": 0.6023},
    ]  # fmt: skip
    code = "\n".join(lines) + f"\nconsole.log(JSON.stringify({json.dumps(rows)}.map(robustCells)))"
    out = subprocess.run(
        ["node", "-e", code], capture_output=True, text=True, timeout=30, check=True
    )
    unstable, stable, quiet = json.loads(out.stdout)
    assert "UNSTABLE on the model" in unstable and "3404" not in unstable
    assert 'colspan="6"' in unstable  # across the output noise's column too
    assert stable == "<td>1.39</td><td>4.72</td><td>57.8</td><td>16.9</td><td>0.00</td><td>—</td>"
    # the output noise the gains make of the PV's (``design.output_noise``)
    assert quiet.endswith("<td>0.0</td><td>—</td><td>0.60</td>")
