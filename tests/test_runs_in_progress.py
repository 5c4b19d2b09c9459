"""`autotune runs` tells a run a logger is still writing from a broken file."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from services.logger.commands import runs
from services.logger.commands.runs import summarize
from services.logger.mcap_io import MAGIC, being_written, read_run
from shared.errors import AutotuneError
from shared.messages import PidGains
from tests.recorded_run import record_in_process


def test_a_footerless_file_held_open_is_recording_and_unreadable_once_closed(tmp_path: Path):
    path = tmp_path / "20261202T061216Z_hx1_relay_c57d84e83047.mcap"
    f = path.open("wb")
    f.write(MAGIC + b"\x01\x02\x03")  # a header started, no footer yet
    f.flush()
    try:
        assert being_written(path)
        row = summarize(path)
        assert row["status"] == "recording", row
        assert (row["loop"], row["method"]) == ("hx1", "relay")
        assert row["started"] == "2026-12-02T06:12:16+00:00"  # as a readable row's, ISO
        # analyze, report, replay: a run in progress, not "try recover" (noticed last stop)
        with pytest.raises(AutotuneError, match=r"still being recorded .* wait for the run"):
            read_run(path)
    finally:
        f.close()
    assert not being_written(path)  # nobody has it open: a logger killed mid-run
    row = summarize(path)
    assert row["status"] == "unreadable" and (row["loop"], row["method"]) == ("hx1", "relay")
    with pytest.raises(AutotuneError, match="try: autotune recover"):
        read_run(path)


def test_a_finished_file_is_never_recording(tmp_path: Path):
    path = tmp_path / "x.mcap"
    with path.open("wb") as f:
        f.write(MAGIC + b"body" + MAGIC)
        f.flush()
        assert not being_written(path)  # ends with the magic: finished, open or not


def test_an_apply_run_is_listed_as_apply_not_as_another_test(tmp_path: Path, capsys):
    """An `autotune apply` run carries the recorded run's method: `runs` listed it as a
    second step test of the loop. It is listed as "apply", and --json has ``applied_from``."""
    plant = {"seed": 1, "loops": {"x": {"model": "fopdt", "gain": 1.0, "time_constant": 5.0,
             "delay": 1.0, "sample_time": 0.1, "noise_std": 0.0}}}  # fmt: skip
    request = {"apply_from": "0123456789ab", "rule": "simc-pi", "apply_timescale": 10.0,
               "apply_gains": PidGains(kc=1.0, ti=5.0), "apply_noise": 0.0}  # fmt: skip
    path, live = record_in_process(tmp_path, "p", plant, "x", "step", **request)
    assert live.status == "ok", live.reason
    row = summarize(path)
    assert row["method"] == "step" and row["applied_from"] == "0123456789ab"
    runs.run(argparse.Namespace(runs=str(tmp_path), compare=None, json=False))
    (line,) = [x for x in capsys.readouterr().out.splitlines() if x.endswith(path.name)]
    assert line.split()[1:3] == ["x", "apply"]


def test_gains_a_run_did_not_leave_on_the_loop_are_listed_in_parentheses(tmp_path, capsys):
    """`runs` listed a rejected run's gains as any ok run's (helper trial E misread them as the
    loop's): they are in ( ), with a line saying what that means."""
    plant = {"seed": 1, "loops": {"x": {"model": "fopdt", "gain": 1.0, "time_constant": 5.0,
             "delay": 1.0, "sample_time": 0.1, "noise_std": 0.0}}}  # fmt: skip
    ok, live = record_in_process(tmp_path, "p", plant, "x", "relay")
    assert live.status == "ok", live.reason
    proposed, live = record_in_process(tmp_path, "p", plant, "x", "relay", apply=False)
    assert live.status == "proposed", live.reason
    runs.run(argparse.Namespace(runs=str(tmp_path), compare=None, json=False))
    out = capsys.readouterr().out.splitlines()
    (applied,) = [x for x in out if x.endswith(ok.name)]
    (computed,) = [x for x in out if x.endswith(proposed.name)]
    assert "(" not in applied and computed.count("(") == 3, computed
    assert out[-1].startswith("gains in ( ): computed by the run, not left on the loop")


def test_a_rule_refused_by_the_safety_envelope_lists_its_gains_in_parentheses(tmp_path, capsys):
    """`--rule zn-pid` on a loop where ZN's PID is outside the safety envelope: the run is
    refused before any gains are chosen, and `runs` listed '—' where the refused gains were
    (the README: refused runs show theirs in ( )); they are the result's own zn-pid ones."""
    plant = {"seed": 1, "loops": {"x": {"model": "fopdt", "gain": 1.0, "time_constant": 5.0,
             "delay": 1.0, "sample_time": 0.1, "noise_std": 0.0}}}  # fmt: skip
    path, live = record_in_process(tmp_path, "p", plant, "x", "relay", rule="zn-pid")
    assert live.status == "rejected" and not live.applied and live.chosen is None, live.reason
    isa = PidGains(**live.gains["zn-pid"]["isa"])
    runs.run(argparse.Namespace(runs=str(tmp_path), compare=None, json=False))
    (row,) = [x for x in capsys.readouterr().out.splitlines() if x.endswith(path.name)]
    for v in (isa.kc, isa.ti, isa.td):
        assert f"({v:.4g})" in row, (v, row)
    listed = summarize(path)
    assert listed["gains"]["kc"] == isa.kc and listed["gains_on_loop"] is False
