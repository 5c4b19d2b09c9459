"""The logger's recorder takes a lockstep batch (``pv_batch``, one ProcessSamples) as its
samples one by one: the run file is the one the same samples sent one message each make, to
the byte (one ``pv`` message per sample, log time from its own t), and a batch missing, out of
order or not valid counts as its samples would have (a gap, a new plant instance, invalid)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from services.logger.mcap_io import read_run, topic_of
from services.logger.recorder import Recorder, batch_elements
from shared import keys, wire
from shared.messages import ProcessSample, ProcessSamples, TuneProgress, TuneResult

P = "batch"
LOOP = "hx1"
DT = 0.25


def sample(seq: int) -> ProcessSample:
    """Sample ``seq`` of a loop ringing about 50 (values that differ from sample to sample)."""
    return ProcessSample(
        loop=LOOP, seq=seq, t=seq * DT, pv=50.0 + 0.1 * (seq % 7), sp=50.0, op=40.0 + 0.01 * seq,
        mode="auto",
    )  # fmt: skip


def one_by_one(rec: Recorder, first: int, last: int) -> None:
    for n in range(first, last + 1):
        rec.handle(keys.pv(P, LOOP), wire.encode(sample(n)))


def batched(rec: Recorder, first: int, last: int) -> None:
    batch = ProcessSamples(loop=LOOP, samples=[sample(n) for n in range(first, last + 1)])
    rec.handle(keys.pv_batch(P, LOOP), wire.encode(batch))


def recorded(tmp_path: Path, name: str, traffic: Callable[[Recorder], None]) -> tuple:
    """One run (start at sample 10, result at sample 40) with ``traffic`` between: the file's
    metadata (less what names the file or the wall clock), its records (topic, schema, data,
    log time from the first) and the recorder's counts."""
    rec = Recorder(tmp_path / name, P, flush_interval=3600.0, clock=lambda: 0.0)
    start = TuneProgress(run_id="r1", loop=LOOP, t=10 * DT, phase="start", message="ramp test")
    rec.handle(keys.tune_progress(P, LOOP), wire.encode(start))
    traffic(rec)
    end = TuneResult(run_id="r1", loop=LOOP, t=40 * DT, method="ramp", rule="zn-pi", status="ok")
    rec.handle(keys.tune_result(P, LOOP), wire.encode(end))
    assert len(rec.finished) == 1, rec.finished
    meta, records = read_run(rec.finished[0])
    meta = {k: v for k, v in meta.items() if k not in ("started", "finished", "log_time_zero")}
    t0 = records[0].log_time
    rows = [(r.topic, r.schema, r.data, r.log_time - t0) for r in records]
    return meta, rows, dict(rec.counts)


def test_a_batch_is_written_as_its_samples_one_message_each(tmp_path: Path) -> None:
    def singles(rec: Recorder) -> None:
        one_by_one(rec, 10, 40)

    def batches(rec: Recorder) -> None:
        batched(rec, 10, 10)
        batched(rec, 11, 30)
        one_by_one(rec, 31, 31)
        batched(rec, 32, 40)

    meta, rows, counts = recorded(tmp_path, "batches", batches)
    assert (meta, rows, counts) == recorded(tmp_path, "singles", singles)
    pv = [r for r in rows if r[0] == topic_of(keys.pv(P, LOOP))]
    assert len(pv) == 31 and meta["samples"] == "31" and meta["dropped"] == "0"
    # each its own message, logged at its own t (ns from the run's first message at t = 2.5 s)
    assert [r[3] for r in pv] == [round((n - 10) * DT * 1e9) for n in range(10, 41)]
    assert [json.loads(r[2])["seq"] for r in pv] == list(range(10, 41))


def test_a_missing_batch_is_a_gap_of_its_samples(tmp_path: Path) -> None:
    def singles(rec: Recorder) -> None:
        one_by_one(rec, 10, 19)
        one_by_one(rec, 30, 40)  # 20…29 lost

    def batches(rec: Recorder) -> None:
        batched(rec, 10, 19)
        batched(rec, 30, 40)  # the batch 20…29 lost

    meta, rows, counts = recorded(tmp_path, "batches", batches)
    assert (meta, rows, counts) == recorded(tmp_path, "singles", singles)
    assert meta["dropped"] == "10" and counts["dropped"] == 10


def test_a_batch_out_of_order_counts_as_its_samples_out_of_order(tmp_path: Path) -> None:
    def singles(rec: Recorder) -> None:
        one_by_one(rec, 10, 19)
        one_by_one(rec, 30, 40)
        one_by_one(rec, 20, 29)  # late: the numbering went back

    def batches(rec: Recorder) -> None:
        batched(rec, 10, 19)
        batched(rec, 30, 40)
        batched(rec, 20, 29)

    meta, rows, counts = recorded(tmp_path, "batches", batches)
    assert (meta, rows, counts) == recorded(tmp_path, "singles", singles)
    assert meta["dropped"] == "10" and meta["plant_changed"].startswith("the sample number went")


def test_a_bad_batch_is_counted_invalid_and_left_out_whole(tmp_path: Path) -> None:
    good = ProcessSamples(loop=LOOP, samples=[sample(n) for n in range(20, 30)])
    bad = json.loads(wire.encode(good))
    bad["samples"][3]["op"] = 150.0  # one sample out of range: the whole batch is refused

    def traffic(rec: Recorder) -> None:
        batched(rec, 10, 19)
        rec.handle(keys.pv_batch(P, LOOP), json.dumps(bad).encode())
        rec.handle(keys.pv_batch(P, LOOP), b"not json")
        hx2 = [s.model_copy(update={"loop": "hx2"}) for s in good.samples]
        other = ProcessSamples(loop="hx2", samples=hx2)  # not the loop its key names
        rec.handle(keys.pv_batch(P, LOOP), wire.encode(other))
        batched(rec, 30, 40)

    meta, _, counts = recorded(tmp_path, "bad", traffic)
    assert counts["invalid"] == 3 and meta["dropped"] == "10" and meta["samples"] == "21"


def _variant(seq: int, v: int, t: float | None = None) -> ProcessSample:
    """Sample ``seq`` as variant ``v`` of the plant gives it (another instance's values), at
    sim time ``t`` (default seq·DT)."""
    s = sample(seq)
    return s.model_copy(update={"pv": s.pv + v, "t": seq * DT if t is None else t})


def _both_ways(tmp_path: Path, name: str, parts: list[list[ProcessSample]], result_early: bool):
    """The run file and counts of ``parts`` sent as batches, and sent a sample a message;
    with ``result_early`` the run's result (t = 40·DT) comes after the first part, the run
    ending where a later sample reaches it."""

    def traffic(as_batches: bool) -> Callable[[Recorder], None]:
        def send(rec: Recorder) -> None:
            for i, part in enumerate(parts):
                if result_early and i == 1:
                    end = TuneResult(
                        run_id="r1", loop=LOOP, t=40 * DT, method="ramp", rule="zn-pi", status="ok"
                    )
                    rec.handle(keys.tune_result(P, LOOP), wire.encode(end))
                if as_batches:
                    batch = ProcessSamples(loop=LOOP, samples=part)
                    rec.handle(keys.pv_batch(P, LOOP), wire.encode(batch))
                else:
                    for s in part:
                        rec.handle(keys.pv(P, LOOP), wire.encode(s))

        return send

    return (
        recorded(tmp_path, f"{name}-batches", traffic(True)),
        recorded(tmp_path, f"{name}-singles", traffic(False)),
    )


def test_batches_are_their_samples_through_repeats_restarts_and_the_run_end(tmp_path: Path):
    """The samples of a batch after its first are written at once where nothing but their
    writing is left to decide (``Recorder._run_samples``); where anything is (a repeat, a
    plant that started again with the same numbers, a sim time that went back inside the
    batch, the run's end reached), the file and the counts are still those of the same
    samples one message each."""
    seq = range
    cases = {
        "plain": ([[sample(n) for n in seq(10, 25)], [sample(n) for n in seq(25, 41)]], False),
        "a repeat first": (
            [[sample(n) for n in seq(10, 20)], [sample(n) for n in seq(19, 41)]],
            False,
        ),
        # the plant started again, its numbering where the first one's was: the same number
        # with other values, then on from it (not the run's)
        "a restart": (
            [[sample(n) for n in seq(10, 20)], [_variant(n, 1) for n in seq(19, 30)]],
            False,
        ),
        "time back inside": (
            [
                [sample(n) for n in seq(10, 20)],
                [sample(20), sample(21), _variant(22, 0, t=3.0), *map(sample, seq(23, 41))],
            ],
            False,
        ),
        "the end reached": (
            [[sample(n) for n in seq(10, 20)], [sample(n) for n in seq(20, 50)]],
            True,
        ),
    }
    for name, (parts, result_early) in cases.items():
        batches, singles = _both_ways(tmp_path, name.replace(" ", "_"), parts, result_early)
        assert batches == singles, name
    # the cases do what they say: the restart and the time going back start a new instance
    restart, _ = _both_ways(tmp_path, "restart2", *cases["a restart"])
    assert restart[0]["plant_changed"].startswith("sample 19 came again")
    back, _ = _both_ways(tmp_path, "back2", *cases["time back inside"])
    assert back[0]["plant_changed"].startswith("the sim time went back")


def test_a_batch_is_cut_into_its_samples_texts_as_the_plant_encodes_each():
    """``batch_elements``: each sample's text cut out of the batch is the one the plant puts
    on ``pv`` for it; a batch whose texts cannot be cut surely (whitespace between its
    samples) is left to be encoded again (None)."""
    samples = [sample(n) for n in range(10, 30)]
    rows = [s.model_dump() for s in samples]
    for payload in (wire.encode(ProcessSamples(loop=LOOP, samples=samples)),
                    wire.encode_samples(LOOP, rows)):  # fmt: skip
        assert batch_elements(payload, len(samples)) == [wire.encode(s) for s in samples]
    one = wire.encode(ProcessSamples(loop=LOOP, samples=samples[:1]))
    assert batch_elements(one, 1) == [wire.encode(samples[0])]
    spaced = json.dumps({"loop": LOOP, "samples": rows}).encode()  # ", " and ": " between
    assert batch_elements(spaced, len(samples)) is None
    assert batch_elements(wire.encode(ProcessSamples(loop=LOOP, samples=samples)), 19) is None


def test_a_batch_spaced_out_is_recorded_as_its_samples_encoded(tmp_path: Path):
    """Where the cut is not sure, the file is as with the batch encoded compactly."""
    rows = [sample(n).model_dump() for n in range(10, 41)]

    def spaced(rec: Recorder) -> None:
        rec.handle(keys.pv_batch(P, LOOP), json.dumps({"loop": LOOP, "samples": rows}).encode())

    def compact(rec: Recorder) -> None:
        batched(rec, 10, 40)

    assert recorded(tmp_path, "spaced", spaced) == recorded(tmp_path, "compact", compact)


def _s(n: int) -> bytes:
    return wire.encode(sample(n))


# valid batches (pydantic keeps a duplicate key's last value and checks no other) whose
# texts a cut would get wrong, and a batch spaced inside its array
UNSURE = {
    "a dropped loop holding a bracket": b'{"loop":"[","loop":"hx1","samples":['
    + _s(11) + b"," + _s(12) + b"]}",
    "a dropped array": b'{"loop":"hx1","samples":[],"samples":[' + _s(11) + b"]}",
    "a dropped mode holding a cut": b'{"loop":"hx1","samples":['
    + _s(11)[:-1] + b',"mode":"},{","mode":"auto"}, ' + _s(12) + b"]}",
    "spaces inside the array": b'{"loop":"hx1","samples":[ ' + _s(11) + b"," + _s(12) + b" ]}",
}  # fmt: skip


def test_a_batch_whose_cut_is_not_sure_is_encoded_again(tmp_path: Path):
    """Each of these is a valid batch; the cut is refused, and the file holds each sample as
    the plant would have put it on ``pv`` (found in review: the first three were recorded
    as text that is not JSON)."""
    for name, payload in UNSURE.items():
        batch = ProcessSamples.model_validate_json(payload)  # valid
        assert batch_elements(payload, len(batch.samples)) is None, name

        n = len(batch.samples)

        def traffic(rec: Recorder, payload: bytes = payload, n: int = n) -> None:
            one_by_one(rec, 10, 10)
            rec.handle(keys.pv_batch(P, LOOP), payload)
            one_by_one(rec, 11 + n, 40)

        _, rows, _ = recorded(tmp_path, name.replace(" ", "_"), traffic)
        pv = [r[2] for r in rows if r[0] == topic_of(keys.pv(P, LOOP))]
        assert pv == [_s(k) for k in range(10, 41)], name
