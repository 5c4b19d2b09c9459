"""Speed and scale of the product on this machine, measured side by side in one run.

Each measurement is a function returning a dataclass; ``autotune perf`` (perf_command.py)
runs them and prints absolute figures and ratios (machines differ, ratios less so). Every
service runs as a process on loopback with its own random key prefix and free TCP ports,
every wait is bounded and every process is stopped (try/finally).

* ``pingpong``: a ~150-byte JSON payload bounced between two processes over Zenoh, peer to
  peer on loopback (this process and a ponger started from this module): round trips/s, the
  limit of any lockstep exchange.
* ``inprocess``: a relay tune of hx1 against the plant in this process (no bus): samples/s,
  the numeric limit.
* ``lockstep``: plant_sim, the autotuner and the logger as processes; one ``autotune tune``
  (timed on the bus from its first progress message to its result: the CLI's start-up is
  not in it), then N at once on N loops of the same plant through the one tuner, then N more
  spread over N tuner processes: samples/s; and the CPU each service used during the single
  tune per sample (µs/sample).
* ``realtime``: a plant process serving L linear loops at R samples/s on the realtime clock,
  every sample subscribed to here: the fraction of real time it keeps (each loop's samples
  per wall second against R, from their arrival times; the slowest loop and the mean).
* ``logger``: synthetic runs (a start progress, samples, a result) published at increasing
  rates to a logger process; the highest rate whose file holds every sample sent and that
  the logger keeps up with; against the raw MCAP writer (RunWriter) in this process.
* ``demo``: the wall time of ``autotune demo``.

    python -m services.offline.perf pong ENDPOINT KEY   (the ponger; used by pingpong)
"""

from __future__ import annotations

import json
import math
import os
import secrets
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path

import numpy as np
import zenoh

from services.autotuner.commands.tune import submit
from services.autotuner.loop_client import wait_for_token
from services.autotuner.tuning import TuningRun
from services.launcher import free_tcp_port, start_service, stop_service
from services.logger.mcap_io import RunWriter, read_run
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from services.stack import Stack
from shared import keys, wire
from shared.errors import AutotuneError
from shared.messages import (
    LoggerStatus,
    ProcessSample,
    ServiceStatus,
    TuneProgress,
    TuneRequest,
    TuneResult,
)
from shared.session import ZenohSettings, open_session

PARTS = ("pingpong", "inprocess", "lockstep", "realtime", "logger", "demo")
HX = "heat_exchanger"  # the linear heat-exchanger preset (hx1 of the default plant)
HX_SAMPLE_TIME = 0.25  # s, its sample time
CLK_TCK = os.sysconf("SC_CLK_TCK")
PONG_LIFETIME = 300.0  # s: a ponger whose parent vanished ends by itself


@dataclass(frozen=True)
class Size:
    pingpong_count: int  # round trips timed
    realtime: tuple[tuple[int, float], ...]  # (loops, samples/s per loop) tried in turn
    realtime_seconds: float  # wall s measured per realtime size
    logger_rates: tuple[float, ...]  # samples/s tried in turn
    logger_seconds: float  # wall s of publishing per logger rate


SIZES = {
    "tiny": Size(200, ((10, 10.0),), 1.0, (500.0, 2000.0), 0.3),
    "normal": Size(
        5000,
        ((100, 10.0), (1000, 1.0), (1000, 10.0), (10000, 1.0)),
        5.0,
        (5000.0, 20000.0, 40000.0, 80000.0, 160000.0),
        2.0,
    ),
}


def _settings(endpoint: str, listen: bool = False) -> ZenohSettings:
    """A peer on loopback that listens on ``endpoint`` or connects to it, no scouting."""
    if listen:
        return ZenohSettings(mode="peer", listen=(endpoint,), no_multicast_scouting=True)
    return ZenohSettings(
        mode="peer",
        connect=(endpoint,),
        cfg=("connect/timeout_ms:10000",),
        no_multicast_scouting=True,
    )


def _client_args(endpoint: str) -> list[str]:
    return ["-e", endpoint, "--no-multicast-scouting", "--cfg", "connect/timeout_ms:10000"]


def _prefix(what: str) -> str:
    return f"perf{what}{os.getpid()}x{secrets.token_hex(3)}"


def _stat(pid: int) -> list[str] | None:
    """The fields of /proc/PID/stat after the command (field 3 on); None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return None


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (all its threads) and of its descendants —
    the tuner's compute workers are its work too — living or ended, s."""
    parent: dict[int, int] = {}
    for entry in os.scandir("/proc"):
        if entry.name.isdigit() and (fields := _stat(int(entry.name))) is not None:
            parent[int(entry.name)] = int(fields[1])
    family, total = {pid}, 0.0
    for p in sorted(parent):  # a child's pid may be below its parent's: close the family
        q = p
        while q in parent and q not in family and q > 1:
            q = parent[q]
        if q in family:
            family.add(p)
    for p in family:
        if (fields := _stat(p)) is not None:
            # utime, stime, and cutime, cstime: those of its children already ended
            total += sum(int(fields[i]) for i in (11, 12, 13, 14)) / CLK_TCK
    return total


# --- 1. raw Zenoh ping-pong -----------------------------------------------------------------


def payload(size: int = 150) -> bytes:
    """A JSON object of ``size`` bytes shaped like a process sample."""
    base = {"loop": "hx1", "seq": 12345, "t": 3086.25, "pv": 47.1234, "sp": 50.0, "op": 42.98}
    text = json.dumps({**base, "pad": ""}, separators=(",", ":"))
    return json.dumps(
        {**base, "pad": "x" * max(0, size - len(text))}, separators=(",", ":")
    ).encode()


def pong(endpoint: str, key: str) -> None:
    """The ponger: echo every ``<key>/ping`` on ``<key>/pong`` until killed (or the lifetime)."""
    with open_session(_settings(endpoint, listen=True)) as s:
        pub = s.declare_publisher(f"{key}/pong")
        sub = s.declare_subscriber(f"{key}/ping")  # a FIFO channel, read by one thread

        def echo() -> None:
            while True:
                pub.put(sub.recv().payload)

        threading.Thread(target=echo, daemon=True).start()
        time.sleep(PONG_LIFETIME)
    os._exit(0)


@dataclass
class PingPong:
    round_trips: int
    payload_bytes: int
    wall: float  # s
    rate: float  # round trips/s
    how: str = "two processes, zenoh-python peers on loopback TCP, put + FIFO-channel recv"


STOP = b"perf: stop"


def ping_pong(count: int, timeout: float = 60.0) -> PingPong:
    """``count`` round trips of a ~150-byte JSON payload with a ponger process."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    key = _prefix("pp")
    data = payload()
    proc = start_service("services.offline.perf", ["pong", endpoint, key])
    try:
        with open_session(_settings(endpoint)) as s:
            sub = s.declare_subscriber(f"{key}/pong")
            pub = s.declare_publisher(f"{key}/ping")
            deadline = time.monotonic() + 20.0
            while sub.try_recv() is None:  # until the ponger answers: up, the route known
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise AutotuneError("perf: the ponger did not answer within 20 s")
                pub.put(data)
                time.sleep(0.1)
            time.sleep(0.2)
            while sub.try_recv() is not None:
                pass
            # the wait is bounded: past the timeout, a stop reaches our own subscriber
            timer = threading.Timer(timeout, lambda: s.put(f"{key}/pong", STOP))
            timer.start()
            try:
                t0 = time.perf_counter()
                for _ in range(count):
                    pub.put(data)
                    if sub.recv().payload.to_bytes() == STOP:
                        raise AutotuneError(f"perf: ping-pong did not finish within {timeout:g} s")
                wall = time.perf_counter() - t0
            finally:
                timer.cancel()
            sub.undeclare()
    finally:
        stop_service(proc)
    return PingPong(count, len(data), wall, count / wall)


# --- 2. in-process experiment rate ----------------------------------------------------------


@dataclass
class InProcess:
    status: str
    samples: float  # sim_duration / sample_time
    wall: float  # s
    rate: float  # samples/s


def in_process() -> InProcess:
    """A relay tune of hx1 (the whole run: experiment, apply, verify) in this process."""
    text = files("services.plant_sim").joinpath("plants/default.toml").read_text()
    sim = build_plant(tomllib.loads(text), "default")["hx1"]
    t0 = time.perf_counter()
    result = TuningRun(LocalLoopClient(sim), TuneRequest(loop="hx1"), "perf").run()
    wall = time.perf_counter() - t0
    samples = result.sim_duration / sim.sample_time
    return InProcess(result.status, samples, wall, samples / wall)


# --- 3, 4. lockstep over the bus, CPU per sample --------------------------------------------


class TuneWatch:
    """Times the runs on the bus: first progress and result of each loop (monotonic s), and
    the services' CPU seconds at those moments."""

    def __init__(self, session: zenoh.Session, prefix: str, pids: dict[str, int]):
        self.prefix, self.pids = prefix, pids
        self.started: dict[str, float] = {}
        self.ended: dict[str, float] = {}
        self.cpu_start: dict[str, dict[str, float]] = {}
        self.cpu_end: dict[str, dict[str, float]] = {}
        self.results: dict[str, TuneResult] = {}
        self.done = threading.Condition()
        self._subs = [
            session.declare_subscriber(keys.tune_progress(prefix, "*"), self._progress),
            session.declare_subscriber(keys.tune_result(prefix, "*"), self._result),
        ]

    def _cpu(self) -> dict[str, float]:
        return {name: cpu_seconds(pid) for name, pid in self.pids.items()}

    def _progress(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse_tune_key(self.prefix, str(sample.key_expr))
        if parsed and parsed[0] not in self.started:
            self.cpu_start[parsed[0]] = self._cpu()
            self.started[parsed[0]] = time.monotonic()

    def _result(self, sample: zenoh.Sample) -> None:
        now, cpu = time.monotonic(), self._cpu()
        parsed = keys.parse_tune_key(self.prefix, str(sample.key_expr))
        if not parsed:
            return
        with self.done:
            self.ended[parsed[0]], self.cpu_end[parsed[0]] = now, cpu
            self.results[parsed[0]] = wire.decode_sample(TuneResult, sample)
            self.done.notify_all()

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


@dataclass
class Lockstep:
    loops: int
    statuses: list[str]
    samples: float  # in all: Σ sim_duration / sample_time
    wall: float  # s, first progress to last result on the bus (CLI start-up not included)
    rate: float  # samples/s in all
    submit_wall: float  # s, from the first request submitted to the last result seen


@dataclass
class LockstepReport:
    one: Lockstep
    many: Lockstep
    cpu_us_per_sample: dict[str, float]  # service → CPU µs per sample of the single tune
    many_tuners: Lockstep | None = None  # the same number at once, each through its own tuner


def _plant_file(path: Path, names: list[str], model: str, sample_time: float) -> None:
    lines = ["seed = 1", ""]
    for n in names:
        lines += [f"[loops.{n}]", f'model = "{model}"', f"sample_time = {sample_time!r}", ""]
    path.write_text("\n".join(lines))


def _tunes(
    watch: TuneWatch,
    session: zenoh.Session,
    loops: list[str],
    prefix: str,
    timeout: float,
    nodes: list[str] | None = None,
) -> Lockstep:
    """A relay tune of each of ``loops`` at once, each through the tuner of ``nodes`` at its
    place (default: the one named ``tuner``), submitted from this process as ``autotune
    tune`` submits (``submit``), one after the other in a few ms: N command-line processes
    starting at once would spend seconds of CPU importing on the cores the tunes run on."""
    t0 = time.perf_counter()
    nodes = nodes or ["tuner"] * len(loops)
    for loop, node in zip(loops, nodes, strict=True):
        submit(session, prefix, node, TuneRequest(loop=loop), timeout=min(30.0, timeout))
    with watch.done:
        done = watch.done.wait_for(
            lambda: all(lp in watch.results for lp in loops),
            timeout=max(1.0, timeout - (time.perf_counter() - t0)),
        )
    if not done:
        raise AutotuneError(f"perf: {len(loops)} tune(s) did not end within {timeout:g} s")
    submit_wall = time.perf_counter() - t0
    missing = [lp for lp in loops if lp not in watch.started]
    if missing:
        raise AutotuneError(f"perf: no progress seen on the bus for {', '.join(missing)}")
    samples = sum(watch.results[lp].sim_duration / HX_SAMPLE_TIME for lp in loops)
    wall = max(watch.ended[lp] for lp in loops) - min(watch.started[lp] for lp in loops)
    statuses = [watch.results[lp].status for lp in loops]
    if not (samples > 0 and wall > 0):  # a tune that ran no sample measures nothing
        why = "; ".join(
            f"{lp}: {watch.results[lp].status}, {watch.results[lp].reason}" for lp in loops
        )
        raise AutotuneError(f"perf: the tune(s) ran {samples:g} samples in {wall:.3g} s ({why})")
    return Lockstep(len(loops), statuses, samples, wall, samples / wall, submit_wall)


def lockstep(
    tunes: int, tuners: int = 0, timeout: float = 300.0, source: Path | None = None
) -> LockstepReport:
    """One tune, then ``tunes`` at once, through one plant, one tuner and one logger; then,
    with ``tuners`` > 1, ``tunes`` more at once on other loops spread over that many tuner
    processes (round robin); the services from ``source`` (default: this tree). First a
    tune through each tuner, not measured: a service's
    first run pays its start-up (its compute workers coming up, modules imported on first
    use), which is not the cost of a sample."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = _prefix("ls")
    many = [f"hx{i}" for i in range(1, tunes + 1)]
    spread = [f"hy{i}" for i in range(1, tunes + 1)] if tuners > 1 else []
    others = [f"tuner{i}" for i in range(2, tuners + 1)] if tuners > 1 else []
    nodes = ["tuner", *others]
    warm = [f"warm{i}" for i in range(len(nodes))]
    with tempfile.TemporaryDirectory() as tmp, tempfile.TemporaryFile("w+") as logs:
        plant = Path(tmp) / "plant.toml"
        _plant_file(plant, [*warm, "one", *many, *spread], HX, HX_SAMPLE_TIME)
        stack = Stack(prefix, _settings(endpoint), logs, source=source)
        try:
            pre = ["--prefix", prefix]
            stack.start(
                "plant",
                "services.plant_sim",
                [*pre, "--plant", str(plant)],
                ["-l", endpoint, "--no-multicast-scouting"],
            )
            zc = _client_args(endpoint)
            stack.start("tuner", "services.autotuner", pre, zc)
            stack.start("logger", "services.logger", [*pre, "--runs", f"{tmp}/runs"], zc)
            for node in others:  # idle until the last measurement
                stack.start(node, "services.autotuner", [*pre, "--node", node], zc)
            stack.wait_ready(
                [
                    keys.tuner_alive(prefix, "tuner"),
                    *(keys.tuner_alive(prefix, node) for node in others),
                    keys.logger_alive(prefix, "logger"),
                    keys.loop_alive(prefix, "one"),
                    keys.loop_alive(prefix, [*many, *spread][-1]),
                ]
            )
            pids = {name: stack.procs[name].pid for name in ("plant", "tuner", "logger")}
            with open_session(_settings(endpoint)) as s:
                watch = TuneWatch(s, prefix, pids)
                try:
                    _tunes(watch, s, warm, prefix, timeout, nodes)
                    one = _tunes(watch, s, ["one"], prefix, timeout)
                    cpu = {
                        name: 1e6
                        * (watch.cpu_end["one"][name] - watch.cpu_start["one"][name])
                        / one.samples
                        for name in pids
                    }
                    par = _tunes(watch, s, many, prefix, timeout)
                    by_node = [nodes[i % len(nodes)] for i in range(len(spread))]
                    apart = _tunes(watch, s, spread, prefix, timeout, by_node) if spread else None
                finally:
                    watch.close()
        finally:
            for node in others:  # the stack stops the services it knows by name
                stop_service(stack.procs.pop(node), timeout=30.0)
            stack.stop()
    return LockstepReport(one, par, cpu, apart)


# --- 5. realtime plant capacity -------------------------------------------------------------


@dataclass
class Realtime:
    loops: int
    rate: float  # samples/s per loop asked for
    wall: float  # s measured
    kept: float  # sim time advanced / wall time, the slowest loop (1.0: keeps real time)
    kept_mean: float  # the same, mean over the loops
    overruns: int  # realtime periods started late, during the measurement
    cpu: float  # the plant process's CPU s per wall s (1.0: one core busy)
    received: int = 0  # samples that reached the subscriber in this process
    start_s: float = 0.0  # s from the plant's start to its service token (loops built, declared)

    @property
    def samples_per_s(self) -> float:
        """Samples produced per wall second, all loops."""
        return self.loops * self.rate * self.kept_mean


class ArrivalLog:
    """Every pv sample's arrival (monotonic s) by key, from a subscriber on all loops: a
    loop's pace is its samples' spacing, measured to the tick (the plant's status gives sim
    time only to the sample period, 1 s at 1 sample/s)."""

    def __init__(self) -> None:
        self.on = False
        self.times: dict[str, list[float]] = {}

    def __call__(self, sample: zenoh.Sample) -> None:
        if self.on:
            now = time.monotonic()
            self.times.setdefault(str(sample.key_expr), []).append(now)

    def kept(self, loops: int, period: float) -> tuple[float, float, int]:
        """(slowest, mean, samples) of sim time per wall time, each loop's from the
        least-squares slope of its arrival times against the sample count (the delivery's
        jitter averages out); a loop with fewer than three arrivals kept nothing."""
        paces = []
        for t in self.times.values():
            if len(t) < 3:
                paces.append(0.0)
                continue
            k = np.arange(len(t), dtype=float)
            slope = np.polyfit(k, np.asarray(t) - t[0], 1)[0]  # wall s per sample
            paces.append(period / slope if slope > 0 else 0.0)
        paces += [0.0] * (loops - len(paces))
        received = sum(len(t) for t in self.times.values())
        return min(paces), sum(paces) / len(paces), received


def realtime(loops: int, rate: float, seconds: float, timeout: float = 120.0) -> Realtime:
    """A plant process serving ``loops`` linear loops at ``rate`` samples/s in realtime, every
    sample subscribed to in this process (as a logger would): how much of real time it keeps."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = _prefix("rt")
    with tempfile.TemporaryDirectory() as tmp, tempfile.TemporaryFile("w+") as logs:
        plant = Path(tmp) / "plant.toml"
        _plant_file(plant, [f"r{i}" for i in range(loops)], HX, 1.0 / rate)
        t0 = time.monotonic()
        proc = start_service(
            "services.plant_sim",
            [
                "--prefix",
                prefix,
                "--plant",
                str(plant),
                "--clock",
                "realtime",
                "-l",
                endpoint,
                "--no-multicast-scouting",
            ],
            stderr=logs,
        )
        try:
            key = keys.service_status(prefix, "plant_sim", "plant")
            arrivals = ArrivalLog()
            # a client of the plant: a peer subscriber pays per message in proportion to the
            # loops' liveliness tokens under the same keys (zenoh 1.10: ~350 samples/s with
            # 10,000 loops), which would measure the subscriber, not the plant
            client = ZenohSettings(
                mode="client",
                connect=(endpoint,),
                cfg=(f"connect/timeout_ms:{round(timeout * 1000)}",),  # the loops are built first
                no_multicast_scouting=True,
            )
            with open_session(client) as s:
                sub = s.declare_subscriber(keys.pv(prefix, keys.ANY), arrivals)
                alive = keys.service_alive(prefix, "plant_sim", "plant")  # announced last
                if not wait_for_token(s, alive, timeout):
                    raise AutotuneError(f"perf: a plant of {loops} loops did not come up")
                started = time.monotonic() - t0
                time.sleep(min(1.0, seconds / 2))  # past the start
                a, wa, ca = _status(s, key), time.monotonic(), cpu_seconds(proc.pid)
                arrivals.on = True
                time.sleep(max(seconds, 10.0 / rate))  # at least 10 samples a loop
                arrivals.on = False
                b, wb, cb = _status(s, key), time.monotonic(), cpu_seconds(proc.pid)
                sub.undeclare()
        finally:
            stop_service(proc)
    wall = wb - wa
    kept, kept_mean, received = arrivals.kept(loops, 1.0 / rate)
    return Realtime(
        loops,
        rate,
        wall,
        kept,
        kept_mean,
        b.overruns - a.overruns,
        (cb - ca) / wall,
        received,
        started,
    )


def _status(s: zenoh.Session, key: str) -> ServiceStatus:
    st = wire.query_one(s, key, ServiceStatus, 10.0)
    if st is None:
        raise AutotuneError("perf: the realtime plant stopped answering its status query")
    return st


# --- 6. logger capacity ---------------------------------------------------------------------


@dataclass
class LoggerTrial:
    rate: float  # samples/s asked for
    sent: int
    send_rate: float  # samples/s achieved by the sender
    written: int  # samples in the finished file
    dropped: int  # gaps the logger counted
    drain: float  # s from the last publish to the file finished
    kept_up: bool  # every sample written, none dropped, drained within 0.5 s + 10 % of the send
    reached: bool  # the sender achieved the rate (≥ 95 %): if not, the limit was the sender's


@dataclass
class LoggerReport:
    trials: list[LoggerTrial]
    capacity: float  # samples/s: the highest rate (or send rate) kept up with (0: none)
    at_least: bool  # every rate tried was kept up with: the capacity is a lower bound
    raw_writer: float  # samples/s of RunWriter in this process, the same messages
    raw_messages: int


def _run_messages(
    prefix: str, loop: str, run_id: str, n: int
) -> tuple[tuple[str, type, bytes, float], list[tuple[str, type, bytes, float]], tuple]:
    """(start progress, samples, result) of a synthetic run, encoded: (key, model, payload, t)."""
    ts = HX_SAMPLE_TIME
    start = TuneProgress(run_id=run_id, loop=loop, t=0.0, phase="start", message="relay")
    samples = [
        ProcessSample(
            loop=loop, seq=i, t=i * ts, pv=50.0 + math.sin(i / 20), sp=50.0, op=40.0, mode="manual"
        )
        for i in range(n)
    ]
    result = TuneResult(
        run_id=run_id, loop=loop, t=(n - 1) * ts, method="relay", rule="zn", status="ok"
    )
    pv = keys.pv(prefix, loop)
    return (
        (keys.tune_progress(prefix, loop), TuneProgress, wire.encode(start), 0.0),
        [(pv, ProcessSample, wire.encode(m), m.t) for m in samples],
        (keys.tune_result(prefix, loop), TuneResult, wire.encode(result), result.t),
    )


def raw_writer_rate(n: int) -> tuple[float, int]:
    """(samples/s, messages) of RunWriter writing a synthetic run of ``n`` samples."""
    start, samples, result = _run_messages("perf", "raw1", "raw", n)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        w = RunWriter(Path(tmp) / "raw.mcap")
        for key, model, data, t in [start, *samples, result]:
            w.write(key, model, data, t)
            w.flush_if_due()
        w.finish({"samples": str(n)})
        wall = time.perf_counter() - t0
    return n / wall, n + 2


def _logger_status(s: zenoh.Session, prefix: str) -> LoggerStatus | None:
    return wire.query_one(s, keys.logger_status(prefix, "logger"), LoggerStatus, 5.0)


def _logger_trial(
    s: zenoh.Session, prefix: str, runs: Path, index: int, rate: float, seconds: float
) -> LoggerTrial:
    loop, run_id = f"lg{index}", f"perf{index}"
    n = max(10, round(rate * seconds))
    start, samples, result = _run_messages(prefix, loop, run_id, n)
    token = s.liveliness().declare_token(keys.tune_running(prefix, loop))
    enc_start = wire.encoding_for(TuneProgress)
    enc_sample = wire.encoding_for(ProcessSample)
    block = zenoh.CongestionControl.BLOCK
    pub = s.declare_publisher(samples[0][0], encoding=enc_sample, congestion_control=block)
    try:
        s.put(start[0], start[2], encoding=enc_start, congestion_control=block)
        time.sleep(0.05)
        t0 = time.perf_counter()
        for i, (_, _, data, _) in enumerate(samples):
            ahead = i / rate - (time.perf_counter() - t0)
            if ahead > 0.001:
                time.sleep(ahead)
            pub.put(data)
        sent_wall = time.perf_counter() - t0
        last = time.monotonic()
        s.put(
            result[0], result[2], encoding=wire.encoding_for(TuneResult), congestion_control=block
        )
        limit = 0.5 + 0.1 * seconds
        deadline = last + max(10.0, 20 * limit)
        finished = None
        while time.monotonic() < deadline:
            st = _logger_status(s, prefix)
            if st is not None and st.finished_runs > index:
                finished = time.monotonic()
                break
            time.sleep(0.01)
    finally:
        pub.undeclare()
        token.undeclare()
    if finished is None:
        return LoggerTrial(rate, n, n / sent_wall, 0, 0, math.inf, False, False)
    path = next(runs.glob(f"*_{loop}_*_{run_id}.mcap"), None)
    if path is None:
        raise AutotuneError(f"perf: the logger finished run {run_id} but its file is not in {runs}")
    meta, _ = read_run(path)
    written, dropped = int(meta.get("samples", 0)), int(meta.get("dropped", 0))
    drain = finished - last
    kept = written == n and dropped == 0 and drain <= limit
    reached = n / sent_wall >= 0.95 * rate
    return LoggerTrial(rate, n, n / sent_wall, written, dropped, drain, kept, reached)


def logger_capacity(rates: tuple[float, ...], seconds: float) -> LoggerReport:
    """Synthetic runs at each of ``rates`` (stopping at the first not kept up with)."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = _prefix("lg")
    trials: list[LoggerTrial] = []
    with tempfile.TemporaryDirectory() as tmp, tempfile.TemporaryFile("w+") as logs:
        runs = Path(tmp) / "runs"
        proc = start_service(
            "services.logger",
            ["--prefix", prefix, "--runs", str(runs), "-l", endpoint, "--no-multicast-scouting"],
            stderr=logs,
        )
        try:
            with open_session(_settings(endpoint)) as s:
                if _logger_status(s, prefix) is None and _logger_status(s, prefix) is None:
                    raise AutotuneError("perf: the logger did not answer within 10 s")
                for i, rate in enumerate(rates):
                    trials.append(_logger_trial(s, prefix, runs, i, rate, seconds))
                    if not (trials[-1].kept_up and trials[-1].reached):
                        break
        finally:
            stop_service(proc)
    raw, messages = raw_writer_rate(max(1000, round(max(rates) * seconds)))
    capacity = max((min(t.rate, t.send_rate) for t in trials if t.kept_up), default=0.0)
    at_least = all(t.kept_up for t in trials)  # the sender's limit or the last rate tried
    return LoggerReport(trials, capacity, at_least, raw, messages)


# --- 7. autotune demo -----------------------------------------------------------------------


@dataclass
class Demo:
    wall: float  # s, the whole command as a process
    status: str


def demo(timeout: float = 300.0) -> Demo:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        run = subprocess.run(
            [sys.executable, "-m", "services.cli", "demo", "--runs", f"{tmp}/runs", "--json"],
            capture_output=True,
            text=True,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
        )
        wall = time.perf_counter() - t0
    try:
        status = str(json.loads(run.stdout).get("status", "?"))
    except (ValueError, AttributeError):
        status = f"exit {run.returncode}"
    return Demo(wall, status)


@dataclass
class Report:
    size: str
    parts: dict[str, object] = field(default_factory=dict)
    seconds: float = 0.0  # wall s of the whole measurement


def _main(argv: list[str]) -> int:
    if len(argv) == 3 and argv[0] == "pong":
        pong(argv[1], argv[2])
        return 0
    print("usage: python -m services.offline.perf pong ENDPOINT KEY", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
