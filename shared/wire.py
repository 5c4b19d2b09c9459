"""JSON on the wire, the model's name as the encoding schema, validation on receipt."""

from __future__ import annotations

import json
import time
from functools import cache
from typing import TypeVar

import pydantic
import pydantic_core
import zenoh

from shared import json_text
from shared.errors import DecodeError
from shared.messages import Message

M = TypeVar("M", bound=Message)

JSON = "application/json"


@cache
def encoding_for(model: type[Message]) -> zenoh.Encoding:
    """``application/json;<ModelName>``: what Foxglove-style tools and our decoders expect."""
    return zenoh.Encoding.APPLICATION_JSON.with_schema(model.__name__)


def encode(msg: Message) -> bytes:
    """``msg``'s JSON, the bytes of ``msg.model_dump_json().encode()``: the model's own
    serializer called directly (a third of the cost: no keyword handling, no str round trip;
    the logger encodes every sample of a batch this way)."""
    return type(msg).__pydantic_serializer__.to_json(msg)


def encode_samples(loop: str, rows: list[dict]) -> bytes:
    """A ``ProcessSamples`` of ``loop``'s samples given as the dicts of their fields: the bytes
    ``encode`` gives for the model built from them (pydantic's serializer of plain values),
    without building it. For the plant's own samples on the lockstep hot path: their values
    are its own (each consumer validates the batch on receipt)."""
    return pydantic_core.to_json({"loop": loop, "samples": rows})


def put(session: zenoh.Session, key: str, msg: Message) -> None:
    """Publish ``msg`` reliably: blocks rather than drops when the link is congested."""
    session.put(
        key,
        encode(msg),
        encoding=encoding_for(type(msg)),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def reply(query: zenoh.Query, key: str, msg: Message) -> None:
    query.reply(key, encode(msg), encoding=encoding_for(type(msg)))


def describe_validation_error(err: pydantic.ValidationError, limit: int = 3) -> str:
    """One line naming each bad field and the reason, e.g. ``op: Input should be ≤ 100``."""
    parts = []
    for e in err.errors()[:limit]:
        loc = ".".join(str(p) for p in e["loc"]) or "payload"
        parts.append(f"{loc}: {e['msg']}")
    more = err.error_count() - limit
    if more > 0:
        parts.append(f"(+{more} more)")
    return "; ".join(parts)


def decode(model: type[M], payload: bytes, encoding: str | None = None) -> M:
    """Validate ``payload`` as ``model``; raise DecodeError with a one-line reason otherwise.

    ``encoding`` is the sample's encoding string; a JSON encoding naming another schema is refused.
    """
    if encoding is not None:
        mime, _, schema = encoding.partition(";")
        if mime not in (JSON, "zenoh/bytes", "zenoh/string", "text/plain"):
            raise DecodeError(f"encoding {encoding!r} is not {JSON}")
        if schema and schema != model.__name__:
            raise DecodeError(f"schema {schema!r} does not match expected {model.__name__}")
    try:
        return model.model_validate_json(payload)
    except pydantic.ValidationError as err:
        raise DecodeError(describe_validation_error(err)) from None


def decode_sample(model: type[M], sample: zenoh.Sample) -> M:
    return decode(model, sample.payload.to_bytes(), str(sample.encoding))


def query_one(session: zenoh.Session, key: str, model: type[M], timeout: float) -> M | None:
    """The first valid reply to a query on ``key``, asking again until ``timeout``.

    A session that has just joined may not know the queryable yet (peers discover each
    other by gossip): a query that nobody answers is repeated rather than taken as final.
    """
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        for reply in session.get(key, timeout=max(0.05, min(left, 2.0))):
            if reply.ok is not None:
                try:
                    return decode_sample(model, reply.ok)
                except DecodeError:
                    continue
        if time.monotonic() >= deadline:
            return None
        time.sleep(0.02)


def query_all(
    session: zenoh.Session,
    key: str,
    model: type[M],
    timeout: float,
    target: zenoh.QueryTarget = zenoh.QueryTarget.BEST_MATCHING,
) -> list[M]:
    """Every valid reply to one query on ``key`` within ``timeout`` s, decoded as ``model``:
    an error reply or a payload that fails validation is left out (it is no answer).
    ``target``: ``ALL`` for every queryable's; and every reply is kept, not only the latest
    on a key (two tuners' last results of one loop share its key)."""
    out: list[M] = []
    replies = session.get(
        key, target=target, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout
    )
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            out.append(decode_sample(model, reply.ok))
        except DecodeError:
            continue
    return out


REPLAY_ATTACHMENT_KEY = "replay"


def replay_attachment(source: str) -> bytes:
    """The attachment ``autotune replay`` puts on every message: ``{"replay": source}``."""
    return json.dumps({REPLAY_ATTACHMENT_KEY: source}).encode()


def replay_source(attachment: bytes | None) -> str | None:
    """The replayed file's name if ``attachment`` marks a replay, else None (live traffic)."""
    if not attachment:
        return None
    try:
        mark = json_text.loads(attachment)
    except (ValueError, UnicodeDecodeError):
        return None
    source = mark.get(REPLAY_ATTACHMENT_KEY) if isinstance(mark, dict) else None
    return str(source) if source is not None else None
