"""``autotune model check`` of a user's model that is slow but returns, or that calls itself.

A step() that took 50 ms was within the per-call bound (``--load-timeout``), but the check
makes tens of thousands of calls: a 5 s lag at 0.1 s samples took 143 s, silent, and a 300 s
lag would have taken 2.3 h (2816 and 164,096 calls; helper trial). The calls of a loop's
model are now bounded in all by ``--model-time``, and the check refuses one as soon as its
look ahead (the calls it still needs × the cost per call so far) passes it.

A step() that called its own reset() cleared its call's bound as the reset returned: it then
slept 30 s past a 0.5 s ``--load-timeout`` and was checked "ok" (helper trial).
"""

from __future__ import annotations

import math
import time

import pytest

from services.plant_sim import load_bound
from services.plant_sim.model_check import FIRST_WINDOW, REST_SAMPLES, check_model
from tests.cli_run import run_cli
from tests.lag_model import Lag

HERE = "tests.test_model_check_slow"


class FakeClock:
    """The wall clock the bound reads, moved on only by the model's calls."""

    t = 0.0

    def __call__(self) -> float:
        return self.t


CLOCK = FakeClock()


class Slow(Lag):
    """A lag of ``tau`` whose reset() and step() take 50 ms each on the bound's clock (none
    of the test's time)."""

    def __init__(self, sample_time, op0=50.0, tau=5.0):
        super().__init__(sample_time, op0)
        self.tau = tau

    def reset(self):
        CLOCK.t += 0.05
        return super().reset()

    def step(self, op):
        CLOCK.t += 0.05
        self.n += 1
        a = math.exp(-self.sample_time / self.tau)
        self.x = a * self.x + (1 - a) * (50.0 + op - self.op0)
        return self.x


class SlowsDown(Lag):
    """Fast for its run at rest, then 10 ms a step (really): no look ahead sees it coming."""

    def step(self, op):
        if self.n > REST_SAMPLES:
            time.sleep(0.01)
        return super().step(op)


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


class BlocksFifth(Lag):
    """Fast, but its 5th step() blocks (up to 3 s, so a check that misses it ends)."""

    def step(self, op):
        if self.n == 4:
            end = time.monotonic() + 3.0
            while time.monotonic() < end:
                time.sleep(0.01)
        return super().step(op)


@pytest.fixture
def fake_clock(monkeypatch):
    CLOCK.t = 0.0
    monkeypatch.setattr(load_bound, "clock", CLOCK, raising=False)
    return CLOCK


def plant(tmp_path, cls: str, extra: str = ""):
    path = tmp_path / "p.toml"
    path.write_text(f'[loops.u1]\nmodel = "{HERE}:{cls}"\nsample_time = 0.1\n{extra}')
    return str(path)


def test_a_slow_model_is_refused_from_its_first_calls(tmp_path, capsys, fake_clock):
    """A 300 s lag at 0.1 s samples, 50 ms a call: 164,096 steps, 2.3 h. The look ahead
    before each window of the first step (a reset and 64 steps, then 128, 256, …) is that
    window and four more runs as long (three steps, the first again). Before the window of
    4096: 257 + 65 + 64 + … + 1024 = 2306 calls made (115.3 s), and 2048 + 4·4097 = 18,436
    ahead (921.8 s, 15.4 min): 1037.1 s past 600 s. Before the window of 2048 it was 1282
    made and 1024 + 4·2049 = 9220 ahead: 525.1 s, within."""
    code, out, err = run_cli(capsys, "model", "check", plant(tmp_path, "Slow", "tau = 300.0\n"))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert (
        "loops.u1.model: refused: tests.test_model_check_slow:Slow takes 50 ms a call "
        "(measured over 2,306 calls): the check needs some 18,436 more at least, 15.4 min, "
        "past its bound on the model's time (--model-time 600; 115 s spent): give the loop a "
        "longer sample_time (fewer samples to the same response), a faster model, or allow "
        "it with --model-time 1100 or more"
    ) in err, err
    assert "REFUSED: tests.test_model_check_slow:Slow takes 50 ms a call" in out


def test_a_slow_model_within_its_bound_is_checked(tmp_path, capsys, fake_clock):
    """A 5 s lag: each step's response is judged at its window of 512 samples (the last
    quarter's spread e^{−0.75·n·0.1/5} ≤ 5e-4 from n = 507), so the check is a reset and 256
    steps at rest, a reset and 512 steps for each of the four steps and the first again:
    2822 calls, 141.1 s at 50 ms. The look ahead is exact by the first step's last window:
    514 made, 256 + 4·513 = 2308 ahead (115.4 s). Within 150 s it is checked; past 140 s it
    is refused there."""
    code, out, err = run_cli(
        capsys, "model", "check", plant(tmp_path, "Slow"), "--model-time", "150"
    )
    assert code == 0 and "ok: nothing stands in the way" in out, err
    code, out, err = run_cli(
        capsys, "model", "check", plant(tmp_path, "Slow"), "--model-time", "140"
    )
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert (
        "Slow takes 50 ms a call (measured over 514 calls): the check needs some 2,308 more at "
        "least, 115 s, past its bound on the model's time (--model-time 140; 25.7 s spent): "
    ) in err, err
    assert "or allow it with --model-time 150 or more" in err, err


def test_the_look_ahead_is_the_checks_plan():
    """What the core asks before each run, for the 5 s lag: the run at rest and five first
    windows (257 + 5·65 = 582); the first step's windows (65 + 4·65 = 325, then 64 + 4·129 =
    580, …); a reason refuses the model with it, as it stands."""
    asked: list[int] = []

    def pace(calls: int) -> str | None:
        asked.append(calls)
        return "too slow, as it stands" if len(asked) == 4 else None

    report = check_model(Lag(0.1), sample_time=0.1)
    assert report.refused is None
    report = check_model(Lag(0.1), sample_time=0.1, pace=pace)
    assert report.refused == "too slow, as it stands"
    w = FIRST_WINDOW
    assert asked == [
        REST_SAMPLES + 1 + 5 * (w + 1),
        w + 1 + 4 * (w + 1),
        w + 4 * (2 * w + 1),
        2 * w + 4 * (4 * w + 1),
    ]


def test_a_model_that_slows_down_is_stopped_at_its_bound(tmp_path, capsys):
    """No look ahead foresaw it (its run at rest cost nothing): the bound on all its calls
    interrupts the call that reaches it."""
    t0 = time.monotonic()
    code, _, err = run_cli(
        capsys, "model", "check", plant(tmp_path, "SlowsDown"), "--model-time", "0.3"
    )
    assert time.monotonic() - t0 < 2.0
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert (
        "loops.u1.model: refused: the model's step() raised ModelTooSlow: "
        "tests.test_model_check_slow:SlowsDown has taken 0.3 s of wall time in "
    ) in err, err
    assert "its bound (--model-time 0.3), and the check is not done" in err, err


def test_a_call_that_blocks_at_the_bound_is_said_as_one(tmp_path, capsys):
    """Four quick calls, then one that blocks past --model-time 0.3 (within its per-call
    bound): said as the call it is, not averaged over them ("5 calls (1e+03 ms a call)":
    helper review)."""
    code, _, err = run_cli(
        capsys, "model", "check", plant(tmp_path, "BlocksFifth"), "--model-time", "0.3"
    )
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    # (its reset() and four quick step()s, then the fifth)
    assert "has taken 0.3 s of wall time in 6 calls of this check (5 of them took " in err, err
    assert "then one ran 0.3 s and had not returned), its bound (--model-time 0.3)" in err, err


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


@pytest.mark.parametrize(
    ("value", "says"),
    [
        ("0", "--model-time 0: must be > 0 and at most 86400 s"),
        ("-1", "--model-time -1: must be > 0 and at most 86400 s"),
        ("1e10", "--model-time 1e+10: must be > 0 and at most 86400 s"),
        ("nan", "--model-time nan: must be a finite number"),
    ],
)
def test_a_model_time_out_of_range_is_refused_in_one_line(value, says, capsys):
    code, _, err = run_cli(capsys, "model", "check", "x.toml", "--model-time", value)
    assert code == 2 and len(err.strip().splitlines()) == 1 and says in err, err
