"""RecorderWatch: a run's result says when no logger recorded it, or one went out of sight
during it, from the loggers' liveliness tokens (one session on loopback, alone)."""

from __future__ import annotations

import time

from services.autotuner.recorder_watch import RecorderWatch
from shared import keys, wire
from shared.messages import LoggerStatus
from shared.session import ZenohSettings, open_session

ALONE = ZenohSettings(listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)


def _until(check, timeout: float = 5.0) -> None:
    """Bounded wait for what a liveliness callback sets."""
    deadline = time.monotonic() + timeout
    while not check() and time.monotonic() < deadline:
        time.sleep(0.01)


def test_no_logger_in_sight_is_said():
    with open_session(ALONE) as s:
        said = RecorderWatch(s, "rw1").verdict()
    assert said is not None and said.startswith("no logger recorded this run")


def _status(prefix: str, dropped: int = 0, open_runs: tuple[str, ...] = ()):
    """A logger's status queryable's answer."""

    def answer(query):
        st = LoggerStatus(
            node="logger",
            runs_dir="runs",
            open_runs=list(open_runs),
            finished_runs=0,
            received=0,
            written=0,
            invalid=0,
            dropped=dropped,
        )
        wire.reply(query, keys.logger_status(prefix, "logger"), st)

    return answer


def _verdict(prefix: str, answer, run_id: str | None = None) -> str | None:
    """The verdict of a run (``run_id``) during which a logger stayed in sight, its status
    queries answered by ``answer``."""
    with open_session(ALONE) as s:
        token = s.liveliness().declare_token(keys.logger_alive(prefix, "logger"))
        queryable = s.declare_queryable(keys.logger_status(prefix, "logger"), answer)
        watch = RecorderWatch(s, prefix)
        _until(lambda: watch._seen)
        said = watch.verdict(run_id=run_id)
        queryable.undeclare()
        token.undeclare()
    return said


def test_a_logger_throughout_says_nothing():
    assert _verdict("rw2", _status("rw2")) is None
    assert _verdict("rw7", _status("rw7", open_runs=("r1", "r0")), run_id="r1") is None


def test_a_logger_in_sight_that_does_not_hold_the_run_open_is_said():
    """A tune started as `autotune up` brought the stack up: the logger, up a moment after
    the run's start, never opened it, and the result said nothing (helper trial)."""
    said = _verdict("rw8", _status("rw8", open_runs=("r0",)), run_id="r1")
    assert said is not None and said.startswith("no logger has this run open (logger answered)")


def _gone_verdict(prefix: str, stalled: float = 0.0) -> str | None:
    """The verdict of a run during which the one logger went out of sight (``stalled``: s
    this tuner's own process did not run meanwhile)."""
    with open_session(ALONE) as s:
        token = s.liveliness().declare_token(keys.logger_alive(prefix, "logger"))
        watch = RecorderWatch(s, prefix)
        _until(lambda: watch._seen)
        token.undeclare()
        _until(lambda: watch._gap)
        return watch.verdict(stalled=stalled)


def test_a_logger_gone_during_the_run_is_said():
    said = _gone_verdict("rw3")
    assert said is not None and "went out of sight during the run" in said
    assert "none is back" in said


def test_a_logger_out_of_sight_while_this_tuner_stalled_is_not_blamed_on_the_logger():
    """This tuner's own process paused 10 s (its peers dropped it): the logger went out of
    its sight with everything else, and the result said "the logger went out of sight
    (killed, paused or cut off)" of a logger never touched (helper trial E)."""
    said = _gone_verdict("rw6", stalled=10.0)
    assert said is not None and said.startswith("this tuner's own process did not run for 10 s")
    assert "went out of sight during the run" not in said


def test_samples_a_logger_missed_during_the_run_are_said():
    """A logger's ``dropped`` count (process samples missing) grew between the run's start
    and end: its record may have gaps (a logger paused 20 s missed 1,601 samples of a run,
    and the tune said nothing)."""
    dropped = iter([5, 12])

    said = _verdict("rw4", lambda query: _status("rw4", next(dropped))(query))
    assert said is not None and said.startswith("the logger missed 7 process samples"), said


def test_a_logger_that_answers_neither_at_the_start_nor_the_end_is_said():
    """Its token in sight, its status query unanswered at the start and at the end (a logger
    paused through a short lockstep run: the run was never recorded, and the ok run said
    nothing, helper trial E): not known whether the run is on record, said (the second
    question costs 2 s, only when the first went unanswered)."""
    asked: list[str] = []
    said = _verdict("rw5", lambda q: asked.append(str(q.key_expr)))
    assert len(asked) == 2
    assert said is not None and said.startswith("no logger answered at the start or the end")


def test_a_logger_that_answered_at_the_start_but_not_the_end_is_said():
    """Paused during a lockstep run (helper trial E): its record lacks the samples of the
    pause, and the ok run said nothing."""
    answered: list[int] = []

    def answer(query):
        if not answered:  # the start's question only
            answered.append(1)
            _status("rw7")(query)

    said = _verdict("rw7", answer)
    assert said is not None and said.startswith("the logger did not answer at the end"), said


def test_a_runs_file_the_logger_could_not_finish_is_said_in_one_line(tmp_path):
    """A disk full at a run file's last write, as the run ended, was said in the logger's
    log alone: `autotune tune` ended ok without a word, `autotune demo` failed on the file
    with the run's result unprinted. The client asks the loggers' status once the result
    is in, while the run is still open there, and says what one lists as incomplete."""
    from pathlib import Path

    from services.autotuner.recorder_watch import incomplete_line, incomplete_record
    from services.demo import wait_for_file
    from shared.messages import IncompleteRun

    prefix, path = "rw9", str(tmp_path / "20261207T144337Z_hx1_relay_r1.mcap")
    cut = IncompleteRun(
        run_id="r1", loop="hx1", path=path, reason="No space left on device", on_disk=True
    )
    asked = []

    def answer(query):  # open at the first question, then finished, its file cut short
        asked.append(1)
        st = LoggerStatus(
            node="logger",
            runs_dir=str(tmp_path),
            open_runs=["r1"] if len(asked) == 1 else [],
            finished_runs=0 if len(asked) == 1 else 1,
            received=0,
            written=0,
            invalid=0,
            dropped=0,
            incomplete_runs=[] if len(asked) == 1 else [cut],
        )
        wire.reply(query, keys.logger_status(prefix, "logger"), st)

    with open_session(ALONE) as s:
        queryable = s.declare_queryable(keys.logger_status(prefix, "logger"), answer)
        try:
            got = incomplete_record(s, prefix, "r1")
            assert len(asked) == 2  # waited while the logger held the run open
            assert incomplete_record(s, prefix, "r0") is None  # another run: nothing said
            # the demo: the file the logger names, and its word, not the file as the record
            assert wait_for_file(s, prefix, tmp_path, "r1", timeout=5.0) == (Path(path), cut)
        finally:
            queryable.undeclare()
        assert incomplete_record(s, prefix, "r1", wait=0.5) is None  # no logger: nothing
    assert got == cut
    line = incomplete_line(cut)
    assert "\n" not in line
    assert line == (
        f"warning: run r1's record is incomplete: the logger could not finish its file {path} "
        f"(No space left on device); what reached the disk: autotune recover {path} -o "
        "FIXED.mcap"
    )
    gone = incomplete_line(cut.model_copy(update={"on_disk": False}))
    assert gone.startswith(
        f"warning: run r1 is not on record: the logger could not write its file {path}"
    )
