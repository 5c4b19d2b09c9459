"""MCAP files of tuning runs: writing with schemas and sim time, reading with clear errors.

Topics are the Zenoh key expressions with a leading '/'; messages are ``json`` with a
``jsonschema`` schema generated from the pydantic model (Foxglove plots them as they are);
``log_time`` is the message's sim time in nanoseconds, so the time axis is the plant's.

Reading never trusts the file: a damaged container (truncated, not MCAP, corrupt chunks), a
run written by a newer format (``format`` in the run's metadata), and — through ``decode`` —
a message that is not its model's JSON each raise one AutotuneError, one line naming the
file, the record (topic, index in the file, log time), the field and the reason.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TypeVar

import pydantic
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from shared import keys
from shared.errors import AutotuneError, one_line
from shared.messages import Message, ProcessSample, TuneResult

PROFILE = ""  # no ROS profile: plain JSON messages
MAGIC = b"\x89MCAP0\r\n"
LIBRARY = "autotune"
FORMAT_VERSION = 1  # of the run files written here: "format" in the run's metadata
M = TypeVar("M", bound=Message)


def topic_of(key: str) -> str:
    return "/" + key


def key_of(topic: str) -> str:
    return topic[1:] if topic.startswith("/") else topic


def sim_ns(t: float) -> int:
    """Sim time in s → integer nanoseconds (MCAP timestamps)."""
    return max(0, round(t * 1e9))


class RunWriter:
    """One MCAP file being written: schemas and channels on first use, flushed on demand."""

    def __init__(self, path: Path, flush_interval: float = 1.0):
        self.path = path
        self._file: IO[bytes] = path.open("wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._writer.flush()  # the header is on disk at once: even a killed writer leaves MCAP
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self.messages = 0
        self.flush_interval = flush_interval
        self._last_flush = time.monotonic()
        self.finished = False

    def _schema(self, model: type[Message]) -> int:
        name = model.__name__
        if name not in self._schemas:
            schema = json.dumps(model.model_json_schema()).encode()
            self._schemas[name] = self._writer.register_schema(name, "jsonschema", schema)
        return self._schemas[name]

    def write(self, key: str, model: type[Message], payload: bytes, t: float) -> None:
        topic = topic_of(key)
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic, "json", self._schema(model)
            )
        channel = self._channels[topic]
        seq = self._sequence.get(channel, 0)
        self._sequence[channel] = seq + 1
        ns = sim_ns(t)
        self._writer.add_message(channel, log_time=ns, data=payload, publish_time=ns, sequence=seq)
        self.messages += 1

    def flush_if_due(self) -> None:
        """Close the chunk in progress at most every ``flush_interval`` s (bounds a crash's
        loss to about that much)."""
        if time.monotonic() - self._last_flush >= self.flush_interval:
            self._writer.flush()
            self._last_flush = time.monotonic()

    def finish(self, metadata: dict[str, str]) -> None:
        if self.finished:
            return
        self._writer.add_metadata("run", {"format": str(FORMAT_VERSION), **metadata})
        self._writer.finish()
        self._file.close()
        self.finished = True


def not_readable(path: Path | str, why: str) -> AutotuneError:
    return AutotuneError(
        f"{path}: not a readable MCAP file ({why}); if a logger was killed "
        f"while writing it, try: autotune recover {path} -o FIXED.mcap"
    )


@dataclass(frozen=True)
class Record:
    """One message of a run file, in file order."""

    topic: str
    schema: str
    log_time: int
    data: bytes
    index: int = -1  # position among the file's messages, 0 first
    encoding: str = "json"  # the channel's message encoding

    @property
    def key(self) -> str:
        return key_of(self.topic)

    def json(self) -> dict:
        return json.loads(self.data)

    def where(self) -> str:
        """The record as an error message names it: topic, index, log time."""
        return f"{self.topic} message {self.index} (log time {self.log_time / 1e9:.9g} s)"


def decode(path: Path | str, record: Record, model: type[M]) -> M:
    """The record as ``model``; AutotuneError naming the record, the field and the reason."""
    if record.encoding != "json":
        raise AutotuneError(
            f"{path}: {record.where()}: message encoding {record.encoding!r}, expected json"
        )
    if record.schema and record.schema != model.__name__:
        raise AutotuneError(
            f"{path}: {record.where()}: schema {record.schema!r}, expected {model.__name__}"
        )
    try:
        return model.model_validate_json(record.data)
    except pydantic.ValidationError as err:
        raise AutotuneError(f"{path}: {record.where()}: {validation_reason(err)}") from None


def validation_reason(err: pydantic.ValidationError, within: str = "") -> str:
    """``field: reason[, got value]`` of a validation error's first complaint, on one line;
    ``within`` names where the validated value sits (``data.request``), the field is in it."""
    e = err.errors()[0]
    if e["type"] == "json_invalid":
        return f"{within or 'payload'}: not JSON ({one_line(e['msg'])})"
    where = ".".join(str(p) for p in (within, *e["loc"]) if p != "") or "payload"
    msg = one_line(e["msg"]).removeprefix("Value error, ")
    value = e.get("input")
    got = ""
    if isinstance(value, bool | int | float | str) and len(repr(value)) <= 40:
        got = f", got {value!r}"
    return f"{where}: {msg}{got}"


def unique_samples(path: Path | str, records: list[Record]) -> list[ProcessSample]:
    """The run's process samples by seq; a sample recorded twice is taken once, but two
    different samples with one seq are an AutotuneError naming both records."""
    by_seq: dict[int, tuple[Record, ProcessSample]] = {}
    for r in records:
        if keys.leaf(r.topic) != "pv":
            continue
        s = decode(path, r, ProcessSample)
        seen = by_seq.get(s.seq)
        if seen is not None and seen[1] != s:
            raise AutotuneError(
                f"{path}: {r.where()}: seq {s.seq} was recorded before with other values "
                f"({seen[0].where()})"
            )
        by_seq.setdefault(s.seq, (r, s))
    return [s for _, (_, s) in sorted(by_seq.items())]


def one_result(path: Path | str, results: list[tuple[Record, TuneResult]]) -> TuneResult | None:
    """The run's result: None when there is none; a repeat of it is harmless, but a second,
    different one is an AutotuneError naming both records."""
    if not results:
        return None
    (first_record, first), *rest = results
    other = next((r for r, x in rest if x != first), None)
    if other is not None:
        raise AutotuneError(
            f"{path}: {other.where()}: a second, different result of run {first.run_id} "
            f"(the first: {first_record.where()})"
        )
    return first


def check_format(path: Path | str, meta: dict[str, str]) -> None:
    """AutotuneError when the run's metadata says a format this code cannot read."""
    raw = meta.get("format")
    if raw is None:
        return  # files from before the field: version 1
    shown = one_line(repr(raw if len(raw) <= 40 else raw[:40] + "…"))  # one short line
    try:
        version = int(raw)
    except ValueError:
        raise AutotuneError(
            f"{path}: metadata 'run', field format: not a version number: {shown}"
        ) from None
    if version > FORMAT_VERSION or version < 1:
        raise AutotuneError(
            f"{path}: metadata 'run', field format: version "
            f"{version if len(raw) <= 40 else shown}, this autotune reads version {FORMAT_VERSION}"
            + (" (a newer autotune wrote it: upgrade to read it)" if version > 1 else "")
        )


def read_run(path: Path | str) -> tuple[dict[str, str], list[Record]]:
    """(the run's metadata, its messages in file order); AutotuneError for a bad file."""
    path = Path(path)
    if not path.is_file():
        raise AutotuneError(f"{path}: no such file")
    try:
        with path.open("rb") as f:
            head = f.read(len(MAGIC))
    except OSError as err:
        raise AutotuneError(f"{path}: cannot read it: {err.strerror}") from None
    if head != MAGIC:
        raise AutotuneError(
            f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)"
        )
    try:
        with path.open("rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                raise not_readable(path, "no summary: the file was not finished")
            meta: dict[str, str] = {}
            for m in reader.iter_metadata():
                if m.name == "run":
                    meta = dict(m.metadata)
            f.seek(0)
            records = [
                Record(
                    ch.topic, sc.name if sc else "", msg.log_time, msg.data, i, ch.message_encoding
                )
                for i, (sc, ch, msg) in enumerate(
                    make_reader(f).iter_messages(log_time_order=False)
                )
            ]
    except AutotuneError:
        raise
    except Exception as err:  # the mcap library on damaged bytes: any of a dozen kinds
        raise not_readable(path, f"{type(err).__name__}: {one_line(err)}") from None
    check_format(path, meta)
    return meta, records
