"""MCAP files of tuning runs: writing with schemas and sim time, reading with clear errors.

Topics are the Zenoh key expressions with a leading '/'; messages are ``json`` with a
``jsonschema`` schema generated from the pydantic model (Foxglove plots them as they are);
``log_time`` is the message's sim time in nanoseconds, so the time axis is the plant's.
"""

from __future__ import annotations

import json
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from shared.errors import AutotuneError
from shared.messages import Message

PROFILE = ""  # no ROS profile: plain JSON messages
MAGIC = b"\x89MCAP0\r\n"
LIBRARY = "autotune"


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
        self._writer.add_metadata("run", metadata)
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

    @property
    def key(self) -> str:
        return key_of(self.topic)

    def json(self) -> dict:
        return json.loads(self.data)


def read_run(path: Path | str) -> tuple[dict[str, str], list[Record]]:
    """(the run's metadata, its messages in file order); AutotuneError for a bad file."""
    path = Path(path)
    if not path.is_file():
        raise AutotuneError(f"{path}: no such file")
    with path.open("rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
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
                Record(ch.topic, sc.name if sc else "", msg.log_time, msg.data)
                for sc, ch, msg in make_reader(f).iter_messages(log_time_order=False)
            ]
    except AutotuneError:
        raise
    except (McapError, struct.error, ValueError, EOFError, OSError) as err:
        raise not_readable(path, str(err) or type(err).__name__) from None
    return meta, records
