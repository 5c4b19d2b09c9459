"""The fault matrix: a peer killed, paused or cut off at a chosen phase of a run.

Each case starts the real services as separate processes on loopback (a fast FOPDT loop, P_u ≈
1.1 s; at ×10 stretched to 5.5 s, so a whole relay run is seconds), asks `autotune tune` for a
run, and at the phase named (the tuner's own progress and event messages say when it is there)
SIGKILLs or SIGSTOPs (then SIGCONTs) the tuner, the plant or the logger, or restarts the router
the services are clients of. It then asserts the loop's exact state (mode, output, setpoint and
gains equal to before the run, or the applied gains after an ``ok``), that the run ended with a
reason within a bound, what the client printed and its exit code, and that the recording opens
(after ``autotune recover`` where the logger was killed).

Bounds are wall time from the fault (or from SIGCONT of a pause) to the run's end as the client
saw it; they are generous against a loaded 2-core machine and say what each mechanism promises:
a killed tuner's loop is restored by the plant as soon as its run token vanishes; a paused
tuner's lease lapses after --lease-timeout; a vanished plant is noticed from its liveliness
token at once.
"""

from __future__ import annotations

import json
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from services.autotuner.loop_client import wait_for_token
from services.launcher import free_tcp_port, start_service, stop_service
from shared import keys, wire
from shared.messages import LoopStatus, ServiceStatus, TuneProgress, TunerEvent
from shared.session import ZenohSettings, open_session

pytestmark = pytest.mark.integration

LOOP = "f1"
# s: the tuner's --lease-timeout here (10 s by default). Short, so that a paused tuner's lease
# lapses within the test, but not so short that a loaded machine's scheduling reads as the
# tuner's silence: at 1.5 s a CI run lost the lease of a healthy run (kill-logger-relay1-x10)
LEASE = 3.0
# the relay's cycles agree within this on the realtime clock: a period is 55 samples (×1, ×10),
# and a loaded machine that holds one switch a sample late moves it 1.8 %, near the default
# 2 %; the cases test the faults, not the relay's convergence (lockstep keeps the default)
RT_TOLERANCE = 0.05


def plant_file(scale: float) -> str:
    """The loop, its times stretched by ``scale``: at ×10 it is 5 times slower in sim time, so
    a sample is 10 ms of wall time (20 ms at ×1). At 2 ms a sample a loaded 2-core machine
    delays the relay's switches by several samples, and the relay rightly aborts on cycles
    that do not repeat: a limit of the machine, not a fault under test."""
    return f"""seed = 1
[loops.{LOOP}]
model = "transfer_function"
num = [1.0]
den = [{scale!r}, 1.0]
delay = {0.3 * scale!r}
sample_time = {0.02 * scale!r}
noise_std = 0.0
mode = "manual"
"""


@dataclass(frozen=True)
class Case:
    fault: str  # kill | pause | restart (router)
    target: str  # tuner | plant | logger | router
    phase: str  # quiet | relay1 | relay2 | trial | verify
    clock: str  # lockstep | x1 | x10
    expect: str  # status the run ends with: ok | aborted | gone (the client saw no result)
    bound: float  # s from the fault (SIGCONT for a pause) to the run's end, at most
    method: str = "relay"
    pause: float = 0.0  # s a SIGSTOP lasts
    gap: float = 0.0  # s a killed router stays down before its restart

    @property
    def id(self) -> str:
        return f"{self.fault}-{self.target}-{self.phase}-{self.clock}"


CASES = [
    Case("kill", "tuner", "relay1", "lockstep", "gone", 4.0),
    Case("kill", "tuner", "quiet", "x1", "gone", 4.0),
    Case("kill", "tuner", "verify", "x10", "gone", 4.0),
    Case("pause", "tuner", "relay2", "lockstep", "aborted", 3.0, pause=2 * LEASE),
    Case("pause", "tuner", "trial", "x10", "aborted", 3.0, method="ramp", pause=2 * LEASE),
    Case("pause", "tuner", "relay1", "x1", "aborted", 3.0, pause=2 * LEASE),
    # shorter than the lease: the relay could not switch while paused, and its cycles then
    # are not the process's (6 s at ×20 ran 6,308 s of relay before its abort: helper review)
    Case("pause", "tuner", "relay2", "x10", "aborted", 5.0, pause=0.5 * LEASE),
    # noticed at once; the run then asks the plant's status for 2 s (is it back in reach?)
    Case("kill", "plant", "relay2", "lockstep", "aborted", 4.0),
    Case("kill", "plant", "trial", "x10", "aborted", 4.0, method="ramp"),
    Case("pause", "plant", "relay1", "lockstep", "ok", 60.0, pause=2.0),
    Case("pause", "plant", "verify", "x10", "aborted", 15.0, pause=7.0),
    # at stage 2, seconds into the run: past the logger's first flush (at relay1, within the
    # run's first second, nothing had reached the disk, and recover read 0 messages)
    Case("kill", "logger", "relay2", "x10", "ok", 60.0),
    Case("pause", "logger", "trial", "lockstep", "ok", 60.0, method="ramp", pause=2.0),
    Case("restart", "router", "relay2", "x10", "aborted", 15.0),
    # down long enough that the client rejoins while the tuner has not yet: its result,
    # published while cut off, is still asked for (it said "tuner gone" in CI, exit 2)
    Case("restart", "router", "quiet", "lockstep", "aborted", 15.0, gap=1.4),
]


def _phase_reached(case: Case, msg: TuneProgress | TunerEvent) -> bool:
    if isinstance(msg, TuneProgress):
        return msg.phase == case.phase and case.phase in ("quiet", "verify")
    if isinstance(msg, TunerEvent):
        if case.phase == "relay1":
            return msg.kind == "relay_start"
        if case.phase == "relay2":
            return msg.kind == "stage" and msg.data.get("stage") == 2
        if case.phase == "trial":
            return msg.kind == "trial"
    return False


class Stack:
    """Plant, tuner and logger as processes (clients of a router for the router cases)."""

    def __init__(self, tmp: Path, case: Case, prefix: str):
        self.tmp, self.case, self.prefix = tmp, case, prefix
        self.port = free_tcp_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.via_router = case.target == "router"
        self.procs: dict[str, subprocess.Popen] = {}
        scale = {"lockstep": 1.0, "x1": 1.0, "x10": 5.0}[case.clock]
        (tmp / "plant.toml").write_text(plant_file(scale))
        self.runs = tmp / "runs"
        if self.via_router:
            self.start("router")
            _wait_listening(self.port)
        self.start("plant")
        self.start("tuner")
        self.start("logger")
        self.settings = ZenohSettings(
            mode="client" if self.via_router else "peer",
            connect=(self.endpoint,),
            cfg=("connect/timeout_ms:10000",),
            no_multicast_scouting=True,
        )
        self.session = open_session(self.settings)
        for key in (
            keys.loop_alive(prefix, LOOP),
            keys.tuner_alive(prefix, "tuner"),
            keys.logger_alive(prefix, "logger"),
        ):
            if not wait_for_token(self.session, key, 20.0):
                self.close()  # no process outlives a failed start
                raise AssertionError(f"{key} did not come up:\n{self.logs()}")

    def bus_args(self, service: str) -> list[str]:
        if service == "router":
            return ["-l", self.endpoint, "--no-multicast-scouting"]
        if self.via_router:  # clients keep trying their router while it restarts
            return [
                "-m",
                "client",
                "-e",
                self.endpoint,
                "--no-multicast-scouting",
                "--cfg",
                "connect/timeout_ms:10000",
            ]
        if service == "plant":
            return ["-l", self.endpoint, "--no-multicast-scouting"]
        return ["-e", self.endpoint, "--no-multicast-scouting", "--cfg", "connect/timeout_ms:10000"]

    def start(self, service: str) -> None:
        clock = self.case.clock
        own = {
            "router": [],
            "plant": ["--plant", str(self.tmp / "plant.toml")]
            + (["--clock", "lockstep"] if clock == "lockstep" else ["--clock", "realtime"])
            + (["--speed", clock[1:]] if clock != "lockstep" else []),
            "tuner": ["--lease-timeout", str(LEASE)],
            "logger": ["--runs", str(self.runs)],
        }[service]
        module = {
            "router": "services.cli",
            "plant": "services.plant_sim",
            "tuner": "services.autotuner",
            "logger": "services.logger",
        }[service]
        # the router takes no --prefix: it routes every key
        args = ["router"] if service == "router" else ["--prefix", self.prefix, *own]
        n = sum(1 for _ in self.tmp.glob(f"{service}*.log"))
        with (self.tmp / f"{service}{n}.log").open("w") as f:
            self.procs[service] = start_service(module, [*args, *self.bus_args(service)], stderr=f)

    def logs(self) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}" for p in self.tmp.glob("*.log"))

    def status(self) -> LoopStatus:
        st = wire.query_one(self.session, keys.status(self.prefix, LOOP), LoopStatus, 10.0)
        assert st is not None, "the plant did not answer a status query"
        return st

    def close(self) -> None:
        self.session.close()
        for name in ("logger", "tuner", "plant", "router"):
            if name in self.procs:
                with_cont = self.procs[name]
                if with_cont.poll() is None:
                    with_cont.send_signal(signal.SIGCONT)
                stop_service(with_cont)


def _wait_listening(port: int, timeout: float = 20.0) -> None:
    """Block until something accepts TCP connections on 127.0.0.1:``port``."""
    deadline = time.monotonic() + timeout
    while True:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        if time.monotonic() > deadline:
            raise AssertionError(f"nothing listens on {port} after {timeout:g} s")
        time.sleep(0.05)


def _tune(stack: Stack) -> subprocess.Popen:
    case = stack.case
    args = ["tune", LOOP, "--json", "--method", case.method, "--prefix", stack.prefix]
    args += ["-m", stack.settings.mode, "-e", stack.endpoint, "--no-multicast-scouting"]
    if case.method == "relay" and case.clock != "lockstep":
        args += ["--tolerance", str(RT_TOLERANCE)]
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _watch(stack: Stack) -> tuple[queue.Queue, list[float]]:
    """Progress and events of the loop's runs, decoded, in order; and the wall times at which
    the plant said it took the loop back (a watchdog restore or a release)."""
    inbox: queue.Queue = queue.Queue()
    handbacks: list[float] = []
    fifo = zenoh.handlers.FifoChannel
    sub = stack.session.declare_subscriber(f"{keys.tune_root(stack.prefix, LOOP)}/*", fifo(65536))
    status = stack.session.declare_subscriber(keys.status(stack.prefix, LOOP), fifo(65536))

    def read() -> None:
        for s in sub:
            key = str(s.key_expr)
            model = {"progress": TuneProgress, "event": TunerEvent}.get(key.rsplit("/", 1)[-1])
            if model is not None:
                inbox.put(wire.decode_sample(model, s))

    def read_status() -> None:
        for s in status:
            if wire.decode_sample(LoopStatus, s).reason in ("watchdog", "release"):
                handbacks.append(time.monotonic())

    threading.Thread(target=read, daemon=True).start()
    threading.Thread(target=read_status, daemon=True).start()
    return inbox, handbacks


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_fault(tmp_path, case: Case):
    prefix = f"fm{id(case) % 100000}/{case.id}"
    stack = Stack(tmp_path, case, prefix)
    try:
        _run_case(stack)
    finally:
        stack.close()


def _run_case(stack: Stack) -> None:
    case = stack.case
    before = stack.status()
    inbox, handbacks = _watch(stack)
    client = _tune(stack)
    proc = stack.procs[case.target]
    deadline = time.monotonic() + 120.0
    while True:  # to the phase
        try:
            msg = inbox.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            client.kill()
            raise AssertionError(f"{case.phase} not reached:\n{stack.logs()}") from None
        if _phase_reached(case, msg):
            break
    if case.fault == "kill":
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        t_fault = t_begin = time.monotonic()
    elif case.fault == "pause":
        t_begin = time.monotonic()
        proc.send_signal(signal.SIGSTOP)
        time.sleep(case.pause)  # the fault itself: a pause of this length
        proc.send_signal(signal.SIGCONT)
        t_fault = time.monotonic()
    else:  # the router goes away and comes back on the same endpoint
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        t_fault = t_begin = time.monotonic()
        time.sleep(case.gap)  # the fault itself: the bus gone this long
        stack.start("router")
    out, err = client.communicate(timeout=120.0)
    ended = time.monotonic() - t_fault
    if case.target == "plant" and case.fault == "kill":
        stack.start("plant")  # a fresh instance: the tuner must have written nothing to it
        wait_for_token(stack.session, keys.loop_alive(stack.prefix, LOOP), 20.0)
    after = _settled_status(stack, before, case)
    back = [t - t_begin for t in handbacks if t >= t_begin]  # from the fault's start
    report = {
        "case": case.id,
        "restored_s": round(back[0], 3) if back else None,
        "ended_s": round(ended, 2),
        "exit": client.returncode,
    }
    print(json.dumps(report))
    context = f"{case.id}: exit {client.returncode}\nstdout {out[-2000:]}\nstderr {err[-2000:]}"
    context += f"\n{stack.logs()}"
    if case.expect == "gone":
        assert client.returncode == 2, context
        assert "its tuner is gone" in err and f"loop {LOOP} now: manual" in err, context
        assert ended < case.bound + 4.0, context  # + the client's grace for a late result
    else:
        assert client.returncode == (0 if case.expect == "ok" else 1), context
        result = json.loads(out)
        assert result["status"] == case.expect, context
        assert ended < case.bound, context
        if case.expect != "ok":
            assert result["reason"], context
        if case.fault == "pause" and case.target == "tuner":  # its own pause, not the plant's
            assert "lease lost" in result["reason"] or "paused" in result["reason"], context
        if case.fault == "pause" and case.target == "plant" and case.expect != "ok":
            assert "token is still up" in result["reason"], context  # silent, not gone
        if case.target == "plant" and case.expect != "ok" and not result["restored"]:
            # not seen restored: said to be not known, with what the plant does with it
            assert "the loop's state is not known" in result["reason"], context
            if case.fault == "kill":
                assert "a plant started again begins from its plant file" in result["reason"]
    if case.expect == "ok":
        assert after.mode == "auto", context
        isa = result["chosen"]["isa"]
        assert (after.gains.kc, after.gains.ti, after.gains.td) == (
            isa["kc"],
            isa["ti"],
            isa["td"],
        ), context
    else:
        assert (after.mode, after.op, after.sp, after.gains) == (
            before.mode,
            before.op,
            before.sp,
            before.gains,
        ), f"loop not restored: {after}\n{context}"
        assert after.leased_by is None, context
    if case.target == "plant" and case.fault == "kill":
        svc = wire.query_one(
            stack.session,
            keys.service_status(stack.prefix, "plant_sim", "*"),
            ServiceStatus,
            5.0,
        )
        assert svc is not None and svc.accepted == 0 and svc.rejected == 0, (svc, context)
    _recording_opens(stack)


def _settled_status(stack: Stack, before: LoopStatus, case: Case) -> LoopStatus:
    """The loop's status once the plant has had the last word (its watchdog acts on the
    run token's disappearance in milliseconds; a lease lapse within LEASE)."""
    deadline = time.monotonic() + LEASE + 5.0
    while True:
        st = stack.status()
        if st.leased_by is None or time.monotonic() > deadline:
            return st
        time.sleep(0.1)


def _recording_opens(stack: Stack) -> None:
    """Every run file opens with the mcap reader (recovered first if the logger died)."""
    case = stack.case
    if case.target == "logger" and case.fault == "kill":
        files = sorted(stack.runs.glob("*.mcap"))
        assert files, "the killed logger left no file"
        for f in files:
            fixed = f.with_suffix(".recovered.mcap")
            run = subprocess.run(
                [sys.executable, "-m", "services.cli", "recover", str(f), "-o", str(fixed)],
                capture_output=True,
                text=True,
            )
            assert run.returncode == 0, run.stderr
            recovered = int(run.stdout.split("recovered ", 1)[1].split(" ", 1)[0])
            assert recovered > 0, run.stdout  # what was flushed before the kill is kept
        return
    stop_service(stack.procs["logger"])  # finishes its files
    files = sorted(stack.runs.glob("*.mcap"))
    assert files, f"no recording:\n{stack.logs()}"
    from mcap.reader import make_reader

    for f in files:
        with f.open("rb") as fh:
            assert sum(1 for _ in make_reader(fh).iter_messages()) > 0
