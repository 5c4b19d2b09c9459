"""``autotune model check``'s reasons (user trial): a model returning 1e300 × its PV was told
"it ignores its input: the PV did not move in 0.1 s" (it moved by 5e301), and a plant file of
``sample_time = 1e-300`` "ignores its input … in 1.31072e-295 s". The first is said to blow up;
the second is refused at its sample_time, as a file."""

from __future__ import annotations

import pytest

from services.plant_sim.model_check import check_loop
from services.plant_sim.plant_file import build_plant
from shared.errors import ConfigError
from tests.cli_run import run_cli
from tests.lag_model import Lag

HERE = "tests.test_model_check_blow_up"


class Huge(Lag):
    """Its PV at reset, then 1e300 times it."""

    def step(self, op):
        return 1e300 * super().step(op)


def test_a_pv_that_blows_up_is_said_to(tmp_path, capsys):
    r = check_loop(
        "u1", build_plant({"loops": {"u1": {"model": f"{HERE}:Huge", "sample_time": 0.1}}})["u1"]
    )
    assert r.refused is not None and "ignores its input" not in r.refused, r.refused
    assert r.refused.startswith("its PV blows up: held at op0"), r.refused
    assert "5e+301" in r.refused and "\n" not in r.refused
    plant = tmp_path / "p.toml"
    plant.write_text(f'[loops.u1]\nmodel = "{HERE}:Huge"\nsample_time = 0.1\n')
    code, _, err = run_cli(capsys, "model", "check", str(plant))
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "loops.u1.model: refused: its PV blows up" in err, err


@pytest.mark.parametrize("sample_time", [1e-300, 5e-324, 1e-7])
def test_an_absurd_sample_time_is_refused_at_its_field(tmp_path, capsys, sample_time):
    table = {"model": "fopdt", "gain": 1.0, "time_constant": 5.0, "sample_time": sample_time}
    with pytest.raises(ConfigError, match=r"loops\.a\.sample_time: "):
        build_plant({"loops": {"a": table}})
    plant = tmp_path / "p.toml"
    plant.write_text(
        '[loops.a]\nmodel = "fopdt"\ngain = 1.0\ntime_constant = 5.0\n'
        f"sample_time = {sample_time!r}\n"
    )
    code, _, err = run_cli(capsys, "model", "check", str(plant))
    assert code == 2 and "loops.a.sample_time:" in err and "ignores its input" not in err, err


def test_a_microsecond_is_still_a_sample_time():
    table = {"model": "fopdt", "gain": 1.0, "time_constant": 5.0, "sample_time": 1e-6}
    assert build_plant({"loops": {"a": table}})["a"].settings.sample_time == 1e-6
