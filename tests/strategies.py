"""Hypothesis strategies for schema-valid messages, built from the contract's JSON Schemas.

Every value the schema allows can be drawn (any step, any number in range), so a property test
over these strategies exercises forgeries that the codec cannot reject.
"""

from __future__ import annotations

import base64
import json

from hypothesis import strategies as st

from messages.codec import json_schema
from messages.topics import Topic

NESTED_ITEMS = 3
"""Most items drawn for an array inside an array (8 at the top level): a scene's entities, their
primitives and their points stay every shape the schema allows without payloads of 8³ points."""


def from_schema(schema: dict, depth: int = 0) -> st.SearchStrategy:
    """A strategy for JSON values valid under ``schema`` (the subset the contract uses); ``depth``
    counts the arrays it stands in."""
    if "anyOf" in schema:
        return st.one_of([from_schema(s, depth) for s in schema["anyOf"]])
    if "enum" in schema:
        return st.sampled_from(schema["enum"])
    kind = schema.get("type")
    if kind == "number":
        low = schema.get("minimum", schema.get("exclusiveMinimum", -1e12))
        high = schema.get("maximum", 1e12)
        return st.floats(low, high, allow_nan=False, allow_infinity=False,
                         exclude_min="exclusiveMinimum" in schema)
    if kind == "integer":
        return st.integers(schema.get("minimum", -(2**31)), schema.get("maximum", 2**31 - 1))
    if kind == "boolean":
        return st.booleans()
    if kind == "null":
        return st.none()
    if kind == "string":
        if schema.get("contentEncoding") == "base64":
            return st.binary(max_size=64).map(lambda b: base64.b64encode(b).decode())
        if "pattern" in schema:
            return st.from_regex(schema["pattern"], fullmatch=True)
        return st.text(max_size=min(schema.get("maxLength", 32), 32))
    if kind == "array":
        most = 8 if depth == 0 else NESTED_ITEMS
        return st.lists(from_schema(schema["items"], depth + 1), max_size=min(schema.get("maxItems", most), most))
    if kind == "object" and "properties" in schema:
        required = set(schema.get("required", ()))
        props = schema["properties"]
        return st.fixed_dictionaries(
            {k: from_schema(v, depth) for k, v in props.items() if k in required},
            optional={k: from_schema(v, depth) for k, v in props.items() if k not in required},
        )
    if kind == "object":
        values = schema.get("additionalProperties", {"type": "integer", "minimum": 0})
        return st.dictionaries(st.text(max_size=16), from_schema(values, depth), max_size=4)
    raise NotImplementedError(f"schema construct not covered: {schema}")


def payloads(topic: Topic, **fixed: object) -> st.SearchStrategy[bytes]:
    """Schema-valid JSON payloads of ``topic``, with ``fixed`` fields set (e.g. ``run_id``)."""
    return from_schema(json_schema(topic)).map(lambda d: json.dumps({**d, **fixed}).encode())
