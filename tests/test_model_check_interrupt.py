"""``autotune model check`` of a user's class whose step() raises ``KeyboardInterrupt`` (user
trial): it ended "autotune model check: interrupted", exit 130, as if the user had pressed
Ctrl-C. README: any BaseException from the model is the model's failure, one line, exit 2
(plant_sim faults the loop). A Ctrl-C (SIGINT) is still the user's: exit 130."""

from __future__ import annotations

import signal

import pytest

from tests.cli_run import run_cli
from tests.lag_model import Lag

HERE = "tests.test_model_check_interrupt"


class RaisesKeyboardInterrupt(Lag):
    def step(self, op):
        if self.n >= 200:
            raise KeyboardInterrupt("the model's own")
        return super().step(op)


class CtrlC(Lag):
    """The user presses Ctrl-C while its step() runs."""

    def step(self, op):
        if self.n == 200:
            signal.raise_signal(signal.SIGINT)
        return super().step(op)


@pytest.fixture(autouse=True)
def python_sigint():
    """Python's own SIGINT handler during each test, whatever a test before left (a CLI
    command run in process installs a service's stop handlers): the check must put back
    the handler it found."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def plant(tmp_path, cls: str):
    path = tmp_path / "p.toml"
    path.write_text(f'[loops.u1]\nmodel = "{HERE}:{cls}"\nsample_time = 0.1\n')
    return str(path)


def test_a_keyboard_interrupt_from_the_model_is_its_failure(tmp_path, capsys):
    code, out, err = run_cli(capsys, "model", "check", plant(tmp_path, "RaisesKeyboardInterrupt"))
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "loops.u1.model: refused: the model's step() raised KeyboardInterrupt" in err, err
    assert "REFUSED" in out
    # and Python's own handler is back once the command is done
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_the_users_ctrl_c_is_still_an_interruption(tmp_path, capsys):
    code, _, err = run_cli(capsys, "model", "check", plant(tmp_path, "CtrlC"))
    assert code == 130 and err.strip() == "autotune model check: interrupted", err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
