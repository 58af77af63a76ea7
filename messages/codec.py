"""JSON encoding and validating decoding of contract messages, and their JSON Schemas.

Encoding validates by round trip, so an out-of-range or non-finite value is never sent.
Decoding rejects oversized payloads before parsing, then malformed JSON, wrong types, missing
or unknown fields, out-of-range and non-finite values, each with :class:`MessageError` carrying
a one-line reason. Callers count and drop such messages; they never crash on them.

Limits: a payload's size by its topic (``Topic.max_bytes``), its nesting by its type (no message
field holds untyped JSON, so a nested array or object where the type has none is a type error at
once); :func:`loads` parses free-form JSON (a node's configuration, recording metadata) with a
:data:`MAX_TEXT_BYTES` size limit and refuses nesting deeper than the interpreter's recursion
limit with a :class:`MessageError`, as :func:`decode` does should a type ever allow it.
"""

from __future__ import annotations

import copy
from functools import cache
from typing import Any, TypeVar

import msgspec

from messages.topics import Topic

M = TypeVar("M")


class MessageError(ValueError):
    """A payload that is not a valid message of its topic (one-line reason in ``str(err)``)."""


@cache
def _decoder(cls: type) -> msgspec.json.Decoder:
    return msgspec.json.Decoder(cls)


_ENCODER = msgspec.json.Encoder()
MAX_TEXT_BYTES = 1024 * 1024
"""Largest free-form JSON text :func:`loads` parses [bytes]."""


def encode(msg: Any) -> bytes:
    """Serialise ``msg`` to JSON bytes, after checking it decodes back as a valid message.

    Raises
    ------
    MessageError
        If a field is out of its declared range (e.g. a negative power).
    """
    payload = _ENCODER.encode(msg)
    try:
        _decoder(type(msg)).decode(payload)
    except (msgspec.ValidationError, msgspec.DecodeError) as err:
        raise MessageError(f"{type(msg).__name__}: {err}") from None
    return payload


def prepare(topic: Topic) -> None:
    """Build ``topic``'s validating decoder now, when a node declares a publisher or an inbox.

    Its construction compiles the message type (msgspec), many times the cost of a decode, which
    the first message encoded (validated by round trip) or decoded would otherwise pay on the
    loop's hot path: in a fast loop, the deadline of a step or more.
    """
    _decoder(topic.type)


def decode(topic: Topic, payload: bytes | bytearray | memoryview) -> Any:
    """Parse and validate ``payload`` as a message of ``topic``.

    Parameters
    ----------
    topic : Topic
        The topic it arrived on (gives the type and the size limit).
    payload : bytes-like
        Raw JSON bytes.

    Returns
    -------
    The decoded, frozen message (an instance of ``topic.type``).

    Raises
    ------
    MessageError
        One-line reason: oversized, malformed JSON, wrong type, missing field, out of range,
        non-finite value.
    """
    if len(payload) > topic.max_bytes:
        raise MessageError(f"{topic.channel}: payload of {len(payload)} bytes exceeds the {topic.max_bytes}-byte limit")
    try:
        return _decoder(topic.type).decode(payload)
    except (msgspec.ValidationError, msgspec.DecodeError) as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise MessageError(f"{topic.channel}: {reason}") from None
    except RecursionError:
        raise MessageError(f"{topic.channel}: nested too deeply") from None


def loads(text: str | bytes, what: str) -> Any:
    """Parse free-form JSON ``text`` (``what`` names it in errors) within the module's limits.

    Raises
    ------
    MessageError
        One line: larger than :data:`MAX_TEXT_BYTES`, malformed, or nested too deeply.
    """
    if len(text) > MAX_TEXT_BYTES:
        raise MessageError(f"{what}: {len(text)} bytes of JSON exceed the {MAX_TEXT_BYTES}-byte limit")
    try:
        return msgspec.json.decode(text)
    except msgspec.DecodeError as err:
        raise MessageError(f"{what}: {str(err).splitlines()[0]}") from None
    except RecursionError:
        raise MessageError(f"{what}: JSON nested too deeply") from None


def _inline_refs(node: Any, defs: dict[str, Any]) -> Any:
    if isinstance(node, dict):
        if "$ref" in node:
            return _inline_refs(copy.deepcopy(defs[node["$ref"].split("/")[-1]]), defs)
        return {k: _inline_refs(v, defs) for k, v in node.items()}
    if isinstance(node, list):
        return [_inline_refs(v, defs) for v in node]
    return node


@cache
def _schema(cls: type, title: str) -> dict[str, Any]:
    raw = msgspec.json.schema(cls)
    schema = _inline_refs(raw, raw.get("$defs", {}))
    schema.pop("$defs", None)
    schema["title"] = title
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    return schema


def json_schema(topic: Topic) -> dict[str, Any]:
    """Self-contained JSON Schema (no ``$ref``) of the topic's message, titled by its schema name.

    Generated from the message class, the single source of truth.
    """
    return copy.deepcopy(_schema(topic.type, topic.schema_name))
