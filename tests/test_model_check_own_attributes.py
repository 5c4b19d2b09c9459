"""A user's class's own attributes (user trial): a ``disturbances`` property that raises was
accepted by the plant and by ``autotune model check`` (README: anything a property raises
refuses the file), and a class whose own ``sample_time`` (0.5 s) is not the plant file's
(0.1 s) was checked "ok" without a word."""

from __future__ import annotations

import pytest

from services.plant_sim.model_check import check_loop
from services.plant_sim.plant_file import build_plant
from shared.errors import ConfigError
from tests.cli_run import run_cli
from tests.lag_model import Lag

HERE = "tests.test_model_check_own_attributes"


class DisturbancesRaise(Lag):
    @property
    def disturbances(self):
        raise RuntimeError("prop boom")


class OwnSampleTime(Lag):
    def __init__(self, sample_time, op0=50.0):
        super().__init__(sample_time, op0)
        self.sample_time = 0.5


def table(cls: str) -> dict:
    return {"loops": {"u1": {"model": f"{HERE}:{cls}", "sample_time": 0.1}}}


def test_a_disturbances_property_that_raises_refuses_the_file(tmp_path, capsys):
    with pytest.raises(ConfigError, match=r"loops\.u1\.model: .*\.disturbances raised "):
        build_plant(table("DisturbancesRaise"))
    plant = tmp_path / "p.toml"
    plant.write_text(f'[loops.u1]\nmodel = "{HERE}:DisturbancesRaise"\nsample_time = 0.1\n')
    code, out, err = run_cli(capsys, "model", "check", str(plant))
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1, (out, err)
    assert ".disturbances raised RuntimeError: prop boom" in err


def test_a_class_whose_own_sample_time_differs_is_warned_of():
    r = check_loop("u1", build_plant(table("OwnSampleTime"))["u1"])
    said = [w for w in r.warnings if "sample_time" in w]
    assert len(said) == 1, r.warnings
    assert "own sample_time is 0.5 s, the plant file's 0.1 s" in said[0]
    # one that keeps the sample time it is given is not
    r = check_loop("u1", build_plant(table("Lag"))["u1"])
    assert not any("sample_time" in w for w in r.warnings), r.warnings
