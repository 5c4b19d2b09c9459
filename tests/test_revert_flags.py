"""``autotune revert``'s ``--to`` and ``--steps`` name the change to undo two ways: one or the
other. ``--to RUN --steps 1`` was let through while ``--to RUN --steps 3`` was refused
(argparse took a value equal to the default for the flag's absence: helper trial)."""

from __future__ import annotations

import pytest

from tests.cli_run import run_cli


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--to", "r1", "--steps", "1"], "argument --steps: not allowed with argument --to"),
        (["--to", "r1", "--steps", "3"], "argument --steps: not allowed with argument --to"),
        (["--steps", "1", "--to", "r1"], "argument --to: not allowed with argument --steps"),
    ],
)  # fmt: skip
def test_to_and_steps_are_refused_together_whatever_the_value(capsys, argv, says):
    code, out, err = run_cli(capsys, "revert", "flow1", *argv)
    assert code == 2 and out == "", (code, out, err)
    assert err == f"autotune revert: error: {says} (see autotune revert --help)\n", err


def test_steps_below_one_is_refused_before_the_bus(capsys, tmp_path):
    code, out, err = run_cli(capsys, "revert", "flow1", "--steps", "0", "--runs", str(tmp_path))
    assert (code, out, err) == (2, "", "autotune revert: error: --steps 0: must be ≥ 1\n")
