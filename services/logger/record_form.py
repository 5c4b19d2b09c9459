"""The recorded form of bus messages: what Foxglove (and any JSON Schema reader) takes as it is.

A run file's channels carry the bus's JSON with three differences, each undone on reading
(``bus_payload``), so every reader of a run sees the bus's messages:

* an absent value is left out, not ``null``: the open-source Foxglove/Lichtblick parser
  (``parseJsonSchema``) takes one ``type`` per property, so an optional number is
  ``{"type": "number"}``, not required, and still plottable;
* a request event's ``data.request`` and ``data.info`` (JSON text on the bus) are objects,
  so they can be plotted and filtered;
* the schema is draft 2020-12 (``$schema`` stated) with no ``$ref``, ``anyOf [T, null]`` or
  ``prefixItems``: references are inlined, a tuple is an array of ``items``. A property that
  takes values of several types (``repeat``: a count or "auto") is declared under
  ``patternProperties``, which validators check and Foxglove's parser passes over.

The run's metadata (strings, by MCAP's spec) is also recorded as one ``RunRecord`` message
on ``<prefix>/tune/<loop>/run`` with its request, loop info and result as objects.
"""

from __future__ import annotations

import json
import re
import types
import typing
from functools import cache
from typing import Any

from pydantic import BaseModel, ConfigDict

from shared import json_text
from shared.messages import (
    COMMANDS,
    LoopInfo,
    LoopStatus,
    Message,
    ProcessSample,
    TuneProgress,
    TuneRequest,
    TuneResult,
    TunerEvent,
)

DIALECT = "https://json-schema.org/draft/2020-12/schema"
FOXGLOVE_TYPES = ("boolean", "string", "number", "integer", "object", "array")
EVENT_OBJECTS: dict[str, type[Message]] = {"request": TuneRequest, "info": LoopInfo}
"""A request event's data fields that are JSON text on the bus and objects in a run file."""


class RunRecord(BaseModel):
    """The run's metadata as one message (a file record, not a bus message): the same
    fields as the metadata ``run``, numbers as numbers, request, info and result as objects.
    ``t`` is the sim time the run ended at, s."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    run_id: str
    loop: str
    t: float
    method: str
    rule: str
    status: str
    started: str
    finished: str
    prefix: str
    samples: int
    first_seq: int | None = None
    last_seq: int | None = None
    dropped: int
    messages: int
    left_out: int
    ku: float | None = None
    pu: float | None = None
    replay: str = ""
    plant_node: str = ""
    plant_changed: str = ""
    log_time_zero: int
    request: TuneRequest | None = None
    info: LoopInfo | None = None
    result: TuneResult | None = None


RECORDED: dict[str, type[BaseModel]] = {
    m.__name__: m
    for m in (ProcessSample, LoopStatus, TuneProgress, TunerEvent, TuneResult, RunRecord)
}
RECORDED.update({c.__name__: c for c in COMMANDS.values()})


# --- schemas ----------------------------------------------------------------------------------


def _is_null(s: dict) -> bool:
    return s.get("type") == "null"


def _single_type(s: dict) -> bool:
    return isinstance(s.get("type"), str) and s["type"] in FOXGLOVE_TYPES


def _node(s: dict, defs: dict[str, dict], omit_null: bool = False) -> dict:
    """One schema node in Foxglove's form: references inlined, tuples as arrays with
    ``items``; with ``omit_null`` (a property: None is left out, not written) ``anyOf [T,
    null]`` is ``T``. Elsewhere (a map's values) null stays allowed: Foxglove's parser reads
    only ``properties``."""
    s = dict(s)
    ref = s.pop("$ref", None)
    if ref is not None:
        s = {**defs[ref.rsplit("/", 1)[-1]], **s}
    if s.get("default", 0) is None:
        del s["default"]
    if "anyOf" in s:
        alts = [a for a in s.pop("anyOf") if not (omit_null and _is_null(a))]
        if len(alts) == 1:
            return {**_node(alts[0], defs), **s}
        return {**s, "anyOf": [_node(a, defs) for a in alts]}
    if s.get("type") == "object":
        props = s.pop("properties", None)
        if props is not None:
            nullable = {n for n, p in props.items() if any(map(_is_null, p.get("anyOf", [])))}
            s["properties"], pattern = {}, {}
            for name, p in props.items():
                node = _node(p, defs, omit_null=True)
                if _single_type(node):
                    s["properties"][name] = node
                else:  # several types: validated, passed over by Foxglove's parser
                    pattern[f"^{re.escape(name)}$"] = node
            if pattern:
                s["patternProperties"] = pattern
            if "required" in s:
                s["required"] = [n for n in s["required"] if n not in nullable]
        extra = s.get("additionalProperties")
        if isinstance(extra, dict):
            s["additionalProperties"] = _node(extra, defs)
        return s
    if s.get("type") == "array":
        prefix = s.pop("prefixItems", None)
        if prefix is not None:
            nodes = [_node(p, defs) for p in prefix]
            if any(n != nodes[0] for n in nodes):
                raise ValueError(f"a tuple of mixed item types: {prefix}")
            s["items"] = nodes[0]
        elif isinstance(s.get("items"), dict):
            s["items"] = _node(s["items"], defs)
    return s


def _model_node(model: type[BaseModel]) -> dict:
    raw = model.model_json_schema()
    defs = raw.pop("$defs", {})
    node = _node(raw, defs)
    if model is TunerEvent:  # the request event's JSON text is recorded as objects
        data = node["properties"]["data"]
        data["properties"] = {
            name: {**_model_node(m), "description": f"request events: the {name} as an object"}
            for name, m in EVENT_OBJECTS.items()
        }
    return node


@cache
def schema_of(model: type[BaseModel]) -> dict:
    """The JSON Schema (draft 2020-12) of ``model``'s recorded form."""
    return {"$schema": DIALECT, **_model_node(model)}


@cache
def schema_bytes(model: type[BaseModel]) -> bytes:
    return json.dumps(schema_of(model)).encode()


# --- payloads ---------------------------------------------------------------------------------


def _optional_models(annotation: Any) -> list[type[BaseModel]]:
    """The models inside a field's annotation (``Verification | None`` → [Verification])."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return [m for a in typing.get_args(annotation) for m in _optional_models(a)]
    return []


def _allows_none(annotation: Any) -> bool:
    return annotation is None or type(None) in typing.get_args(annotation)


@cache
def _holds_nulls(model: type[BaseModel]) -> bool:
    """Can a message of ``model`` have a field that is None (left out of its recorded form)?"""
    return any(
        _allows_none(f.annotation) or any(_holds_nulls(m) for m in _optional_models(f.annotation))
        for f in model.model_fields.values()
    )


def recorded_payload(msg: BaseModel, payload: bytes) -> bytes:
    """The recorded form of a validated bus message (``payload`` its bus JSON)."""
    model = type(msg)
    if isinstance(msg, TunerEvent) and msg.kind == "request":
        obj = msg.model_dump(mode="json", exclude_none=True)
        for name, inner in EVENT_OBJECTS.items():
            text = obj["data"].get(name)
            if isinstance(text, str):
                obj["data"][name] = _as_object(text, inner)
        return json.dumps(obj, separators=(",", ":"), ensure_ascii=False).encode()
    if not _holds_nulls(model):
        return payload
    return msg.model_dump_json(exclude_none=True).encode()


def _as_object(text: str, model: type[BaseModel]) -> dict | str:
    """A model's JSON text as an object in its recorded form (None fields left out); text
    that is not the model's is recorded as it came (the file's readers judge it)."""
    try:
        return model.model_validate_json(text).model_dump(mode="json", exclude_none=True)
    except ValueError:
        return text


def _fill_nulls(model: type[BaseModel], obj: dict) -> None:
    """Put back the required fields that were None (left out of the recorded form)."""
    for name, f in model.model_fields.items():
        value = obj.get(name)
        if name not in obj and f.is_required() and _allows_none(f.annotation):
            obj[name] = None
        elif isinstance(value, dict):
            for m in _optional_models(f.annotation):
                _fill_nulls(m, value)


@cache
def _needs_restoring(model: type[BaseModel]) -> bool:
    """Does the recorded form of ``model`` miss anything its bus form must have?"""
    if model is TunerEvent:
        return True
    return any(
        (f.is_required() and _allows_none(f.annotation))
        or any(_needs_restoring(m) for m in _optional_models(f.annotation))
        for f in model.model_fields.values()
    )


def bus_payload(schema: str, data: bytes) -> bytes:
    """The bus JSON of a recorded message (schema name ``schema``); data that is not its
    model's recorded form comes back as it is (the reader's validation names the fault)."""
    model = RECORDED.get(schema)
    if model is None or not _needs_restoring(model):
        return data
    try:
        obj = json_text.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return data
    if not isinstance(obj, dict):
        return data
    _fill_nulls(model, obj)
    if model is TunerEvent and isinstance(obj.get("data"), dict):
        for name in EVENT_OBJECTS:
            value = obj["data"].get(name)
            if isinstance(value, dict):
                obj["data"][name] = json.dumps(value, separators=(",", ":"), ensure_ascii=False)
    return json.dumps(obj, separators=(",", ":"), ensure_ascii=False).encode()


def run_record(meta: dict[str, str], t: float, log_time_zero: int) -> bytes:
    """The run's metadata as a ``RunRecord`` message (its recorded form)."""

    def num(key: str, kind: type) -> Any:
        raw = meta.get(key, "")
        try:
            return kind(raw) if raw not in ("", "None") else None
        except ValueError:
            return None

    def obj(key: str, model: type[BaseModel]) -> Any:
        try:
            return model.model_validate_json(meta[key]) if meta.get(key) else None
        except ValueError:
            return None

    record = RunRecord(
        **{k: meta.get(k, "") for k in ("run_id", "loop", "method", "rule", "status")},
        **{k: meta.get(k, "") for k in ("started", "finished", "prefix", "replay")},
        plant_node=meta.get("plant_node", ""),
        plant_changed=meta.get("plant_changed", ""),
        t=t,
        samples=num("samples", int) or 0,
        first_seq=num("first_seq", int),
        last_seq=num("last_seq", int),
        dropped=num("dropped", int) or 0,
        messages=num("messages", int) or 0,
        left_out=num("left_out", int) or 0,
        ku=num("ku", float),
        pu=num("pu", float),
        log_time_zero=log_time_zero,
        request=obj("request", TuneRequest),
        info=obj("info", LoopInfo),
        result=obj("result", TuneResult),
    )
    return record.model_dump_json(exclude_none=True).encode()


def metadata_of_record(data: bytes) -> dict[str, str]:
    """The fields of a run's ``run`` metadata that a RunRecord message (``data``, its recorded
    form) carries, as the logger writes them (numbers as text, request, info and result as
    their bus JSON): for ``autotune recover`` of a file whose metadata record fails the CRC,
    the run's figures from the copy of them inside a CRC-checked chunk. {} if ``data`` is not
    a RunRecord."""
    try:
        rec = RunRecord.model_validate_json(bus_payload(RunRecord.__name__, data))
    except ValueError:
        return {}
    meta = {
        k: getattr(rec, k)
        for k in ("run_id", "loop", "method", "rule", "status", "started", "finished", "prefix")
    }
    meta.update(replay=rec.replay, plant_node=rec.plant_node, plant_changed=rec.plant_changed)
    for k in ("samples", "first_seq", "last_seq", "dropped", "messages", "left_out"):
        meta[k] = str(getattr(rec, k))
    for k in ("ku", "pu"):
        v = getattr(rec, k)
        meta[k] = "" if v is None else repr(v)
    for k in ("request", "info", "result"):
        v = getattr(rec, k)
        meta[k] = "" if v is None else v.model_dump_json()
    meta["log_time_zero"] = str(rec.log_time_zero)
    return meta
