"""Run files read by independent readers: the TypeScript MCAP reader (``@mcap/core``), ajv
for the JSON Schema draft the schemas declare (2020-12), and Foxglove's own JSON Schema parser
(Lichtblick's ``parseJsonSchema``, in ``tests/node/parse_json_schema.js``).

A demo run (the real services, ``autotune demo``) and a ramp run (the live tuner's code
in-process, through the logger's recorder) are read in node (``tests/node/check_mcap.mjs``):
every message validates against its channel's schema and matches the datatypes Foxglove
derives; log times are the run's wall-clock start plus the sim time since; the demo records
under the topics of ``autotune up``. The packages are installed with ``npm ci`` on first use;
without node and npm the tests are skipped, saying so.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import re
import shutil
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import pytest
from mcap.reader import make_reader

from services.logger.mcap_io import read_run, topic_of
from services.logger.record_form import DIALECT, RECORDED, schema_of
from shared import keys
from shared.messages import LoopStatus, TuneResult, TunerEvent
from tests.recorded_run import record_in_process

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(
        shutil.which("node") is None or shutil.which("npm") is None,
        reason="node and npm are not installed: the independent readers (@mcap/core, ajv, "
        "Foxglove's parser) run in node",
    ),
]

NODE_DIR = Path(__file__).resolve().parents[1] / "node"
STAMP = NODE_DIR / "node_modules" / ".autotune-package-lock.sha256"
PREFIX = keys.DEFAULT_PREFIX  # what `autotune up` (and now the demo) records under
RAMP_LOOP = "x1"
RAMP_PLANT = {  # a fast third-order loop: 6/((s+1)(s+2)(s+3)), K_u = 10, ω_u = √11
    "seed": 5,
    "loops": {
        RAMP_LOOP: {
            "model": "transfer_function",
            "num": [6.0],
            "den": [1.0, 6.0, 11.0, 6.0],
            "sample_time": 0.05,
            "noise_std": 0.002,
        }
    },
}


@pytest.fixture(scope="module")
def node() -> Path:
    """tests/node with its packages installed (``npm ci`` once per lock file, one worker at a
    time: the others wait on the lock, each install bounded by its timeout)."""
    want = hashlib.sha256((NODE_DIR / "package-lock.json").read_bytes()).hexdigest()
    with (NODE_DIR / ".install.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not STAMP.is_file() or STAMP.read_text() != want:
            run = subprocess.run(
                ["npm", "ci", "--no-audit", "--no-fund"],
                cwd=NODE_DIR,
                capture_output=True,
                text=True,
                timeout=600,
            )
            assert run.returncode == 0, f"npm ci in {NODE_DIR} failed:\n{run.stderr}"
            STAMP.write_text(want)
    return NODE_DIR


@pytest.fixture(scope="module")
def checked(node, runs) -> dict[str, dict]:
    """What check_mcap.mjs found in each run file (one node process for both)."""
    names = list(runs)
    run = subprocess.run(
        ["node", str(node / "check_mcap.mjs"), *(str(runs[n][0]) for n in names)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    return dict(zip(names, json.loads(run.stdout)["files"], strict=True))


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, tuple[Path, dict, float, float]]:
    """{"demo": …, "ramp": …}: (file, the result as the run returned it, wall clock before
    and after the run, s since the epoch)."""
    tmp = tmp_path_factory.mktemp("node_runs")
    before = time.time()
    demo = subprocess.run(
        [sys.executable, "-m", "services.cli", "demo", "--json", "--runs", str(tmp / "demo")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert demo.returncode == 0, demo.stderr
    out = json.loads(demo.stdout)
    after = time.time()
    ramp_before = time.time()
    path, live = record_in_process(tmp / "ramp", PREFIX, RAMP_PLANT, RAMP_LOOP, "ramp")
    assert live.status == "ok", live.reason
    return {
        "demo": (Path(out["mcap"]), out, before, after),
        "ramp": (path, live.model_dump(mode="json"), ramp_before, time.time()),
    }


def test_foxglove_parser_takes_every_recorded_schema_and_refuses_pydantics_own(node) -> None:
    schemas = {name: schema_of(model) for name, model in RECORDED.items()}
    schemas["raw LoopStatus"] = LoopStatus.model_json_schema()  # anyOf [T, null], $ref
    schemas["raw TunerEvent"] = TunerEvent.model_json_schema()
    run = subprocess.run(
        ["node", str(node / "check_mcap.mjs"), "--schemas"],
        input=json.dumps(schemas),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    verdicts = json.loads(run.stdout)
    assert {n: v for n, v in verdicts.items() if not n.startswith("raw")} == {
        n: "ok" for n in RECORDED
    }
    # the check can fail: pydantic's schemas as they are (Optional fields) are refused
    assert verdicts["raw LoopStatus"] == "Unsupported type undefined for gains"  # a $ref
    assert verdicts["raw TunerEvent"] == "ok"  # a map with no properties is taken (and empty)
    assert all(schema_of(m)["$schema"] == DIALECT for m in RECORDED.values())


def test_a_demo_run_and_a_ramp_run_as_the_independent_readers_see_them(runs, checked) -> None:
    """One test for both runs: pytest-xdist would make the runs again on each worker."""
    for which in ("demo", "ramp"):
        every_message_validates_against_its_schema(runs[which][0], checked[which])
        log_times_are_the_wall_clock_start_plus_sim_time(runs[which], checked[which])
    the_demo_records_under_the_topics_of_autotune_up(checked["demo"])
    structured_data_is_recorded_as_objects_and_read_back_as_the_bus_had_it(runs["demo"])
    the_foxglove_layout_finds_every_series(runs["demo"][0])


def every_message_validates_against_its_schema(path: Path, f: dict) -> None:
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    count = summary.statistics.message_count
    assert f["errors"] == [] and f["error_count"] == 0
    assert f["messages"] == f["valid"] == f["statistics"]["messages"] == count > 1000
    assert f["chunk_indexes"] > 0 and f["statistics"]["channels"] == len(summary.channels)
    for name, s in f["schemas"].items():
        assert (s["encoding"], s["dialect"], s["foxglove"], s["ajv"]) == (
            "jsonschema",
            DIALECT,
            "ok",
            "ok",
        ), name
    # optional numbers stay plottable: Foxglove types them as numbers
    assert {"ku", "pu", "ku_percent", "noise"} <= set(f["schemas"]["TuneResult"]["numeric"])
    assert {"ku", "pu", "cycles"} <= set(f["schemas"]["TuneProgress"]["numeric"])
    assert {"pv", "sp", "op", "t"} <= set(f["schemas"]["ProcessSample"]["numeric"])


def log_times_are_the_wall_clock_start_plus_sim_time(run: tuple, f: dict) -> None:
    _, _, before, after = run
    meta = f["metadata"]["run"]
    zero = int(meta["log_time_zero"])
    timed = [(int(ns), t) for _, ns, t in f["times"] if t is not None]
    assert len(timed) == f["messages"] - sum(1 for _, _, t in f["times"] if t is None) > 1000
    assert all(ns == zero + round(t * 1e9) for ns, t in timed)
    start = datetime.fromisoformat(meta["started"]).timestamp()
    t_start = min(t for _, t in timed)
    assert abs((zero + t_start * 1e9) / 1e9 - start) < 1e-3  # the run's start, on the wall
    assert before <= start <= after


def the_demo_records_under_the_topics_of_autotune_up(f: dict) -> None:
    loop = "hx1"
    assert topic_of(keys.pv(PREFIX, loop)) == "/autotune/plant/hx1/pv"  # the README's path
    assert {
        topic_of(k)
        for k in (
            keys.pv(PREFIX, loop),
            keys.status(PREFIX, loop),
            keys.tune_progress(PREFIX, loop),
            keys.tune_event(PREFIX, loop),
            keys.tune_result(PREFIX, loop),
            keys.tune_run_record(PREFIX, loop),
        )
    } <= set(f["channels"])
    assert all(t.startswith(f"/{PREFIX}/") for t in f["channels"])
    meta = f["metadata"]["run"]
    assert meta["prefix"] == PREFIX and meta["namespace"].startswith("demo")


def structured_data_is_recorded_as_objects_and_read_back_as_the_bus_had_it(run: tuple) -> None:
    path, out, _, _ = run
    with path.open("rb") as fh:
        raw = [
            (ch.topic, json.loads(m.data))
            for _, ch, m in make_reader(fh).iter_messages(log_time_order=False)
        ]
    request_events = [o for t, o in raw if t.endswith("/event") and o["kind"] == "request"]
    (record,) = [o for t, o in raw if t.endswith("/run")]
    (event,) = request_events
    assert isinstance(event["data"]["request"], dict) and isinstance(event["data"]["info"], dict)
    assert event["data"]["request"]["loop"] == "hx1"
    assert record["request"] == event["data"]["request"] and record["info"]["loop"] == "hx1"
    assert record["result"]["ku"] == out["ku"] and record["ku"] == out["ku"]
    # the readers get the bus's messages back: the request as JSON text, the result whole
    meta, records = read_run(path)
    assert not any(r.key.endswith("/run") for r in records)
    (ev,) = [
        TunerEvent.model_validate_json(r.data)
        for r in records
        if r.key.endswith("/event") and b'"request"' in r.data
    ]
    assert json.loads(ev.data["request"]) == event["data"]["request"]
    (res,) = [TuneResult.model_validate_json(r.data) for r in records if r.key.endswith("/result")]
    assert res == TuneResult.model_validate_json(json.dumps(_result(out)))
    assert TuneResult.model_validate_json(meta["result"]) == res


def _result(out: dict) -> dict:
    """The demo's --json output without the fields the demo adds to the result."""
    return {k: v for k, v in out.items() if k not in ("mcap", "report", "mcap_incomplete", "exact")}


LAYOUT = Path(__file__).resolve().parents[2] / "foxglove" / "tuning-run.json"
FILTER = re.compile(
    r'^(?P<topic>/[^.{]+)(\{(?P<field>\w+)=="(?P<value>[^"]*)"\})?(?P<path>(\.\w+)*)$'
)


def leaves(node) -> list[str]:
    return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])


def the_foxglove_layout_finds_every_series(path: Path) -> None:
    """Every panel of foxglove/tuning-run.json shows data of the run: each message path
    resolves, in at least one message, to a number (plots) or a text (states, indicator)."""
    layout = json.loads(LAYOUT.read_text())
    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])
    with path.open("rb") as fh:
        by_topic: dict[str, list[dict]] = {}
        for _, ch, m in make_reader(fh).iter_messages(log_time_order=False):
            by_topic.setdefault(ch.topic, []).append(json.loads(m.data))
    wanted: list[tuple[str, type]] = []
    for panel, config in layout["configById"].items():
        kind = panel.split("!")[0]
        if kind in ("Plot", "StateTransitions"):
            wanted += [(p["value"], float if kind == "Plot" else str) for p in config["paths"]]
        elif kind == "Indicator":
            wanted.append((config["path"], str))
        elif kind == "RawMessages":
            wanted.append((config["topicPath"], dict))
    assert {"/autotune/plant/hx1/pv.pv", "/autotune/plant/hx1/pv.sp"} <= {v for v, _ in wanted}
    assert {"/autotune/plant/hx1/pv.op", "/autotune/tune/hx1/result"} <= {v for v, _ in wanted}
    for value, kind in wanted:
        m = FILTER.match(value)
        assert m is not None, value
        found = []
        for msg in by_topic.get(m["topic"], []):
            if m["field"] and str(msg.get(m["field"])) != m["value"]:
                continue
            for name in filter(None, m["path"].split(".")):
                msg = msg.get(name) if isinstance(msg, dict) else None
            found.append(msg)
        ok = [x for x in found if isinstance(x, int | float if kind is float else kind)]
        assert ok, f"{value}: no {kind.__name__} in the demo run's messages"
