"""Input from outside the product that once escaped its one-line refusals (a helper's fuzz):
a user's model raising a ``BaseException`` subclass (its loop was left unanswered, not
faulted), one whose ``__getattr__`` raises, one whose ``__init__`` blocks ``model check``;
JSON nested too deeply for Python's ``json`` (a RecursionError traceback per message in the
logger's and the tuner's logs, uncounted; ``runs`` exit 70); flags whose values overflowed
what they feed (``--load-timeout 1e10``, ``replay --rate 1e-308``, ``tune --node ""``)."""

from __future__ import annotations

import contextlib
import json
import threading
import time
from pathlib import Path

import pytest

from services.logger.commands.runs import _row
from services.plant_sim.plant_file import build_plant
from shared import json_text, wire
from shared.errors import AutotuneError
from tests.cli_run import run_cli

HERE = __name__


class _User:
    pv_units = "bar"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time: float, op0: float = 50.0):
        self.sample_time, self.op0, self.n = sample_time, op0, 0

    def reset(self) -> float:
        self.n = 0
        return 50.0

    def step(self, op: float) -> float:
        self.n += 1
        return 50.0 + 0.5 * (op - self.op0)

    def disturbance_names(self) -> tuple[str, ...]:
        return ()

    def set_disturbance(self, name: str, value: float) -> None:
        raise KeyError(name)


class Quit(BaseException):
    """Not an Exception: no ``except Exception`` takes it."""


class StepQuits(_User):
    def step(self, op: float) -> float:
        self.n += 1
        if self.n > 3:
            raise Quit("the valve's driver gave up")
        return 50.0 + 0.5 * (op - self.op0)


class StepInterrupts(_User):
    def step(self, op: float) -> float:
        raise KeyboardInterrupt


class AttributesRaise(_User):
    """Its own ``__getattr__`` raises for any attribute it lacks (``num``, ``den``)."""

    def __getattr__(self, name: str):
        raise RuntimeError(f"no {name} here")


class UnitsQuit(_User):
    @property
    def pv_units(self) -> str:
        raise Quit("no units today")


class UnitsExit(_User):
    @property
    def pv_units(self) -> str:
        raise SystemExit(3)


class SlowInit(_User):
    def __init__(self, sample_time: float, op0: float = 50.0):
        time.sleep(30.0)  # a device that never answers
        super().__init__(sample_time, op0)


class SlowReset(_User):
    def reset(self) -> float:
        time.sleep(5.0)  # a device that does not answer (5 s: the test's cost without a bound)
        return super().reset()


class StepBlocks(_User):
    def step(self, op: float) -> float:
        if self.n == 5:
            time.sleep(3.0)  # a device that does not answer (3 s: the test's cost without a bound)
        return super().step(op)


class StepBlocksCatching(_User):
    def step(self, op: float) -> float:
        if self.n == 5:
            for _ in range(3):  # swallows what interrupts it, and waits on
                with contextlib.suppress(Exception):
                    time.sleep(1.5)
        return super().step(op)


def _loop(cls: str):
    return build_plant({"seed": 1, "loops": {"u": {"model": f"{HERE}:{cls}", "sample_time": 1.0}}})[
        "u"
    ]


def _plant_file(tmp_path: Path, cls: str) -> Path:
    path = tmp_path / "plant.toml"
    path.write_text(f'[loops.u]\nmodel = "{HERE}:{cls}"\nsample_time = 1.0\n')
    return path


def test_a_step_raising_a_base_exception_faults_its_loop_there():
    loop = _loop("StepQuits")
    samples = loop.advance_many(10)
    assert loop.fault is not None and "the model's step() raised Quit" in loop.fault
    assert "the valve's driver gave up" in loop.fault
    # the 4th step raised: the advance ends at that sample, the fault said there
    assert [s.t for s in samples] == [1.0, 2.0, 3.0, 4.0] and loop.process.n == 4


def test_a_keyboard_interrupt_from_a_model_faults_its_loop_off_the_main_thread_only():
    """In a service's threads a KeyboardInterrupt can only be the model's (the services take
    Ctrl-C by a handler): the loop faults. In the main thread it may be the user's Ctrl-C
    (``model check``): it goes on up."""
    loop = _loop("StepInterrupts")
    worker = threading.Thread(target=loop.advance_many, args=(2,))
    worker.start()
    worker.join()
    assert loop.fault is not None and "raised KeyboardInterrupt" in loop.fault
    with pytest.raises(KeyboardInterrupt):
        _loop("StepInterrupts").advance_many(2)


def test_model_check_refuses_a_base_exception_in_one_line(tmp_path, capsys):
    code, _, err = run_cli(capsys, "model", "check", str(_plant_file(tmp_path, "StepQuits")))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "loops.u.model: refused: the model's step() raised Quit" in err


def test_model_check_of_a_model_whose_attribute_look_up_raises(tmp_path, capsys):
    """No transfer function is stated (``num`` raised): the ultimate point is read from the
    step response, 0.5·e^{-s}... (the model's own gain), not an exit 70."""
    code, out, err = run_cli(
        capsys, "model", "check", str(_plant_file(tmp_path, "AttributesRaise")), "--json"
    )
    assert code == 0, err
    (report,) = json.loads(out)["loops"]
    assert report["ku_exact"] is None and report["status"] == "ok"
    assert report["steps"][0]["gain"] == pytest.approx(0.5, rel=1e-9)


def test_model_check_bounds_a_model_that_blocks_as_it_loads(tmp_path, capsys):
    path = _plant_file(tmp_path, "SlowInit")
    code, _, err = run_cli(capsys, "model", "check", str(path), "--load-timeout", "0.5")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "still loading after 0.5 s (--load-timeout)" in err


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["plant", "--load-timeout", "1e10"], "--load-timeout 1e+10: must be > 0 and at most"),
        (["model", "check", "x.toml", "--load-timeout", "0"], "--load-timeout 0: must be > 0"),
        (["replay", "x.mcap", "--rate", "1e-308"], "--rate 1e-308: must be from 0.0001 to"),
        (["replay", "x.mcap", "--rate", "1e308"], "--rate 1e+308: must be from 0.0001 to"),
        (["tune", "hx1", "--node", ""], "--node: tuner id '' is not valid"),
        (["tune", "hx1", "--node", "a/b"], "--node: tuner id 'a/b' is not valid"),
        (["apply", "r1", "--node", ""], "--node: tuner id '' is not valid"),
    ],
)
def test_flags_that_overflowed_are_refused_in_one_line(argv, says, capsys):
    code, _, err = run_cli(capsys, *argv)
    assert code == 2 and len(err.strip().splitlines()) == 1 and says in err, err


def test_a_tuner_node_with_wildcards_is_still_any_matching_tuner(capsys):
    from shared.cli import check_tuner_node

    for node in ("*", "tuner*", "tuner"):
        check_tuner_node(node)


DEEP = "[" * 100_000


def test_json_nested_too_deeply_is_not_json_to_the_product():
    with pytest.raises(json.JSONDecodeError, match="nested too deeply"):
        json_text.loads(DEEP)
    # a bus message's attachment: not a replay's mark (no traceback, the message goes on)
    assert wire.replay_source(DEEP.encode()) is None
    assert wire.replay_source(wire.replay_attachment("a.mcap")) == "a.mcap"
    # a run file's recorded result: the file is listed as unreadable, with the reason
    with pytest.raises(AutotuneError, match="field result: not JSON"):
        _row(Path("x.mcap"), {"run_id": "r1", "loop": "x1", "result": DEEP})


@pytest.mark.parametrize(("cls", "raised"), [("UnitsQuit", "Quit"), ("UnitsExit", "SystemExit")])
def test_a_protocol_attribute_raising_anything_is_refused_in_one_line(
    cls, raised, tmp_path, capsys
):
    """``pv_units`` as a property that raised a BaseException subclass printed a traceback
    (model check, plant_sim); one that raised SystemExit(3) ended them with exit 3, silent."""
    code, _, err = run_cli(capsys, "model", "check", str(_plant_file(tmp_path, cls)))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert f".pv_units raised {raised}" in err


def test_demo_and_up_bound_a_model_that_blocks_as_they_check_the_plant_file(tmp_path, monkeypatch):
    """``autotune demo --plant`` and ``autotune up --plant`` build the file before anything
    starts; a model whose reset() blocked held both silent for good (user trial: 100 s and
    counting, where ``autotune plant`` refuses it after --load-timeout)."""
    import argparse

    from services import demo, up
    from services.plant_sim import load_bound
    from shared.errors import ConfigError

    path = _plant_file(tmp_path, "SlowReset")
    monkeypatch.setattr(demo, "LOAD_TIMEOUT", 0.5, raising=False)
    with pytest.raises(ConfigError) as err:
        demo.check_loop(str(path), "u", None)
    assert "loops.u.model" in str(err.value) and "still loading after 0.5 s" in str(err.value)

    parser = argparse.ArgumentParser()
    up.add_arguments(parser)
    args = parser.parse_args(["--plant", str(path)])
    monkeypatch.setattr(load_bound, "LOAD_TIMEOUT", 0.5)
    with pytest.raises(ConfigError) as err:
        up.load_config(args)
    assert "loops.u.model" in str(err.value) and "still loading after 0.5 s" in str(err.value)


@pytest.mark.parametrize("cls", ["StepBlocks", "StepBlocksCatching"])
def test_model_check_bounds_a_step_that_blocks(tmp_path, capsys, cls):
    """``model check`` of a model whose step() did not return (a device that never answers)
    never ended, silent (user trial); each call is now bounded by --load-timeout."""
    code, _, err = run_cli(
        capsys, "model", "check", str(_plant_file(tmp_path, cls)), "--load-timeout", "0.5"
    )
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "loops.u.model: refused: " in err and "has not returned after 0.5 s" in err, err
