"""Damaged run files for every command that reads them (analyze, report, runs, recover): a
real recorded run (made once, in-process: the live tuner's code over a plant_sim loop, its
traffic through the logger's recorder) and altered copies written with the ``mcap`` library —
missing, extra, renamed, mistyped fields, non-JSON payloads, a negative sample time, duplicate
and foreign records, channels with unknown schemas or encodings, future format versions,
truncated, empty and random files — plus seeded random damage. Every case: exit 2 and one
line naming the record (topic, index, log time), the field and the reason, or, where the
damage is harmless, the correct answer. ``autotune runs`` lists the good files and marks the
bad ones."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from services.cli import main
from services.logger.compare import compare, format_compare
from services.logger.report import build_report, load_report
from shared.messages import ProcessSample, TuneResult
from tests.recorded_run import record_in_process

PREFIX = "fuzz"
LOOP = "x1"
PLANT = {
    "seed": 3,
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
ROOT = Path(__file__).resolve().parents[1]


# --- a real run, recorded in-process ------------------------------------------------------


@dataclass(frozen=True)
class Recorded:
    path: Path
    live: TuneResult  # what the live run returned, not read from the file


def record_run(runs: Path, method: str, **request) -> Recorded:
    """One tuning run through the live tuner's code (TuningRun over an in-process loop), every
    message it and the loop publish handed to the logger's Recorder as the bus would."""
    path, live = record_in_process(runs, PREFIX, PLANT, LOOP, method, **request)
    assert live.status == ("ok" if request.get("apply", True) else "proposed"), live.reason
    return Recorded(path, live)


@pytest.fixture(scope="session")
def recorded(tmp_path_factory) -> dict[str, Recorded]:
    runs = tmp_path_factory.mktemp("recorded")
    return {
        "relay": record_run(runs / "relay", "relay"),
        "step": record_run(runs / "step", "step", rule="cc-pi", apply=False),
    }


# --- reading and rewriting MCAP files with the mcap library itself ------------------------


@dataclass(frozen=True)
class Msg:
    topic: str
    schema: str
    encoding: str
    log_time: int
    data: bytes
    schema_data: bytes = b"{}"

    def obj(self) -> dict:
        return json.loads(self.data)


def load(path: Path) -> tuple[list[Msg], list[tuple[str, dict[str, str]]]]:
    with path.open("rb") as f:
        reader = make_reader(f)
        msgs = [
            Msg(
                ch.topic,
                sc.name if sc else "",
                ch.message_encoding,
                m.log_time,
                m.data,
                sc.data if sc else b"",
            )
            for sc, ch, m in reader.iter_messages(log_time_order=False)
        ]
        meta = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
    return msgs, meta


def save(
    path: Path,
    msgs: list[Msg],
    meta: list[tuple[str, dict[str, str]]],
    compress: bool = True,
    chunk_size: int = 1024 * 1024,  # the mcap Writer's own default
) -> Path:
    with path.open("wb") as f:
        compression = CompressionType.ZSTD if compress else CompressionType.NONE
        w = Writer(f, compression=compression, chunk_size=chunk_size)
        w.start(profile="", library="fuzz")
        schemas: dict[str, int] = {"": 0}
        channels: dict[tuple[str, str, str], int] = {}
        for m in msgs:
            if m.schema not in schemas:
                schemas[m.schema] = w.register_schema(m.schema, "jsonschema", m.schema_data)
            key = (m.topic, m.schema, m.encoding)
            if key not in channels:
                channels[key] = w.register_channel(m.topic, m.encoding, schemas[m.schema])
            w.add_message(channels[key], log_time=m.log_time, data=m.data, publish_time=m.log_time)
        for name, data in meta:
            w.add_metadata(name, data)
        w.finish()
    return path


def nth(msgs: list[Msg], suffix: str, n: int = 0, where=None) -> int:
    """The file index of the n-th message on a topic ending with ``suffix`` (and ``where``)."""
    hits = [
        i
        for i, m in enumerate(msgs)
        if m.topic.endswith(suffix) and (where is None or where(m.obj()))
    ]
    return hits[n]


def with_data(m: Msg, obj_or_bytes) -> Msg:
    data = obj_or_bytes if isinstance(obj_or_bytes, bytes) else json.dumps(obj_or_bytes).encode()
    return replace(m, data=data)


def event(kind: str):
    return lambda o: o.get("kind") == kind


# --- the corpus --------------------------------------------------------------------------
# Each case: (id, source run, edit) where edit(msgs, meta) returns (msgs, meta, hit) and hit
# is the file index of the record the damage is in (None: not one record); and what each
# command must do: OK (the correct answer) or a list of needles of its one-line refusal
# (for ``runs``: of the row's reason).

OK = None
REC = "{hit}"  # stands for "the damaged record": its topic and index must be named


def edit_json(suffix: str, n: int, fn, where=None):
    def edit(msgs, meta):
        i = nth(msgs, suffix, n, where)
        msgs = list(msgs)
        o = msgs[i].obj()
        msgs[i] = with_data(msgs[i], fn(o))
        return msgs, meta, i

    return edit


def edit_event_data(kind: str, fn):
    def change(o):
        o["data"] = fn(dict(o["data"]))
        return o

    return edit_json("/event", 0, change, event(kind))


def drop(suffix: str, where=None):
    def edit(msgs, meta):
        keep = [
            m for m in msgs if not (m.topic.endswith(suffix) and (where is None or where(m.obj())))
        ]
        assert len(keep) < len(msgs)
        return keep, meta, None

    return edit


def duplicate(suffix: str, n: int, fn=None, where=None):
    def edit(msgs, meta):
        i = nth(msgs, suffix, n, where)
        copy = msgs[i] if fn is None else with_data(msgs[i], fn(msgs[i].obj()))
        return [*msgs, copy], meta, len(msgs)

    return edit


def append(topic: str, schema: str, data: bytes, encoding: str = "json"):
    def edit(msgs, meta):
        return [*msgs, Msg(topic, schema, encoding, msgs[-1].log_time, data)], meta, len(msgs)

    return edit


def rechannel(suffix: str, schema: str | None = None, encoding: str | None = None):
    def edit(msgs, meta):
        out = [
            replace(
                m,
                schema=schema if schema is not None else m.schema,
                encoding=encoding or m.encoding,
            )
            if m.topic.endswith(suffix)
            else m
            for m in msgs
        ]
        return out, meta, nth(msgs, suffix)

    return edit


def edit_meta(fn):
    def edit(msgs, meta):
        return msgs, [(n, fn(dict(d)) if n == "run" else d) for n, d in meta], None

    return edit


def each_event_of_another_run(msgs, meta):
    stale = [
        with_data(m, {**m.obj(), "run_id": "stale"})
        for m in msgs
        if m.topic.endswith(("/event", "/progress"))
    ]
    return msgs + stale, meta, None


def keep_first_pv(n: int):
    def edit(msgs, meta):
        seen = 0
        out = []
        for m in msgs:
            if m.topic.endswith("/pv"):
                seen += 1
                if seen > n:
                    continue
            out.append(m)
        return out, meta, None

    return edit


def set_(key, value):
    def fn(o):
        o[key] = value
        return o

    return fn


def delete(key):
    def fn(o):
        del o[key]
        return o

    return fn


def rename(key, new):
    def fn(o):
        o[new] = o.pop(key)
        return o

    return fn


PV_N = 500  # a sample in the middle of the experiment
CASES = [
    # (id, run, edit, {"analyze": …, "report": …, "runs": …}; missing commands: OK)
    (
        "pv-missing-field",
        "relay",
        edit_json("/pv", PV_N, delete("pv")),
        {"analyze": [REC, "pv: Field required"], "report": [REC, "pv: Field required"]},
    ),
    (
        "pv-extra-field",
        "relay",
        edit_json("/pv", PV_N, set_("quality", "good")),
        {"analyze": [REC, "quality: Extra inputs"], "report": [REC, "quality"]},
    ),
    (
        "pv-renamed-field",
        "relay",
        edit_json("/pv", PV_N, rename("pv", "PV")),
        {"analyze": [REC, "pv: Field required"], "report": [REC, "pv"]},
    ),
    (
        "pv-string-for-number",
        "relay",
        edit_json("/pv", PV_N, lambda o: {**o, "pv": str(o["pv"])}),
        {"analyze": [REC, "pv: Input should be a valid number"], "report": [REC, "pv"]},
    ),
    (
        "pv-not-json",
        "relay",
        edit_json("/pv", PV_N, lambda o: b"pv=50.1;sp=50"),
        {"analyze": [REC, "not JSON"], "report": [REC, "not JSON"]},
    ),
    (
        "pv-not-utf8",
        "relay",
        edit_json("/pv", PV_N, lambda o: b"\xff\xfe\x00{"),
        {"analyze": [REC, "not JSON"], "report": [REC, "not JSON"]},
    ),
    (
        "pv-empty-payload",
        "relay",
        edit_json("/pv", PV_N, lambda o: b""),
        {"analyze": [REC, "not JSON"], "report": [REC, "not JSON"]},
    ),
    (
        "pv-json-array",
        "relay",
        edit_json("/pv", PV_N, lambda o: [1, 2]),
        {"analyze": [REC], "report": [REC]},
    ),
    (
        "pv-negative-time",
        "relay",
        edit_json("/pv", PV_N, set_("t", -0.02)),
        {"analyze": [REC, "t: Input should be greater than or equal to 0"], "report": [REC, "t:"]},
    ),
    (
        "pv-nan",
        "relay",
        edit_json(
            "/pv",
            PV_N,
            lambda o: json.dumps(o).replace(f'"pv": {json.dumps(o["pv"])}', '"pv": NaN').encode(),
        ),
        {"analyze": [REC, "pv:"], "report": [REC, "pv:"]},
    ),
    (
        "pv-op-out-of-range",
        "relay",
        edit_json("/pv", PV_N, set_("op", 150.0)),
        {"analyze": [REC, "op:"], "report": [REC, "op:"]},
    ),
    (
        "pv-seq-string",
        "relay",
        edit_json("/pv", PV_N, lambda o: {**o, "seq": str(o["seq"])}),
        {"analyze": [REC, "seq:"], "report": [REC, "seq:"]},
    ),
    ("pv-duplicate-identical", "step", duplicate("/pv", PV_N), {}),
    (
        "pv-duplicate-different",
        "relay",
        duplicate("/pv", PV_N, lambda o: {**o, "pv": o["pv"] + 1.0}),
        {
            "analyze": [REC, "recorded before with other values"],
            "report": [REC, "recorded before with other values"],
        },
    ),
    (
        "pv-all-dropped",
        "relay",
        drop("/pv"),
        {"analyze": ["do not complete the relay test"], "report": ["no process samples"]},
    ),
    ("pv-tail-lost", "relay", keep_first_pv(300), {"analyze": ["do not complete the relay test"]}),
    (
        "request-not-json",
        "relay",
        edit_event_data("request", set_("request", "{")),
        {"analyze": [REC, "data.request", "not JSON"]},
    ),
    (
        "request-bad-method",
        "relay",
        edit_event_data("request", lambda d: {**d, "request": {**d["request"], "method": "guess"}}),
        {"analyze": [REC, "data.request.method"]},
    ),
    (
        "request-bad-rule",
        "relay",
        edit_event_data(
            "request", lambda d: {**d, "request": {**d["request"], "rule": "zn-banana"}}
        ),
        {"analyze": [REC, "data.request.rule"]},
    ),
    (
        "request-missing",
        "relay",
        edit_event_data("request", delete("request")),
        {"analyze": [REC, "data.request: missing"]},
    ),
    (
        "request-number",
        "relay",
        edit_event_data("request", set_("request", 5)),
        {"analyze": [REC, "data.request"]},
    ),
    (
        "setup-negative-sample-time",
        "relay",
        edit_event_data("experiment", set_("sample_time", -0.02)),
        {"analyze": [REC, "data.sample_time", "greater than 0"]},
    ),
    (
        "setup-zero-sample-time",
        "relay",
        edit_event_data("experiment", set_("sample_time", 0)),
        {"analyze": [REC, "data.sample_time"]},
    ),
    (
        "setup-sample-time-string",
        "relay",
        edit_event_data("experiment", set_("sample_time", "0.02")),
        {"analyze": [REC, "data.sample_time"]},
    ),
    (
        "setup-no-first-seq",
        "relay",
        edit_event_data("experiment", delete("first_seq")),
        {"analyze": [REC, "data.first_seq: Field required"]},
    ),
    (
        "setup-first-seq-negative",
        "relay",
        edit_event_data("experiment", set_("first_seq", -4)),
        {"analyze": [REC, "data.first_seq"]},
    ),
    (
        "setup-op-limits-reversed",
        "relay",
        edit_event_data("experiment", lambda d: {**d, "op_lo": d["op_hi"], "op_hi": d["op_lo"]}),
        {"analyze": [REC, "op_lo"]},
    ),
    (
        "setup-direction-zero",
        "relay",
        edit_event_data("experiment", set_("direction", 0.0)),
        {"analyze": [REC, "data.direction"]},
    ),
    (
        "setup-no-op-start",
        "relay",
        edit_event_data("experiment", delete("op_start")),
        {"analyze": [REC, "data.op_start: required"]},
    ),
    (
        "setup-op-start-null",
        "relay",
        edit_event_data("experiment", set_("op_start", None)),
        {"analyze": [REC, "data.op_start"]},
    ),
    (
        "setup-pv-limits-equal",
        "relay",
        edit_event_data("experiment", lambda d: {**d, "pv_hi": d["pv_lo"]}),
        {"analyze": [REC, "pv_lo"]},
    ),
    ("setup-unknown-key", "step", edit_event_data("experiment", set_("flux_capacitor", 1.21)), {}),
    (
        "experiment-dropped",
        "relay",
        drop("/event", event("experiment")),
        {"analyze": ["no experiment recorded"]},
    ),
    (
        "event-kind-missing",
        "relay",
        edit_json("/event", 0, delete("kind"), event("cycle")),
        {"analyze": [REC, "kind: Field required"], "report": [REC, "kind"]},
    ),
    (
        "event-data-list",
        "relay",
        edit_json("/event", 0, set_("data", [1, 2]), event("cycle")),
        {"analyze": [REC, "data"], "report": [REC, "data"]},
    ),
    (
        "event-negative-time",
        "relay",
        edit_json("/event", 0, set_("t", -1.0), event("cycle")),
        {"analyze": [REC, "t:"], "report": [REC, "t:"]},
    ),
    (
        "progress-phase-number",
        "step",
        edit_json("/progress", 3, set_("phase", 5)),
        {"report": [REC, "phase"]},
    ),
    (
        "progress-not-json",
        "step",
        edit_json("/progress", 3, lambda o: b"<xml/>"),
        {"report": [REC, "not JSON"]},
    ),
    (
        "status-garbage",
        "step",
        append(f"/{PREFIX}/plant/{LOOP}/status", "LoopStatus", b"garbage"),
        {},
    ),
    ("result-duplicate-identical", "step", duplicate("/result", 0), {}),
    (
        "result-duplicate-different",
        "relay",
        duplicate("/result", 0, set_("status", "failed")),
        {
            "analyze": [REC, "a second, different result"],
            "report": [REC, "a second, different result"],
        },
    ),
    (
        "result-of-another-run",
        "step",
        duplicate("/result", 0, lambda o: {**o, "run_id": "other", "ku": 1.0}),
        {},
    ),
    (
        "result-missing-field",
        "relay",
        edit_json("/result", 0, delete("status")),
        {"analyze": [REC, "status: Field required"], "report": [REC, "status"]},
    ),
    (
        "result-not-json",
        "relay",
        edit_json("/result", 0, lambda o: b"\x00\x01"),
        {"analyze": [REC, "not JSON"], "report": [REC, "not JSON"]},
    ),
    (
        "result-ku-string",
        "relay",
        edit_json("/result", 0, lambda o: {**o, "ku": "big"}),
        {"analyze": [REC, "ku"], "report": [REC, "ku"]},
    ),
    ("stale-messages-of-another-run", "step", each_event_of_another_run, {}),
    (
        "unknown-channel-unknown-schema",
        "step",
        append(f"/{PREFIX}/somewhere/else", "Mystery", b'{"a": 1}'),
        {},
    ),
    (
        "unknown-channel-binary",
        "step",
        append("/elsewhere", "", b"\x00\xff" * 10, encoding="cdr"),
        {},
    ),
    (
        "pv-channel-unknown-schema",
        "relay",
        rechannel("/pv", schema="Mystery"),
        {
            "analyze": [REC, "schema 'Mystery', expected ProcessSample"],
            "report": [REC, "schema 'Mystery'"],
        },
    ),
    (
        "pv-channel-protobuf",
        "relay",
        rechannel("/pv", encoding="protobuf"),
        {"analyze": [REC, "message encoding 'protobuf'"], "report": [REC, "protobuf"]},
    ),
    ("pv-channel-no-schema", "step", rechannel("/pv", schema=""), {}),
    (
        "meta-future-format",
        "relay",
        edit_meta(set_("format", "3")),
        {
            "analyze": ["format", "version 3", "upgrade"],
            "report": ["format", "version 3"],
            "runs": ["format", "version 3"],
        },
    ),
    (
        "meta-format-garbage",
        "relay",
        edit_meta(set_("format", "one")),
        {"analyze": ["format", "not a version number"], "report": ["format"], "runs": ["format"]},
    ),
    (
        "meta-format-zero",
        "relay",
        edit_meta(set_("format", "0")),
        {"analyze": ["format", "version 0"], "report": ["format"], "runs": ["format"]},
    ),
    ("meta-missing", "step", lambda msgs, meta: (msgs, [], None), {"runs": ["no 'run' metadata"]}),
    (
        "meta-run-id-wrong",
        "relay",
        edit_meta(set_("run_id", "zzz")),
        {"analyze": ["run_id", "'zzz'", "runrelay"]},
    ),
    (
        "meta-result-not-json",
        "relay",
        edit_meta(set_("result", "{oops")),
        {"runs": ["field result: not JSON"]},
    ),
    (
        "meta-result-ku-string",
        "relay",
        edit_meta(lambda d: {**d, "result": json.dumps({**json.loads(d["result"]), "ku": "big"})}),
        {"runs": ["result.ku"]},
    ),
    (
        "meta-samples-not-a-count",
        "relay",
        edit_meta(set_("samples", "many")),
        {"runs": ["field samples"]},
    ),
    (
        "meta-dropped-negative",
        "relay",
        edit_meta(set_("dropped", "-3")),
        {"runs": ["field dropped"]},
    ),
    ("meta-extra-keys", "relay", edit_meta(set_("operator", "jo")), {}),
    (
        "step-start-time-dropped",
        "step",
        drop("/event", event("step_started")),
        {"analyze": ["step's start time was not recorded"]},
    ),
    (
        "step-start-time-string",
        "step",
        edit_event_data("step_started", set_("t", "soon")),
        {"analyze": [REC, "data.t"]},
    ),
    (
        "step-start-time-negative",
        "step",
        edit_event_data("step_started", set_("t", -1)),
        {"analyze": [REC, "data.t"]},
    ),
    (
        "step-setup-no-op-start",
        "step",
        edit_event_data("experiment", delete("op_start")),
        {"analyze": [REC, "data.op_start: required for a step test"]},
    ),
    (
        "step-pv-string",
        "step",
        edit_json("/pv", 100, lambda o: {**o, "pv": "hot"}),
        {"analyze": [REC, "pv:"], "report": [REC, "pv:"]},
    ),
    ("relay-uncompressed", "relay", lambda msgs, meta: (msgs, meta, "uncompressed"), {}),
    ("step-untouched", "step", lambda msgs, meta: (msgs, meta, None), {}),
]


# Metadata fields that only ``runs`` reads: the other commands are not run on these.
RUNS_ONLY = {
    "meta-result-not-json",
    "meta-result-ku-string",
    "meta-samples-not-a-count",
    "meta-dropped-negative",
    "meta-extra-keys",
}


def build_case(
    tmp: Path, recorded: dict[str, Recorded], case
) -> tuple[Path, str | None, list[Msg]]:
    """Write the case's file; return it, the damaged record's 'topic message index' (or
    None) and the messages written."""
    cid, run, edit, _ = case
    msgs, meta = load(recorded[run].path)
    msgs, meta, hit = edit(msgs, meta)
    path = tmp / f"{cid}.mcap"
    save(path, msgs, meta, compress=hit != "uncompressed")
    where = f"{msgs[hit].topic} message {hit}" if isinstance(hit, int) else None
    return path, where, msgs


def cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def refused(code: int, err: str, what: str, needles: list[str]) -> None:
    assert code == 2, (what, code, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, (what, err)
    for n in needles:
        assert n in err, (what, n, err)


def answers_correctly(code: int, out: str, err: str, what: str, live: TuneResult) -> None:
    assert code == 0 and err == "", (what, err)
    a = json.loads(out)
    assert (a["ku"], a["pu"], a["step"]) == (live.ku, live.pu, live.step), what
    assert a["gains"] == live.gains and a["matches_live"] is True, what


def samples_in(msgs: list[Msg]) -> int:
    return len({m.obj()["seq"] for m in msgs if m.topic.endswith("/pv")})


# Harmless cases the report also draws (a figure costs 0.1 s; the others' series are read
# through the report's own loader and summary, which is all the figure is drawn from).
DRAWN = {"pv-duplicate-identical", "relay-uncompressed", "step-untouched", "meta-missing"}


@pytest.fixture(scope="module")
def case_files(recorded, tmp_path_factory) -> dict[str, tuple[Path, str | None, list[Msg]]]:
    folder = tmp_path_factory.mktemp("cases")
    return {case[0]: build_case(folder, recorded, case) for case in CASES}


def test_each_damaged_file_is_refused_in_one_line_or_read_correctly(
    recorded, case_files, tmp_path, capsys
):
    """analyze and report, in-process through the CLI's entry point, on every case."""
    from services.logger.report import _summary, load_series

    counts = {"refused": 0, "correct": 0}
    for cid, run, _, expect in CASES:
        if cid in RUNS_ONLY:
            continue
        path, where, msgs = case_files[cid]
        for command in ("analyze", "report"):
            what = f"{command} {cid}"
            needles = expect.get(command, OK)
            if command == "report" and needles is OK and cid not in DRAWN:
                series = load_series(path)
                assert series.t.size == samples_in(msgs) and _summary(series), what
                counts["correct"] += 1
                continue
            argv = (
                [command, str(path), "--json"]
                if command == "analyze"
                else [command, str(path), "-o", str(tmp_path / "r.png"), "--dpi", "10", "--json"]
            )
            code, out, err = cli(capsys, *argv)
            if needles is OK:
                if command == "analyze":
                    answers_correctly(code, out, err, what, recorded[run].live)
                else:
                    assert code == 0 and err == "", (what, err)
                    assert json.loads(out)["samples"] == samples_in(msgs), what
                counts["correct"] += 1
            else:
                refused(code, err, what, [str(path), *[where if n == REC else n for n in needles]])
                counts["refused"] += 1
    print(f"hand-made MCAP cases: {len(CASES)} files, {counts}")
    assert counts["refused"] > 60 and counts["correct"] > 20


CONTAINER = [
    # (id, make bytes from the good file's bytes, analyze/report needles, recover: rc)
    (
        "truncated-half",
        lambda b: b[: len(b) // 2],
        ["not a readable MCAP file", "autotune recover"],
        0,  # in its summary (its schemas again), past its one chunk: nothing lost
    ),
    (
        "truncated-in-its-chunk",
        lambda b: b[:3000],
        ["not a readable MCAP file", "autotune recover"],
        2,  # the fixture's run is one chunk: a part of it decompresses to nothing
    ),
    # it said "not a readable MCAP file (OSError: [Errno 22] Invalid argument)"
    ("truncated-to-magic", lambda b: b[:8], ["MCAP magic bytes and nothing after"], 2),
    ("footer-zeroed", lambda b: b[:-40] + bytes(40), ["not a readable MCAP file"], 0),
    ("zero-length", lambda b: b"", ["not an MCAP file"], 2),
    ("random-bytes", lambda b: np.random.default_rng(1).bytes(5000), ["not an MCAP file"], 2),
    (
        "magic-then-random",
        lambda b: b[:8] + np.random.default_rng(2).bytes(5000),
        ["not a readable MCAP file"],
        2,
    ),
    ("text-file", lambda b: b"started,loop\n2026,x1\n", ["not an MCAP file"], 2),
    (
        "chunk-bytes-flipped",
        lambda b: b[:2000] + bytes(x ^ 0xFF for x in b[2000:2050]) + b[2050:],
        ["fails its CRC check", "autotune recover"],
        2,
    ),
]


def test_damaged_containers_and_what_recover_makes_of_them(recorded, tmp_path, capsys):
    good = recorded["relay"].path.read_bytes()
    for cid, make, needles, recover_rc in CONTAINER:
        path = tmp_path / f"{cid}.mcap"
        path.write_bytes(make(good))
        for argv in (["analyze", str(path)], ["report", str(path), "-o", str(tmp_path / "r.png")]):
            code, _, err = cli(capsys, *argv)
            refused(code, err, f"{argv[0]} {cid}", [str(path), *needles])
        fixed = tmp_path / f"{cid}.fixed.mcap"
        code, out, err = cli(capsys, "recover", str(path), "-o", str(fixed))
        if recover_rc == 0:
            assert code == 0 and err == "" and "recovered" in out, (cid, err)
            code, _, err = cli(capsys, "analyze", str(fixed))  # what it made opens
            assert code in (0, 2) and "not a readable MCAP" not in err, (cid, err)
            assert len(err.strip().splitlines()) <= 1, (cid, err)
        else:  # nothing readable: said, exit 2, and no empty file left behind
            refused(code, err, f"recover {cid}", [str(path), "nothing to recover"])
            assert not fixed.exists(), cid
    folder = tmp_path / "a.mcap"
    folder.mkdir()
    for argv in (
        ["analyze", str(folder)],
        ["report", str(folder)],
        ["recover", str(folder), "-o", str(tmp_path / "x.mcap")],
    ):
        code, _, err = cli(capsys, *argv)
        refused(code, err, argv[0], ["is a directory, not a run file"])  # was "no such file"
    # a FIFO (or a device): recover said "no such file" where the others say what it is
    fifo = tmp_path / "fifo.mcap"
    os.mkfifo(fifo)
    for argv in (
        ["analyze", str(fifo)],
        ["recover", str(fifo), "-o", str(tmp_path / "x.mcap")],
    ):
        code, _, err = cli(capsys, *argv)
        refused(code, err, argv[0], ["not a regular file (a FIFO or a device)"])
    code, _, err = cli(capsys, "recover", str(recorded["relay"].path), "-o", str(tmp_path))
    refused(code, err, "recover -o DIR", ["is a directory"])
    # an existing file is not overwritten without --force (it was, without a word)
    kept = tmp_path / "kept.mcap"
    kept.write_bytes(b"someone's file")
    code, _, err = cli(capsys, "recover", str(recorded["relay"].path), "-o", str(kept))
    refused(code, err, "recover -o EXISTING", [str(kept), "exists already", "--force"])
    assert kept.read_bytes() == b"someone's file"
    code, out, _ = cli(capsys, "recover", str(recorded["relay"].path), "-o", str(kept), "--force")
    assert code == 0 and "recovered" in out and kept.read_bytes()[:8] == b"\x89MCAP0\r\n"
    # the flag named where it was not: "No such file or directory: /nowhere/o.mcap"
    nowhere = tmp_path / "nowhere" / "o.mcap"
    code, _, err = cli(capsys, "recover", str(recorded["relay"].path), "-o", str(nowhere))
    refused(code, err, "recover -o NOWHERE", [f"-o {nowhere}: no such directory"])
    # a file given as the runs directory: "no such directory" where it is there, a file
    code, _, err = cli(capsys, "runs", str(kept))
    refused(code, err, "runs FILE", [f"{kept}: not a directory (the logger's --runs)"])


def test_a_chunk_altered_after_it_was_written_is_refused_and_recover_leaves_it_out(
    recorded, tmp_path, capsys
):
    """One digit of a PV changed inside an uncompressed chunk is still valid JSON: every
    command read the altered sample without a word (a helper's flipped bit moved a PV by
    0.04 °C; another an output by 20 points for 168 samples), and `recover` copied it with
    new CRCs that hid the damage. The CRC the writer gave each chunk is checked: the readers
    refuse the file naming the chunk's sim times; `recover` copies the chunks that pass,
    says what it left out, and marks the run's metadata; `runs` lists it so."""
    msgs, meta = load(recorded["relay"].path)
    # the run in chunks of 16 kB, uncompressed
    path = save(tmp_path / "altered.mcap", msgs, meta, compress=False, chunk_size=16 * 1024)
    good = path.read_bytes()
    assert cli(capsys, "analyze", str(path))[0] == 0  # the rewritten file reads as the run
    at = good.index(b'"pv":', len(good) // 3) + len(b'"pv":')  # a PV a third of the way in
    digit = next(i for i in range(at, at + 30) if good[i : i + 1].isdigit() and good[i] != 57)
    path.write_bytes(good[:digit] + bytes([good[digit] + 1]) + good[digit + 1 :])
    for argv in (["analyze", str(path)], ["report", str(path), "-o", str(tmp_path / "r.png")],
                 ["replay", str(path), "--wait", "0"]):  # fmt: skip
        code, _, err = cli(capsys, *argv)
        refused(code, err, argv[0], [str(path), "fails its CRC check", "sim time"])
    fixed = tmp_path / "fixed.mcap"
    code, out, err = cli(capsys, "recover", str(path), "-o", str(fixed))
    assert code == 0 and err == "", err
    assert "1 chunk(s) left out" in out and "fails its CRC check" in out
    assert "the file's summary counts" in out
    kept = load(fixed)[0]
    assert 0 < len(kept) < len(msgs)  # the other chunks' messages, not the altered one's
    altered = {(m.topic, m.log_time, m.data) for m in kept} - {
        (m.topic, m.log_time, m.data) for m in msgs
    }
    assert altered == set()  # nothing that was changed was copied
    code, out, err = cli(capsys, "runs", str(tmp_path), "--json")
    row = next(r for r in json.loads(out) if r["file"] == "fixed.mcap")
    assert row["status"] == recorded["relay"].live.status and "left out" in row["lost"]
    code, out, err = cli(capsys, "runs", str(tmp_path))
    assert "(recovered, data lost)  fixed.mcap" in out


def test_recover_keeps_every_intact_chunk_whatever_the_damaged_one(recorded, tmp_path, capsys):
    """The first chunk damaged (it holds the schemas and channels, the logger writes each
    where it is first used): every message of the intact chunks after it was left out for
    want of its channel, 19 of 9,983 kept; a chunk whose compressed bytes no longer
    decompress ended the reading there, called "truncated" (review). Both lose that one
    chunk alone: the channels come from the summary, and the chunk is left out and said."""
    msgs, meta = load(recorded["relay"].path)
    # zstd chunks of 16 kB, as the logger's are compressed
    path = save(tmp_path / "run.mcap", msgs, meta, chunk_size=16 * 1024)
    good = path.read_bytes()
    with path.open("rb") as f:  # where the chunks' compressed bytes are
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) >= 4
    first = good.index(chunks[0].data)
    third = good.index(chunks[2].data)
    # the first chunk's uncompressed CRC (before its compression name and records length):
    # a byte flipped inside the compressed bytes instead was, by the recording's content,
    # sometimes a CRC failure and sometimes zstd's own "cannot be decompressed" (CI)
    crc_at = first - 8 - (4 + len(chunks[0].compression)) - 4
    assert good[crc_at : crc_at + 4] == chunks[0].uncompressed_crc.to_bytes(4, "little")
    for name, at, what in (("first", crc_at, "fails its CRC check"),
                           ("third", third, "cannot be decompressed")):  # fmt: skip
        bad = tmp_path / f"{name}.mcap"
        bad.write_bytes(good[:at] + bytes([good[at] ^ 0xFF]) + good[at + 1 :])
        fixed = tmp_path / f"{name}.fixed.mcap"
        code, out, err = cli(capsys, "recover", str(bad), "-o", str(fixed))
        assert code == 0 and "1 chunk(s) left out" in out and what in out, (name, out, err)
        kept = load(fixed)[0]  # all but one chunk's share, give or take
        assert len(msgs) - len(kept) < 2 * len(msgs) / len(chunks), (name, len(kept))


def test_runs_lists_the_good_files_and_marks_the_bad_ones(recorded, case_files, tmp_path, capsys):
    folder = tmp_path / "runs"
    folder.mkdir()
    for path, _, _ in case_files.values():
        (folder / path.name).symlink_to(path)
    expected: dict[str, list[str] | None] = {}
    run_of: dict[str, str] = {}
    for cid, run, _, expect in CASES:
        expected[f"{cid}.mcap"] = expect.get("runs", OK)
        run_of[f"{cid}.mcap"] = run
    good = recorded["relay"].path.read_bytes()
    for cid, make, needles, _ in CONTAINER:
        (folder / f"{cid}.mcap").write_bytes(make(good))
        expected[f"{cid}.mcap"] = ["MCAP"] if "MCAP" in " ".join(needles) else needles[:1]
    (folder / "zz-a-folder.mcap").mkdir()
    expected["zz-a-folder.mcap"] = ["is a directory"]
    code, out, err = cli(capsys, "runs", str(folder), "--json")
    assert code == 0 and err == "", err
    rows = {r["file"]: r for r in json.loads(out)}
    assert set(rows) == set(expected)
    for name, needles in expected.items():
        row = rows[name]
        if needles is OK:
            live = recorded[run_of[name]].live
            assert row["status"] == live.status and row["ku"] == live.ku and row["loop"] == LOOP
        else:
            assert row["status"] == "unreadable", row
            assert "\n" not in row["reason"] and all(n in row["reason"] for n in needles), row
    bad = sum(v is not OK for v in expected.values())
    few = tmp_path / "few"  # the table, on one good file and three bad ones
    few.mkdir()
    for name in ("step-untouched", "meta-future-format", "truncated-half", "zero-length"):
        (few / f"{name}.mcap").symlink_to(folder / f"{name}.mcap")
    code, out, err = cli(capsys, "runs", str(few))
    assert code == 0 and err == ""
    lines = out.splitlines()
    # a header, a row per file, and what ( ) means (the step test's gains, not applied)
    assert len(lines) == 7 and lines[0].startswith("started")
    assert lines[5].startswith("gains in ( ): computed by the run, not left on the loop")
    # and once, for the truncated one, what salvages a file a killed logger left
    assert lines[-1].startswith("a file not readable as MCAP") and "autotune recover" in lines[-1]
    assert sum("unreadable: " in ln for ln in lines) == 3
    assert " proposed  step-untouched.mcap" in out
    assert "unreadable: metadata 'run', field format" in out
    print(f"runs: {len(expected)} files, {bad} marked unreadable")


# --- seeded random damage -----------------------------------------------------------------

VALUES = [None, "", "x", -1, 0, -1e308, 1e308, 1e-320, True, [], {}, [1, "a"], {"k": None}, 2**70]


def random_record_damage(rng, msgs: list[Msg]) -> tuple[list[Msg], int]:
    """One record of a topic the commands read: a key deleted, added, renamed, or its value
    replaced (from VALUES, or a NaN token); or the payload cut short."""
    picks = [
        i for i, m in enumerate(msgs) if m.topic.endswith(("/pv", "/event", "/result", "/progress"))
    ]
    i = int(rng.choice(picks))
    o = msgs[i].obj()
    op = int(rng.integers(6))
    key = str(rng.choice(sorted(o)))
    if op == 0:
        del o[key]
        data = json.dumps(o).encode()
    elif op == 1:
        o[f"k{int(rng.integers(100))}"] = VALUES[int(rng.integers(len(VALUES)))]
        data = json.dumps(o).encode()
    elif op == 2:
        o[key.upper() + "_"] = o.pop(key)
        data = json.dumps(o).encode()
    elif op == 3:
        o[key] = VALUES[int(rng.integers(len(VALUES)))]
        data = json.dumps(o).encode()
    elif op == 4:
        data = (
            json.dumps(o).replace(json.dumps(o[key]), "NaN", 1).encode()
            if not isinstance(o[key], dict | list)
            else b"{"
        )
    else:
        data = msgs[i].data[: int(rng.integers(len(msgs[i].data)))]
    out = list(msgs)
    out[i] = replace(msgs[i], data=data)
    return out, i


def _valid(m: Msg) -> bool:
    """Whether the record is still valid as its topic's message (the models themselves)."""
    from pydantic import ValidationError

    from shared.messages import TuneProgress, TunerEvent

    model = {
        "pv": ProcessSample,
        "event": TunerEvent,
        "result": TuneResult,
        "progress": TuneProgress,
    }
    try:
        model[m.topic.rsplit("/", 1)[1]].model_validate_json(m.data)
    except ValidationError:
        return False
    return True


def test_seeded_random_damage_is_refused_in_one_line_or_answered(recorded, tmp_path, capsys):
    rng = np.random.default_rng(20261201)
    source, meta = load(recorded["relay"].path)
    outcome = {"refused": 0, "answered": 0}
    for k in range(25):
        msgs, hit = random_record_damage(rng, source)
        path = save(tmp_path / f"random{k}.mcap", msgs, meta)
        invalid = not _valid(msgs[hit])
        for argv in (
            ["analyze", str(path)],
            ["report", str(path), "-o", str(tmp_path / "r.png"), "--dpi", "10"],
        ):
            code, _, err = cli(capsys, *argv)
            assert code in (0, 2) and "Traceback" not in err, (k, argv[0], err)
            if code == 2:
                assert len(err.strip().splitlines()) == 1 and str(path) in err, (k, err)
                outcome["refused"] += 1
            if invalid and (argv[0] == "report" or not msgs[hit].topic.endswith("/progress")):
                # a record its own model refuses: named, whatever else is wrong
                assert code == 2 and f"{msgs[hit].topic} message {hit} " in err, (k, err)
            else:
                assert err == "", (k, err)
                outcome["answered"] += 1
    for k in range(20):  # bytes flipped, dropped or inserted anywhere in the container
        b = bytearray(recorded["relay"].path.read_bytes())
        pos = int(rng.integers(len(b)))
        if k % 3 == 0:
            b[pos : pos + 8] = rng.bytes(8)
        elif k % 3 == 1:
            del b[pos : pos + int(rng.integers(1, 64))]
        else:
            b[pos:pos] = rng.bytes(int(rng.integers(1, 64)))
        path = tmp_path / f"bytes{k}.mcap"
        path.write_bytes(bytes(b))
        for argv in (
            ["analyze", str(path)],
            ["recover", str(path), "-o", str(tmp_path / f"fix{k}.mcap")],
        ):
            code, _, err = cli(capsys, *argv)
            assert code in (0, 2) and "Traceback" not in err, (k, argv[0], err)
            assert len(err.strip().splitlines()) == (1 if code == 2 else 0), (k, err)
            outcome["refused" if code == 2 else "answered"] += 1
    print(f"random MCAP damage: 45 files, {outcome}")
    assert outcome["refused"] > 30


def test_through_real_interpreters_exit_2_one_line_no_traceback(recorded, tmp_path):
    msgs, meta = load(recorded["relay"].path)
    bad = save(tmp_path / "bad.mcap", *edit_json("/pv", PV_N, delete("pv"))(msgs, meta)[:2])
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(recorded["relay"].path.read_bytes()[:5000])
    # a copy of its own for `runs`: a footerless file another process has open (`report`,
    # reading it at the same moment) is listed as one a logger is writing (seen in CI)
    listed = tmp_path / "listed"
    listed.mkdir()
    (listed / "truncated.mcap").write_bytes(truncated.read_bytes())
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    runs = [
        (["analyze", str(bad)], 2, "pv: Field required"),
        (["report", str(truncated), "-o", str(tmp_path / "r.png")], 2, "autotune recover"),
        (["runs", str(listed)], 0, "unreadable: "),
    ]
    procs = [
        (
            argv,
            rc,
            needle,
            subprocess.Popen(
                [sys.executable, "-m", "services.cli", *argv],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                env=env,
            ),
        )
        for argv, rc, needle in runs
    ]
    for argv, rc, needle, proc in procs:  # started together: each is an interpreter's start-up
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == rc and "Traceback" not in err, (argv, err)
        assert len(err.strip().splitlines()) == (1 if rc == 2 else 0), (argv, err)
        assert needle in (err if rc == 2 else out), (argv, out, err)


def test_analyze_refuses_a_rule_the_run_does_not_give_and_reads_a_step_as_one(recorded, capsys):
    """A relay run has no open-loop rules: ``--rule zn-ol-pi`` printed an empty table, exit
    0. A step run's live comparison printed "K_u = None, P_u = None" (noticed last stop)."""
    relay, step = (str(recorded[k].path) for k in ("relay", "step"))
    code, _, err = cli(capsys, "analyze", relay, "--rule", "zn-ol-pi")
    refused(code, err, "analyze --rule zn-ol-pi", ["--rule zn-ol-pi", "relay test", "zn-pid"])
    code, out, _ = cli(capsys, "analyze", relay, "--rule", "zn-pid")
    assert code == 0 and out.splitlines()[-1].split()[0] == "zn-pid"
    code, out, err = cli(capsys, "analyze", step)
    assert code == 0 and err == "", err
    assert "None" not in out and "live run: its step response's figures → identical" in out


def test_analyze_says_samples_are_missing_from_the_record(recorded, tmp_path, capsys):
    """One sample taken out of the experiment (a gap in the loop's seq): analyze re-identified
    on the record with holes without a word (noticed last stop); it says how many are missing
    and where, as text and as ``missing_samples``."""
    msgs, meta = load(recorded["relay"].path)
    i = nth(msgs, "/pv", PV_N)
    gone = msgs[i].obj()["seq"]
    holed = save(tmp_path / "holed.mcap", [m for k, m in enumerate(msgs) if k != i], meta)
    code, out, err = cli(capsys, "analyze", str(holed))
    assert code == 0 and err == "", err
    assert f"WARNING: 1 samples missing from the record (the first gap after seq {gone - 1})" in out
    code, out, _ = cli(capsys, "analyze", str(holed), "--json")
    assert json.loads(out)["missing_samples"] == 1
    code, out, _ = cli(capsys, "analyze", str(recorded["relay"].path), "--json")
    assert json.loads(out)["missing_samples"] == 0


def test_replay_that_keeps_nothing_says_what_the_file_holds(recorded, capsys):
    """A filter that matches nothing printed "nothing to replay" and no more (noticed last
    stop): the file's loops, topics and length follow, so the filter can be set right. It is
    bad input, exit 2, naming the flag (it was exit 0: helper trial)."""
    path = str(recorded["relay"].path)
    for flag, extra in (
        ("--loop", ["--loop", "nosuch"]),
        ("--start-offset", ["--start-offset", "1e9"]),
        ("--topics", ["--topics", "/nonexistent"]),
    ):
        code, out, err = cli(capsys, "replay", path, "--wait", "0", *extra)
        assert code == 2 and out == "", out
        assert f"error: {flag}: nothing to replay: no message passes the filters; the file " in err
        assert "loop(s) " in err and "pv" in err and "s long" in err
        # its topics as --topics takes them: "/fuzz/plant/x1/pv", not "pv" (which matched none)
        assert f"/{PREFIX}/plant/{LOOP}/pv" in err, err


def test_replay_past_the_runs_start_says_a_logger_records_none_of_it(recorded, capsys):
    """``--start-offset`` past the run's start: a logger with --record-replays opens its file
    on the run's start, and recorded nothing of the replay, which said nothing (helper
    trial). It says so, on stderr; from the start, nothing is said."""
    path = str(recorded["relay"].path)
    code, out, err = cli(
        capsys, "replay", path, "--wait", "0", "--rate", "1e6", "--start-offset", "1"
    )
    assert code == 0 and out.startswith("replayed "), out
    assert "skips the run's start" in err and "--record-replays" in err, err
    code, out, err = cli(capsys, "replay", path, "--wait", "0", "--rate", "1e6", "--loop", LOOP)
    assert code == 0 and out.startswith("replayed ") and err == "", err


def test_analyze_blames_a_long_hole_not_the_end_of_the_recording(recorded, tmp_path, capsys):
    """A hundred samples cut out of a step test's response: analyze said the samples do not
    complete it because "the recording ends first", which it does not; it names the gap."""
    msgs, meta = load(recorded["step"].path)
    pv = [k for k, m in enumerate(msgs) if m.topic.endswith("/pv")]
    gone = set(pv[200:300])
    holed = save(tmp_path / "holed.mcap", [m for k, m in enumerate(msgs) if k not in gone], meta)
    code, _, err = cli(capsys, "analyze", str(holed))
    seq = msgs[pv[199]].obj()["seq"]
    said = f"100 samples are missing from the record (the first gap after seq {seq})"
    refused(code, err, "analyze", ["do not complete the step test", said])
    assert "the recording ends first" not in err
    # the report draws what is there, and says what is not
    fig = build_report(load_report(holed))
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert any(
        f"WARNING: 100 samples missing from the record (first after seq {seq})" in t for t in texts
    )
    # and draws no line across the hole: the trend's PV, setpoint and output break there (a
    # straight line across 344 missing samples of a relay looked like a record: helper trial)
    lines = [ln for ax in fig.axes for ln in ax.lines if ln.get_label() in ("PV", "output")]
    assert len(lines) == 2
    for ln in lines:
        y = np.asarray(ln.get_ydata(), dtype=float)
        assert np.isnan(y).sum() == 1, ln.get_label()
    # the model against the data stops at the hole: simulated across it, sample after sample,
    # the model ran on as if the samples after came straight after those before
    rep = load_report(holed)
    first_gone = msgs[pv[200]].obj()["t"]
    assert rep.overlay is not None and rep.overlay.hole == pytest.approx(first_gone)
    assert rep.overlay.end < first_gone
    title = next(ax.get_title() for ax in fig.axes if ax.get_title().startswith("model against"))
    assert f"up to the hole in the record at {first_gone:.6g} s" in title


def test_runs_compare_keeps_unlike_figures_apart(recorded):
    """A step test's L/T (its reaction curve's tangent) against a relay run's (its model's
    first-order equivalent) was given a change of +78 %: they are not one figure. Figures in %
    change by percentage points (a predicted overshoot of 0.0001 % against 10 % read
    +10,916,844.5 %)."""
    c = compare(recorded["relay"].path, recorded["step"].path)
    rows = {r["key"]: r for r in c["rows"]}
    lt = rows["l_over_t"]
    assert lt["unit"] == "model FOPDT | step tangent" and lt["change"] is None, lt
    over = rows["overshoot_pct"]
    assert over["points"] == pytest.approx(over["b"] - over["a"]), over
    text = format_compare(c)
    line = next(x for x in text.splitlines() if x.startswith("overshoot (predicted) (%)"))
    assert line.endswith(f"{over['points']:+.3g} pt"), line
    same = compare(recorded["relay"].path, recorded["relay"].path)
    lt = {r["key"]: r for r in same["rows"]}["l_over_t"]
    assert lt["unit"] == "model FOPDT" and lt["change"] == 0.0, lt
    # no label is cut short, however long its units
    long = {"key": "max_deviation_load", "label": "max deviation, load", "unit": "degC | m3/h"}
    c["rows"].append({**long, "a": 1.0, "b": 2.0, "change": 1.0})
    assert "max deviation, load (degC | m3/h) " in format_compare(c)


def test_runs_compare_gives_an_integrators_gain_as_a_rate(recorded, tmp_path):
    """An IPDT model's K is a rate (K' of K'·e^{−Ls}/s, PV/s per %): two level loops' IPDT
    models were compared as "model K (m/%)", and an IPDT's K against a lag model's static
    gain given a change in % (helper trial)."""
    msgs, meta = load(recorded["relay"].path)

    def ipdt(o):
        o["experiment"] = {**o["experiment"], "model": "ipdt"}
        return o

    msgs, meta, _ = edit_json("/result", 0, ipdt)(msgs, meta)
    integ = save(tmp_path / recorded["relay"].path.name, msgs, meta)
    both = {r["key"]: r for r in compare(integ, integ)["rows"]}["model_gain"]
    pv = recorded["relay"].live.pv_units or "PV unit"
    assert both["unit"] == f"{pv}/s per %" and both["change"] == 0.0, both
    mixed = {r["key"]: r for r in compare(recorded["relay"].path, integ)["rows"]}["model_gain"]
    assert mixed["unit"] == f"{pv}/% | {pv}/s per %" and mixed["change"] is None, mixed


def test_runs_compare_with_a_run_without_its_result_says_no_units_differ(recorded, tmp_path):
    """A run without its result (a recovered file of a killed logger) against a finished run
    of the same loop: "PV units differ (A degC, B —)" was said of a run whose units are not
    known, and the rows labelled in both (helper trial)."""
    msgs, meta = load(recorded["relay"].path)
    msgs, meta, _ = drop("/result")(msgs, meta)
    cut = save(tmp_path / recorded["relay"].path.name, msgs, meta)
    c = compare(recorded["relay"].path, cut)
    assert c["pv_units_differ"] is False, c
    ku = {r["key"]: r for r in c["rows"]}["ku"]
    assert " | " not in ku["unit"] and ku["b"] is None, ku
    assert "PV units differ" not in format_compare(c)


def test_runs_says_a_run_recorded_with_dropped_samples(recorded, tmp_path, capsys):
    """A logger paused 25 s in a relay run (realtime, ×5) dropped 344 of its samples: `runs`
    listed it plain "ok", while `analyze` found it "DIFFERENT" for the holes (helper
    trial). The count of dropped samples is in the listing's status."""
    msgs, meta = load(recorded["relay"].path)
    msgs, meta, _ = edit_meta(set_("dropped", "344"))(msgs, meta)
    folder = tmp_path / "runs"
    folder.mkdir()
    save(folder / recorded["relay"].path.name, msgs, meta)
    code, out, err = cli(capsys, "runs", str(folder))
    assert code == 0, err
    (line,) = [x for x in out.splitlines() if x.endswith(recorded["relay"].path.name)]
    assert "ok (344 samples dropped)" in line, line


@pytest.mark.parametrize("with_record", [False, True])
def test_a_recovered_file_is_listed_with_its_loop_and_method(
    recorded, tmp_path, capsys, with_record
):
    """A file whose logger was killed has no 'run' metadata (written as a run ends): the
    recovered file was listed "unreadable: no 'run' metadata record" (helper trial E). Recover
    gives it one from the file's name, status ``incomplete``; or, where the run's record
    (the metadata's copy, written with it as the run ended) was read, from that record."""
    good = recorded["relay"].path.read_bytes()
    # named as the logger names it, for the loop its samples are of (x1)
    broken = tmp_path / "20261204T232357Z_x1_relay_abcdef012345.mcap"
    # killed mid-run: its records as the logger wrote them, no 'run' metadata (written as a
    # run ends), no summary, the file never finished
    import io

    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import Writer

    with broken.open("wb") as f:
        w = Writer(f, chunk_size=4096)  # chunks written as they fill, as the logger flushes
        w.start(profile="", library="test")
        ids: dict[int, int] = {}
        records: set[int] = set()  # the channel of the run's record
        for rec in StreamReader(io.BytesIO(good), skip_magic=False).records:
            if isinstance(rec, Channel) and rec.topic.endswith("/run"):
                records.add(rec.id)
            if isinstance(rec, Message) and rec.channel_id in records and not with_record:
                continue  # killed before the run ended: its record never written
            if isinstance(rec, Schema) and rec.id not in ids:
                ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
            elif isinstance(rec, Channel) and -rec.id not in ids:
                ids[-rec.id] = w.register_channel(
                    rec.topic, rec.message_encoding, ids[rec.schema_id]
                )
            elif isinstance(rec, Message):
                w.add_message(ids[-rec.channel_id], rec.log_time, rec.data, rec.publish_time)
        # not finished: the chunk in progress and the summary never written
    out_dir = tmp_path / "fixed"
    out_dir.mkdir()
    fixed = out_dir / broken.name
    code, out, err = cli(capsys, "recover", str(broken), "-o", str(fixed))
    assert code == 0 and "recovered" in out, err
    code, out, err = cli(capsys, "runs", str(out_dir))
    assert code == 0, err
    (line,) = [x for x in out.splitlines() if x.endswith(fixed.name)]
    if with_record:  # the run's own start, figures and status
        meta = dict(load(recorded["relay"].path)[1])["run"]
        assert line.split()[:3] == [meta["started"][:19], "x1", "relay"], line
        # killed after the run's record (its last message, in a chunk of its own): every
        # message is there, its metadata rebuilt from the record; it was listed "recovered,
        # data lost" (helper trial)
        assert _messages(fixed) == _messages(recorded["relay"].path)
        assert "ok (recovered, metadata rebuilt)" in line, line
        return
    assert line.split()[:3] == ["2026-12-04T23:23:57", "x1", "relay"], line
    assert "incomplete" in line and "unreadable" not in line
    # a copy under another name: the run as its messages name it (it was listed "unreadable:
    # … has no run_id nor loop": helper trial)
    renamed = tmp_path / "killed.mcap"
    renamed.write_bytes(broken.read_bytes())
    fixed = out_dir / "killed_fixed.mcap"
    code, out, err = cli(capsys, "recover", str(renamed), "-o", str(fixed))
    assert code == 0, err
    code, out, err = cli(capsys, "runs", "--json", str(out_dir))
    row = next(r for r in json.loads(out) if r["file"] == fixed.name)
    assert (row["loop"], row["method"], row["status"]) == ("x1", "relay", "incomplete"), row


def test_a_truncated_file_recovered_is_listed_with_its_loss(recorded, tmp_path, capsys):
    """The first two thirds of a finished run's file, recovered, were listed `ok` with the
    whole run's sample count and no word of a loss (helper trial): a file that breaks off
    lost what came after, and its listing says so."""
    msgs, meta = load(recorded["relay"].path)
    # in chunks of 4 kB, as a long run's are (the run's file is one chunk): two thirds into
    # its data section, its last chunks and its metadata record cut off
    good = save(tmp_path / "chunked.mcap", msgs, meta, chunk_size=4096).read_bytes()
    cut = tmp_path / recorded["relay"].path.name
    cut.write_bytes(good[: 2 * _data_end(good) // 3])
    out_dir = tmp_path / "fixed"
    out_dir.mkdir()
    fixed = out_dir / cut.name
    code, out, err = cli(capsys, "recover", str(cut), "-o", str(fixed))
    assert code == 0 and "recovered" in out and "stopped at: truncated" in out, err
    assert "the file breaks off before its end" in out, out
    code, out, err = cli(capsys, "runs", str(out_dir), "--json")
    assert code == 0, err
    (row,) = json.loads(out)
    assert row["lost"] and "the file breaks off" in row["lost"], row
    code, out, err = cli(capsys, "runs", str(out_dir))
    assert f"{row['status']} (recovered, data lost)" in out, out


def _data_end(data: bytes) -> int:
    """Where a finished run file's DataEnd record starts (its footer's summary start, less
    the 13 bytes of that record): the end of its data section."""
    footer = data[-8 - 29 : -8]
    return int.from_bytes(footer[9:17], "little") - 13


def _messages(path) -> int:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return sum(1 for _ in make_reader(f).iter_messages())


def test_a_file_cut_in_its_summary_lost_nothing_and_says_so(recorded, tmp_path, capsys):
    """Ten bytes off the end (its footer), or a cut anywhere after its data section: every
    message is recovered, and it was listed "recovered, data lost", "the file breaks off
    (truncated: unpack requires a buffer of 4 bytes)" (helper trial)."""
    good = recorded["relay"].path.read_bytes()
    end = _data_end(good) + 13  # the data section and its DataEnd record whole
    for keep in (len(good) - 10, (end + len(good)) // 2):
        cut = tmp_path / f"cut{keep}" / recorded["relay"].path.name
        cut.parent.mkdir()
        cut.write_bytes(good[:keep])
        out_dir = tmp_path / f"fixed{keep}"
        out_dir.mkdir()
        fixed = out_dir / cut.name
        code, out, err = cli(capsys, "recover", str(cut), "-o", str(fixed))
        assert code == 0 and "no data lost" in out, (out, err)
        assert _messages(fixed) == _messages(recorded["relay"].path)
        code, out, err = cli(capsys, "runs", str(out_dir), "--json")
        (row,) = json.loads(out)
        assert not row["lost"] and row["status"] == "ok", row


def test_analyze_gives_the_designs_warnings_as_the_live_result_does(recorded, capsys):
    """`analyze` printed none of the design's warnings while its gains matched the live run's
    (an inverse response's "robustness … optimistic" left out: helper review). Every warning
    of the live result that the design gives (the run's own, of its verification, aside) is
    printed, once."""
    from services.logger.analysis import analyze_file

    rec = recorded["relay"]
    a = analyze_file(rec.path)
    assert a.selection is not None and a.selection.warnings  # the relay's, at least one
    code, out, _ = cli(capsys, "analyze", str(rec.path))
    assert code == 0
    for w in a.selection.warnings:
        assert w in rec.live.warnings and out.count(f"warning: {w}") == 1, (w, out)
    # the identification's notes too, in the order the live result gives them
    assert a.warnings == rec.live.warnings[: len(a.warnings)]
    assert set(a.ident.notes) <= set(a.warnings)


def test_analyze_gives_the_identifications_notes_as_the_live_result_does(tmp_path, capsys):
    """A step test of a lag with no dead time: the live result says the record did not
    resolve a dead time (a note of the identification, which the design's rules rest on);
    `analyze --json` left the identification's notes out (a relay's "cycle ran at −136°: K_u
    and P_u were not measured", a ramp's hold correction: helper review). Its warnings are
    the live result's, in order (no verification: the run proposed its gains)."""
    plant = {"seed": 3, "loops": {LOOP: {"model": "transfer_function", "num": [1.0],
             "den": [5.0, 1.0], "sample_time": 0.1, "noise_std": 0.002}}}  # fmt: skip
    path, live = record_in_process(tmp_path, PREFIX, plant, LOOP, "step", apply=False)
    assert live.status == "proposed" and "dead time not resolved" in live.warnings[0]
    code, out, _ = cli(capsys, "analyze", str(path), "--json")
    assert code == 0 and json.loads(out)["warnings"] == live.warnings
    code, out, _ = cli(capsys, "analyze", str(path))
    assert code == 0 and all(out.count(f"warning: {w}") == 1 for w in live.warnings), out


def test_a_second_run_metadata_record_is_refused_by_every_reader(recorded, tmp_path, capsys):
    """A second ``run`` metadata record naming another run: `report` drew that run ("status:
    ok", every panel "not available") while `analyze` refused it (helper review). The logger
    writes one; with two, which run the file holds is not known: every reader says so."""
    msgs, meta = load(recorded["relay"].path)
    run = next(m for name, m in meta if name == "run")
    bad = save(tmp_path / "two.mcap", msgs, [*meta, ("run", {**run, "run_id": "aaaaaaaaaaaa"})])
    for argv in (["analyze", str(bad)], ["report", str(bad), "-o", str(tmp_path / "r.png")]):
        code, _, err = cli(capsys, *argv)
        refused(code, err, argv[0], ["metadata 'run': 2 records, a run file has one"])
    assert not (tmp_path / "r.png").exists()


def test_runs_prints_no_control_character_of_a_file(recorded, tmp_path, capsys):
    """A status of "x\\n\\x1b[31mRED" in a file's metadata broke the table and passed a
    terminal escape straight through (helper review): written as its escapes, one row."""
    msgs, meta = load(recorded["relay"].path)
    meta = [(n, {**m, "status": "x\n\x1b[31mRED"} if n == "run" else m) for n, m in meta]
    save(tmp_path / "20260101T000000Z_x1_relay_abc.mcap", msgs, meta)
    code, out, _ = cli(capsys, "runs", str(tmp_path))
    assert code == 0 and "\x1b" not in out and "x\\n\\x1b[31mRED" in out, out
    assert out.splitlines()[1].endswith("x\\n\\x1b[31mRED  20260101T000000Z_x1_relay_abc.mcap")


def test_a_metadata_loop_that_none_of_the_samples_are_of_is_refused(recorded, tmp_path, capsys):
    """An hx1 run's metadata edited to say loop "f1": `analyze` said "relay test of f1" and the
    report was titled f1 (helper review). The samples' keys name the loop: a metadata loop
    none of them is of is refused by every reader, in one line."""
    msgs, meta = load(recorded["relay"].path)
    meta = [(n, {**m, "loop": "f1"} if n == "run" else m) for n, m in meta]
    bad = save(tmp_path / "loop.mcap", msgs, meta)
    for argv in (["analyze", str(bad)], ["report", str(bad), "-o", str(tmp_path / "r.png")]):
        code, _, err = cli(capsys, *argv)
        refused(code, err, argv[0], ["metadata 'run', field loop: 'f1', but its samples are of"])


def test_an_altered_run_metadata_record_fails_the_data_crc_and_recover_restores_it(
    recorded, tmp_path, capsys
):
    """One digit of the run's K_u changed in its metadata record (outside every chunk, so no
    chunk CRC saw it): `runs` listed K_u 3.544 for 2.544, `ok`, without a word (helper
    trial). The data section's CRC now refuses it, and `recover` takes the run's figures
    from its run record, a copy inside a chunk that passes its CRC."""
    good = recorded["relay"].path.read_bytes()
    meta = dict(load(recorded["relay"].path)[1])["run"]
    ku = meta["ku"]
    assert ku and ku[0] != "9"
    at = good.index(b"\x02\x00\x00\x00ku" + len(ku).to_bytes(4, "little") + ku.encode())
    at += 4 + 2 + 4  # the value's first digit
    bad = bytearray(good)
    bad[at] = ord(str(int(ku[0]) + 1))
    folder = tmp_path / "altered"
    folder.mkdir()
    path = folder / recorded["relay"].path.name
    path.write_bytes(bytes(bad))
    assert dict(load(path)[1])["run"]["ku"] != ku  # what a reader of the metadata sees
    code, out, err = cli(capsys, "runs", str(folder), "--json")
    assert code == 0, err
    (row,) = json.loads(out)
    assert row["status"] == "unreadable" and "fails the CRC" in row["reason"], row
    assert row["reason"].endswith("are not trusted"), row  # whole, the hint aside
    code, out, err = cli(capsys, "analyze", str(path))
    assert code == 2 and "its data section fails the CRC" in err and len(err.splitlines()) == 1
    fixed = tmp_path / "fixed" / path.name
    fixed.parent.mkdir()
    code, out, err = cli(capsys, "recover", str(path), "-o", str(fixed))
    assert code == 0 and "taken from its run record" in out, (out, err)
    code, out, err = cli(capsys, "runs", str(fixed.parent), "--json")
    (row,) = json.loads(out)
    # the written figure, the damage said; every message was there: no data lost
    assert repr(row["ku"]) == ku and row["rebuilt"] and not row["lost"], row
    code, out, err = cli(capsys, "runs", str(fixed.parent))
    assert "ok (recovered, metadata rebuilt)" in out, out
    code, out, err = cli(capsys, "analyze", str(fixed))
    assert code == 0, err


def test_a_foreign_mcap_file_is_said_to_be_no_run(tmp_path, capsys):
    """A valid MCAP file of something else: `runs --compare` printed a header of Nones and
    exit 0, `analyze` "no experiment recorded", `recover` made a run of it (helper trial)."""
    foreign = save(
        tmp_path / "foreign.mcap",
        [Msg("/foo", "Foo", "json", 1, b'{"x": 1}')],
        [],
    )
    for args in (
        ["analyze", str(foreign)],
        ["report", str(foreign), "-o", str(tmp_path / "x.png")],
    ):
        code, out, err = cli(capsys, *args)
        assert code == 2 and "not an autotune run file" in err, (args, err)
    code, out, err = cli(capsys, "runs", str(tmp_path), "--compare", str(foreign), str(foreign))
    assert code == 2 and "not an autotune run file" in err, (out, err)
    code, out, err = cli(capsys, "recover", str(foreign), "-o", str(tmp_path / "r.mcap"))
    assert code == 2 and "not an autotune run file" in err and not (tmp_path / "r.mcap").exists()


def test_compare_names_a_run_without_its_metadata_record_from_its_result(
    recorded, tmp_path, capsys
):
    """A run's messages without its 'run' metadata (a logger killed after the result):
    `runs --compare` headed it "None None run None ( UTC)" (helper trial)."""
    msgs, _ = load(recorded["relay"].path)
    bare = save(tmp_path / "bare.mcap", msgs, [])
    code, out, err = cli(capsys, "runs", str(tmp_path), "--compare", str(bare), str(bare))
    assert code == 0, err
    assert "None" not in out, out
    run_id = recorded["relay"].path.stem.rsplit("_", 1)[-1]
    assert f"x1 relay run {run_id}  (start not recorded)" in out, out


def test_a_file_the_library_cannot_read_is_said_cut_short_or_damaged_within(
    recorded, tmp_path, capsys
):
    """The mcap library's own words alone ("HEADER record has length 56673435648 that exceeds
    limit 4294967296" of a file cut at 100 bytes; "ZstdError: … Data corruption detected" of
    one byte changed in a chunk) said neither what happened nor what to do (helper trial)."""
    good = recorded["relay"].path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good[:100])
    code, _, err = cli(capsys, "analyze", str(cut))
    assert code == 2 and "it is cut short (no MCAP footer at its end" in err, err
    assert "autotune recover" in err and len(err.strip().splitlines()) == 1
    # without the library's words on the footer it did not find ("HEADER record has length
    # 56673435648 that exceeds limit 4294967296", of a SIGKILLed logger's file "unknown
    # (opcode 0) record has length 10557226335955058688 …": helper trial)
    assert "exceeds limit" not in err and "record has length" not in err, err
    chunk_start = 8 + 1 + 8  # after the magic and the Header record's opcode and length
    whole = bytearray(good)
    body = good.index(b"\x28\xb5\x2f\xfd", chunk_start)  # the chunk's zstd frame
    whole[body + 200] ^= 0xFF
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(whole))
    code, _, err = cli(capsys, "analyze", str(damaged))
    assert code == 2 and ("damaged within" in err or "fails its CRC" in err), err


def test_analyze_of_an_aborted_run_reports_the_same_abort(tmp_path, capsys):
    """An aborted run's file re-run offline ends as the live run did: `analyze` gave exit 2
    and, with --json, nothing, as for a damaged file (helper trial). It reports the abort,
    exit 0, and whether it is the live run's."""
    path, live = record_in_process(tmp_path, PREFIX, PLANT, LOOP, "relay", max_time=3.0)
    assert live.status == "aborted", live.reason
    code, out, err = cli(capsys, "analyze", str(path), "--json")
    assert code == 0, err
    got = json.loads(out)
    assert got["status"] == "aborted" and got["matches_live"] is True, got
    assert got["reason"] in live.reason and got["live"]["reason"] == live.reason
    code, out, err = cli(capsys, "analyze", str(path))
    assert code == 0 and "ends as the live run did (identical), aborted: " in out, (out, err)


def test_analyze_of_a_run_cancelled_mid_test_reports_the_runs_stop(tmp_path, capsys):
    """A run cancelled mid-relay (`tune --wait 2`, Ctrl-C) leaves a record that ends before
    the test does: `analyze` refused it, exit 2, as a file cut short ("the recording ends
    first": helper trial). It is the run's own stop, said as such, exit 0."""
    path, live = record_in_process(tmp_path, PREFIX, PLANT, LOOP, "relay", cancel_at=5.0)
    assert (live.status, live.reason) == ("aborted", "cancelled")
    code, out, err = cli(capsys, "analyze", str(path), "--json")
    assert code == 0, err
    got = json.loads(out)
    assert (got["status"], got["reason"], got["stopped_by_run"]) == ("aborted", "cancelled", True)
    assert got["matches_live"] is True
    code, out, err = cli(capsys, "analyze", str(path))
    assert code == 0 and "the live run stopped the test before it found anything" in out, err


def test_analyze_of_a_relay_aborted_at_its_limits_finds_its_reason(tmp_path, capsys):
    """A relay aborted at its PV limits: the live result's reason carries the relay's advice
    (the --amplitude that would keep to them) after the machine's own, which the re-run
    finds in it (the advice in the machine's reason made every such run recorded before it
    "not as the live run", review)."""
    path, live = record_in_process(tmp_path, PREFIX, PLANT, LOOP, "relay", pv_limits=(49.95, 50.05))
    assert live.status == "aborted" and "left its limits" in live.reason, live.reason
    assert "--amplitude" in live.reason or "too little" in live.reason, live.reason
    code, out, err = cli(capsys, "analyze", str(path), "--json")
    assert code == 0, err
    got = json.loads(out)
    assert got["matches_live"] is True and "--amplitude" not in got["reason"], got


def test_a_file_cut_within_its_metadata_record_keeps_the_runs_figures(recorded, tmp_path, capsys):
    """The run's record (its metadata as a message) is written in a chunk closed before the
    metadata record, so a file cut within that record still has the run's figures: recover
    takes them from it (review: the library wrote the record's chunk after the metadata)."""
    good = recorded["relay"].path.read_bytes()
    at = good.index(b"\x03\x00\x00\x00run") - 9  # the Metadata record: opcode, length
    assert good[at] == 0x0C
    cut = tmp_path / "cut" / recorded["relay"].path.name
    cut.parent.mkdir()
    cut.write_bytes(good[: at + 40])
    fixed = tmp_path / "fixed" / cut.name
    fixed.parent.mkdir()
    code, said, err = cli(capsys, "recover", str(cut), "-o", str(fixed))
    assert code == 0, err
    code, out, err = cli(capsys, "runs", str(fixed.parent), "--json")
    (row,) = json.loads(out)
    live = recorded["relay"].live
    assert (row["status"], row["ku"], row["pu"]) == (live.status, live.ku, live.pu), row
    # its metadata record was cut off: said, as rebuilt from the run's record; no message was
    # lost (it was listed "recovered, data lost", "the file breaks off": helper trial)
    assert row["rebuilt"] and not row["lost"], row
    assert "no data lost" in said, said
    assert _messages(fixed) == _messages(recorded["relay"].path)
    code, _, err = cli(capsys, "analyze", str(fixed))
    assert code == 0, err


def test_a_footer_pointing_past_the_end_is_recovered_not_an_internal_error(
    recorded, tmp_path, capsys
):
    """A footer whose summary offset points past the file's end: recover raised IndexError
    (exit 70) checking the data section's CRC (review)."""
    bad = bytearray(recorded["relay"].path.read_bytes())
    footer = len(bad) - 8 - 29
    bad[footer + 9 : footer + 17] = (10**12).to_bytes(8, "little")
    path = tmp_path / "footer.mcap"
    path.write_bytes(bytes(bad))
    code, out, err = cli(capsys, "recover", str(path), "-o", str(tmp_path / "fixed.mcap"))
    assert code in (0, 2) and "internal error" not in err, (out, err)
    code, out, err = cli(capsys, "analyze", str(path))
    assert code in (0, 2) and "internal error" not in err, (out, err)


def test_a_foreign_file_with_a_run_metadata_record_is_no_run(tmp_path, capsys):
    """A foreign MCAP that happens to have a 'run' metadata record of its own ({"foo":
    "bar"}): `runs` listed it as a blank run and `recover` copied it (helper trial)."""
    folder = tmp_path / "f"
    folder.mkdir()
    foreign = save(folder / "foreign.mcap", [Msg("/a", "Foo", "json", 1, b'{"x": 1}')],
                   [("run", {"foo": "bar"})])  # fmt: skip
    code, out, err = cli(capsys, "runs", str(folder), "--json")
    (row,) = json.loads(out)
    assert row["status"] == "unreadable" and "not an autotune run file" in row["reason"], row
    code, out, err = cli(capsys, "recover", str(foreign), "-o", str(tmp_path / "r.mcap"))
    assert code == 2 and "not an autotune run file" in err and not (tmp_path / "r.mcap").exists()
    code, out, err = cli(capsys, "analyze", str(foreign))
    assert code == 2 and "not an autotune run file" in err, err


def test_a_hole_in_the_recording_is_replayed_as_one_spacing():
    """A replay paced by log time went silent for a hole's length (samples a paused logger
    missed: 70 s at --rate 1), and a logger recording the replay ended its file incomplete at
    60 s of silence (review). A gap over 20 usual spacings (and 1 s) is replayed as one."""
    from services.logger.commands.replay import paced

    ns = [round(x * 1e9) for x in (0.0, 0.1, 0.1, 0.2, 0.3, 70.3, 70.4, 70.5)]
    schedule, cut = paced(ns)
    assert schedule == pytest.approx([0.0, 0.1, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    assert cut == pytest.approx(69.9)
    # no hole: the recording's own pace, to the ns
    schedule, cut = paced(ns[:5])
    assert schedule == pytest.approx([0.0, 0.1, 0.1, 0.2, 0.3]) and cut == 0.0
    # in file order, not time order (a lockstep advance's command before its samples): the
    # timeline's holes, not the file's jumps
    filed = [ns[0], ns[4], ns[1], ns[2], ns[3], ns[7], ns[5], ns[6]]
    schedule, cut = paced(filed)
    assert schedule == pytest.approx([0.0, 0.3, 0.1, 0.1, 0.2, 0.6, 0.4, 0.5])
    assert cut == pytest.approx(69.9)


def test_a_file_cut_where_its_last_bytes_read_as_a_footer_is_no_internal_error(tmp_path):
    """A run file cut short ends in the bytes of whatever it was cut in: where the byte a
    Footer's opcode would be at reads 0x02, its 'summary offset' was any 64-bit number, and
    ``recover`` (which checks the data section's CRC first) raised "cannot fit 'int' into an
    offset-sized integer" as an internal error (CI: a relay run cut at 3,000 bytes; one cut
    in about 400). Such a tail, with the offset past the file and past 2⁶³, is no footer."""
    from services.logger.mcap_io import MAGIC, data_section_problem

    for offset in (2**64 - 1, 2**63 + 5, 10**9):
        # MAGIC, some bytes, then what reads as opcode 0x02, length, summary offset, …
        tail = bytes([0x02]) + (20).to_bytes(8, "little") + offset.to_bytes(8, "little")
        body = MAGIC + bytes(range(200)) + tail + bytes(12)
        for ending in (b"", MAGIC):  # cut in a chunk; or as if closed by the magic
            path = tmp_path / "cut.mcap"
            path.write_bytes(body + ending)
            assert data_section_problem(path) is None
            fixed = tmp_path / "cut.fixed.mcap"
            code = main(["recover", str(path), "-o", str(fixed)])
            assert code == 2  # nothing to recover, said in one line, not an internal error
