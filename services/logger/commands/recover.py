"""``autotune recover BROKEN.mcap -o FIXED.mcap``: salvage a file whose writer was killed.

Reads the file record by record (``mcap``'s StreamReader, which decompresses chunks as it
goes) and copies every schema, channel, message and metadata record it can read into a new
file, then finishes that file properly. The truncated tail (at most the chunk in progress,
about a second with the logger's flushing) is what is lost.
"""

from __future__ import annotations

import argparse
from datetime import UTC, datetime
from pathlib import Path

from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from services.logger.mcap_io import LIBRARY, MAGIC, PROFILE
from shared.errors import AutotuneError, one_line

HELP = "salvage a truncated MCAP file (from a killed logger)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="BROKEN.mcap")
    parser.add_argument("-o", "--output", required=True, metavar="FIXED.mcap")
    parser.add_argument(
        "--force", action="store_true", help="overwrite FIXED.mcap if it exists already"
    )


def recover(src: Path, dst: Path, force: bool = False) -> dict[str, int | str]:
    """Copy what is readable of ``src`` into ``dst``; return counts and where reading stopped.
    An existing ``dst`` is refused unless ``force`` (it was overwritten without a word: a
    recovered file of another run, or a good one, lost to a typo)."""
    if src.is_dir():
        raise AutotuneError(f"{src}: is a directory, not a run file")
    if not src.is_file():
        raise AutotuneError(f"{src}: no such file")
    if src.resolve() == dst.resolve():
        raise AutotuneError("-o must name a new file, not the broken one")
    if dst.is_dir():
        raise AutotuneError(f"-o {dst}: is a directory (name the new file)")
    if dst.exists() and not force:
        raise AutotuneError(f"-o {dst}: exists already (name a new file, or --force)")
    if not dst.parent.is_dir():
        raise AutotuneError(f"-o {dst}: no such directory {dst.parent} to write it in")
    with src.open("rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise AutotuneError(
                f"{src}: not an MCAP file (it does not start with the MCAP "
                "magic bytes): nothing to recover"
            )
    counts = {"schemas": 0, "channels": 0, "messages": 0, "metadata": 0}
    stopped = "end of file"
    has_run = False  # the run's metadata record was read
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    with src.open("rb") as f, dst.open("wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile=PROFILE, library=LIBRARY)
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Schema | Channel) and rec.id in (
                    schemas if isinstance(rec, Schema) else channels
                ):
                    continue  # the summary section repeats them
                if isinstance(rec, Schema):
                    schemas[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
                    counts["schemas"] += 1
                elif isinstance(rec, Channel):
                    channels[rec.id] = writer.register_channel(
                        rec.topic, rec.message_encoding, schemas.get(rec.schema_id, 0), rec.metadata
                    )
                    counts["channels"] += 1
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    writer.add_message(
                        channels[rec.channel_id],
                        rec.log_time,
                        rec.data,
                        rec.publish_time,
                        rec.sequence,
                    )
                    counts["messages"] += 1
                elif isinstance(rec, Metadata):
                    writer.add_metadata(rec.name, rec.metadata)
                    counts["metadata"] += 1
                    has_run = has_run or rec.name == "run"
        except Exception as err:  # the mcap library on damaged bytes: any of a dozen kinds
            stopped = f"truncated: {one_line(err) or type(err).__name__}"
        if not has_run:  # written only as the logger finished a run: what the name tells
            writer.add_metadata("run", run_of_name(src, counts["messages"], stopped))
        writer.finish()
    if counts["messages"] == 0:  # a file with nothing in it is no recovery: say so, leave none
        dst.unlink()
        raise AutotuneError(
            f"{src}: no message could be read (reading stopped at: {stopped}): nothing to "
            f"recover, {dst} not written"
        )
    return {**counts, "stopped": stopped}


def run_of_name(src: Path, messages: int, stopped: str) -> dict[str, str]:
    """The ``run`` metadata of a file its logger never finished, from its name
    (``<UTC>_<loop>_<method>_<id>.mcap``): `autotune runs` listed the recovered file as
    "unreadable: no 'run' metadata record" (helper trial E). Status ``incomplete``."""
    parts = src.stem.removesuffix("_replay").split("_")
    meta = {"status": "incomplete", "recovered": f"{messages} messages; reading stopped at: "
            f"{stopped}"}  # fmt: skip
    if len(parts) >= 4:
        try:
            started = datetime.strptime(parts[0], "%Y%m%dT%H%M%SZ").replace(tzinfo=UTC)
            meta["started"] = started.isoformat()
        except ValueError:
            pass
        meta.update(loop="_".join(parts[1:-2]), method=parts[-2], run_id=parts[-1])
    return meta


def run(args: argparse.Namespace) -> int:
    counts = recover(Path(args.file), Path(args.output), args.force)
    print(
        f"recovered {counts['messages']} messages on {counts['channels']} channels "
        f"({counts['schemas']} schemas, {counts['metadata']} metadata records) into "
        f"{args.output}; reading stopped at: {counts['stopped']}"
    )
    return 0
