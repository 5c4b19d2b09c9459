"""services/logger/record_form.py and the run file's format 2: the recorded form of each
message reads back as the bus had it; wall-clock log times; files of format 1 (sim-time log
times, the bus's JSON, pydantic's schemas) still read the same in every reader."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from services.cli import main
from services.logger.mcap_io import FORMAT_VERSION, RunWriter, log_time_zero, read_run
from services.logger.record_form import (
    DIALECT,
    RECORDED,
    bus_payload,
    recorded_payload,
    schema_of,
)
from shared import keys, wire
from shared.messages import (
    LoopInfo,
    PidGains,
    ProcessSample,
    TuneRequest,
    TuneResult,
    TunerEvent,
    Verification,
)
from tests.recorded_run import record_in_process

LOOP = "x1"
PLANT = {  # 1/((s+1)(s+2)(s+3))·6: a fast loop
    "seed": 7,
    "loops": {
        LOOP: {
            "model": "transfer_function",
            "num": [6.0],
            "den": [1.0, 6.0, 11.0, 6.0],
            "sample_time": 0.05,
            "noise_std": 0.002,
        }
    },
}
GAINS = PidGains(kc=2.0, ti=None, td=0.5)
VERIFY = Verification(
    gains=GAINS,
    sp_step=1.0,
    overshoot=None,
    decay_ratio=None,
    rise_time=2.0,
    settling_time=None,
    iae_sp=1.5,
    load_step=None,
    iae_load=None,
    max_deviation_load=None,
    recovery_time=None,
    stable=True,
    saturated=False,
    score=1.5,
)
INFO = LoopInfo(
    loop=LOOP,
    node="plant",
    t=0.0,
    model="transfer_function",
    description="",
    model_params={"num": [6.0], "den": [1.0, 6.0]},
    sample_time=0.05,
    pv_units="%",
    pv_range=(0.0, 100.0),
    op_limits=(0.0, 100.0),
    disturbances=[],
    noise_std=0.0,
    clock="lockstep",
    speed=1.0,
)
REQUEST = TuneRequest(loop=LOOP, repeat="auto", pv_limits=(10.0, 90.0))
MESSAGES = [
    TuneResult(
        run_id="r",
        loop=LOOP,
        t=3.0,
        method="relay",
        rule="zn-pi",
        status="ok",
        ku=None,
        before=VERIFY,
        after=VERIFY,
        step={"gain": None, "ok": True},
        previous_gains=GAINS,
    ),
    TunerEvent(
        run_id="r",
        loop=LOOP,
        t=1.0,
        kind="request",
        data={"request": REQUEST.model_dump_json(), "info": INFO.model_dump_json(), "n": None},
    ),
    TunerEvent(run_id="r", loop=LOOP, t=1.0, kind="cycle", data={"n": 1, "ku": None}),
    ProcessSample(loop=LOOP, seq=3, t=0.15, pv=1.0, sp=1.0, op=50.0, mode="auto"),
]


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: type(m).__name__)
def test_the_recorded_form_reads_back_as_the_bus_message(msg) -> None:
    recorded = recorded_payload(msg, wire.encode(msg))
    back = type(msg).model_validate_json(bus_payload(type(msg).__name__, recorded))
    if isinstance(msg, TunerEvent) and msg.kind == "request":  # the same request and info
        for name, model in (("request", TuneRequest), ("info", LoopInfo)):
            assert model.model_validate_json(back.data[name]) == model.model_validate_json(
                msg.data[name]
            )
        back = back.model_copy(update={"data": msg.data})
    assert back == msg


def test_a_field_that_is_none_is_left_out_a_maps_none_is_kept() -> None:
    obj = json.loads(recorded_payload(MESSAGES[0], wire.encode(MESSAGES[0])))
    assert "ku" not in obj and "reason" not in obj and "overshoot" not in obj["before"]
    assert "ti" not in obj["previous_gains"] and obj["step"] == {"gain": None, "ok": True}


def test_a_request_events_json_text_is_recorded_as_objects_without_nulls() -> None:
    msg = MESSAGES[1]
    data = json.loads(recorded_payload(msg, wire.encode(msg)))["data"]
    assert data["request"]["repeat"] == "auto" and data["request"]["pv_limits"] == [10.0, 90.0]
    assert "amplitude" not in data["request"] and "instance" not in data["info"]
    assert data["n"] is None  # a map's value: kept (the schema allows null there)


def test_every_schema_states_its_dialect_and_has_no_construct_foxglove_refuses() -> None:
    for name, model in RECORDED.items():
        text = json.dumps(schema_of(model))
        assert schema_of(model)["$schema"] == DIALECT, name
        assert '"$ref"' not in text and '"prefixItems"' not in text, name


def test_log_times_are_the_wall_clock_start_plus_sim_time(tmp_path: Path) -> None:
    wall_ns, t_start = 1_800_000_000_123_456_789, 12.5
    zero = log_time_zero(wall_ns, t_start)
    w = RunWriter(tmp_path / "a.mcap", log_time_zero=zero)
    for t in (12.5, 13.0, 20.25):
        m = ProcessSample(loop=LOOP, seq=round(t / 0.05), t=t, pv=1.0, sp=1.0, op=1.0, mode="auto")
        w.write(keys.pv("p", LOOP), ProcessSample, wire.encode(m), t)
    w.finish({})
    meta, records = read_run(w.path)
    assert meta["format"] == str(FORMAT_VERSION) and int(meta["log_time_zero"]) == zero
    assert [r.log_time for r in records] == [
        wall_ns,
        wall_ns + 500_000_000,
        wall_ns + 7_750_000_000,
    ]


def as_format_1(new: Path, old: Path) -> None:
    """Rewrite a run file as the logger wrote it before format 2: the bus's JSON, pydantic's
    own schemas, log time = sim time, metadata format 1."""
    meta, records = read_run(new)
    with new.open("rb") as f:
        times = [
            m.log_time
            for _, ch, m in make_reader(f).iter_messages(log_time_order=False)
            if not ch.topic.endswith("/run")
        ]
    zero = int(meta["log_time_zero"])
    with old.open("wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="autotune")
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        for r, ns in zip(records, times, strict=True):
            if r.schema not in schemas:
                raw = json.dumps(RECORDED[r.schema].model_json_schema()).encode()
                schemas[r.schema] = w.register_schema(r.schema, "jsonschema", raw)
            if r.topic not in channels:
                channels[r.topic] = w.register_channel(r.topic, "json", schemas[r.schema])
            w.add_message(channels[r.topic], log_time=ns - zero, data=r.data, publish_time=0)
        old_meta = {k: v for k, v in meta.items() if k not in ("log_time_zero", "namespace")}
        w.add_metadata("run", {**old_meta, "format": "1"})
        w.finish()


def test_a_format_1_file_reads_as_before_in_every_reader(tmp_path: Path, capsys) -> None:
    new, live = record_in_process(tmp_path / "new", "p", PLANT, LOOP, "relay")
    assert live.status == "ok", live.reason
    old = tmp_path / "old" / new.name
    old.parent.mkdir()
    as_format_1(new, old)
    (meta_new, recs_new), (meta_old, recs_old) = read_run(new), read_run(old)
    assert [(r.topic, r.data) for r in recs_old] == [(r.topic, r.data) for r in recs_new]
    assert recs_old[0].log_time < 10**12 < recs_new[0].log_time  # sim time / wall clock
    assert meta_old["format"] == "1" and meta_new["format"] == "2"
    for path in (old, new):
        assert main(["analyze", str(path), "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert (out["ku"], out["pu"]) == (live.ku, live.pu)
    assert main(["report", str(old), "-o", str(tmp_path / "r.png"), "--dpi", "10"]) == 0
    assert main(["runs", str(tmp_path / "old")]) == 0 and main(["runs", str(tmp_path / "new")]) == 0
