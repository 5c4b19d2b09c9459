"""services/logger/recorder.py in-process, no Zenoh: messages handed to the Recorder as the
bus would, the files read back. One run one file, the pre-run buffer and its bound, dedupe,
the run's end statuses, replays; and the logger service asking a tuner for the result of a
run it closed "tuner lost" (one session on loopback, alone)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from services.logger.mcap_io import FORMAT_VERSION, read_run
from services.logger.recorder import (
    BUFFER,
    LEASED_BUFFER,
    REPLAY_SILENCE,
    RESULT_GRACE,
    Recorder,
    model_for,
)
from shared import keys, wire
from shared.messages import (
    LeaseCommand,
    LoggerStatus,
    LoopStatus,
    Message,
    OutputCommand,
    PidGains,
    ProcessSample,
    SetpointCommand,
    TuneProgress,
    TuneRequest,
    TuneResult,
    TunerEvent,
)
from tests.test_record_form import INFO  # a loop's info, the loop and time set here

P = "rec"
LOOP = "hx1"
DT = 0.05


class Clock:
    """A monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def rec(tmp_path: Path, clock: Clock) -> Recorder:
    return Recorder(tmp_path, P, flush_interval=3600.0, clock=clock)


def send(rec: Recorder, key: str, msg: Message, replay: str | None = None) -> None:
    rec.handle(key, wire.encode(msg), replay)


def sample(seq: int, pv: float = 60.0, loop: str = LOOP) -> ProcessSample:
    return ProcessSample(loop=loop, seq=seq, t=seq * DT, pv=pv, sp=60.0, op=40.0, mode="auto")


def status(seq: int, reason: str, node: str = "plant", leased_by: str | None = None) -> LoopStatus:
    return LoopStatus(
        loop=LOOP,
        node=node,
        seq=seq,
        t=seq * DT,
        pv=60.0,
        sp=60.0,
        op=40.0,
        mode="auto",
        action="reverse",
        gains=PidGains(kc=1.0, ti=10.0),
        op_limits=(0.0, 100.0),
        pv_range=(0.0, 100.0),
        disturbances={},
        clock="lockstep",
        accepted=0,
        rejected=0,
        reason=reason,
        leased_by=leased_by,
    )


def start(run_id: str, t: float) -> TuneProgress:
    return TuneProgress(run_id=run_id, loop=LOOP, t=t, phase="start", message="relay test")


def result(run_id: str, t: float, status: str = "ok") -> TuneResult:
    return TuneResult(
        run_id=run_id, loop=LOOP, t=t, method="relay", rule="zn-pi", status=status, ku=2.5, pu=8.0
    )


def samples(rec: Recorder, first: int, last: int) -> None:
    for n in range(first, last + 1):
        send(rec, keys.pv(P, LOOP), sample(n))


def only_file(rec: Recorder) -> tuple[dict[str, str], list[str]]:
    """The one finished file's metadata and its records' keys."""
    assert len(rec.finished) == 1, rec.finished
    meta, records = read_run(rec.finished[0])
    return meta, [r.key for r in records]


# --- one run, one file --------------------------------------------------------------------


def test_a_run_from_start_to_result_is_one_file_with_its_messages(rec: Recorder) -> None:
    samples(rec, 0, 9)  # before the run: t < its start, not its context
    send(rec, keys.tune_progress(P, LOOP), start("r1", 10 * DT))
    samples(rec, 10, 14)
    send(rec, keys.command(P, LOOP, "lease", "tuner"), LeaseCommand(loop=LOOP, source="tuner:r1"))
    send(rec, keys.command(P, LOOP, "output"), OutputCommand(loop=LOOP, op=45.0))
    send(rec, keys.status(P, LOOP), status(14, "output"))
    ev = TunerEvent(run_id="r1", loop=LOOP, t=14 * DT, kind="cycle", data={"n": 1})
    send(rec, keys.tune_event(P, LOOP), ev)
    samples(rec, 15, 19)
    send(rec, keys.tune_result(P, LOOP), result("r1", 19 * DT))
    samples(rec, 20, 22)  # after the result: no run, not written

    meta, recorded = only_file(rec)
    assert rec.finished[0].name.endswith(f"_{LOOP}_relay_r1.mcap")
    assert recorded == [
        keys.tune_progress(P, LOOP),
        *[keys.pv(P, LOOP)] * 5,
        keys.command(P, LOOP, "lease", "tuner"),
        keys.command(P, LOOP, "output"),
        keys.status(P, LOOP),
        keys.tune_event(P, LOOP),
        *[keys.pv(P, LOOP)] * 5,
        keys.tune_result(P, LOOP),
    ]
    assert meta["format"] == str(FORMAT_VERSION)
    assert (meta["run_id"], meta["loop"], meta["status"], meta["prefix"]) == ("r1", LOOP, "ok", P)
    assert (meta["samples"], meta["first_seq"], meta["last_seq"]) == ("10", "10", "19")
    assert (meta["dropped"], meta["messages"], meta["left_out"]) == ("0", "16", "0")
    assert (meta["ku"], meta["pu"], meta["plant_node"]) == ("2.5", "8.0", "plant")
    assert TuneResult.model_validate_json(meta["result"]) == result("r1", 19 * DT)
    assert rec.open_runs() == [] and rec.counts["runs"] == 1 and rec.counts["written"] == 16


def test_another_runs_tuner_messages_are_left_out_and_counted(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 2)
    stale = TunerEvent(run_id="old", loop=LOOP, t=0.1, kind="cycle", data={})
    send(rec, keys.tune_event(P, LOOP), stale)
    send(rec, keys.tune_result(P, LOOP), result("old", 0.1))  # ends nothing: not this run's
    assert rec.open_runs() == ["r1"]
    send(rec, keys.tune_result(P, LOOP), result("r1", 0.1))
    meta, recorded = only_file(rec)
    assert meta["left_out"] == "2" and meta["status"] == "ok"
    assert recorded.count(keys.tune_result(P, LOOP)) == 1


def test_gaps_in_the_sample_numbers_are_counted_as_dropped(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    for n in (0, 1, 4, 5, 9):
        send(rec, keys.pv(P, LOOP), sample(n))
    send(rec, keys.tune_result(P, LOOP), result("r1", 9 * DT))
    meta, _ = only_file(rec)
    assert (meta["samples"], meta["dropped"]) == ("5", "5")  # 2, 3, 6, 7, 8
    assert rec.counts["dropped"] == 5


# --- the pre-run buffer -------------------------------------------------------------------


def test_samples_that_overtook_the_start_go_into_the_file_if_not_older_than_it(
    rec: Recorder,
) -> None:
    samples(rec, 0, 9)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 6 * DT))  # samples 6..9 came first
    send(rec, keys.tune_result(P, LOOP), result("r1", 9 * DT))
    meta, recorded = only_file(rec)
    assert (meta["first_seq"], meta["last_seq"], meta["samples"]) == ("6", "9", "4")
    assert recorded[0] == keys.pv(P, LOOP)  # in arrival order: the samples, then the start
    assert recorded[4] == keys.tune_progress(P, LOOP)


def test_the_pre_run_buffer_keeps_the_last_BUFFER_messages_of_a_loop(rec: Recorder) -> None:
    n = BUFFER + 500
    samples(rec, 0, n - 1)
    assert len(rec.streams[(LOOP, "")].recent) == BUFFER
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))  # all of them would qualify
    send(rec, keys.tune_result(P, LOOP), result("r1", (n - 1) * DT))
    meta, _ = only_file(rec)
    # the buffer holds the start itself and the BUFFER - 1 samples before it
    assert meta["samples"] == str(BUFFER - 1)
    assert meta["first_seq"] == str(n - (BUFFER - 1)) and meta["last_seq"] == str(n - 1)
    # those that left the buffer are counted missing (seq 0, at the start's own sim time, is
    # taken for the last sample before the run): the file does not say 0 dropped
    assert meta["dropped"] == str(n - BUFFER)


def test_a_leased_loop_keeps_its_samples_until_the_run_s_late_start(rec: Recorder) -> None:
    """A logger that fell behind takes the run's samples (after the plant's lease status, on
    the plant's link) before the run's start (on the tuner's): none is lost."""
    n = BUFFER + 500
    send(rec, keys.status(P, LOOP), status(0, "lease", leased_by="tuner:r1"))
    samples(rec, 1, n)
    assert rec.streams[(LOOP, "")].recent.maxlen == LEASED_BUFFER
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    send(rec, keys.tune_result(P, LOOP), result("r1", n * DT))
    meta, _ = only_file(rec)
    assert (meta["samples"], meta["first_seq"], meta["dropped"]) == (str(n), "1", "0")
    assert rec.streams[(LOOP, "")].recent.maxlen == BUFFER  # back once the run is closed


def test_a_run_whose_samples_start_on_time_counts_no_head_missing(rec: Recorder) -> None:
    samples(rec, 0, 9)
    send(rec, keys.tune_result(P, LOOP), result("r0", 9 * DT))  # nothing open: ignored
    send(rec, keys.tune_progress(P, LOOP), start("r1", 9 * DT))
    samples(rec, 10, 20)
    send(rec, keys.tune_result(P, LOOP), result("r1", 20 * DT))
    meta, _ = only_file(rec)
    assert meta["dropped"] == "0" and meta["first_seq"] in ("9", "10")


def test_what_came_before_the_previous_run_ended_is_not_the_next_runs(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 4)
    send(rec, keys.tune_result(P, LOOP), result("r1", 4 * DT))
    send(rec, keys.tune_progress(P, LOOP), start("r2", 0.0))  # t 0: would take anything
    send(rec, keys.tune_result(P, LOOP), result("r2", 4 * DT))
    assert len(rec.finished) == 2
    meta, recorded = read_run(rec.finished[1])
    assert meta["samples"] == "0"
    assert [r.key for r in recorded] == [keys.tune_progress(P, LOOP), keys.tune_result(P, LOOP)]


# --- dedupe and plant instances -----------------------------------------------------------


def test_a_sample_delivered_twice_is_written_once(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 3)
    send(rec, keys.pv(P, LOOP), sample(3))  # the same bytes again
    samples(rec, 4, 5)
    send(rec, keys.tune_result(P, LOOP), result("r1", 5 * DT))
    meta, _ = only_file(rec)
    assert rec.counts["duplicates"] == 1
    assert (meta["samples"], meta["dropped"], meta["plant_changed"]) == ("6", "0", "")


def test_a_sample_number_again_with_other_values_is_a_new_plant_left_out(
    rec: Recorder,
) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 5)
    send(rec, keys.pv(P, LOOP), sample(5, pv=99.0))  # another plant numbering from here
    send(rec, keys.pv(P, LOOP), sample(6, pv=99.0))
    send(rec, keys.command(P, LOOP, "setpoint"), SetpointCommand(loop=LOOP, sp=61.0))
    send(rec, keys.tune_result(P, LOOP), result("r1", 6 * DT))
    meta, recorded = only_file(rec)
    assert meta["plant_changed"] == "sample 5 came again, with other values"
    assert (meta["samples"], meta["last_seq"], meta["left_out"]) == ("6", "5", "3")
    assert keys.command(P, LOOP, "setpoint") not in recorded
    assert rec.counts["plant_instances"] == 1


def test_a_start_status_mid_run_is_a_new_plant_instance(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 3)
    send(rec, keys.status(P, LOOP), status(0, "start"))
    samples(rec, 1, 2)  # the restarted plant's: going back is no longer evidence
    send(rec, keys.tune_result(P, LOOP), result("r1", 3 * DT))
    meta, _ = only_file(rec)
    assert meta["plant_changed"] == "the plant started (status 'start')"
    assert (meta["samples"], meta["left_out"]) == ("4", "3")


# --- how a run ends -----------------------------------------------------------------------


@pytest.mark.parametrize("status", ["ok", "rejected", "aborted", "failed"])
def test_a_result_ends_the_run_with_its_status(rec: Recorder, status: str) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    send(rec, keys.tune_result(P, LOOP), result("r1", 0.0, status))
    assert only_file(rec)[0]["status"] == status


def test_a_result_that_overtook_the_last_samples_waits_for_them(rec: Recorder) -> None:
    """The result comes from the tuner, the samples from the plant: on a loaded machine the
    result can arrive first. The file closes once the sample of the result's time is in."""
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 5)
    send(rec, keys.tune_result(P, LOOP), result("r1", 9 * DT))
    assert rec.open_runs() == ["r1"]
    samples(rec, 6, 8)
    assert rec.open_runs() == ["r1"]
    samples(rec, 9, 11)  # 9 closes it; 10 and 11 come after the run
    meta, recorded = only_file(rec)
    assert (meta["status"], meta["last_seq"], meta["samples"]) == ("ok", "9", "10")
    assert recorded[-1] == keys.pv(P, LOOP) and recorded[7] == keys.tune_result(P, LOOP)


def test_a_result_whose_samples_never_come_ends_the_run_after_the_grace(
    rec: Recorder, clock: Clock
) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 5)
    send(rec, keys.tune_result(P, LOOP), result("r1", 9 * DT, "aborted"))
    send(rec, keys.status(P, LOOP), status(5, "watchdog"))  # the result is in: not "lost"
    clock.now += RESULT_GRACE - 0.01
    rec.tick()
    assert rec.open_runs() == ["r1"]
    clock.now += 0.01
    rec.tick()
    meta, _ = only_file(rec)
    assert (meta["status"], meta["last_seq"]) == ("aborted", "5")
    assert TuneResult.model_validate_json(meta["result"]).status == "aborted"
    # the samples to the result's sim time that never came: 6 to 9, not in the file
    assert meta["dropped"] == "4" and rec.counts["dropped"] == 4


def test_a_result_after_the_plant_is_gone_ends_the_run_at_once(rec: Recorder, clock: Clock) -> None:
    """The plant killed mid-run: its token vanished before the tuner's result came. The
    samples to the result's time are not coming, so the file closes with the result, not a
    grace later (as it did where the token vanished after the result)."""
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 5)
    rec.plant_token(LOOP, False)
    assert rec.open_runs() == ["r1"]  # the tuner still ends it
    send(rec, keys.tune_result(P, LOOP), result("r1", 9 * DT, "aborted"))
    assert rec.open_runs() == []  # no tick, no time passed
    meta, _ = only_file(rec)
    assert (meta["status"], meta["last_seq"], meta["dropped"]) == ("aborted", "5", "4")


def _request(run_id: str, t: float) -> TunerEvent:
    """The run's request event, the loop's info in it (what the tuner publishes first)."""
    info = INFO.model_copy(update={"loop": LOOP, "t": t, "sample_time": DT})
    data = {"request": TuneRequest(loop=LOOP).model_dump_json(), "info": info.model_dump_json()}
    return TunerEvent(run_id=run_id, loop=LOOP, t=t, kind="request", data=data)


def test_a_run_whose_samples_never_reached_the_logger_counts_them_dropped(
    rec: Recorder,
) -> None:
    """The tuner's messages came, the plant's did not (a user's trial recorded 131 messages,
    0 samples and said 0 dropped of a run whose tuner took 7,800): every sample from the
    run's start to its result's sim time is counted as dropped, the sample time taken from
    the loop's info."""
    send(rec, keys.tune_progress(P, LOOP), start("r1", 10 * DT))
    send(rec, keys.tune_event(P, LOOP), _request("r1", 10 * DT))
    send(rec, keys.command(P, LOOP, "lease", "tuner"), LeaseCommand(loop=LOOP, source="tuner:r1"))
    send(rec, keys.command(P, LOOP, "output"), OutputCommand(loop=LOOP, op=45.0))
    send(rec, keys.tune_result(P, LOOP), result("r1", 30 * DT, "aborted"))
    meta, _ = only_file(rec)
    assert (meta["samples"], meta["dropped"], meta["status"]) == ("0", "20", "aborted")
    assert rec.counts["dropped"] == 20


def test_a_sample_whose_time_is_not_its_number_is_not_the_plants(rec: Recorder) -> None:
    """A sample with seq 10⁹ published on the loop's key mid-run (a bus without credentials)
    made the run's file say 999,757,179 samples dropped (helper trial). The plant's samples
    are at t = seq × the loop's sample time; one that is not is left out and counted, and the
    run's count of dropped samples is the plant's own."""
    send(rec, keys.tune_progress(P, LOOP), start("r1", 10 * DT))
    send(rec, keys.tune_event(P, LOOP), _request("r1", 10 * DT))
    samples(rec, 10, 14)
    forged = sample(10**9).model_copy(update={"t": 15 * DT})
    send(rec, keys.pv(P, LOOP), forged)
    samples(rec, 15, 20)
    send(rec, keys.tune_result(P, LOOP), result("r1", 20 * DT))
    meta, _ = only_file(rec)
    assert (meta["samples"], meta["dropped"], meta["last_seq"]) == ("11", "0", "20")
    assert rec.counts["inconsistent"] == 1


def test_a_run_that_took_no_sample_drops_none(rec: Recorder) -> None:
    """A run that ended at its start's sim time (refused, say, in lockstep: no sample taken)
    is missing nothing."""
    send(rec, keys.tune_progress(P, LOOP), start("r1", 10 * DT))
    send(rec, keys.tune_event(P, LOOP), _request("r1", 10 * DT))
    send(rec, keys.tune_result(P, LOOP), result("r1", 10 * DT, "aborted"))
    meta, _ = only_file(rec)
    assert (meta["samples"], meta["dropped"]) == ("0", "0")


def test_a_new_start_while_the_last_samples_are_awaited_ends_the_run_with_its_result(
    rec: Recorder,
) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 2)
    send(rec, keys.tune_result(P, LOOP), result("r1", 5 * DT))
    send(rec, keys.tune_progress(P, LOOP), start("r2", 5 * DT))
    assert rec.open_runs() == ["r2"]
    meta, _ = read_run(rec.finished[0])
    assert (meta["run_id"], meta["status"]) == ("r1", "ok")
    rec.close_all()
    assert read_run(rec.finished[1])[0]["status"] == "incomplete"


def _second_start_while_r1_holds_the_loop(rec: Recorder) -> None:
    """r1 started and holds the loop (the plant says so); r2, a second tuner's run, starts
    at sample 3 (it waits for the loop's rest before it asks for the lease)."""
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    send(rec, keys.status(P, LOOP), status(0, "lease", leased_by="tuner:r1"))
    samples(rec, 0, 2)
    send(rec, keys.tune_progress(P, LOOP), start("r2", 3 * DT))
    samples(rec, 3, 5)
    rest = TuneProgress(run_id="r2", loop=LOOP, t=5 * DT, phase="rest", message="waiting")
    send(rec, keys.tune_progress(P, LOOP), rest)


def test_a_second_run_refused_the_loop_leaves_the_open_runs_file_alone(
    rec: Recorder, clock: Clock
) -> None:
    """Seen with two tuners: the second run's start closed the first one's file
    "superseded", and the first went on to end ok on no record."""
    _second_start_while_r1_holds_the_loop(rec)
    assert rec.open_runs() == ["r1"]
    refused = result("r2", 5 * DT, status="aborted")
    send(rec, keys.tune_result(P, LOOP), refused)
    samples(rec, 6, 8)
    send(rec, keys.tune_result(P, LOOP), result("r1", 8 * DT))
    clock.now += RESULT_GRACE
    rec.tick()
    meta, _ = only_file(rec)
    assert (meta["run_id"], meta["status"], meta["last_seq"]) == ("r1", "ok", "8")
    assert meta["left_out"] == "0"  # r2's messages are not counted against r1
    assert rec.counts["unrecorded_runs"] == 1 and rec.open_runs() == []


def test_a_run_refused_the_loop_has_no_file_when_it_started_first_too(
    rec: Recorder, tmp_path: Path
) -> None:
    """The other order (helper 60): r1 starts first, r2 starts behind it and takes the loop
    (the plant shows it holding), r1 is refused the lease. r1 had a file ("aborted") where,
    started second, it had none: one rule now, none; r2 is recorded from its start."""
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 2)
    send(rec, keys.tune_progress(P, LOOP), start("r2", 3 * DT))
    samples(rec, 3, 4)
    send(rec, keys.status(P, LOOP), status(5, "lease", leased_by="tuner:r2"))
    refused = result("r1", 4 * DT, status="aborted").model_copy(
        update={"untouched": True, "reason": "not started: lease refused"}
    )
    send(rec, keys.tune_result(P, LOOP), refused)
    assert rec.open_runs() == ["r2"] and rec.counts["unrecorded_runs"] == 1
    samples(rec, 6, 8)
    send(rec, keys.tune_result(P, LOOP), result("r2", 8 * DT))
    meta, _ = only_file(rec)
    assert (meta["run_id"], meta["status"]) == ("r2", "ok")
    assert [p.name for p in tmp_path.iterdir() if p.suffix == ".mcap"] == [rec.finished[0].name]


def test_an_untouched_run_that_nobody_else_held_the_loop_for_is_recorded(rec: Recorder) -> None:
    """Not started for want of rest, no other run about: its file stays (its rest wait)."""
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 4)
    nope = result("r1", 4 * DT, status="aborted").model_copy(update={"untouched": True})
    send(rec, keys.tune_result(P, LOOP), nope)
    meta, _ = only_file(rec)
    assert (meta["run_id"], meta["status"]) == ("r1", "aborted")


def test_a_run_that_waited_behind_the_open_one_is_recorded_from_its_start(
    rec: Recorder,
) -> None:
    """r1 ends while r2 waits for the loop's rest: r2 then holds the loop, and its file has
    its start and everything since (the samples both runs saw in both files)."""
    _second_start_while_r1_holds_the_loop(rec)
    send(rec, keys.tune_result(P, LOOP), result("r1", 5 * DT))  # its samples are all in
    assert rec.open_runs() == ["r2"]
    send(rec, keys.status(P, LOOP), status(6, "lease", leased_by="tuner:r2"))
    samples(rec, 6, 7)
    send(rec, keys.tune_result(P, LOOP), result("r2", 7 * DT))
    first, second = (read_run(f) for f in rec.finished)
    assert (first[0]["run_id"], first[0]["status"], first[0]["last_seq"]) == ("r1", "ok", "5")
    meta, records = second
    assert (meta["run_id"], meta["status"], meta["dropped"]) == ("r2", "ok", "0")
    assert (meta["first_seq"], meta["last_seq"], meta["samples"]) == ("3", "7", "5")
    progress = [r.key for r in records if r.key == keys.tune_progress(P, LOOP)]
    assert len(progress) == 2  # its start and its rest


def test_the_run_the_plant_shows_holding_the_loop_supersedes_the_open_one(
    rec: Recorder, clock: Clock
) -> None:
    """The open run's result may trail the plant's status that shows the next run holding
    the loop (another link): it closes the file within RESULT_GRACE; without it the open
    run was superseded."""
    _second_start_while_r1_holds_the_loop(rec)
    send(rec, keys.status(P, LOOP), status(6, "lease", leased_by="tuner:r2"))
    rec.tick()
    assert rec.open_runs() == ["r1"]
    clock.now += RESULT_GRACE
    rec.tick()
    assert rec.open_runs() == ["r2"]
    meta, _ = read_run(rec.finished[0])
    assert (meta["run_id"], meta["status"], meta["result"]) == ("r1", "superseded", "")


def test_a_result_within_the_grace_still_closes_the_superseded_run(
    rec: Recorder, clock: Clock
) -> None:
    _second_start_while_r1_holds_the_loop(rec)
    send(rec, keys.status(P, LOOP), status(6, "lease", leased_by="tuner:r2"))
    clock.now += 0.5 * RESULT_GRACE
    send(rec, keys.tune_result(P, LOOP), result("r1", 5 * DT))
    assert rec.open_runs() == ["r2"]
    meta, _ = read_run(rec.finished[0])
    assert (meta["run_id"], meta["status"]) == ("r1", "ok")


def test_a_replayed_new_start_supersedes_the_open_replay(rec: Recorder) -> None:
    rec.record_replays = True
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0), replay="a.mcap")
    send(rec, keys.tune_progress(P, LOOP), start("r2", 2 * DT), replay="a.mcap")
    assert rec.open_runs() == ["r2"]
    meta, _ = read_run(rec.finished[0])
    assert (meta["run_id"], meta["status"], meta["result"]) == ("r1", "superseded", "")


def test_the_same_start_again_opens_nothing(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))  # delivered twice: written twice
    send(rec, keys.tune_result(P, LOOP), result("r1", 0.0))
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))  # after its file: never again
    assert rec.counts["repeated_runs"] == 1 and rec.counts["runs"] == 1
    assert rec.open_runs() == []
    assert only_file(rec)[1].count(keys.tune_progress(P, LOOP)) == 2


def test_a_vanished_run_token_ends_the_run_after_the_grace(rec: Recorder, clock: Clock) -> None:
    rec.run_token(LOOP, True)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    rec.run_token(LOOP, False)
    clock.now += RESULT_GRACE - 0.01
    rec.tick()
    assert rec.open_runs() == ["r1"]  # the result may still be on its way
    clock.now += 0.01
    rec.tick()
    assert rec.open_runs() == []
    assert only_file(rec)[0]["status"] == "tuner lost"


def _closed_tuner_lost(rec: Recorder, clock: Clock) -> None:
    """Run r1 of three samples, its token gone and no result within the grace: its file
    closed "tuner lost"."""
    rec.run_token(LOOP, True)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 3)
    rec.run_token(LOOP, False)
    clock.now += RESULT_GRACE
    rec.tick()


def test_a_result_after_the_grace_goes_into_the_file_closed_tuner_lost(
    rec: Recorder, clock: Clock
) -> None:
    """A tuner paused past the grace, then resumed: its file was closed "tuner lost"; its
    result (an abort: the plant restored the loop meanwhile) is written into it after all,
    every message before it kept as it was."""
    _closed_tuner_lost(rec, clock)
    assert only_file(rec)[0]["status"] == "tuner lost"
    before = read_run(rec.finished[0])[1]
    clock.now += 30.0
    late = result("r1", 3 * DT, status="aborted").model_copy(update={"ku": None, "pu": None})
    send(rec, keys.tune_result(P, LOOP), late)
    assert rec.counts["late_results"] == 1
    meta, records = read_run(rec.finished[0])
    assert (meta["status"], meta["run_id"], meta["ku"]) == ("aborted", "r1", "")
    assert meta["late_result"] and TuneResult.model_validate_json(meta["result"]) == late
    assert records[:-1] == before  # the same messages, the same times
    assert records[-1].key == keys.tune_result(P, LOOP)
    assert TuneResult.model_validate_json(records[-1].data) == late
    assert meta["messages"] == str(len(records))
    # only once: the same result again, or another run's, changes nothing more
    send(rec, keys.tune_result(P, LOOP), late)
    assert rec.counts["late_results"] == 1 and len(read_run(rec.finished[0])[1]) == len(records)


def test_a_run_token_back_within_the_grace_keeps_the_run(rec: Recorder, clock: Clock) -> None:
    rec.run_token(LOOP, True)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    rec.run_token(LOOP, False)
    clock.now += 1.0
    rec.run_token(LOOP, True)  # a reconnection
    clock.now += 10 * RESULT_GRACE
    rec.tick()
    assert rec.open_runs() == ["r1"]


def test_the_result_within_the_grace_ends_the_run_ok(rec: Recorder, clock: Clock) -> None:
    rec.run_token(LOOP, True)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    rec.run_token(LOOP, False)
    clock.now += RESULT_GRACE / 2
    send(rec, keys.tune_result(P, LOOP), result("r1", 0.0))
    assert only_file(rec)[0]["status"] == "ok"


def test_a_watchdog_restore_without_the_run_token_ends_the_run(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 2)
    send(rec, keys.status(P, LOOP), status(2, "watchdog"))
    assert rec.open_runs() == []
    meta, recorded = only_file(rec)
    assert meta["status"] == "tuner lost" and recorded[-1] == keys.status(P, LOOP)


def test_a_watchdog_status_naming_the_runs_lease_ends_nothing(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    send(rec, keys.status(P, LOOP), status(0, "watchdog", leased_by="tuner:r1"))
    assert rec.open_runs() == ["r1"]


def test_a_watchdog_while_the_token_lives_waits_for_the_token(rec: Recorder) -> None:
    rec.run_token(LOOP, True)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    send(rec, keys.status(P, LOOP), status(0, "watchdog"))
    assert rec.open_runs() == ["r1"]  # the tuner lives: it ends its run with a result
    rec.run_token(LOOP, False)  # it did not: gone now, nothing more to wait for
    assert rec.open_runs() == []
    assert only_file(rec)[0]["status"] == "tuner lost"


def test_close_all_finishes_every_open_file_incomplete(rec: Recorder) -> None:
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    send(rec, keys.tune_progress(P, "lvl1"), start("r2", 0.0).model_copy(update={"loop": "lvl1"}))
    rec.close_all()
    assert sorted(read_run(f)[0]["status"] for f in rec.finished) == ["incomplete"] * 2
    assert rec.open_runs() == []


# --- input it does not record -------------------------------------------------------------


def disk_room(monkeypatch: pytest.MonkeyPatch, room: int) -> dict[str, int]:
    """Run files (``*.mcap`` opened "wb") on a disk with ``room`` bytes left: a write that
    does not fit raises ENOSPC. The room left is the dict's ``bytes``, for the test to set."""
    import errno
    import io

    real_open = Path.open
    left = {"bytes": room}

    class Full(io.RawIOBase):
        def __init__(self, f) -> None:
            self.f = f

        def writable(self) -> bool:
            return True

        def seekable(self) -> bool:
            return True

        def seek(self, offset: int, whence: int = 0) -> int:
            return self.f.seek(offset, whence)

        def write(self, b) -> int:
            if len(b) > left["bytes"]:
                raise OSError(errno.ENOSPC, "No space left on device")
            left["bytes"] -= len(b)
            return self.f.write(b)

        def close(self) -> None:
            self.f.close()
            super().close()

    def full_open(self, mode="r", *args, **kw):
        f = real_open(self, mode, *args, **kw)
        return io.BufferedWriter(Full(f)) if mode == "wb" and self.suffix == ".mcap" else f

    monkeypatch.setattr(Path, "open", full_open)
    return left


def test_a_full_disk_cuts_the_runs_file_short_and_the_logger_goes_on(
    tmp_path: Path, clock: Clock, monkeypatch: pytest.MonkeyPatch, caplog
) -> None:
    """A logger whose --runs filled up (a 300 kB tmpfs) exited "autotune logger: error: No
    space left on device" in the middle of a run, every other run's recording (and the change
    history) with it (helper trial). The run's file is now left as it stands (what reached
    the disk, for `autotune recover`), said once, and the logger goes on: the run ends, the
    next one starts, nothing raises."""
    room = disk_room(monkeypatch, 2000)  # the header fits, the first chunk (its schemas) not
    rec = Recorder(tmp_path, P, flush_interval=0.0, clock=clock)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 50)
    assert rec.open_runs() == ["r1"]
    rec.tick()  # the flush that finds the disk full: it raised, and the logger exited
    # no longer open to the loggers' status: the tuner says the run is not on record
    assert rec.open_runs() == []
    samples(rec, 51, 60)
    send(rec, keys.tune_result(P, LOOP), result("r1", 60 * DT))
    clock.now += RESULT_GRACE
    rec.tick()
    assert rec.finished[0].name.endswith("_r1.mcap")
    said = [r.getMessage() for r in caplog.records if "cannot be written" in r.getMessage()]
    assert len(said) == 1 and "No space left on device" in said[0], said
    assert any("is cut short" in r.getMessage() for r in caplog.records)
    # the next run on a disk still full, not even its header written: no file left behind,
    # and said so, no exception either
    room["bytes"] = 0
    send(rec, keys.tune_progress(P, LOOP), start("r2", 61 * DT))
    samples(rec, 61, 70)
    rec.tick()
    send(rec, keys.tune_result(P, LOOP), result("r2", 70 * DT))
    clock.now += RESULT_GRACE
    rec.tick()
    assert len(rec.finished) == 2 and not rec.finished[1].exists()
    assert any("r2 on hx1: ok, but not recorded" in r.getMessage() for r in caplog.records)


def test_a_disk_full_at_the_files_last_write_is_said_in_the_loggers_status(
    tmp_path: Path, clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A disk that filled as the run's file was finished (its chunk, metadata and summary
    are written as the run ends, after the tuner's result) was said in the logger's log
    alone: its status showed the run closed like any other, and `autotune tune` and `demo`
    took the file for the run's record (the demo failed on it "cut short … if a logger was
    killed", the run's result unprinted: helper trial, a 420 kB tmpfs). The status now
    lists the run's file as incomplete, where and why, while open or finished."""
    from services.logger.service import LoggerService
    from shared.messages import IncompleteRun

    room = disk_room(monkeypatch, 1 << 30)
    rec = Recorder(tmp_path, P, flush_interval=3600.0, clock=clock)  # no flush mid-run
    service = LoggerService(None, rec, "logger")  # its status, no session needed
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))
    samples(rec, 0, 50)
    rec.tick()
    assert rec.open_runs() == ["r1"] and service.status().incomplete_runs == []
    room["bytes"] = 0  # full: the run's end is the next write
    send(rec, keys.tune_result(P, LOOP), result("r1", 50 * DT))
    assert rec.open_runs() == [] and len(rec.finished) == 1
    path = rec.finished[0]
    cut = IncompleteRun(
        run_id="r1",
        loop=LOOP,
        path=str(path.absolute()),
        reason="No space left on device",
        on_disk=True,  # its header reached the disk as the file was opened
    )
    assert path.exists() and service.status().incomplete_runs == [cut]
    # a run written whole is not listed; a run whose file fails mid-run is, while still open
    room["bytes"] = 1 << 30
    send(rec, keys.tune_progress(P, LOOP), start("r2", 51 * DT))
    samples(rec, 51, 60)
    send(rec, keys.tune_result(P, LOOP), result("r2", 60 * DT))
    send(rec, keys.tune_progress(P, LOOP), start("r3", 61 * DT))
    samples(rec, 61, 70)
    room["bytes"] = 0
    rec.flush_interval = rec.streams[(LOOP, "")].run.writer.flush_interval = 0.0
    rec.tick()
    st = wire.decode(LoggerStatus, wire.encode(service.status()))  # as on the bus
    assert [(r.run_id, r.on_disk) for r in st.incomplete_runs] == [("r3", True), ("r1", True)]
    assert st.incomplete_runs[1] == cut


def test_invalid_and_foreign_messages_are_counted_not_recorded(rec: Recorder) -> None:
    rec.handle(keys.pv(P, LOOP), b'{"loop": "hx1"}')
    rec.handle(keys.info(P, LOOP), b"{}")
    rec.handle("elsewhere/plant/hx1/pv", wire.encode(sample(0)))
    rec.handle(keys.command(P, LOOP, "explode"), b"{}")
    assert (rec.counts["received"], rec.counts["invalid"], rec.counts["ignored"]) == (4, 1, 3)
    assert rec.streams == {}


def test_model_for_reads_each_recorded_key() -> None:
    assert model_for(P, keys.pv(P, LOOP)) == (LOOP, ProcessSample)
    assert model_for(P, keys.status(P, LOOP)) == (LOOP, LoopStatus)
    assert model_for(P, keys.command(P, LOOP, "output", "u")) == (LOOP, OutputCommand)
    assert model_for(P, keys.tune_progress(P, LOOP)) == (LOOP, TuneProgress)
    assert model_for(P, keys.tune_event(P, LOOP)) == (LOOP, TunerEvent)
    assert model_for(P, keys.tune_result(P, LOOP)) == (LOOP, TuneResult)
    for key in (
        keys.info(P, LOOP),
        keys.loop_alive(P, LOOP),
        keys.tune_cancel(P, LOOP),
        keys.tune_running(P, LOOP),
        keys.logger_status(P, "logger"),
        keys.pv("other", LOOP),
    ):
        assert model_for(P, key) is None, key


def test_replays_are_left_out_unless_asked_for(tmp_path: Path, clock: Clock) -> None:
    rec = Recorder(tmp_path, P, flush_interval=3600.0, clock=clock)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0), replay="a.mcap")
    assert rec.counts["replayed_ignored"] == 1 and rec.streams == {}


def test_a_recorded_replay_is_its_own_stream_and_file(tmp_path: Path, clock: Clock) -> None:
    rec = Recorder(tmp_path, P, flush_interval=3600.0, record_replays=True, clock=clock)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))  # live
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0), replay="a.mcap")
    send(rec, keys.pv(P, LOOP), sample(0), replay="a.mcap")
    send(rec, keys.tune_result(P, LOOP), result("r1", 0.0), replay="a.mcap")
    assert rec.open_runs() == ["r1"]  # the live run is untouched
    meta, _ = read_run(rec.finished[0])
    assert rec.finished[0].name.endswith("_r1_replay.mcap")
    assert (meta["replay"], meta["status"], meta["samples"]) == ("a.mcap", "ok", "1")
    assert (LOOP, "a.mcap") not in rec.streams  # a replay's stream ends with its run


def test_an_interrupted_replay_s_file_ends_incomplete_after_its_silence(
    tmp_path: Path, clock: Clock
) -> None:
    """A replay stopped mid-run (Ctrl-C) left its file open, listed "recording", until the
    logger stopped (helper trial: 5.5 min); a replay has no token to lose. Its file ends
    ``incomplete`` once nothing of it came for REPLAY_SILENCE s, or ten of its samples' gaps
    at the pace it came at (a slow --rate is no interruption); a live run is not ended so."""
    rec = Recorder(tmp_path, P, flush_interval=3600.0, record_replays=True, clock=clock)
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0))  # live, its tuner silent
    send(rec, keys.tune_progress(P, LOOP), start("r1", 0.0), replay="a.mcap")
    for n in range(5):  # at 10 s of wall time a sample (DT s of sim time each)
        send(rec, keys.pv(P, LOOP), sample(n), replay="a.mcap")
        clock.now += 10.0
    clock.now += 100.0 - 10.0 - 0.01  # 100 s since the last sample: ten gaps less a hair
    rec.tick()
    assert rec.finished == []
    clock.now += 0.02
    rec.tick()
    meta, _ = read_run(rec.finished[0])
    assert (meta["replay"], meta["status"], meta["samples"]) == ("a.mcap", "incomplete", "5")
    assert rec.open_runs() == ["r1"]  # the live run is not ended by silence
    # at a quick pace the bound is REPLAY_SILENCE itself
    send(rec, keys.tune_progress(P, LOOP), start("r2", 0.0), replay="b.mcap")
    send(rec, keys.pv(P, LOOP), sample(0), replay="b.mcap")
    send(rec, keys.pv(P, LOOP), sample(1), replay="b.mcap")
    clock.now += REPLAY_SILENCE
    rec.tick()
    assert len(rec.finished) == 2


def test_the_logger_asks_the_tuner_for_the_result_of_a_run_it_closed_tuner_lost(
    rec: Recorder, clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A logger paused past Zenoh's lease as an ok run ended never heard its result: the run
    was recorded "tuner lost", and its report, history and `runs` said so (helper trial E).
    The logger now asks the tuner (``<prefix>/tune/<loop>/result``, the last result per loop,
    on a real session here) and writes the result in, as a late one."""
    from services.logger import service as logger_service
    from shared.session import ZenohSettings, open_session

    monkeypatch.setattr(logger_service, "LATE_ASK", 0.05)
    _closed_tuner_lost(rec, clock)
    assert only_file(rec)[0]["status"] == "tuner lost" and rec.lost_runs() == [("r1", LOOP)]
    ok = result("r1", 3 * DT)
    alone = ZenohSettings(listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)
    with open_session(alone) as s:
        key = keys.tune_result(P, LOOP)
        answer = s.declare_queryable(key, lambda q: wire.reply(q, key, ok))
        svc = logger_service.LoggerService(s, rec, "logger")
        stop = threading.Event()
        asker = threading.Thread(target=svc._ask_late_results, args=(stop,))
        asker.start()
        deadline = time.monotonic() + 10.0  # bounded: the answer comes within moments
        while rec.lost_runs() and time.monotonic() < deadline:
            time.sleep(0.01)
        stop.set()
        asker.join(5.0)
        answer.undeclare()
    meta = only_file(rec)[0]
    assert (meta["status"], rec.counts["late_results"]) == ("ok", 1)
    assert "this logger" in meta["late_result"] and rec.lost_runs() == []
    # and the change history has its tune record (it had none: helper trial)
    from shared.history_file import read_history

    tunes = [x for x in read_history(svc.history.path) if x["record"] == "tune"]
    assert [(x["run_id"], x["status"]) for x in tunes] == [("r1", "ok")]


def test_replay_waits_for_a_subscriber_of_every_key_it_publishes() -> None:
    """`autotune replay --with-commands` waited for a subscriber of its first key only (a
    command: the plant's), and the logger, known a moment later, missed the run's start:
    the replay was not recorded (helper trial). The wait is for every key."""
    from services.logger.commands.replay import wait_for_subscriber
    from shared.session import open_session
    from tests.test_plant_stream import ALONE

    with open_session(ALONE) as session:
        sub = session.declare_subscriber("waiting/plant/x1/cmd/*", lambda s: None)
        try:
            keys_ = ["waiting/plant/x1/cmd/sync", "waiting/tune/x1/progress"]
            assert wait_for_subscriber(session, keys_, 0.3) is False  # none for the second
            assert wait_for_subscriber(session, keys_[:1], 0.3) is True
            everything = session.declare_subscriber("waiting/**", lambda s: None)
            assert wait_for_subscriber(session, keys_, 0.3) is True
            everything.undeclare()
        finally:
            sub.undeclare()
