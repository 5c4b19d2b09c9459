"""A long lockstep advance is stepped and published part by part (``FIRST_CHUNK`` samples,
then twice as many each time up to ``STREAM_CHUNK``, a message each), so that its asker reads
one part while the plant steps the next: the samples equal
the same advance stepped at once, to the bit; it ends with the sample its stops name, also on a
part's last sample; and a lease that ends between parts (the watchdog restored the loop) ends
the advance there: the plant never steps a loop for an asker who no longer holds it.

The plant service runs in this process on a session of its own; what it publishes is caught
at its publishers."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from services.plant_sim import service as plant_service
from services.plant_sim.plant_file import build_plant
from services.plant_sim.service import (
    FIRST_CHUNK,
    MODEL_STALL,
    STREAM_CHUNK,
    PlantService,
    ServiceOptions,
)
from shared import keys, wire
from shared.messages import (
    AdvanceCommand,
    LeaseCommand,
    ProcessSample,
    ProcessSamples,
    RecordStops,
    ReleaseCommand,
    SettleStop,
)
from shared.reject_log import RejectLog
from shared.session import ZenohSettings, open_session

ALONE = ZenohSettings(listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)
PREFIX = "stream"
SPEC = {
    "model": "fopdt",
    "sample_time": 0.1,
    "gain": 1.5,
    "time_constant": 4.0,
    "delay": 0.35,
    "noise_std": 0.05,
    "mode": "auto",
    "setpoint": 52.0,
    "pid": {"kc": 1.2, "ti": 5.0},
}


def plant():
    return build_plant({"seed": 4, "loops": {"x": SPEC}})


class Caught:
    """Stands in for the plant's publishers: keeps what it is given, in order."""

    def __init__(self, on_put=None):
        self.sent: list[tuple[str, bytes]] = []
        self.on_put = on_put

    def put_json(self, key, model, payload) -> None:
        self.sent.append((key, payload))
        if self.on_put is not None:
            self.on_put(len(self.sent))

    def put(self, key, msg) -> None:
        self.put_json(key, type(msg), wire.encode(msg))

    def held_since(self):
        return None

    def samples(self) -> tuple[list[ProcessSample], int]:
        """The samples published, in order, and the number of messages they came in."""
        out, messages = [], 0
        for key, payload in self.sent:
            if key == keys.pv_batch(PREFIX, "x"):
                out += wire.decode(ProcessSamples, payload).samples
                messages += 1
            elif key == keys.pv(PREFIX, "x"):
                out.append(wire.decode(ProcessSample, payload))
                messages += 1
        return out, messages


@pytest.fixture()
def service():
    with open_session(ALONE) as session:
        yield PlantService(session, plant(), ServiceOptions(prefix=PREFIX))


def send(svc: PlantService, cmd) -> None:
    svc.handle_command(keys.command(PREFIX, "x", cmd.kind), wire.encode(cmd), None)


def advance(steps: int, **stops) -> AdvanceCommand:
    return AdvanceCommand(loop="x", steps=steps, source="me", t=0.0, **stops)


def test_a_long_advance_comes_in_parts_equal_to_one_stepping(service) -> None:
    caught = service.publishers = Caught()
    steps = 3 * STREAM_CHUNK + 17
    send(service, advance(steps))
    got, messages = caught.samples()
    want = plant()["x"].advance_many(steps)
    sizes = [FIRST_CHUNK, 2 * FIRST_CHUNK, *[STREAM_CHUNK] * 3]  # 64, 128, 256, 256, 256 …
    assert FIRST_CHUNK * 4 == STREAM_CHUNK
    assert [len(wire.decode(ProcessSamples, p).samples) for _, p in caught.sent] == [
        *sizes[:4],
        steps - sum(sizes[:4]),
    ]
    assert messages == 5
    assert [s.model_dump() for s in got] == [s.model_dump() for s in want]


def test_a_slow_models_parts_are_cut_to_keep_its_asker_hearing_from_it(
    service, monkeypatch
) -> None:
    """A user model whose step() took 20 ms stepped 256 samples (5.1 s) between two messages,
    and its tuner, which must hear from the plant within 5 s, aborted a healthy run (helper
    trial F). Once a part takes over twice PART_SECONDS, the next are cut to PART_SECONDS
    (here 0.05 s, a model of 2 ms a sample), the samples the same."""
    monkeypatch.setattr(plant_service, "PART_SECONDS", 0.05)
    loop = service.loops["x"]
    step = loop.advance_rows

    def slow(n, stops=None, until=None):
        time.sleep(0.002 * n)  # the model's cost, at once for the part
        return step(n, stops)

    monkeypatch.setattr(loop, "advance_rows", slow)
    caught = service.publishers = Caught()
    send(service, advance(200))
    sizes = [len(wire.decode(ProcessSamples, p).samples) for _, p in caught.sent]
    assert sizes[0] == FIRST_CHUNK and sum(sizes) == 200
    assert all(n <= 25 for n in sizes[1:]), sizes  # 0.05 s / 2 ms: 25 (fewer if slower)
    got, _ = caught.samples()
    want = plant()["x"].advance_many(200)
    assert [s.model_dump() for s in got] == [s.model_dump() for s in want]


def test_a_slow_models_first_part_ends_part_seconds_into_it(service, monkeypatch) -> None:
    """The part size is learnt from a slow part: a model of 80 ms a sample stepped its first
    part of FIRST_CHUNK samples for 5.1 s, past its asker's 5 s silence bound. A model
    stepped a sample at a time stops at PART_SECONDS into a part, from the first (the clock
    here is the model's own: 0.125 s a step; PART_SECONDS 1 s, so 8 samples a part)."""
    from services.plant_sim.simulation import linear_steps
    from services.plant_sim.simulation import loop as sim_loop

    now = [100.0]

    class Clock:
        @staticmethod
        def monotonic() -> float:
            return now[0]

    monkeypatch.setattr(sim_loop, "time", Clock)
    monkeypatch.setattr(plant_service.time, "monotonic", Clock.monotonic)
    monkeypatch.setattr(linear_steps, "steppable", lambda loop: False)  # one sample at a time
    loop = service.loops["x"]
    process_step = loop.process.step

    def step(op):
        now[0] += 0.125
        return process_step(op)

    monkeypatch.setattr(loop.process, "step", step)
    caught = service.publishers = Caught()
    send(service, advance(45))
    sizes = [len(wire.decode(ProcessSamples, p).samples) for _, p in caught.sent]
    assert sizes == [8, 8, 8, 8, 8, 5], sizes
    got, _ = caught.samples()
    want = plant()["x"].advance_many(45)
    assert [s.model_dump() for s in got] == [s.model_dump() for s in want]


@pytest.mark.parametrize("at", [STREAM_CHUNK + 40, 1])
def test_it_ends_with_the_sample_its_stops_name(service, at: int) -> None:
    """Also when that sample is the first of all."""
    want = plant()["x"].advance_many(at + 300)
    level = want[at - 1].pv  # the first sample at or above it ends the advance
    first = next(j for j, s in enumerate(want) if s.pv >= level) + 1
    caught = service.publishers = Caught()
    send(service, advance(5 * STREAM_CHUNK, stop_above=level))
    got, _ = caught.samples()
    assert len(got) == first
    assert [s.model_dump() for s in got] == [s.model_dump() for s in want[:first]]


def test_a_lease_that_ends_between_parts_ends_the_advance(service) -> None:
    send(service, LeaseCommand(loop="x", source="me", timeout=30.0, t=0.0))

    def lapse(n: int) -> None:
        if n == 1:  # the first part out: the watchdog strikes
            service.expire_lease("x", "test")

    caught = service.publishers = Caught(on_put=lapse)
    send(service, advance(4 * STREAM_CHUNK))
    got, messages = caught.samples()
    assert (len(got), messages) == (FIRST_CHUNK, 1)
    assert "x" not in service.leases


def test_a_stop_on_a_parts_last_sample_ends_the_advance(service) -> None:
    """A record judged every 8 samples settles at its first settling point, the 64th
    sample: the last of the first part, and the advance's last."""
    assert FIRST_CHUNK == 8 * 8
    want = plant()["x"].advance_many(FIRST_CHUNK)
    settle = SettleStop(k=1, target=want[-1].pv, band=1e-9)
    caught = service.publishers = Caught()
    send(service, advance(4 * STREAM_CHUNK, record=RecordStops(judge=8, settle=settle)))
    got, messages = caught.samples()
    assert (len(got), messages) == (FIRST_CHUNK, 1)
    assert [s.model_dump() for s in got] == [s.model_dump() for s in want]


def test_a_long_advance_keeps_its_holders_lease(service, monkeypatch) -> None:
    """The holder waits while the plant steps for it (its commands queue behind the advance):
    an advance that outlasts the lease's timeout does not let the watchdog take the loop back.
    The plant's clock is made to run 0.4 s a part (the lease: 1 s), the watchdog ticking
    between parts as its thread would."""
    clock = [1000.0]
    monkeypatch.setattr(plant_service.time, "monotonic", lambda: clock[0])
    send(service, LeaseCommand(loop="x", source="me", timeout=1.0, t=0.0))

    def tick(n: int) -> None:
        clock[0] += 0.4
        service._check_leases(clock[0], 0.05)

    caught = service.publishers = Caught(on_put=tick)
    steps = 2 * FIRST_CHUNK + 6 * STREAM_CHUNK  # 64, 128, then 256 each: 8 parts, 3.2 s
    send(service, advance(steps))
    got, messages = caught.samples()
    assert clock[0] - 1000.0 > 3 * 1.0  # the advance lasted three lease timeouts
    assert (len(got), messages) == (steps, 8)
    assert service.leases["x"].source == "me"
    # and a holder that goes silent after it still loses the loop
    clock[0] += 1.5
    service._check_leases(clock[0], 0.05)
    assert "x" not in service.leases


def test_a_model_step_that_hangs_is_named_once(service, caplog) -> None:
    """A user's step() that blocks holds the plant's lock: every loop of the process waits
    on it, and nothing said why. The watchdog reads each loop's ``stepping_since`` (set
    around the model's step()) without the lock, and says which loop, once a hang."""
    loop = service.loops["x"]
    with caplog.at_level(logging.ERROR, logger="plant_sim"):
        loop.stepping_since = 100.0
        service._watch_models(100.0 + MODEL_STALL - 1.0)  # not yet
        service._watch_models(100.0 + MODEL_STALL + 1.0)
        service._watch_models(100.0 + MODEL_STALL + 2.0)  # the same hang: said once
        loop.stepping_since = None
        service._watch_models(200.0)  # it returned
        loop.stepping_since = 300.0
        service._watch_models(300.0 + MODEL_STALL + 1.0)  # a new hang: said again
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2
    assert all(m.startswith("loop x: its model's step() has not returned") for m in lines)
    assert "every loop of this plant process waits on it" in lines[0]
    assert loop.advance().seq > 0 and loop.stepping_since is None  # set only during a step


def test_the_model_watch_speaks_while_the_hung_model_holds_the_lock(service) -> None:
    """The watch ran on the lease watchdog's thread, which waits on the lock a hung model
    holds: it never spoke. Its own thread reads without the lock."""
    said = threading.Event()

    class Heard(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if "has not returned" in record.getMessage():
                said.set()

    handler = Heard()
    logging.getLogger("plant_sim").addHandler(handler)
    stop = threading.Event()
    try:
        with service.lock:  # as a model's step() holds it while it hangs
            service.loops["x"].stepping_since = time.monotonic() - MODEL_STALL - 1.0
            threading.Thread(target=service._model_watch, args=(stop,), daemon=True).start()
            assert said.wait(10.0)
    finally:
        stop.set()
        service.loops["x"].stepping_since = None
        logging.getLogger("plant_sim").removeHandler(handler)


def test_refusals_left_unlogged_are_counted_once_their_window_has_passed(caplog) -> None:
    """Past its burst, a kind of refusal is counted, not logged; the count was said only if
    another refusal of the kind came after the window. ``flush`` says it when it has passed."""
    refusals = RejectLog(logging.getLogger("plant_sim"), burst=2, window=10.0)
    with caplog.at_level(logging.WARNING, logger="plant_sim"):
        for _ in range(5):
            refusals("schema", "not JSON")
        refusals.flush(time.monotonic())  # the window still open: nothing yet
        assert sum("more schema rejects" in r.getMessage() for r in caplog.records) == 0
        refusals.flush(time.monotonic() + 11.0)
        refusals.flush(time.monotonic() + 30.0)  # said once
    said = [r.getMessage() for r in caplog.records if "more schema rejects" in r.getMessage()]
    assert said == ["3 more schema rejects were not logged"]


def test_a_lease_ending_on_a_faulted_loop_says_it_stays_in_manual(service, caplog) -> None:
    """The plant's log said a faulted loop was 'restored to its state before the experiment
    (auto, op 50.01 %)' where restore keeps a faulted loop in manual at its held output
    (helper trial): it says so."""
    send(service, LeaseCommand(loop="x", source="me", timeout=30.0, t=0.0))
    loop = service.loops["x"]
    loop.fault = "step() raised RuntimeError: boom"
    with caplog.at_level(logging.WARNING, logger=plant_service.log.name):
        service.expire_lease("x", "its holder fell silent")
    (line,) = [r.getMessage() for r in caplog.records if "its holder fell silent" in r.message]
    assert "restored to its state before the experiment" not in line
    assert "faulted (step() raised RuntimeError: boom)" in line and "stays in manual" in line
    assert loop.mode == "manual"


def test_a_release_that_asks_a_restore_of_a_faulted_loop_says_it_is_faulted(
    service, caplog
) -> None:
    """The plant restores a released loop its holder could not confirm as put back; a loop
    that faulted meanwhile keeps its held output in manual, and the log said "restored to
    its state before the experiment (manual, op 50 %)" of one faulted at 49.01 % (helper
    trial): it says what ``_end_lease`` says, faulted and where it is held."""
    service.publishers = Caught()
    send(service, LeaseCommand(loop="x", source="me", timeout=30.0, t=0.0))
    loop = service.loops["x"]
    loop._set_fault("step() raised RuntimeError: test", 49.01, loop.t)
    with caplog.at_level(logging.WARNING, logger="plant_sim"):
        send(service, ReleaseCommand(loop="x", source="me", t=0.0, restore=True))
    lines = [r.getMessage() for r in caplog.records if "released by" in r.getMessage()]
    assert len(lines) == 1, lines
    assert "but it is faulted" in lines[0] and "restored to its state" not in lines[0]
    assert loop.mode == "manual" and loop.fault is not None
