"""Wall time per sample of the phases where the loop's own PID is in charge: a ramp test's
closed-loop trials and the verification of the gains, over the bus and in this process.

Two ramp tunes of the heat-exchanger preset, one after the other on two loops, go through
plant_sim, the autotuner and the logger as processes on loopback; the progress messages on the
bus mark the phases (the experiment from ``quiet`` to ``identified``; the verification from the
first ``verify`` to ``done``) and carry their sim time, so each phase's samples are its sim
time over the sample time and its wall time is read where the messages arrive. That window
ends with the run's one-off work after the phase's last sample (the process model's fits
after the trials, the verification's figures after its last step): the phase's wall time
per sample while its samples flow (``flow_us_per_sample``) is read where the plant's samples
arrive, from the first message that carries one of the phase's samples to the one that
carries its last, and counts the samples between those arrivals (for services that send
a lockstep advance's samples as batches: ``_batches``). The first tune
of a fresh tuner (``bus``) also pays for the tuner's start-up meanwhile (its compute workers
start with its first run, and compete for the cores); the second (``bus_warm``) is the
steady state, the per-sample cost alone. The same tune in this process (no bus) is the
yardstick: its phases are timed by the run's own progress hook.

The services (and the CLI) can be started from another source tree (``source``): the same
measurement of an older version of the code, on the same machine, in the same run.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from services.autotuner.identify.experiments import Band
from services.autotuner.loop_client import wait_for_token
from services.autotuner.tuning import RunHooks, TuningRun
from services.launcher import free_tcp_port, start_service, stop_service
from services.offline import perf
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from services.plant_sim.simulation.loop import SimLoop
from shared import keys, wire
from shared.errors import AutotuneError
from shared.messages import ProcessSample, RecordStops, TuneProgress, TuneRequest, TuneResult
from shared.session import open_session

LOOP = "ph1"
WARM = "ph2"  # tuned after LOOP, the tuner warm
METHOD = "ramp"  # closed-loop trials, then the verification: both phases in one run
# phase → (progress phase that opens it, progress phase that closes it)
PHASES = {"trials": ("quiet", "identified"), "verify": ("verify", "done")}


@dataclass
class Phase:
    samples: float  # sim time of the phase / sample time
    wall: float  # s
    rate: float  # samples/s
    us_per_sample: float  # wall µs per sample
    # wall µs per sample while the phase's samples flow (its one-off analysis left out), and
    # the samples and wall s that figure is read over (None: no arrivals watched)
    flow_us_per_sample: float | None = None
    flow_samples: float | None = None
    flow_wall: float | None = None


@dataclass
class PhasesReport:
    status: str  # the bus run's status (a figure of a failed run means little)
    source: str  # the source tree the services ran from
    bus: dict[str, Phase]  # the first tune of a fresh tuner
    inprocess: dict[str, Phase]
    bus_warm: dict[str, Phase] | None = None  # the same tune next, the tuner warm


def _phases(
    marks: list[tuple[str, float, float]],
    ts: float,
    arrivals: list[tuple[float, float]] | None = None,
) -> dict[str, Phase]:
    """Each phase from its first opening mark to the first closing mark after it; ``marks``:
    (progress phase, sim time s, wall s) in order of arrival; ``arrivals``: (sim time s of
    the last sample a message of the plant carried, wall s it arrived), in order."""
    out: dict[str, Phase] = {}
    for name, (opens, closes) in PHASES.items():
        start = next((i for i, m in enumerate(marks) if m[0] == opens), None)
        if start is None:
            continue
        end = next((m for m in marks[start + 1 :] if m[0] == closes), None)
        if end is None:
            continue
        _, t0, w0 = marks[start]
        samples, wall = (end[1] - t0) / ts, end[2] - w0
        if samples > 0 and wall > 0:
            phase = Phase(samples, wall, samples / wall, 1e6 * wall / samples)
            if flow := _flow(arrivals or [], t0, end[1], ts):
                phase.flow_samples, phase.flow_wall = flow
                phase.flow_us_per_sample = 1e6 * flow[1] / flow[0]
            out[name] = phase
    return out


def _flow(
    arrivals: list[tuple[float, float]], t0: float, t1: float, ts: float
) -> tuple[float, float] | None:
    """(samples, wall s) from the arrival of the first message carrying a sample after sim
    time ``t0`` to that of the one carrying the sample at ``t1``: the samples counted are
    those after the first message's last (what arrived in the window). None if either end is
    not among the arrivals."""
    first = next(((t, w) for t, w in arrivals if t > t0 + 0.5 * ts), None)
    last = next(((t, w) for t, w in arrivals if t >= t1 - 0.5 * ts), None)
    if first is None or last is None:
        return None
    samples, wall = round((last[0] - first[0]) / ts), last[1] - first[1]
    return (float(samples), wall) if samples > 0 and wall > 0 else None


def _batches(source: Path) -> bool:
    """Whether the services of ``source`` send a lockstep advance's samples as batches: only
    then are the plant's messages watched for the flow figure. Why: an older tree's plant
    sends a message a sample, and a fourth subscriber to each slowed its phases by 7–20 %
    (measured side by side), which would flatter any comparison with it."""
    try:
        return "pv_batch" in (source / "shared" / "keys.py").read_text()
    except OSError:
        return False


def _last_t(payload: bytes) -> float | None:
    """Sim time of the last sample in a plant's ``pv`` or ``pv_batch`` message (the JSON read
    leniently: an older tree's services publish ``pv`` alone)."""
    try:
        msg = json.loads(payload)
        return float(msg["samples"][-1]["t"] if "samples" in msg else msg["t"])
    except (ValueError, KeyError, IndexError, TypeError):
        return None


class _TimedClient(LocalLoopClient):
    """The in-process loop client, each advance's last sample timed as it is handed over."""

    def __init__(self, sim: SimLoop, arrivals: list[tuple[float, float]]):
        super().__init__(sim)
        self.arrivals = arrivals

    def advance(
        self, steps: int, band: Band | None = None, record: RecordStops | None = None
    ) -> list[ProcessSample]:
        out = super().advance(steps, band, record)
        if out:
            self.arrivals.append((out[-1].t, time.perf_counter()))
        return out


def in_process() -> dict[str, Phase]:
    """The ramp tune against the plant in this process, its phases timed by its progress."""
    marks: list[tuple[str, float, float]] = []
    arrivals: list[tuple[float, float]] = []

    def note(p: TuneProgress) -> None:
        marks.append((p.phase, p.t, time.perf_counter()))

    sim = build_plant(
        {"seed": 1, "loops": {LOOP: {"model": perf.HX, "sample_time": perf.HX_SAMPLE_TIME}}}, "perf"
    )[LOOP]
    hooks = RunHooks(progress=note)
    client = _TimedClient(sim, arrivals)
    TuningRun(client, TuneRequest(loop=LOOP, method=METHOD), "perf", hooks).run()
    return _phases(marks, sim.sample_time, arrivals)


def _start(module: str, args: list[str], source: Path, logs) -> subprocess.Popen:
    """``python -m module args`` run from ``source`` (its code first on the path)."""
    return start_service(module, args, stderr=logs, stdout=subprocess.DEVNULL, source=source)


def over_bus(
    source: Path, timeout: float = 300.0
) -> tuple[str, dict[str, Phase], dict[str, Phase]]:
    """The ramp tune through plant_sim, the autotuner and the logger as processes (all, and
    the CLI, run from ``source``), on a fresh tuner and then again; (the statuses, the first
    tune's phases, the second's)."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = perf._prefix("ph")
    marks: dict[str, list[tuple[str, float, float]]] = {LOOP: [], WARM: []}
    # the plant's messages as they arrive (key, wall s, payload): read after the run, so the
    # watching costs this process little while the services work
    raw: list[tuple[str, float, bytes]] = []
    status: dict[str, str] = {}
    done = {LOOP: threading.Event(), WARM: threading.Event()}

    def on_progress(sample: zenoh.Sample) -> None:
        p = wire.decode_sample(TuneProgress, sample)
        if p.loop in marks:
            marks[p.loop].append((p.phase, p.t, time.perf_counter()))

    def on_samples(sample: zenoh.Sample) -> None:
        raw.append((str(sample.key_expr), time.perf_counter(), sample.payload.to_bytes()))

    def on_result(sample: zenoh.Sample) -> None:
        r = wire.decode_sample(TuneResult, sample)
        if r.loop in done:
            status[r.loop] = r.status
            done[r.loop].set()

    source = source.resolve()
    with tempfile.TemporaryDirectory() as tmp, tempfile.TemporaryFile("w+") as logs:
        plant = Path(tmp) / "plant.toml"
        perf._plant_file(plant, [LOOP, WARM], perf.HX, perf.HX_SAMPLE_TIME)
        zc = perf._client_args(endpoint)
        pre = ["--prefix", prefix]
        procs: list[subprocess.Popen] = []
        try:
            listen = ["-l", endpoint, "--no-multicast-scouting"]
            procs.append(
                _start("services.plant_sim", [*pre, "--plant", str(plant), *listen], source, logs)
            )
            procs.append(_start("services.autotuner", [*pre, *zc], source, logs))
            procs.append(
                _start("services.logger", [*pre, "--runs", f"{tmp}/runs", *zc], source, logs)
            )
            with open_session(perf._settings(endpoint)) as s:
                for key in (
                    keys.tuner_alive(prefix, "tuner"),
                    keys.logger_alive(prefix, "logger"),
                    keys.loop_alive(prefix, LOOP),
                    keys.loop_alive(prefix, WARM),
                ):
                    if not wait_for_token(s, key, 20.0):
                        raise AutotuneError(f"perf: {key} did not come up within 20 s")
                subs = [
                    s.declare_subscriber(keys.tune_progress(prefix, "*"), on_progress),
                    s.declare_subscriber(keys.tune_result(prefix, "*"), on_result),
                ]
                if _batches(source):
                    subs += [
                        s.declare_subscriber(keys.pv(prefix, "*"), on_samples),
                        s.declare_subscriber(keys.pv_batch(prefix, "*"), on_samples),
                    ]
                try:
                    for loop in (LOOP, WARM):
                        cli = _start(
                            "services.cli",
                            ["tune", loop, "--method", METHOD, *pre, "--json", *zc],
                            source,
                            logs,
                        )
                        procs.append(cli)
                        try:
                            cli.wait(timeout=timeout)
                        except subprocess.TimeoutExpired:
                            raise AutotuneError(
                                f"perf: the ramp tune of {loop} did not end within {timeout:g} s"
                            ) from None
                        if not done[loop].wait(10.0):
                            raise AutotuneError(f"perf: the ramp tune of {loop}: no result seen")
                finally:
                    for sub in subs:
                        sub.undeclare()
        finally:
            for p in reversed(procs):
                stop_service(p, timeout=30.0)
    statuses = status[LOOP] if status[WARM] == status[LOOP] else f"{status[LOOP]}, {status[WARM]}"
    arrivals: dict[str, list[tuple[float, float]]] = {LOOP: [], WARM: []}
    for key, wall, payload in raw:
        parsed = keys.parse_loop_key(prefix, key)
        t = _last_t(payload)
        if parsed is not None and parsed[0] in arrivals and t is not None:
            arrivals[parsed[0]].append((t, wall))
    ts = perf.HX_SAMPLE_TIME
    return (
        statuses,
        _phases(marks[LOOP], ts, arrivals[LOOP]),
        _phases(marks[WARM], ts, arrivals[WARM]),
    )


def phases(source: Path | None = None) -> PhasesReport:
    """The ramp tune's closed-loop phases over the bus (services from ``source``, default
    this tree) and in this process."""
    here = Path(__file__).resolve().parents[2]
    src = source or here
    status, bus, warm = over_bus(src)
    return PhasesReport(status, str(src), bus, in_process(), warm)
