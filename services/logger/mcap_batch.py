"""Many messages of one channel added to an ``mcap`` Writer at once, the file byte for byte
the one ``Writer.add_message`` makes of them one by one.

Why: ``add_message`` is about 3 µs of Python per message (a record dataclass, five packed
fields, two seeks of the chunk's buffer per record); a lockstep run's samples come 256 to a
batch, and the logger records each as its own message. Here each message is one packed
header and its data appended to the open chunk, with the statistics, the chunk's times and
its message index kept exactly as ``add_message`` keeps them, and the chunk closed where
``add_message`` would close it: about 1.4 µs a message. It reaches into the Writer's private
state, so it is used only where that state is as this code knows it (``usable``: the
``mcap`` releases whose internals it was checked against, a chunked writer); anything else
goes through ``add_message``. ``tests/test_mcap_batch.py`` checks the two make the same
bytes on the installed ``mcap``.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import mcap
from mcap.records import MessageIndex
from mcap.writer import Writer

# the Message record: opcode, record length, channel id, sequence, log time, publish time
_HEADER = struct.Struct("<BQHIQQ")
_MESSAGE = 0x05
_FIXED = 22  # the record's bytes before its data
# the releases whose Writer internals this knows (checked byte for byte against each: the
# product needs 1.5 or later, for Writer.flush)
KNOWN = {(1, 5), (1, 6)}


def release(version: str) -> tuple[int, ...]:
    """(major, minor) of a version string ("1.6.0" → (1, 6)); () if it is not numbers."""
    try:
        return tuple(int(x) for x in version.split(".")[:2])
    except ValueError:
        return ()


def usable(writer: Writer) -> bool:
    """The writer's state is as this code knows it: a known release, chunked."""
    if release(mcap.__version__) not in KNOWN:
        return False
    cb = getattr(writer, "_Writer__chunk_builder", None)
    return (
        cb is not None
        and hasattr(writer, "_Writer__statistics")
        and hasattr(writer, "_Writer__chunk_size")
        and hasattr(writer, "_Writer__finalize_chunk")
        and hasattr(getattr(cb, "record_writer", None), "_buffer")
    )


def add_messages(
    writer: Writer, channel_id: int, messages: Sequence[tuple[int, bytes, int]]
) -> None:
    """Add ``messages`` of channel ``channel_id`` in order, each (log time ns, data, sequence),
    its publish time its log time; as ``writer.add_message`` adds each (``usable`` only)."""
    stats = writer._Writer__statistics  # type: ignore[attr-defined]
    chunk = writer._Writer__chunk_builder  # type: ignore[attr-defined]
    limit = writer._Writer__chunk_size  # type: ignore[attr-defined]
    finalize = writer._Writer__finalize_chunk  # type: ignore[attr-defined]
    counts = stats.channel_message_counts
    pack = _HEADER.pack
    for log_time, data, sequence in messages:
        if stats.message_count == 0:
            stats.message_start_time = log_time
        else:
            stats.message_start_time = min(log_time, stats.message_start_time)
        stats.message_end_time = max(log_time, stats.message_end_time)
        counts[channel_id] += 1
        stats.message_count += 1
        if chunk.num_messages == 0:
            chunk.message_start_time = log_time
        else:
            chunk.message_start_time = min(chunk.message_start_time, log_time)
        chunk.message_end_time = max(chunk.message_end_time, log_time)
        index = chunk.message_indices.get(channel_id)
        if not index:
            index = chunk.message_indices[channel_id] = MessageIndex(
                channel_id=channel_id, records=[]
            )
        buffer = chunk.record_writer._buffer  # a new one after each chunk closed
        index.records.append((log_time, buffer.tell()))
        chunk.num_messages += 1
        buffer.write(pack(_MESSAGE, _FIXED + len(data), channel_id, sequence, log_time, log_time))
        buffer.write(data)
        if buffer.tell() > limit:
            finalize()
