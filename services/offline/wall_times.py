"""Wall times of a tune, measured rather than asserted in the tests (a loaded CI machine makes
any fixed limit flaky): one relay tune of the heat-exchanger preset (hx1) in-process, the same
tune over the bus (plant_sim and the autotuner as processes, the CLI as a client), and the
whole `autotune demo`.

The in-process tune is the yardstick measured in the same run: the other two are printed as
multiples of it, so their cost (processes, Zenoh, lockstep round trips, the report figure) reads
the same on a fast or a slow machine. Each also gives simulated seconds per wall second.

    python -m services.offline.wall_times [--what in-process,bus,demo] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import asdict, dataclass
from importlib.resources import files

from services.autotuner.tuning import TuningRun
from services.launcher import free_tcp_port
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from services.stack import Stack
from shared import json_text, keys
from shared.messages import TuneRequest
from shared.session import ZenohSettings

HELP = "wall time of a relay tune (in-process, over the bus) and of the demo"
LOOP = "hx1"  # the heat-exchanger preset of the default plant file
MEASURES = ("in-process", "bus", "demo")


@dataclass
class WallTime:
    what: str
    wall: float  # s, measured around the whole thing (process start-up included)
    status: str  # the run's status: a wall time of a failed run means little
    sim_duration: float  # s of simulated plant time the run covered
    ratio: float | None = None  # wall / the in-process tune's wall, when that was measured

    @property
    def speed(self) -> float:
        """Simulated seconds per wall second."""
        return self.sim_duration / self.wall if self.wall > 0 else float("inf")


def in_process_tune() -> WallTime:
    """The relay tune of hx1 against the plant in this process: the computation alone."""
    text = files("services.plant_sim").joinpath("plants/default.toml").read_text()
    sim = build_plant(tomllib.loads(text), "default")[LOOP]
    t0 = time.perf_counter()
    result = TuningRun(LocalLoopClient(sim), TuneRequest(loop=LOOP), "wall-times").run()
    wall = time.perf_counter() - t0
    return WallTime("in-process", wall, result.status, result.sim_duration)


def _cli(args: list[str]) -> tuple[float, dict]:
    """``autotune <args> --json`` as a process: (wall time, its JSON result)."""
    t0 = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-m", "services.cli", *args, "--json"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    wall = time.perf_counter() - t0
    if not run.stdout:
        raise SystemExit(f"autotune {' '.join(args)} gave no result:\n{run.stderr}")
    return wall, json.loads(run.stdout)


def bus_tune() -> WallTime:
    """plant_sim and the autotuner as processes (started and ready before the clock starts),
    `autotune tune hx1` timed as the user would see it."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = f"walltimes{os.getpid()}"
    client = ZenohSettings(
        mode="peer",
        connect=(endpoint,),
        cfg=("connect/timeout_ms:10000",),
        no_multicast_scouting=True,
    )
    with tempfile.TemporaryFile("w+") as logs:
        stack = Stack(prefix, client, logs)
        try:
            stack.start(
                "plant",
                "services.plant_sim",
                ["--prefix", prefix],
                ["-l", endpoint, "--no-multicast-scouting"],
            )
            zenoh_client = [
                "-e",
                endpoint,
                "--no-multicast-scouting",
                "--cfg",
                "connect/timeout_ms:10000",
            ]
            stack.start("tuner", "services.autotuner", ["--prefix", prefix], zenoh_client)
            stack.wait_ready([keys.tuner_alive(prefix, "tuner"), keys.loop_alive(prefix, LOOP)])
            wall, r = _cli(["tune", LOOP, "--prefix", prefix, *zenoh_client[:3]])
        finally:
            stack.stop()
    return WallTime("bus", wall, r["status"], r["sim_duration"])


def demo() -> WallTime:
    """`autotune demo` end to end: three services started, the tune, the recording, the
    report figure, everything stopped."""
    with tempfile.TemporaryDirectory() as tmp:
        wall, r = _cli(["demo", "--runs", os.path.join(tmp, "runs")])
    return WallTime("demo", wall, r["status"], r["sim_duration"])


def measure(what: list[str]) -> list[WallTime]:
    run = {"in-process": in_process_tune, "bus": bus_tune, "demo": demo}
    out = [run[w]() for w in MEASURES if w in what]
    base = next((m.wall for m in out if m.what == "in-process"), None)
    for m in out:
        m.ratio = m.wall / base if base else None
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--what",
        default=",".join(MEASURES),
        help="which to measure: in-process, bus, demo (default all; ratios need in-process)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON document on stdout")


def run(args: argparse.Namespace) -> int:
    what = [w.strip() for w in args.what.split(",") if w.strip()]
    unknown = sorted(set(what) - set(MEASURES))
    if unknown or not what:
        raise SystemExit(f"wall_times: --what {args.what!r}: choose from {', '.join(MEASURES)}")
    results = measure(what)
    if args.json:
        print(json_text.dumps([{**asdict(m), "speed": m.speed} for m in results], indent=2))
        return 0
    print(f"relay tune of {LOOP} (heat exchanger), wall times:")
    for m in results:
        ratio = f"  ×{m.ratio:5.1f} the in-process tune" if m.ratio is not None else ""
        print(f"  {m.what:<10} {m.wall:6.2f} s  {m.status:<8} {m.speed:7.0f} sim s per s{ratio}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.offline.wall_times", description=HELP)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
