"""``autotune model check`` of a user's model that calls itself.

A step() that called its own reset() cleared its call's bound as the reset returned: it then
slept 30 s past a 0.5 s ``--load-timeout`` and was checked "ok" (helper trial).
"""

from __future__ import annotations

import time

from tests.cli_run import run_cli
from tests.lag_model import Lag

HERE = "tests.test_model_check_slow"


class NestedReset(Lag):
    """Its 5th step() calls its own reset(), then blocks in that same call (up to 2 s, so a
    check that misses it ends, "ok")."""

    def step(self, op):
        if self.n == 4:
            x = self.x
            self.reset()
            self.x = x
            end = time.monotonic() + 2.0
            while time.monotonic() < end:
                time.sleep(0.01)
        return super().step(op)


def plant(tmp_path, cls: str, extra: str = ""):
    path = tmp_path / "p.toml"
    path.write_text(f'[loops.u1]\nmodel = "{HERE}:{cls}"\nsample_time = 0.1\n{extra}')
    return str(path)


def test_a_nested_call_keeps_the_outer_calls_bound(tmp_path, capsys):
    t0 = time.monotonic()
    code, _, err = run_cli(
        capsys, "model", "check", plant(tmp_path, "NestedReset"), "--load-timeout", "0.3"
    )
    assert time.monotonic() - t0 < 1.5
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert (
        "loops.u1.model: refused: the model's step() raised CallTimeout: has not returned "
        "after 0.3 s (--load-timeout)"
    ) in err, err
