"""An FMU loop tuned through the services like any loop (issue 17, item 4).

``autotune up --plant`` serves the heat-exchanger FMU (built by pythonfmu from
tests/fmus/fmu_heat_exchanger.py) with the loop's 5 s dead time: e^{−5s}/((10s+1)(60s+1))
°C per %, sampled at 0.05 s as the transfer-function twin in test_tuner.py is. The relay's
K_u and P_u are within 1 % of the exact ultimate point computed here, and the logger records
the run like any other.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from services.launcher import free_tcp_port
from services.logger.mcap_io import read_run
from tests.exact import lag_ultimate
from tests.fmus import build_all
from tests.integration.tuning_cli import autotune

pytestmark = pytest.mark.integration

PLANT = """
seed = 3
[loops.hx3]
model = "fmu"
path = "HeatExchanger.fmu"           # beside the plant file
input = "valve"
output = "T_out"
op_scale = [0.0, 1.0]                # the FMU's valve is a fraction
op0 = 40.0
delay = 5.0
sample_time = 0.05
noise_std = 0.0
pv_range = [0.0, 150.0]
pv_units = "degC"
disturbances = { inlet_temp = "T_in" }
"""


@pytest.fixture(scope="session")
def fmus(tmp_path_factory) -> dict[str, Path]:
    return build_all(tmp_path_factory.mktemp("fmus"))


def test_an_fmu_loop_is_tuned_through_autotune_up_and_recorded(fmus, tmp_path):
    (tmp_path / "HeatExchanger.fmu").write_bytes(fmus["HeatExchanger"].read_bytes())
    plant = tmp_path / "plant.toml"
    plant.write_text(PLANT)
    runs = tmp_path / "runs"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    up = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "up",
            "--plant",
            str(plant),
            "--endpoint",
            endpoint,
            "--runs",
            str(runs),
            "--prefix",
            "fmut",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    watchdog = threading.Timer(120.0, up.kill)  # a stack that hangs fails the test, not CI
    watchdog.start()
    try:
        started = ""
        for line in up.stderr:
            started += line
            if "Ctrl-C stops them" in line:
                break
        assert len(re.findall(r"pid \d+", started)) == 3, started
        client = ["--prefix", "fmut", "-e", endpoint, "--no-multicast-scouting"]
        run = autotune("tune", "hx3", "--json", "--method", "relay", "--no-apply", *client)
        assert run.stdout, run.stderr
        r = json.loads(run.stdout)
        assert r["status"] == "proposed", r["reason"]
        ku, pu = lag_ultimate(1.0, (10.0, 60.0), 5.0)
        assert r["ku"] == pytest.approx(ku, rel=0.01)
        assert r["pu"] == pytest.approx(pu, rel=0.01)
        assert r["restored"] is True
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up.communicate(timeout=60)
        finally:
            watchdog.cancel()
    assert up.returncode == 0
    (recorded,) = runs.glob("*_hx3_relay_*.mcap")
    meta, records = read_run(recorded)
    info = json.loads(meta["info"])
    assert info["model"] == "fmu" and info["model_params"]["output"] == "T_out"
    assert info["description"].startswith("FMU HeatExchanger (FMI 2.0 co-simulation)")
    result = json.loads(meta["result"])
    assert result["status"] == "proposed" and (result["ku"], result["pu"]) == (r["ku"], r["pu"])
    assert records
