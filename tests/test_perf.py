"""``autotune perf`` is a benchmark, not a test: here it only runs, on its tiny size, end to end
as the user runs it, and reports a positive finite number for every figure. The figures
themselves are never asserted (a loaded machine makes any limit flaky)."""

from __future__ import annotations

import json
import math
import subprocess
import sys

from services.offline import perf_phases
from tests.test_fuzz_cli import one_line_refusal, run_cli


def _numbers(doc: object, where: str = "") -> list[tuple[str, float]]:
    """(path, value) of every number in ``doc``; booleans and counts of things are left out."""
    if isinstance(doc, dict):
        return [n for k, v in doc.items() for n in _numbers(v, f"{where}.{k}")]
    if isinstance(doc, list):
        return [n for i, v in enumerate(doc) for n in _numbers(v, f"{where}[{i}]")]
    if isinstance(doc, int | float) and not isinstance(doc, bool):
        return [(where, float(doc))]
    return []


# the phases (a ramp tune over the bus, seconds even for a tiny plant) are left out here; their
# arithmetic is tested below
PERF_TINY = ["perf", "--size", "tiny", "--json", "--skip", "demo,phases", "--tunes", "2"]


def test_perf_runs_on_its_tiny_size_and_reports_every_figure():
    run = subprocess.run(
        [sys.executable, "-m", "services.cli", *PERF_TINY],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )
    assert run.returncode == 0, run.stderr
    doc = json.loads(run.stdout)
    assert set(doc) == {
        "size",
        "seconds",
        "pingpong",
        "inprocess",
        "lockstep",
        "realtime",
        "logger",
        "ratios",
    }
    assert set(doc["ratios"]) == {
        "lockstep_one_over_pingpong",
        "lockstep_many_over_one",
        "lockstep_many_tuners_over_one",
        "lockstep_one_over_inprocess",
        "logger_over_raw_writer",
    }
    figures = {
        "pingpong": ("rate",),
        "inprocess": ("rate", "samples"),
        "lockstep.one": ("rate", "samples", "wall"),
        "lockstep.many": ("rate", "samples", "wall"),
        "lockstep.many_tuners": ("rate", "samples", "wall"),
        "lockstep.cpu_us_per_sample": ("plant", "tuner", "logger"),
        "realtime.sizes[0]": ("kept", "kept_mean", "cpu", "samples_per_s"),
        "realtime": ("capacity_samples_per_s",),
        "logger": ("capacity", "raw_writer"),
        "ratios": tuple(doc["ratios"]),
    }
    # the logger's zero-drop capacity may read 0 on a loaded machine (none of the tiny rates
    # drained in time): a figure, not a failure; so may the tiny realtime plant's CPU (10
    # loops at 10/s for 1 s: a few ms, read in the kernel's 10 ms ticks), and its capacity
    # (one second of wall time, the 99 % it must keep missed by a start-up's jitter: seen
    # once in a fresh clone's CI); so may its slowest loop's pace (a loop with under three
    # arrivals in that second keeps nothing by the figure's own rule)
    may_be_zero = {
        ".logger.capacity",
        ".ratios.logger_over_raw_writer",
        ".realtime.sizes[0].cpu",
        ".realtime.sizes[0].kept",
        ".realtime.capacity_samples_per_s",
    }
    numbers = dict(_numbers(doc))
    for part, names in figures.items():
        for name in names:
            key = f".{part}.{name}"
            assert key in numbers, key
            low_ok = key in may_be_zero and numbers[key] == 0
            assert math.isfinite(numbers[key]) and (numbers[key] > 0 or low_ok), (key, numbers[key])
    assert doc["lockstep"]["many"]["loops"] == doc["lockstep"]["many_tuners"]["loops"] == 2


def test_a_phase_runs_from_its_first_opening_mark_to_the_next_closing_one():
    # (progress phase, sim time s, wall s): trials from quiet (t 10) to identified (t 35):
    # 100 samples of 0.25 s in 0.5 s; the verification from the first verify (t 40) to done
    # (t 65) in 0.25 s; a phase without its closing mark is not reported
    marks = [
        ("start", 0.0, 0.0),
        ("quiet", 10.0, 1.0),
        ("ramp", 20.0, 1.2),
        ("identified", 35.0, 1.5),
        ("verify", 40.0, 2.0),
        ("verify", 50.0, 2.1),
        ("done", 65.0, 2.25),
    ]
    got = perf_phases._phases(marks, 0.25)
    assert got["trials"].samples == 100 and math.isclose(got["trials"].wall, 0.5)
    assert math.isclose(got["trials"].rate, 200.0)
    assert math.isclose(got["verify"].us_per_sample, 1e6 * 0.25 / 100)
    assert set(perf_phases._phases(marks[:4], 0.25)) == {"trials"}


def test_a_phase_while_its_samples_flow_leaves_out_the_work_after_its_last_sample():
    # the same marks; the plant's messages (sim time of the last sample each carried, wall s):
    # the trials' first message after t 10 carries up to t 12.5 and arrives at 1.05, the one
    # carrying t 35 at 1.30, so 90 samples flowed in 0.25 s (the 0.2 s to "identified" is the
    # run's work after its last sample); the verification's from t 45 (2.05) to t 65 (2.15)
    marks = [
        ("start", 0.0, 0.0),
        ("quiet", 10.0, 1.0),
        ("identified", 35.0, 1.5),
        ("verify", 40.0, 2.0),
        ("done", 65.0, 2.25),
    ]
    arrivals = [(10.0, 0.99), (12.5, 1.05), (20.0, 1.1), (35.0, 1.3), (45.0, 2.05), (65.0, 2.15)]
    got = perf_phases._phases(marks, 0.25, arrivals)
    trials, verify = got["trials"], got["verify"]
    assert trials.flow_samples == 90 and math.isclose(trials.flow_wall, 0.25)
    assert math.isclose(trials.flow_us_per_sample, 1e6 * 0.25 / 90)
    assert trials.samples == 100 and math.isclose(trials.wall, 0.5)  # the whole window as before
    assert verify.flow_samples == 80 and math.isclose(verify.flow_wall, 0.1)
    # no arrivals watched, or the last sample's never came: no flow figure
    assert perf_phases._phases(marks, 0.25)["trials"].flow_us_per_sample is None
    assert perf_phases._phases(marks, 0.25, arrivals[:3])["trials"].flow_us_per_sample is None


def test_the_last_sample_time_is_read_from_a_sample_or_a_batch():
    assert perf_phases._last_t(b'{"t": 2.5, "pv": 1}') == 2.5
    assert perf_phases._last_t(b'{"loop": "x", "samples": [{"t": 1.0}, {"t": 1.25}]}') == 1.25
    for bad in (b"", b"[]", b'{"samples": []}', b'{"pv": 1}', b"not json"):
        assert perf_phases._last_t(bad) is None


def test_bad_flags_are_refused_in_one_line_naming_the_flag(capsys):
    for argv, flag in (
        (["perf", "--skip", "pingpong,nope"], "--skip"),
        (["perf", "--tunes", "0"], "--tunes"),
        (["perf", "--tuners", "0"], "--tuners"),
        (["perf", "--source", "/nonexistent"], "--source"),
    ):
        code, err = run_cli(capsys, argv)
        one_line_refusal(code, err, argv, flag)
