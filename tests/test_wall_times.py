"""The wall-time benchmark runs on its smallest size (the in-process tune, ~1 s) and reports
what it measured; the timings themselves are printed, never asserted."""

from __future__ import annotations

import json

import pytest

from services.offline import wall_times


def test_the_in_process_tune_is_measured_and_reported(capsys):
    assert wall_times.main(["--what", "in-process", "--json"]) == 0
    (m,) = json.loads(capsys.readouterr().out)
    assert (m["what"], m["status"], m["ratio"]) == ("in-process", "ok", 1.0)
    assert m["wall"] > 0 and m["sim_duration"] > 0
    assert m["speed"] == pytest.approx(m["sim_duration"] / m["wall"], rel=1e-12)


def test_an_unknown_measure_is_refused_by_name():
    with pytest.raises(SystemExit, match="--what 'bus,nope': choose from in-process, bus, demo"):
        wall_times.main(["--what", "bus,nope"])
