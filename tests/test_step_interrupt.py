"""Ctrl-C of ``autotune step`` once it holds the loop: the loop is restored, and the command
says so in one line with the loop's state, as ``autotune tune`` does; it said only "autotune
step: interrupted" (helper trial), leaving the operator to wonder what the loop was left in."""

from __future__ import annotations

import contextlib

import pytest

from services.autotuner.commands import step, tune
from services.autotuner.identify.step_test import StepTestAborted, StepTestConfig
from services.autotuner.loop_client import PlantLost
from services.autotuner.step_run import run_step_test
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import ModeCommand
from tests.cli_run import run_cli


class CtrlCAfterTheStep(LocalLoopClient):
    """Ctrl-C comes once the output held in manual has been stepped."""

    held: float | None = None

    def samples(self, *args, **kw):
        if self.held is None and self.sim.mode == "manual":
            self.held = self.sim.op  # in auto, the test holds the mean output it measured
        if self.held is not None and self.sim.op != self.held:
            raise KeyboardInterrupt
        return super().samples(*args, **kw)


@pytest.mark.parametrize("mode", ["auto", "manual"])
def test_an_interrupted_step_says_what_it_left(monkeypatch, capsys, mode):
    sim = build_plant({"seed": 1, "loops": {"x": {"model": "heat_exchanger"}}})["x"]
    LocalLoopClient(sim).command(ModeCommand(loop="x", mode=mode, source="test"))
    op_before = sim.op
    client = CtrlCAfterTheStep(sim, source="autotune-step")
    monkeypatch.setattr(step, "open_session", lambda *a, **kw: contextlib.nullcontext(None))
    monkeypatch.setattr(step, "wait_for_loop", lambda *a, **kw: None)
    monkeypatch.setattr(step, "LoopClient", lambda *a, **kw: client)
    monkeypatch.setattr(
        tune, "loop_state", lambda session, prefix, loop: f"loop {loop} now: {sim.mode}"
    )
    code, out, err = run_cli(capsys, "step", "x", "--size", "5")
    assert code == 130 and out == "", (code, out, err)
    assert client.held is not None and sim.mode == mode  # stepped in manual, then restored
    if mode == "manual":
        assert sim.op == op_before
    said = f"step test of x interrupted; loop restored ({mode}, output {op_before:g} %); "
    assert f"{said}loop x now: {mode}\n" in err, err
    assert err.endswith("autotune step: interrupted\n"), err


class SilentAfterTheStep(LocalLoopClient):
    """The plant falls silent (paused, cut off) once the output held in manual is stepped;
    its loop answers again for the restore (as a plant resumed does)."""

    held: float | None = None
    silent = True

    def samples(self, *args, **kw):
        if self.held is None and self.sim.mode == "manual":
            self.held = self.sim.op
        if self.silent and self.held is not None and self.sim.op != self.held:
            self.silent = False
            raise PlantLost("loop x: no message from the plant for 5 s")
        return super().samples(*args, **kw)


def test_a_plant_silent_mid_step_is_said_with_what_was_left():
    """A plant paused mid-step ended the command with "no message from the plant for 5 s"
    alone, nothing of the loop (helper trial): now with its restore."""
    sim = build_plant({"seed": 1, "loops": {"x": {"model": "heat_exchanger"}}})["x"]
    op_before = sim.op
    client = SilentAfterTheStep(sim, source="autotune-step-test")
    with pytest.raises(StepTestAborted) as stop:
        run_step_test(client, StepTestConfig(size=5.0))
    said = str(stop.value)
    assert said.startswith("loop x: no message from the plant for 5 s; ")
    assert f"loop restored (manual, {op_before:g} %)" in said
    assert (sim.mode, sim.op) == ("manual", op_before)
