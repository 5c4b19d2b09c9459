"""The logger with plant_sim and the autotuner, all separate processes on loopback."""

from __future__ import annotations

import json
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader

from services.autotuner.loop_client import LoopClient
from services.logger.mcap_io import read_run
from services.logger.report import build_figure, load_series
from shared import keys, wire
from shared.messages import LoggerStatus, ProcessSample
from shared.session import open_session
from shared.wire import replay_source
from tests.integration.tuning_cli import HX, THIRD, autotune, plant_toml, tune

pytestmark = pytest.mark.integration

FAST = {**THIRD, "sample_time": 0.01}


def stack(
    start_plant,
    start_tuner,
    start_logger,
    runs: Path,
    plant: dict,
    noise: float = 0.0,
    clock: tuple[str, ...] = (),
):
    p = start_plant(plant_toml("x1", plant, noise=noise), *clock, loops=("x1",))
    start_tuner(p)
    logger = start_logger(p, runs)
    return p, logger


def logger_status(p) -> LoggerStatus:
    with open_session(p.client_settings()) as s:
        st = wire.query_one(s, keys.logger_status(p.prefix, "logger"), LoggerStatus, 10.0)
    assert st is not None, "the logger did not answer"
    return st


def wait_finished(p, n: int = 1, timeout: float = 30.0) -> LoggerStatus:
    """The logger's own status says the run file is finished (it may trail the result)."""
    deadline = time.monotonic() + timeout
    while True:
        st = logger_status(p)
        if st.finished_runs >= n or time.monotonic() > deadline:
            return st
        time.sleep(0.05)


def final_seq(p) -> int:
    with open_session(p.client_settings()) as s, LoopClient(s, p.prefix, "x1") as c:
        return c.last_status.seq


# the plant's clock for a run of known wall time: in lockstep a relay runs as fast as the
# machine (its half-cycles in one round trip each), in realtime at 20 × it takes P_u/20 s a
# cycle, whatever the machine's speed
REALTIME = ("--clock", "realtime", "--speed", "20")


def long_tune(p) -> subprocess.Popen:
    """A relay tune that runs all its 30 cycles (they never agree within 0.01 %): on a
    realtime plant, several seconds of wall time, in the background."""
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "tune",
            "x1",
            "--cycles",
            "12",
            "--tolerance",
            "0.0001",
            *p.cli_args(),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def seqs(records) -> list[int]:
    return [
        ProcessSample.model_validate_json(r.data).seq for r in records if r.topic.endswith("/pv")
    ]


def test_relay_tune_is_recorded_whole_and_reanalysed_exactly(
    start_plant, start_tuner, start_logger, tmp_path
):
    runs = tmp_path / "runs"
    p, _ = stack(start_plant, start_tuner, start_logger, runs, FAST, noise=0.002)
    live = tune(p, "x1")
    assert live["status"] == "ok", live["reason"]
    assert not [w for w in live["warnings"] if "logger" in w]  # one recorded it throughout
    assert wait_finished(p).finished_runs == 1
    files = list(runs.glob("*_x1_relay_*.mcap"))
    assert len(files) == 1
    meta, records = read_run(files[0])
    got = seqs(records)
    # every sample the plant published during the run, once, in order
    assert got == list(range(got[0], final_seq(p) + 1))
    assert meta["dropped"] == "0" and int(meta["samples"]) == len(got)
    assert json.loads(meta["info"])["model"] == "transfer_function"
    assert json.loads(meta["request"])["loop"] == "x1" and meta["status"] == "ok"
    with files[0].open("rb") as f:  # the mcap reader opens it; every channel has a schema
        summary = make_reader(f).get_summary()
    assert summary.channels and all(
        summary.schemas[ch.schema_id].encoding == "jsonschema" and ch.message_encoding == "json"
        for ch in summary.channels.values()
    )
    # and one RunRecord (the metadata as a message: a file record, not a bus message)
    assert summary.statistics.message_count == len(records) + 1
    # sim time in every message, the tuner's commands too (sync, mode, gains, setpoint had
    # none: noticed last stop)
    commands = [json.loads(r.data) for r in records if "/cmd/" in r.key]
    assert commands and all(c.get("t") is not None for c in commands), [
        c for c in commands if c.get("t") is None
    ][:3]
    # analyze: the same K_u, P_u and gains as the live run, to the bit
    run = autotune("analyze", str(files[0]), "--json")
    assert run.returncode == 0, run.stderr
    a = json.loads(run.stdout)
    assert a["ku"] == live["ku"] and a["pu"] == live["pu"] and a["matches_live"] is True
    assert a["gains"] == live["gains"]
    listing = autotune("runs", str(runs), "--json")
    row = json.loads(listing.stdout)[0]
    assert (row["loop"], row["method"], row["ku"], row["status"]) == (
        "x1",
        "relay",
        live["ku"],
        "ok",
    )
    # the rule whose gains the row shows, and the one asked for ("auto": it listed that)
    assert (row["rule"], row["requested_rule"]) == (live["rule"], "auto") and live["rule"] != "auto"
    assert row["gains"] == live["chosen"]["isa"]


def test_step_and_ramp_runs_reanalyse_exactly(start_plant, start_tuner, start_logger, tmp_path):
    runs = tmp_path / "runs"
    p, _ = stack(start_plant, start_tuner, start_logger, runs, FAST)
    lives = {}
    for args in (
        ["--method", "step", "--rule", "cc-pi"],
        ["--method", "step", "--repeat", "2"],  # every hold time replayed in order
        ["--method", "ramp", "--kc-start", "2"],
    ):
        live = tune(p, "x1", *args, "--no-apply")
        assert live["status"] == "proposed", live["reason"]
        lives[live["run_id"]] = live
    assert wait_finished(p, 3).finished_runs == 3
    assert [len(v["repeats"] or ()) for v in lives.values()] == [0, 2, 0]
    for run_id, live in lives.items():
        f = next(runs.glob(f"*_{run_id}.mcap"))
        a = json.loads(autotune("analyze", str(f), "--json").stdout)
        assert a["matches_live"] is True, f.name
        assert (a["ku"], a["pu"], a["step"]) == (live["ku"], live["pu"], live["step"])
        assert a["gains"] == live["gains"] and a["gains"]
        # and its warnings: the identification's notes as well as the design's (a ramp's hold
        # correction, a repeated test's disagreement were left out of analyze's)
        assert a["warnings"] == live["warnings"], f.name


def signal_mid_run(p, logger, sig: int, after: float):
    """Start a long tune, watch every sample on the bus, and send ``sig`` to the logger once
    ``after`` s of wall time have passed since the run's first progress message. Returns
    (seen, t_start, t_signal): the (seq, wall time) of every sample the test received, and
    the wall times of the run's first progress and of the signal."""
    seen: list[tuple[int, float]] = []
    inbox: queue.Queue = queue.Queue()
    with open_session(p.client_settings()) as s:
        sub = s.declare_subscriber(f"{p.prefix}/**")
        threading.Thread(
            target=lambda: [inbox.put((x, time.monotonic())) for x in sub], daemon=True
        ).start()
        cli = long_tune(p)
        t_start = t_signal = None
        try:
            while t_signal is None:
                sample, at = inbox.get(timeout=60)
                key = str(sample.key_expr)
                assert not key.endswith("/result"), "the run ended before the signal"
                if key.endswith("/progress") and t_start is None:
                    t_start = at
                elif key.endswith("/pv"):
                    seen.append((wire.decode_sample(ProcessSample, sample).seq, at))
                    if t_start is not None and at > t_start + after:
                        logger.send_signal(sig)
                        t_signal = time.monotonic()
            if sig == signal.SIGTERM:
                assert logger.wait(timeout=30) == 0
        finally:
            cli.terminate()  # the run is cancelled (the loop restored): it has done its part
            cli.wait(timeout=60)
            sub.undeclare()
    return seen, t_start, t_signal


def test_logger_killed_mid_run_is_recovered_but_for_the_last_second(
    start_plant, start_tuner, start_logger, tmp_path
):
    runs = tmp_path / "runs"
    p, logger = stack(start_plant, start_tuner, start_logger, runs, HX, clock=REALTIME)
    # mid-run, 4 s into it: the logger flushes at least every second, and on a loaded machine
    # it may start its file a second or more after the test saw the run begin (killed at
    # 1.5 s it once had flushed nothing yet)
    seen, t_start, t_kill = signal_mid_run(p, logger, signal.SIGKILL, 4.0)
    broken = next(runs.glob("*.mcap"))
    run = autotune("analyze", str(broken))
    assert run.returncode == 2 and "autotune recover" in run.stderr
    assert "Traceback" not in run.stderr
    fixed = tmp_path / "fixed.mcap"
    run = autotune("recover", str(broken), "-o", str(fixed))
    assert run.returncode == 0, run.stderr
    _, records = read_run(fixed)
    got = seqs(records)
    assert got == list(range(got[0], got[-1] + 1))  # whole up to where it stops
    missing = [(q, at) for q, at in seen if q > got[-1]]
    lost_for = t_kill - min((at for _, at in missing), default=t_kill)
    print(
        f"SIGKILL: {len(got)} samples recovered, {len(missing)} lost, the earliest "
        f"received {lost_for:.2f} s before the kill"
    )
    # the promise is the last second of what the logger received (flushed every 1 s, checked
    # every 0.25 s); the test receives samples up to ~1 s earlier than a logger that lags
    # on a loaded 2-core machine (a full suite run once lost 1.5 s by the test's clock)
    bound = 2.5
    assert all(at > t_kill - bound for _, at in missing), f"lost more than the last {bound} s"
    # every sample of the run (seen after its first progress: the test also sees the loop's
    # samples from before the run, for as long as the CLI takes to start) up to the bound
    assert got and len(got) >= sum(1 for _, at in seen if t_start <= at <= t_kill - bound)


def test_sigterm_finishes_the_file(start_plant, start_tuner, start_logger, tmp_path):
    runs = tmp_path / "runs"
    p, logger = stack(start_plant, start_tuner, start_logger, runs, HX, clock=REALTIME)
    # let it record for 1.5 s from the run's first progress, then stop it
    seen, t_start, t_term = signal_mid_run(p, logger, signal.SIGTERM, 1.5)
    meta, records = read_run(next(runs.glob("*.mcap")))  # finished: the seeking reader opens it
    assert meta["status"] == "incomplete"
    got = seqs(records)
    assert got == list(range(got[0], got[-1] + 1))
    # nothing received is lost: every sample on the bus from 0.5 s into the run to 0.5 s
    # before the stop (margins for delivery to the logger) is in the file
    settled = [q for q, at in seen if t_start + 0.5 < at < t_term - 0.5]
    assert settled and set(settled) <= set(got)
    assert int(meta["messages"]) == len(records)


def test_a_run_file_the_disk_cannot_take_is_said_by_tune_in_one_line(
    start_plant, start_tuner, start_logger, tmp_path
):
    """A logger whose disk filled as it finished the run's file (a 420 kB tmpfs: the run's
    6127 messages went out with the file's end, after the tuner's result) said so in its log
    alone: `autotune tune` ended ok, not a word. Here the logger's files may grow no larger
    than LIMIT bytes (its own ``ulimit -f``; Python ignores SIGXFSZ, so a write past it fails
    as on a full disk, EFBIG), and tune says in one line that the run's record is incomplete
    and where; its result stays the run's (ok, exit 0)."""
    import resource

    limit = 16384  # the file's header fits (and history.jsonl), the run's samples do not
    runs = tmp_path / "runs"
    p, logger = stack(start_plant, start_tuner, start_logger, runs, FAST, noise=0.002)
    resource.prlimit(logger.pid, resource.RLIMIT_FSIZE, (limit, limit))
    run = autotune("tune", "x1", *p.cli_args())
    assert run.returncode == 0, run.stderr
    (path,) = runs.glob("*.mcap")
    said = [line for line in run.stderr.splitlines() if "record is incomplete" in line]
    assert said == [
        f"autotune tune: warning: run {path.stem.rsplit('_', 1)[1]}'s record is incomplete: "
        f"the logger could not finish its file {path.absolute()} (File too large); what "
        f"reached the disk: autotune recover {path.absolute()} -o FIXED.mcap"
    ], run.stderr
    assert 0 < path.stat().st_size <= limit
    assert logger.poll() is None  # the logger goes on


def test_replay_delivers_every_message_in_order(start_plant, start_tuner, start_logger, tmp_path):
    runs = tmp_path / "runs"
    p, _ = stack(start_plant, start_tuner, start_logger, runs, FAST)
    tune(p, "x1", "--no-verify")
    wait_finished(p)
    f = next(runs.glob("*.mcap"))
    _, records = read_run(f)
    # Replay onto another bus, where the only plant has another prefix: the replayed keys
    # (commands included) reach the test's subscriber and nothing else.
    target = start_plant(plant_toml("other", FAST), loops=("other",))
    for extra, expected in (
        ([], [(r.key, r.data) for r in records if "/cmd/" not in r.key]),
        (["--with-commands"], [(r.key, r.data) for r in records]),
    ):
        got: list[tuple[str, bytes]] = []
        marks: set[str | None] = set()  # every message is marked as a replay of the file
        with open_session(target.client_settings()) as s:
            sub = s.declare_subscriber(f"{p.prefix}/**", zenoh.handlers.FifoChannel(1 << 16))

            def read(sub=sub, got=got, marks=marks) -> None:
                for x in sub:
                    got.append((str(x.key_expr), x.payload.to_bytes()))
                    marks.add(replay_source(x.attachment and x.attachment.to_bytes()))

            reader = threading.Thread(target=read, daemon=True)
            reader.start()
            run = autotune(
                "replay",
                str(f),
                "--rate",
                "10",
                *extra,
                "--prefix",
                p.prefix,
                "-e",
                target.endpoint,
                "--no-multicast-scouting",
            )
            assert run.returncode == 0, run.stderr
            deadline = time.monotonic() + 10
            while len(got) < len(expected) and time.monotonic() < deadline:
                time.sleep(0.05)
            sub.undeclare()
        assert got == expected and marks == {f.name}


def live_run_id(f: Path) -> str:
    return read_run(f)[0]["run_id"]


def test_report_plots_the_recorded_series(start_plant, start_tuner, start_logger, tmp_path):
    runs = tmp_path / "runs"
    p, _ = stack(start_plant, start_tuner, start_logger, runs, FAST)
    tune(p, "x1")
    wait_finished(p)
    f = next(runs.glob("*.mcap"))
    png = tmp_path / "report.png"
    run = autotune("report", str(f), "-o", str(png))
    assert run.returncode == 0, run.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20000
    _, records = read_run(f)
    samples = sorted(
        (ProcessSample.model_validate_json(r.data) for r in records if r.topic.endswith("/pv")),
        key=lambda s: s.seq,
    )
    series = load_series(f)
    fig = build_figure(series)
    ax_pv, ax_op, ax_history = fig.axes  # the run applied its gains: a change on record
    assert series.history[1].startswith("▶") and live_run_id(f) in series.history[1]
    assert ax_history.texts[0].get_text() == "\n".join(series.history)
    pv_line, sp_line = ax_pv.lines[0], ax_pv.lines[1]
    assert list(pv_line.get_xdata()) == [s.t for s in samples]
    assert list(pv_line.get_ydata()) == [s.pv for s in samples]
    assert list(sp_line.get_ydata()) == [s.sp for s in samples]
    assert list(ax_op.lines[0].get_ydata()) == [s.op for s in samples]
    cycles = sum(1 for r in records if r.topic.endswith("/event") and b'"cycle"' in r.data)
    assert sum(1 for ln in ax_pv.lines[2:] if ln.get_linestyle() == ":") == cycles


@pytest.mark.parametrize("content", [b"", b"not an mcap file at all", b"\x89MCAP0\r\n\x00\x01"])
def test_bad_files_get_one_line_errors(tmp_path, content, capsys):
    """In-process through the CLI's entry point (one subprocess below checks the exit code
    end to end): three commands × three files would otherwise start nine interpreters."""
    from services.cli import main

    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    for cmd in (
        ["analyze", str(bad)],
        ["report", str(bad), "-o", str(tmp_path / "r.png")],
        ["replay", str(bad)],
    ):
        assert main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1
        assert str(bad) in err
    if content == b"":
        run = autotune("analyze", str(bad))
        assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1
