"""``mcap_batch.add_messages`` (through ``RunWriter.write_many``) makes the file that
``Writer.add_message`` makes of the same messages one by one, byte for byte, on the installed
``mcap``: over several chunks (closed where ``add_message`` closes them), two channels taking
turns, log times not in order, a writer whose state it does not know (one by one then)."""

from __future__ import annotations

import random
from pathlib import Path

import mcap
import pytest
from mcap.reader import make_reader

from services.logger import mcap_batch
from services.logger.mcap_io import RunWriter, read_run
from shared.messages import ProcessSample, TunerEvent

KEY, OTHER = "b/plant/hx1/pv", "b/tune/hx1/event"


def _traffic(seed: int) -> list[tuple[str, list[tuple[bytes, float]]]]:
    """Runs of messages of one key each, as a logger gets them (batches of samples, events
    between), sim times mostly rising, some going back."""
    rng = random.Random(seed)
    out: list[tuple[str, list[tuple[bytes, float]]]] = []
    t = 0.0
    for _ in range(120):
        key = KEY if rng.random() < 0.8 else OTHER
        items = []
        for _ in range(rng.choice([1, 2, 64, 256])):
            t += -1.0 if rng.random() < 0.05 else 0.25
            size = rng.randint(60, 400)
            items.append((bytes(rng.getrandbits(8) for _ in range(size)), max(t, 0.0)))
        out.append((key, items))
    return out


def _file(
    path: Path, traffic, batched: bool, known: bool = True, first_alone: bool = False
) -> bytes:
    """``first_alone``: each batch's first message by ``write`` (as the logger takes a
    batch's first sample), so that ``add_message`` may begin a chunk's index."""
    w = RunWriter(path, log_time_zero=1_700_000_000 * 10**9)
    w._batched = w._batched and known
    for key, items in traffic:
        model = ProcessSample if key == KEY else TunerEvent
        if batched and first_alone:
            w.write(key, model, *items[0])
            if items[1:]:
                w.write_many(key, model, items[1:])
        elif batched:
            w.write_many(key, model, items)
        else:
            for payload, t in items:
                w.write(key, model, payload, t)
    w.finish({"status": "ok"})
    return path.read_bytes()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_write_many_is_add_message_byte_for_byte(tmp_path: Path, seed: int):
    traffic = _traffic(seed)
    known = mcap_batch.release(mcap.__version__) in mcap_batch.KNOWN
    assert mcap_batch.usable(RunWriter(tmp_path / "probe.mcap")._writer) == known
    one = _file(tmp_path / "one.mcap", traffic, batched=False)
    many = _file(tmp_path / "many.mcap", traffic, batched=True)
    assert many == one
    assert _file(tmp_path / "mixed.mcap", traffic, batched=True, first_alone=True) == one
    _, records = read_run(tmp_path / "many.mcap")
    assert len(records) == sum(len(items) for _, items in traffic)
    with (tmp_path / "many.mcap").open("rb") as f:
        chunks = len(make_reader(f).get_summary().chunk_indexes)
    assert chunks >= 3  # the run spans several chunks: they close where add_message closes them


def test_a_writer_it_does_not_know_is_written_one_by_one(tmp_path: Path):
    traffic = _traffic(4)
    unknown = _file(tmp_path / "unknown.mcap", traffic, batched=True, known=False)
    assert unknown == _file(tmp_path / "one.mcap", traffic, batched=False)


def test_a_release_is_read_as_major_and_minor():
    assert mcap_batch.release("1.6.0") == (1, 6)
    assert mcap_batch.release("1.20.1") == (1, 20)  # not 1.2
    assert mcap_batch.release("2.0.0rc1") == (2, 0)
    assert mcap_batch.release("dev") == ()
