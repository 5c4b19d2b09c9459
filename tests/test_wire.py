"""shared/wire.py: every message type through encode → decode, refusals that name the field,
the encoding checks, and the replay attachment."""

from __future__ import annotations

import json

import pytest

import shared.messages as messages
from shared import wire
from shared.errors import DecodeError
from shared.messages import (
    AdvanceCommand,
    CalmStop,
    DisturbanceCommand,
    GainsCommand,
    GuardStop,
    IncompleteRun,
    LeaseCommand,
    LoggerStatus,
    LoopInfo,
    LoopMonitor,
    LoopStatus,
    Message,
    ModeCommand,
    OutputCommand,
    PidGains,
    ProcessSample,
    ProcessSamples,
    RecordStops,
    ReleaseCommand,
    ServiceStatus,
    SetpointCommand,
    SettleStop,
    SyncCommand,
    TuneAccepted,
    TuneProgress,
    TuneRequest,
    TuneResult,
    TunerEvent,
    Verification,
)

GAINS = PidGains(kc=2.5, ti=30.0, td=1.5, n=8.0, beta=0.5)
VERIFICATION = Verification(
    gains=GAINS,
    sp_step=5.0,
    overshoot=12.5,
    decay_ratio=0.2,
    rise_time=3.0,
    settling_time=None,
    iae_sp=4.25,
    load_step=None,
    iae_load=None,
    max_deviation_load=None,
    recovery_time=None,
    stable=True,
    saturated=False,
    score=1.75,
)
SAMPLE = ProcessSample(loop="hx1", seq=7, t=0.35, pv=60.125, sp=60.0, op=40.5, mode="auto")
NEXT = ProcessSample(loop="hx1", seq=8, t=0.4, pv=60.25, sp=60.0, op=40.25, mode="auto")

EXAMPLES: list[Message] = [
    GAINS,
    SAMPLE,
    ProcessSamples(loop="hx1", samples=[SAMPLE, NEXT]),
    LoopStatus(
        loop="hx1",
        node="plant",
        seq=7,
        t=0.35,
        pv=60.125,
        sp=60.0,
        op=40.5,
        mode="manual",
        action="reverse",
        gains=GAINS,
        op_limits=(0.0, 100.0),
        pv_range=(0.0, 150.0),
        disturbances={"load": 1.5},
        clock="lockstep",
        accepted=3,
        rejected=1,
        last_reject="op: too big",
        sync_token=42,
        reason="sync",
        leased_by="tuner:abc",
        lease_user="tuner",
    ),
    LoopInfo(
        loop="hx1",
        node="plant",
        t=0.0,
        model="fopdt",
        description="a heat exchanger",
        model_params={"gain": 1.2, "lags": [10.0, 2.0]},
        sample_time=0.05,
        pv_units="°C",
        pv_range=(0.0, 150.0),
        op_limits=(0.0, 100.0),
        disturbances=["load"],
        noise_std=0.01,
        clock="realtime",
        speed=10.0,
    ),
    ServiceStatus(
        node="plant",
        clock="lockstep",
        speed=1.0,
        loops={"hx1": 12.5},
        accepted=10,
        rejected=2,
        rejected_by_reason={"malformed": 2},
        overruns=0,
    ),
    ModeCommand(loop="hx1", mode="auto", source="op", t=1.0),
    OutputCommand(loop="hx1", op=55.5),
    SetpointCommand(loop="hx1", sp=-3.25),
    GainsCommand(loop="hx1", gains=GAINS),
    DisturbanceCommand(loop="hx1", name="load", value=-2.0),
    AdvanceCommand(loop="hx1", steps=20),
    AdvanceCommand(
        loop="hx1",
        steps=2600,
        stop_below=10.0,
        stop_above=90.0,
        record=RecordStops(
            judge=26,
            settle=SettleStop(k=174, target=52.0, band=0.04, flat=0.08, min_samples=349),
            guard=GuardStop(window=348, target=52.0, op_low=0.0, op_high=100.0),
        ),
    ),
    RecordStops(judge=3),
    CalmStop(fed=120, start=141, window=40, limit=0.05, history=[50.1, 50.2]),
    AdvanceCommand(
        loop="hx1",
        steps=1024,
        stop_below=10.0,
        calm=CalmStop(fed=0, start=40, every=8, window=40, limit=0.5),
    ),
    SettleStop(k=4, target=-1.5, band=0.0),
    GuardStop(window=8, target=1.0, op_low=-10.0, op_high=110.0),
    SyncCommand(loop="hx1", token=99),
    LeaseCommand(loop="hx1", timeout=7.5, source="tuner:abc"),
    ReleaseCommand(loop="hx1", source="tuner:abc"),
    TuneRequest(loop="hx1", method="ramp", rule="zn-pi", pv_limits=(10.0, 90.0), apply=False),
    TuneAccepted(run_id="abc", loop="hx1", t=0.0, method="relay", rule="auto"),
    TuneProgress(run_id="abc", loop="hx1", t=4.0, phase="relay", cycles=2, ku=3.5, pu=20.0),
    TunerEvent(run_id="abc", loop="hx1", t=4.0, kind="cycle", data={"n": 2, "why": None}),
    VERIFICATION,
    TuneResult(
        run_id="abc",
        loop="hx1",
        t=100.0,
        method="relay",
        rule="zn-pi",
        status="ok",
        ku=3.5,
        pu=20.0,
        gains={"zn-pi": {"kc": 1.575}},
        previous_gains=GAINS,
        after=VERIFICATION,
        warnings=["noisy"],
        wall_time=1.25,
    ),
    LoggerStatus(
        node="logger",
        runs_dir="runs",
        open_runs=["abc"],
        finished_runs=1,
        received=10,
        written=9,
        invalid=1,
        dropped=0,
        incomplete_runs=[
            IncompleteRun(
                run_id="abd",
                loop="hx1",
                path="/runs/20261207T144337Z_hx1_relay_abd.mcap",
                reason="No space left on device",
                on_disk=True,
            )
        ],
    ),
    IncompleteRun(run_id="abe", loop="hx1", path="/runs/x.mcap", reason="EIO", on_disk=False),
    LoopMonitor(
        loop="hx1",
        node="tuner",
        t=600.0,
        t_start=300.0,
        samples=1200,
        auto_fraction=1.0,
        pv_units="degC",
        period=43.7,
        period_source="the last tune's P_u",
        iae_rate=0.02,
        error_std=0.025,
        saturation=0.0,
        travel=120.0,
        travel_rate=1440.0,
        reversals=0,
        oscillating=True,
        oscillation_period=44.1,
        detections=12,
        detection_limit=10,
        iae_limit=20.9,
        idle_index=None,
        flags={"oscillating": "12 detections within 50 T_u (limit 10), period 44.1 s"},
        run_id="abc",
    ),
]


def test_the_examples_cover_every_message_type() -> None:
    defined = {
        c
        for c in vars(messages).values()
        if isinstance(c, type) and issubclass(c, Message) and c not in (Message, messages.Command)
    }
    assert {type(m) for m in EXAMPLES} == defined


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip_with_its_encoding(msg: Message) -> None:
    model = type(msg)
    encoding = str(wire.encoding_for(model))
    assert encoding == f"application/json;{model.__name__}"
    payload = wire.encode(msg)
    assert json.loads(payload) == msg.model_dump(mode="json")  # plain JSON, every field
    assert payload == msg.model_dump_json().encode()  # the model's own dump, to the byte
    assert wire.decode(model, payload, encoding) == msg
    assert wire.decode(model, payload) == msg  # no encoding: the model decides


@pytest.mark.parametrize(
    "encoding", ["zenoh/bytes", "zenoh/string", "text/plain", "application/json"]
)
def test_generic_encodings_are_accepted(encoding: str) -> None:
    assert wire.decode(ProcessSample, wire.encode(SAMPLE), encoding) == SAMPLE


def test_another_schema_or_mime_type_is_refused() -> None:
    payload = wire.encode(SAMPLE)
    with pytest.raises(DecodeError, match=r"^schema 'LoopStatus' does not match expected Process"):
        wire.decode(ProcessSample, payload, "application/json;LoopStatus")
    with pytest.raises(DecodeError, match=r"^encoding 'text/csv' is not application/json$"):
        wire.decode(ProcessSample, payload, "text/csv")


def _sample_json(**change: object) -> bytes:
    fields = SAMPLE.model_dump(mode="json")
    for name, value in change.items():
        if value is _MISSING:
            del fields[name]
        else:
            fields[name] = value
    return json.dumps(fields).encode()


_MISSING = object()


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (_sample_json(op=150.0), "op: Input should be less than or equal to 100"),
        (_sample_json(op=-0.5), "op: Input should be greater than or equal to 0"),
        (_sample_json(seq=_MISSING), "seq: Field required"),
        (_sample_json(seq="7"), "seq: Input should be a valid integer"),  # strict
        (_sample_json(mode="cascade"), "mode: Input should be 'manual' or 'auto'"),
        (_sample_json(loop="a/b"), "loop: String should match pattern"),
        (_sample_json(extra=1), "extra: Extra inputs are not permitted"),
        (_sample_json().replace(b"60.125", b"NaN"), "pv: Input should be a finite number"),
        (b"not json", "payload: Invalid JSON"),
        (b"[1, 2]", "payload: Input should be an object"),
    ],
)
def test_a_bad_payload_is_refused_naming_the_field(payload: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as err:
        wire.decode(ProcessSample, payload, "application/json;ProcessSample")
    assert str(err.value).startswith(reason)
    assert "\n" not in str(err.value)


def _batch_json(loop: str = "hx1", *samples: dict) -> bytes:
    return json.dumps({"loop": loop, "samples": list(samples)}).encode()


_S7, _S8 = SAMPLE.model_dump(mode="json"), NEXT.model_dump(mode="json")


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (_batch_json("hx1"), "samples: List should have at least 1 item"),
        (_batch_json("hx1", _S7, {**_S8, "op": 150.0}), "samples.1.op: Input should be less"),
        (_batch_json("hx2", _S7, _S8), "payload: Value error, samples.0.loop: 'hx1' in a batch"),
        (_batch_json("hx1", _S8, _S7), "payload: Value error, samples.1.seq: 7, expected 9"),
        (_batch_json("hx1", _S7, {**_S8, "seq": 9}), "payload: Value error, samples.1.seq: 9"),
        (_batch_json("hx1", _S7, _S7), "payload: Value error, samples.1.seq: 7, expected 8"),
        (json.dumps({"loop": "hx1", "samples": _S7}).encode(), "samples: Input should be a"),
    ],
)
def test_a_bad_batch_is_refused_whole_in_one_line_naming_the_field(
    payload: bytes, reason: str
) -> None:
    """A batch with a bad sample, a sample of another loop, or a hole or a step back in its
    numbering: refused whole (its samples then show as a gap wherever they are counted)."""
    with pytest.raises(DecodeError) as err:
        wire.decode(ProcessSamples, payload, "application/json;ProcessSamples")
    assert str(err.value).startswith(reason), str(err.value)
    assert "\n" not in str(err.value)


def test_a_batch_holds_at_most_max_batch_samples() -> None:
    many = [
        SAMPLE.model_copy(update={"seq": k, "t": 0.05 * k}) for k in range(messages.MAX_BATCH + 1)
    ]
    assert len(ProcessSamples(loop="hx1", samples=many[:-1]).samples) == messages.MAX_BATCH
    with pytest.raises(DecodeError, match=r"^samples: List should have at most 1024 items"):
        wire.decode(ProcessSamples, _batch_json("hx1", *[s.model_dump() for s in many]))


def test_a_nested_field_is_named_by_its_path() -> None:
    payload = json.dumps({"loop": "hx1", "gains": {"kc": -1.0, "ti": 0.0}, "source": "op"}).encode()
    with pytest.raises(DecodeError) as err:
        wire.decode(GainsCommand, payload)
    assert str(err.value) == (
        "gains.kc: Input should be greater than or equal to 0; "
        "gains.ti: Input should be greater than 0"
    )


def test_many_bad_fields_name_three_and_count_the_rest() -> None:
    with pytest.raises(DecodeError) as err:
        wire.decode(ProcessSample, b'{"loop": "hx1"}')
    assert str(err.value) == (
        "seq: Field required; t: Field required; pv: Field required; (+3 more)"
    )


def test_replay_attachment_round_trip() -> None:
    mark = wire.replay_attachment("20260101T000000Z_hx1_relay_abc.mcap")
    assert json.loads(mark) == {"replay": "20260101T000000Z_hx1_relay_abc.mcap"}
    assert wire.replay_source(mark) == "20260101T000000Z_hx1_relay_abc.mcap"


@pytest.mark.parametrize(
    "attachment",
    [
        None,
        b"",
        b"not json",
        b"\xff\xfe",
        b"[1]",
        b'"replay"',
        b'{"other": "x"}',
        b'{"replay": null}',
    ],
)
def test_what_is_not_a_replay_mark_is_live_traffic(attachment: bytes | None) -> None:
    assert wire.replay_source(attachment) is None


def test_a_replay_mark_that_is_not_a_string_is_read_as_text() -> None:
    assert wire.replay_source(b'{"replay": 12}') == "12"


def test_a_tune_request_over_the_bus_is_bounded_as_the_cli_bounds_it() -> None:
    """A raw request of max_time 1e300 s was accepted over the bus; the CLI says 1e7."""
    payload = json.dumps({"loop": "hx1", "max_time": 1e300}).encode()
    with pytest.raises(DecodeError) as err:
        wire.decode(messages.TuneRequest, payload, "application/json;TuneRequest")
    assert str(err.value).startswith("max_time: Input should be less than or equal to 10000000")


def test_query_all_decodes_every_valid_answer_and_leaves_out_the_rest():
    """One query: a valid answer decoded, a payload that fails validation and an error
    reply left out (one session on loopback, alone)."""
    from shared.messages import LoggerStatus
    from shared.session import ZenohSettings, open_session

    good = _quiet_logger_status()

    def answer(query):
        query.reply("qa/logger/a/status", wire.encode(good))
        query.reply("qa/logger/b/status", b'{"node": "b"}')  # fails validation
        query.reply_err(b"no status")

    alone = ZenohSettings(listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)
    with open_session(alone) as s:
        q = s.declare_queryable("qa/logger/*/status", answer)
        got = wire.query_all(s, "qa/logger/*/status", LoggerStatus, 2.0)
        q.undeclare()
    assert got == [good]


def test_samples_encoded_from_their_fields_are_the_bytes_of_the_model() -> None:
    """``encode_samples`` (the plant's lockstep batches, built from plain dicts) gives the very
    bytes the model's own serializer gives: every number's shortest form, tiny, huge, −0.0
    and subnormal included, and both modes."""
    values = [0.1, 1e-5, 1e22, 123456.789, -0.0, 5e-324, 1.7976931348623157e308, 60.000000001]
    rows = [
        {
            "loop": "a.b-c_1",
            "seq": 7 + k,
            "t": abs(v),
            "pv": v,
            "sp": -v / 3.0,
            "op": min(abs(v), 100.0),
            "mode": "auto" if k % 2 else "manual",
        }
        for k, v in enumerate(values)
    ]
    model = ProcessSamples(loop="a.b-c_1", samples=[ProcessSample(**r) for r in rows])
    assert wire.encode_samples("a.b-c_1", rows) == wire.encode(model)
    assert wire.decode(ProcessSamples, wire.encode_samples("a.b-c_1", rows)) == model


def test_a_tune_request_carries_no_field_unset_that_an_older_tuner_would_refuse():
    """A request's fields added after b961985 are left out where unset: the tuner of that
    version forbids unknown fields, and refused every plain tune of a newer client because
    of ``apply_predicted_ms: null`` (``autotune perf --source``). ``answer_by`` is retried
    without (``tune.UNKNOWN_ANSWER_BY``)."""
    import subprocess
    from pathlib import Path

    from shared.messages import TuneRequest

    old = subprocess.run(
        ["git", "show", "b961985:shared/messages.py"],
        capture_output=True,
        text=True,
        cwd=Path(__file__).parent,
    )
    if old.returncode != 0:
        pytest.skip("b961985 is not in this clone's history")
    body = old.stdout[old.stdout.index("class TuneRequest(") :]
    body = body[: body.index("\nclass ")]
    sent = json.loads(TuneRequest(loop="x1").model_dump_json())
    unknown = [k for k in sent if f"\n    {k}:" not in body]
    assert unknown == [], unknown


def test_a_logger_status_with_no_incomplete_run_is_what_an_older_client_reads():
    """An older client's LoggerStatus forbids fields it does not know: with no incomplete run
    the field is left off the wire, so such a client still reads a newer logger's status."""
    quiet = _quiet_logger_status()
    text = wire.encode(quiet).decode()
    assert "incomplete_runs" not in text
    assert LoggerStatus.model_validate_json(text) == quiet


def _quiet_logger_status():
    """A logger's status with nothing incomplete (an answer the tests query and encode)."""
    return LoggerStatus(
        node="a",
        runs_dir="runs",
        open_runs=[],
        finished_runs=1,
        received=5,
        written=3,
        invalid=0,
        dropped=2,
    )
