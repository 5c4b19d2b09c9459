"""Plants written as plant files, and the `autotune` CLI run as a process against them."""

from __future__ import annotations

import json
import subprocess
import sys

THIRD = {"num": [6.0], "den": [1.0, 6.0, 11.0, 6.0], "delay": 0.0, "sample_time": 0.002}
HX = {"num": [1.0], "den": [600.0, 70.0, 1.0], "delay": 5.0, "sample_time": 0.05}


def plant_toml(loop: str, p: dict, noise: float = 0.0, extra: str = "") -> str:
    return (
        f'seed = 3\n[loops.{loop}]\nmodel = "transfer_function"\nnum = {p["num"]}\n'
        f"den = {p['den']}\ndelay = {p['delay']}\nsample_time = {p['sample_time']}\n"
        f"noise_std = {noise}\n{extra}"
    )


def autotune(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "services.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def tune(plant, loop: str, *args: str) -> dict:
    """``autotune tune loop --json`` against a RunningPlant; the result as a dict."""
    run = autotune("tune", loop, "--json", *args, *plant.cli_args())
    assert run.stdout, run.stderr
    return json.loads(run.stdout)
