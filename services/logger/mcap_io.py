"""MCAP files of tuning runs: writing with schemas and wall-clock log times, reading with
clear errors.

Topics are the Zenoh key expressions with a leading '/'; messages are ``json`` in their
recorded form (``record_form``: what Foxglove's JSON Schema parser takes) with a draft
2020-12 ``jsonschema`` generated from the pydantic model. ``log_time`` is on the wall-clock
timeline: the run's start (ns since the Unix epoch) plus the sim time since the run's start,
``log_time_zero + t·1e9`` with ``log_time_zero`` in the run's metadata; every message keeps its
sim time in ``t``. Files of format 1 (sim-time log times, the bus's JSON) read as before.

Reading never trusts the file: a damaged container (truncated, not MCAP, corrupt chunks, a
chunk whose bytes fail the CRC it was written with), a
run written by a newer format (``format`` in the run's metadata), and — through ``decode`` —
a message that is not its model's JSON each raise one AutotuneError, one line naming the
file, the record (topic, index in the file, log time), the field and the reason.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import itertools
import json
import logging
import os
import time
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, TypeVar

import pydantic
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import CRCValidationError
from mcap.writer import CompressionType, Writer

from services.logger import mcap_batch
from services.logger.record_form import (
    RECORDED,
    RunRecord,
    bus_payload,
    run_record,
    schema_bytes,
)
from shared import json_text, keys
from shared.errors import AutotuneError, one_line
from shared.messages import Message, ProcessSample, TuneResult

log = logging.getLogger("logger")

PROFILE = ""  # no ROS profile: plain JSON messages
MAGIC = b"\x89MCAP0\r\n"
LIBRARY = "autotune"
FORMAT_VERSION = 2  # of the run files written here: "format" in the run's metadata
# 1: log time = sim time, the bus's JSON; 2: wall-clock log times, the recorded form
M = TypeVar("M", bound=Message)
WALL_CLOCK_NS = 10**18  # 2001-09-09: a log time past it is on the wall clock, not sim time
# a DataEnd record: opcode 0x0F, its length (8 bytes), the data section's CRC-32 (4 bytes);
# the Footer after the summary: opcode, length, two offsets and a CRC (29 bytes), then magic
_DATA_END = 0x0F
_FOOTER = 0x02
_DATA_END_SIZE = 1 + 8 + 4
_FOOTER_SIZE = 1 + 8 + 8 + 8 + 4


def new_writer(out: IO[bytes]) -> Writer:
    """A run file's writer: chunks compressed, and the data section's CRC written (MCAP's
    ``DataEnd``): the chunks' own CRCs leave the run's metadata record out, and an altered
    digit there (K_u 2.5436 read 3.5436) was listed by ``runs`` as the run's (helper trial)."""
    return Writer(out, compression=CompressionType.ZSTD, enable_data_crcs=True)


def data_section_problem(path: Path) -> str | None:
    """Why the file's data section fails the CRC its writer put in its DataEnd record (None:
    it passes, or the file has none: written before run files carried it, or by a writer
    that does not). Everything before the DataEnd record is read: the chunks, the run's
    metadata record, the message indexes."""
    try:
        with path.open("rb") as f:
            size = f.seek(0, os.SEEK_END)
            if size < len(MAGIC) * 2 + _FOOTER_SIZE + _DATA_END_SIZE:
                return None
            f.seek(size - len(MAGIC) - _FOOTER_SIZE)
            footer = f.read(_FOOTER_SIZE)
            # a file cut short ends in whatever it was cut in: a byte there that reads as a
            # Footer's opcode gave a summary offset of up to 2⁶⁴, and seeking to it raised
            # ("cannot fit 'int' into an offset-sized integer": recover's internal error on
            # a run file truncated at 3,000 bytes, one cut in 400 or so). A footer is the
            # file's last record before its closing magic, and points inside the file
            if f.read(len(MAGIC)) != MAGIC:
                return None
            summary_start = int.from_bytes(footer[9:17], "little")
            end = summary_start if summary_start else size - len(MAGIC) - _FOOTER_SIZE
            at = end - _DATA_END_SIZE
            if footer[0] != _FOOTER or at < len(MAGIC) or end > size:
                return None
            f.seek(at)
            record = f.read(_DATA_END_SIZE)
            if len(record) < _DATA_END_SIZE:  # a footer pointing past the end
                return None
            if record[0] != _DATA_END or int.from_bytes(record[1:9], "little") != 4:
                return None
            written = int.from_bytes(record[9:13], "little")
            if written == 0:  # not computed (MCAP's convention): nothing to check
                return None
            f.seek(0)
            crc, left = 0, at
            while left > 0:
                block = f.read(min(left, 1 << 20))
                if not block:
                    return None
                crc, left = zlib.crc32(block, crc), left - len(block)
    except OSError:
        return None
    if crc == written:
        return None
    return (
        f"its data section fails the CRC its writer gave it (written {written:08x}, read "
        f"{crc:08x}), though its chunks pass theirs: its 'run' metadata record or its indexes "
        "changed after they were written (a damaged disk or copy, an edit), so the run's "
        "figures in them are not trusted"
    )


def topic_of(key: str) -> str:
    return "/" + key


def key_of(topic: str) -> str:
    return topic[1:] if topic.startswith("/") else topic


def sim_ns(t: float) -> int:
    """Sim time in s → integer nanoseconds (MCAP timestamps)."""
    return max(0, round(t * 1e9))


def bus_name(namespace: str, prefix: str) -> str:
    """The bus a run was recorded on, as the change history names it: the prefix, under the
    Zenoh namespace (``autotune demo``'s) if there was one."""
    return f"{namespace}/{prefix}" if namespace else prefix


def bus_of(meta: dict[str, str]) -> str | None:
    """The bus of a run file's metadata (None: the file does not say)."""
    prefix = meta.get("prefix")
    return bus_name(meta.get("namespace", ""), prefix) if prefix else None


def log_time_zero(wall_ns: int, t_start: float) -> int:
    """The log time of sim time 0 for a run that started at sim time ``t_start`` (s) at the
    wall-clock instant ``wall_ns`` (ns since the Unix epoch): log time = zero + t·1e9."""
    return max(0, wall_ns - sim_ns(t_start))


class RunWriter:
    """One MCAP file being written: schemas and channels on first use, flushed on demand.

    ``log_time_zero``: ns added to each message's sim time for its log time (0: sim time)."""

    def __init__(self, path: Path, flush_interval: float = 1.0, log_time_zero: int = 0):
        self.path = path
        self.log_time_zero = log_time_zero
        # why the file could no longer be written (a full disk), None while it can: the file
        # then stays as it stands, every later write a no-op (the logger died of it, every
        # other run's recording with it: helper trial of a full disk)
        self.error: OSError | None = None
        self._file: IO[bytes] = path.open("wb")
        self._writer = new_writer(self._file)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        try:  # the header on disk at once: even a killed writer leaves MCAP
            self._writer.flush()
        except OSError as err:
            self._failed(err)
        self._batched = mcap_batch.usable(self._writer)  # write_many's way, else one by one
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self.messages = 0
        self.flush_interval = flush_interval
        self._last_flush = time.monotonic()
        self.finished = False

    def _failed(self, err: OSError) -> None:
        """The file cannot be written: said once, closed as it stands (what reached the disk
        is kept for ``autotune recover``); the logger goes on with the other runs."""
        if self.error is not None:
            return
        self.error = err
        with contextlib.suppress(OSError):  # its buffer's bytes have nowhere to go either
            self._file.close()
        kept = f"what reached the disk is kept (autotune recover {self.path} -o FIXED.mcap)"
        with contextlib.suppress(OSError):
            if self.path.stat().st_size == 0:  # not even its header: no empty file left
                self.path.unlink()
                kept = "nothing of it reached the disk"
        why = err.strerror or one_line(err)
        log.error(
            "%s: cannot be written (%s): this run's recording stops here, %s", self.path, why, kept
        )

    def _schema(self, model: type[pydantic.BaseModel]) -> int:
        name = model.__name__
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(
                name, "jsonschema", schema_bytes(model)
            )
        return self._schemas[name]

    def _channel(self, key: str, model: type[pydantic.BaseModel]) -> int:
        """The channel of ``key``'s topic, registered with ``model``'s schema on first use."""
        topic = topic_of(key)
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic, "json", self._schema(model)
            )
        return self._channels[topic]

    def write(self, key: str, model: type[pydantic.BaseModel], payload: bytes, t: float) -> None:
        """Record ``payload`` (the recorded form of a ``model`` message) at sim time ``t``, s."""
        if self.error is not None:
            return
        try:
            channel = self._channel(key, model)
            seq = self._sequence.get(channel, 0)
            self._sequence[channel] = seq + 1
            ns = self.log_time_zero + sim_ns(t)
            self._writer.add_message(
                channel, log_time=ns, data=payload, publish_time=ns, sequence=seq
            )
        except OSError as err:
            self._failed(err)
            return
        self.messages += 1

    def write_many(
        self, key: str, model: type[pydantic.BaseModel], items: list[tuple[bytes, float]]
    ) -> None:
        """Record several messages of one key in order, each (its recorded form, sim time
        s): the file ``write`` makes of them one by one, to the byte (``mcap_batch``)."""
        if not self._batched:
            for payload, t in items:
                self.write(key, model, payload, t)
            return
        if self.error is not None:
            return
        try:
            channel = self._channel(key, model)
            seq = self._sequence.get(channel, 0)
            zero = self.log_time_zero
            messages = [
                (zero + sim_ns(t), payload, seq + i) for i, (payload, t) in enumerate(items)
            ]
            self._sequence[channel] = seq + len(items)
            mcap_batch.add_messages(self._writer, channel, messages)
        except OSError as err:
            self._failed(err)
            return
        self.messages += len(items)

    def copy(self, schema, channel, message) -> None:
        """One message of another MCAP file as it was there (its schema and channel by name,
        its times and sequence kept): a run file rewritten (``amend_run``)."""
        if channel.topic not in self._channels:
            sid = 0
            if schema is not None:
                if schema.name not in self._schemas:
                    self._schemas[schema.name] = self._writer.register_schema(
                        schema.name, schema.encoding, schema.data
                    )
                sid = self._schemas[schema.name]
            self._channels[channel.topic] = self._writer.register_channel(
                channel.topic, channel.message_encoding, sid
            )
        cid = self._channels[channel.topic]
        self._sequence[cid] = max(self._sequence.get(cid, 0), message.sequence + 1)
        self._writer.add_message(
            cid,
            log_time=message.log_time,
            data=message.data,
            publish_time=message.publish_time,
            sequence=message.sequence,
        )
        self.messages += 1

    def flush_if_due(self) -> None:
        """Close the chunk in progress at most every ``flush_interval`` s (bounds a crash's
        loss to about that much)."""
        if self.error is None and time.monotonic() - self._last_flush >= self.flush_interval:
            try:
                self._writer.flush()
            except OSError as err:
                self._failed(err)
            self._last_flush = time.monotonic()

    def discard(self) -> None:
        """Close the file unfinished and remove it: a run the logger does not record after
        all (nothing of it stays on disk)."""
        if self.finished:
            return
        self._file.close()
        self.path.unlink(missing_ok=True)
        self.finished = True

    def finish(
        self, metadata: dict[str, str], record_key: str | None = None, t: float = 0.0
    ) -> None:
        """Write the metadata ``run`` and close the file; with ``record_key`` the metadata also
        goes on that key as a RunRecord message at sim time ``t``, s."""
        if self.finished:
            return
        meta = {"format": str(FORMAT_VERSION), "log_time_zero": str(self.log_time_zero)}
        meta.update(metadata)
        if record_key is not None:
            self.write(record_key, RunRecord, run_record(meta, t, self.log_time_zero), t)
        self.finished = True
        if self.error is not None:  # left as it stands: said when it failed
            return
        try:
            if record_key is not None:
                # its chunk closed before the metadata record: a file cut within that record
                # keeps the run's figures in its RunRecord (``recover``); the library's
                # add_metadata leaves the open chunk to be written after it
                self._writer.flush()
            self._writer.add_metadata("run", meta)
            self._writer.finish()
            self._file.close()
        except OSError as err:
            self._failed(err)


def amend_run(
    path: Path,
    key: str,
    model: type[pydantic.BaseModel],
    payload: bytes,
    t: float,
    metadata: dict[str, str],
    record_key: str,
) -> None:
    """Rewrite a finished run file with one message more (``payload``, the recorded form of
    a ``model`` message on ``key`` at sim time ``t``, s) and its ``run`` metadata updated by
    ``metadata``: every message it held is copied as it was (schema, channel, log and publish
    time, sequence), its RunRecord written again from the new metadata. The new file
    replaces the old at once (a reader sees one or the other, never half of either)."""
    tmp = path.with_name(path.name + ".amending")
    writer: RunWriter | None = None
    try:
        with path.open("rb") as f:
            reader = make_reader(f)
            meta = next((dict(m.metadata) for m in reader.iter_metadata() if m.name == "run"), {})
            meta.update(metadata)
            writer = RunWriter(tmp, log_time_zero=int(meta.get("log_time_zero") or 0))
            for schema, channel, msg in reader.iter_messages(log_time_order=False):
                if schema is not None and schema.name == RunRecord.__name__:
                    continue  # written again below, from the new metadata
                writer.copy(schema, channel, msg)
        writer.write(key, model, payload, t)
        if "messages" in meta:  # the run's messages, its RunRecord aside
            meta["messages"] = str(writer.messages)
        writer.finish(meta, record_key, t)
        if writer.error is not None:  # the old file stays, whole, rather than a cut copy
            raise writer.error
        tmp.replace(path)
    finally:
        if writer is not None and not writer.finished:
            writer._file.close()  # a failed rewrite leaves no open file behind
        tmp.unlink(missing_ok=True)


@functools.cache
def recorded_form(schema: bytes) -> bool:
    """Does a channel with this schema carry the recorded form (format 2: ``$schema`` stated),
    rather than the bus's JSON (format 1)? Told by the schema, so a file that lost its
    metadata (a recovered one) reads right too."""
    try:
        return isinstance(s := json_text.loads(schema), dict) and "$schema" in s
    except (json.JSONDecodeError, UnicodeDecodeError):
        return False


def not_readable(path: Path | str, why: str, cut: bool | None = None) -> AutotuneError:
    """Why ``path`` cannot be read, one line: a run a logger is still writing says so (it
    said "try recover" on a run in progress); otherwise the hint to ``autotune recover``."""
    if being_written(Path(path)):
        return AutotuneError(
            f"{path}: still being recorded (a logger is writing it, its MCAP footer not "
            "yet written): wait for the run to end"
        )
    if cut is None:
        cut, what = _damage(Path(path))
        if cut:  # the library's words on a file with no footer add nothing but noise
            why = ""  # ("unknown (opcode 0) record has length 10557226335955058688 …": helper)
    else:
        what = "it was not finished"
    hint = (
        f"if a logger was killed while writing it, try: autotune recover {path} -o FIXED.mcap"
        if cut
        else f"`autotune recover {path} -o FIXED.mcap` copies what can be read"
    )
    detail = f" ({why})" if why else ""
    return AutotuneError(f"{path}: not a readable MCAP file: {what}{detail}; {hint}")


def _damage(path: Path) -> tuple[bool, str]:
    """What is wrong with a file the mcap library could not read, as far as its ends tell:
    cut short (it does not end with the MCAP magic bytes after a footer), or damaged within
    (it ends as a finished file does). The library's own words ("HEADER record has length
    56673435648 that exceeds limit …" of a file cut at 100 bytes) said neither. (cut short,
    the phrase)"""
    try:
        with path.open("rb") as f:
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - len(MAGIC) - _FOOTER_SIZE))
            tail = f.read()
    except OSError:
        return True, "it cannot be read to its end"
    if len(tail) < len(MAGIC) + _FOOTER_SIZE or tail[-len(MAGIC) :] != MAGIC or tail[0] != _FOOTER:
        return True, "it is cut short (no MCAP footer at its end: truncated, or its writer killed)"
    return False, "its bytes are damaged within (it ends as a finished file does)"


def being_written(path: Path, proc: Path = Path("/proc")) -> bool:
    """No MCAP footer yet, and the file open in a process of this machine (a logger's run in
    progress); a footerless file nobody has open is a broken one (``autotune recover``).
    Never a FIFO or a device: opening one waits for a writer (`autotune runs` hung on a
    FIFO named x.mcap: helper review)."""
    if not path.is_file():
        return False
    try:
        with path.open("rb") as f:
            f.seek(max(0, path.stat().st_size - len(MAGIC)))
            if f.read() == MAGIC:
                return False
        target = path.resolve()
        for fd in proc.glob("[0-9]*/fd/*"):
            try:
                if Path(os.readlink(fd)) == target:
                    return True
            except OSError:  # gone, or another user's
                continue
    except OSError:
        return False
    return False


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
        return json_text.loads(self.data)

    def where(self) -> str:
        """The record as an error message names it: topic, index, log time (UTC for a
        wall-clock log time, seconds for a format-1 file's sim time)."""
        if self.log_time >= WALL_CLOCK_NS:
            at = datetime.fromtimestamp(self.log_time / 1e9, UTC).isoformat(timespec="milliseconds")
            return f"{self.topic} message {self.index} (log time {at.replace('+00:00', 'Z')})"
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


def seq_gaps(seqs: Sequence[int]) -> tuple[int, int | None]:
    """Samples missing between consecutive ones (by their ``seq``, in order), and the seq
    before the first gap (None: none missing)."""
    missing, first = 0, None
    for a, b in itertools.pairwise(seqs):
        if b > a + 1:
            missing += b - a - 1
            first = a if first is None else first
    return missing, first


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
    if path.is_dir():
        raise AutotuneError(f"{path}: is a directory, not a run file")
    if path.exists() and not path.is_file():  # said "no such file"
        raise AutotuneError(f"{path}: not a regular file (a FIFO or a device), not a run file")
    if not path.is_file():
        raise AutotuneError(f"{path}: no such file")
    try:
        with path.open("rb") as f:
            head = f.read(len(MAGIC) + 1)
    except OSError as err:
        raise AutotuneError(f"{path}: cannot read it: {err.strerror}") from None
    if head[: len(MAGIC)] != MAGIC:
        raise AutotuneError(
            f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)"
        )
    if len(head) == len(MAGIC) and not being_written(path):  # said "OSError: Errno 22"
        raise AutotuneError(
            f"{path}: the MCAP magic bytes and nothing after them: nothing was recorded"
        )
    meta: dict[str, str] = {}
    try:
        with path.open("rb") as f:
            reader = make_reader(f, validate_crcs=True)
            summary = reader.get_summary()
            if summary is None:
                raise not_readable(path, "no summary section", cut=True)
            runs = [dict(m.metadata) for m in reader.iter_metadata() if m.name == "run"]
            if len(runs) > 1:  # the logger writes one: which run this file is, is not known
                # (a second one named another run id: `report` drew that run, "status: ok",
                # every panel "not available", while `analyze` refused it: helper review)
                raise AutotuneError(
                    f"{path}: metadata 'run': {len(runs)} records, a run file has one (which "
                    "run it holds is not known)"
                )
            meta = runs[0] if runs else {}
            f.seek(0)
            records = []
            messages = make_reader(f, validate_crcs=True).iter_messages(log_time_order=False)
            for i, (sc, ch, msg) in enumerate(messages):
                name, data = (sc.name, msg.data) if sc else ("", msg.data)
                if sc is not None and recorded_form(sc.data):
                    if name == RunRecord.__name__:
                        continue  # the metadata again, as a message: not a bus message
                    data = bus_payload(name, data)  # back to the bus's message
                records.append(Record(ch.topic, name, msg.log_time, data, i, ch.message_encoding))
    except AutotuneError:
        raise
    except CRCValidationError as err:  # read through without it: altered samples, exit 0
        raise AutotuneError(
            f"{path}: {damaged_chunk(err.record, meta)}, so none of them is trusted; "
            f"`autotune recover {path} -o FIXED.mcap` copies the chunks that pass"
        ) from None
    except OSError as err:
        if err.errno != errno.EINVAL:  # a seek before its start: shorter than a footer
            raise AutotuneError(f"{path}: cannot read it: {err.strerror or err}") from None
        raise not_readable(path, "shorter than an MCAP footer") from None
    except Exception as err:  # the mcap library on damaged bytes: any of a dozen kinds
        said = one_line(err)
        why = f"{type(err).__name__}: {said}" if said else type(err).__name__
        raise not_readable(path, why) from None
    if not meta.get("run_id") and records and not {r.schema for r in records} & set(RECORDED):
        # an MCAP file of something else: said as such, not "no experiment recorded"
        topics = sorted({r.topic for r in records})
        shown = ", ".join(topics[:3]) + (f" and {len(topics) - 3} more" if len(topics) > 3 else "")
        raise AutotuneError(
            f"{path}: not an autotune run file: none of its topics ({shown}) carries an "
            "autotune message, and it has no 'run' metadata record of the logger's"
        )
    altered = data_section_problem(path)
    if altered is not None:
        raise AutotuneError(
            f"{path}: {altered}; `autotune recover {path} -o FIXED.mcap` copies its messages "
            "and takes the run's figures from its run record among them"
        )
    check_format(path, meta)
    _check_loop(path, meta, records)
    return meta, records


def damaged_chunk(chunk: object, meta: dict[str, str], crc: bool = True) -> str:
    """Why a chunk that fails its CRC (``crc``; else: that cannot be decompressed) is not
    read, one line: the sim times of its messages where the run's ``log_time_zero`` gives
    them. Why refused: a flipped bit in a chunk read as a PV 0.04 °C off, or an output 20
    points off for 168 samples, and was analysed and drawn without a word (helper review);
    the CRC the logger wrote says which chunk."""
    where = ""
    if isinstance(chunk, Chunk):
        zero = meta.get("log_time_zero")
        if zero and zero.isdigit():
            a, b = (chunk.message_start_time - int(zero), chunk.message_end_time - int(zero))
            where = f" (sim time {a / 1e9:.6g}–{b / 1e9:.6g} s)"
        else:
            where = f" (log times {chunk.message_start_time}–{chunk.message_end_time} ns)"
    what = "fails its CRC check" if crc else "cannot be decompressed"
    return (
        f"a chunk of its messages{where} {what}: its bytes changed after they were written "
        "(a damaged disk or copy, an edit)"
    )


def _check_loop(path: Path, meta: dict[str, str], records: list[Record]) -> None:
    """AutotuneError where the metadata names a loop that none of the file's samples are of
    (``…/plant/<loop>/pv``): an edited ``loop = "f1"`` titled an hx1 run's report and
    analysis f1 (helper review). A file without samples, or without the field, is left to
    its readers."""
    loop = meta.get("loop")
    if not loop:
        return
    loops = {r.topic.rsplit("/", 2)[-2] for r in records if r.topic.endswith("/pv")}
    loops.discard("")
    if loops and loop not in loops:
        raise AutotuneError(
            f"{path}: metadata 'run', field loop: {one_line(repr(loop))}, but its samples are "
            f"of {', '.join(sorted(loops))}"
        )
