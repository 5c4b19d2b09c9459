"""``autotune up`` and ``demo`` bringing their services up: a setting the plant refuses is
refused where it is read, naming the settings file's field; a service that ends as the stack
starts ends the wait at once (``seed = -4`` in a config file: the plant's flag error, then 40 s
of waiting, then "the tuner did not come up (plant exited)")."""

from __future__ import annotations

import subprocess
import sys

import pytest

from services.launcher import free_tcp_port
from services.stack import Stack
from shared.errors import AutotuneError
from shared.session import ZenohSettings
from tests.cli_run import run_cli


@pytest.mark.parametrize(
    ("setting", "says"),
    [
        ("seed = -4", "seed: Input should be greater than or equal to 0"),
        ("speed = 5000.0", "speed: Input should be less than or equal to 1000"),
        ("speed = nan", "speed: Input should be a finite number"),
    ],
)
def test_a_config_setting_the_plant_would_refuse_is_refused_naming_it(
    setting, says, tmp_path, capsys
):
    cfg = tmp_path / "up.toml"
    cfg.write_text(setting + "\n")
    code, _, err = run_cli(capsys, "up", "--config", str(cfg))
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{cfg}: {says}" in err


def test_a_service_that_ends_as_the_stack_starts_ends_the_wait():
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    bus = ZenohSettings(mode="peer", listen=(endpoint,), no_multicast_scouting=True)
    stack = Stack("startx", bus)
    stack.procs["plant"] = subprocess.Popen([sys.executable, "-c", "raise SystemExit(2)"])
    stack.procs["plant"].wait()
    with pytest.raises(AutotuneError) as err:
        stack.wait_ready(["startx/plant_sim/plant/alive"], timeout=60.0)
    assert str(err.value) == (
        "plant (exit 2) ended as the stack started, before startx/plant_sim/plant/alive came "
        "up (its own error says why)"
    )
