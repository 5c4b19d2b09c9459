"""``autotune model check`` of a user's class whose ``reset()`` does not reset it (user
trial): a first order plus dead time (gain 2, τ 10 s, delay 2 s) whose reset() kept its state
was read "+2 %: 2, -2 %: 4, +10 %: 2.4, -10 %: 4 (NONLINEAR, spread 100 %)", gain 3, K_u
2.8323 (true: gain 2, K_u 4.2512). README: the check tells you when reset does not leave the
process at rest. Now refused in one line, exit 2."""

from __future__ import annotations

import math
from collections import deque

import pytest

from services.plant_sim.model_check import check_loop
from services.plant_sim.plant_file import build_plant
from tests.cli_run import run_cli

HERE = "tests.test_model_check_reset"


class Fopdt:
    """2·e^{−2s}/(10s + 1) about PV 50 at op0, exactly sampled."""

    pv_units = "%"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time, op0=50.0):
        self.sample_time, self.op0 = sample_time, op0
        self.nd = round(2.0 / sample_time)

    def reset(self):
        self.x = 50.0
        self.ops = deque([self.op0] * (self.nd + 1), maxlen=self.nd + 1)
        return self.x

    def step(self, op):
        self.ops.appendleft(op)
        a = math.exp(-self.sample_time / 10.0)
        self.x = a * self.x + (1 - a) * (50.0 + 2.0 * (self.ops[self.nd] - self.op0))
        return self.x

    def disturbance_names(self):
        return ()

    def set_disturbance(self, name, value):
        raise KeyError(name)


class KeepsState(Fopdt):
    """reset() the first time only: then it returns the PV where the last run left it."""

    def reset(self):
        if not hasattr(self, "x"):
            super().reset()
        return self.x


class KeepsDelayLine(Fopdt):
    """reset() puts the lag back at rest and returns PV 50, but keeps the dead time's line of
    past outputs: each run starts with the last one's outputs still on their way."""

    def reset(self):
        ops = getattr(self, "ops", None)
        super().reset()
        if ops is not None:
            self.ops = ops
        return self.x


def check(cls: str):
    table = {"model": f"{HERE}:{cls}", "sample_time": 0.1}
    return check_loop("u1", build_plant({"loops": {"u1": table}})["u1"])


def test_a_model_that_resets_is_read_as_it_is():
    r = check("Fopdt")
    assert r.refused is None
    assert r.gain == pytest.approx(2.0, rel=1e-3)


@pytest.mark.parametrize("cls", ["KeepsState", "KeepsDelayLine"])
def test_a_reset_that_keeps_the_state_is_refused(cls):
    r = check(cls)
    assert r.refused is not None and "\n" not in r.refused, r.gains
    assert "reset() does not reset the model" in r.refused, r.refused


def test_the_command_says_so_in_one_line_exit_2(tmp_path, capsys):
    plant = tmp_path / "p.toml"
    plant.write_text(f'[loops.u1]\nmodel = "{HERE}:KeepsState"\nsample_time = 0.1\n')
    code, out, err = run_cli(capsys, "model", "check", str(plant))
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "loops.u1.model: refused: reset() does not reset the model" in err
    assert "REFUSED" in out and "gain" not in out
