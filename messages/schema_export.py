"""The contract as files: one JSON Schema per topic, ``topics.json``, and the field tables of the docs.

``python -m messages.schema_export`` writes, from the message classes and the topic registry
(the single source of truth), into ``messages/schemas/``:

- ``<suffix with '/' as '.'>.schema.json``: the self-contained JSON Schema (draft 2020-12) of
  each topic's message, e.g. ``plant.state.schema.json``;
- ``topics.json``: per topic its key pattern, MCAP channel, schema name and file, largest
  payload, who publishes it, whether the key ends with the publishing node, and the unit of each
  field whose name carries one (``area_mm2`` -> mm²).

``--doc FILE`` also rewrites the generated field tables of ``docs/messages.md`` between its
``<!-- fields:begin -->`` and ``<!-- fields:end -->`` markers. ``--check`` writes nothing and
exits 1, listing what differs, if a file is not what the code generates (CI runs it through
``tests/test_contract_schemas.py``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from messages.auth import ROLES
from messages.cli import ArgumentParser, run_main
from messages.codec import json_schema
from messages.topics import PREFIX, TOPICS, Topic

SCHEMA_DIR = Path(__file__).resolve().parent / "schemas"
BEGIN, END = "<!-- fields:begin -->", "<!-- fields:end -->"
_UNITS = (("_mm2", "mm²"), ("_mm_s", "mm/s"), ("_mm", "mm"), ("_um", "µm"), ("_us", "µs"), ("_ms", "ms"),
          ("_s", "s"), ("_w", "W"), ("_k", "K"), ("_j", "J"), ("_pct", "%"))


def unit_of(field: str) -> str | None:
    """The unit a field name carries (``speed_mm_s`` -> ``mm/s``), ``None`` if it carries none."""
    return next((unit for suffix, unit in _UNITS if field.endswith(suffix)), None)


def schema_file(topic: Topic) -> str:
    """File name of a topic's schema, e.g. ``plant.state.schema.json``."""
    return topic.suffix.replace("/", ".") + ".schema.json"


def publisher(topic: Topic) -> str:
    """Who may publish on ``topic``: a role (``plant``, ``controller``) or ``every node``."""
    role = topic.suffix.split("/")[0]
    return role if role in ROLES else "every node"


def topic_entry(topic: Topic) -> dict[str, Any]:
    """The machine-readable description of one topic (an entry of ``topics.json``)."""
    fields = list(json_schema(topic)["properties"])
    node_field = ("node" if "node" in fields else "name") if topic.per_node else None
    return {
        "suffix": topic.suffix,
        "key": f"{PREFIX}/{{run_id}}/{topic.suffix}" + ("/{node}" if topic.per_node else ""),
        "channel": topic.channel,
        "schema_name": topic.schema_name,
        "schema_file": schema_file(topic),
        "max_bytes": topic.max_bytes,
        "published_by": publisher(topic),
        "per_node": topic.per_node,
        "node_field": node_field,
        "units": {f: unit for f in fields if (unit := unit_of(f)) is not None},
    }


def topics_document() -> dict[str, Any]:
    """The content of ``topics.json``."""
    return {
        "generated_by": "python -m messages.schema_export",
        "encoding": "one UTF-8 JSON object per message; unknown fields, missing required fields, wrong types, "
                    "non-finite numbers and out-of-range values are invalid",
        "key": f"{PREFIX}/{{run_id}}/{{suffix}}",
        "liveliness_key": f"{PREFIX}/{{run_id}}/alive/{{node}}",
        "topics": [topic_entry(t) for t in TOPICS.values()],
    }


def _dump(data: Any) -> str:
    return json.dumps(data, indent=2, ensure_ascii=False) + "\n"


def generated_files() -> dict[str, str]:
    """Every file of ``messages/schemas/`` by name, as the code generates it."""
    files = {schema_file(t): _dump(json_schema(t)) for t in TOPICS.values()}
    files["topics.json"] = _dump(topics_document())
    return files


def _number(x: float) -> str:
    """``1e5`` for a power of ten from 10⁴ on, other whole numbers in full, else the shortest repr."""
    if float(x).is_integer():
        exponent = len(str(int(abs(x)))) - 1
        return f"{'-' if x < 0 else ''}1e{exponent}" if exponent >= 4 and abs(x) == 10**exponent else str(int(x))
    return repr(float(x))


def _range(spec: dict[str, Any]) -> str:
    """Bounds of one schema node in words (``0 ≤ x ≤ 1e5``, ``≤ 64 chars``)."""
    parts = []
    low = ("≥", spec["minimum"]) if "minimum" in spec else (">", spec.get("exclusiveMinimum"))
    high = ("≤", spec["maximum"]) if "maximum" in spec else ("<", spec.get("exclusiveMaximum"))
    parts += [f"{op} {_number(v)}" for op, v in (low, high) if v is not None]
    parts += [f"≤ {spec['maxLength']} chars"] if "maxLength" in spec else []
    parts += [f"≤ {spec['maxItems']} items"] if "maxItems" in spec else []
    parts += [f"`{spec['pattern']}`"] if "pattern" in spec else []
    parts += [f"{spec['contentEncoding']}-encoded bytes"] if "contentEncoding" in spec else []
    if "enum" in spec:
        parts.append("one of " + ", ".join(f"`{json.dumps(v)}`" for v in spec["enum"]))
    if spec.get("type") == "object" and "properties" in spec:
        parts.append("; ".join(f"`{k}` {_type(v)} {_range(v)}".strip() for k, v in spec["properties"].items()))
    if isinstance(spec.get("additionalProperties"), dict):
        values = spec["additionalProperties"]
        parts.append(f"keys {_range(spec.get('propertyNames', {}))} → {_type(values)} {_range(values)}".strip())
    if spec.get("type") == "array" and spec.get("items"):
        parts.append(f"items {_range(spec['items'])}".strip())
    return ", ".join(p for p in parts if p and p != "items")


def _type(spec: dict[str, Any]) -> str:
    if "anyOf" in spec:
        return " or ".join(_type(s) for s in spec["anyOf"])
    if "enum" in spec:
        return "enum"
    if spec.get("type") == "array":
        return f"array of {_type(spec.get('items', {}))}"
    return spec.get("type", "any")


def _plain(spec: dict[str, Any]) -> dict[str, Any]:
    """The non-null alternative of an optional field's schema."""
    options = [s for s in spec.get("anyOf", [spec]) if s.get("type") != "null"]
    return options[0] if len(options) == 1 else spec


def field_table(topic: Topic) -> str:
    """Markdown table of one topic's message: field, type, unit, required/default, range, meaning."""
    schema = json_schema(topic)
    required = set(schema.get("required", []))
    head = (f"**`{topic.suffix}`** — `{topic.schema_name}`, at most {topic.max_bytes} bytes, published by "
            f"{publisher(topic)}\n\n| field | type | unit | required / default | range | meaning |\n"
            "|---|---|---|---|---|---|\n")
    rows = []
    for name, spec in schema["properties"].items():
        plain = _plain(spec)
        needed = "required" if name in required else f"default `{json.dumps(spec.get('default'))}`"
        meaning = " ".join(str(plain.get("description", spec.get("description", ""))).split())
        rows.append(f"| `{name}` | {_type(spec)} | {unit_of(name) or '–'} | {needed} | {_range(plain) or '–'} "
                    f"| {meaning.replace('|', '/')} |")
    return head + "\n".join(rows) + "\n"


def field_tables() -> str:
    """The generated block of the node contract: one table per topic."""
    tables = "\n".join(field_table(t) for t in TOPICS.values())
    note = "<!-- generated by python -m messages.schema_export --doc; do not edit by hand -->"
    return f"{BEGIN}\n{note}\n\n{tables}{END}"


def with_field_tables(doc: str) -> str:
    """``doc`` with its generated block replaced (``ValueError`` if it has no markers)."""
    start, end = doc.find(BEGIN), doc.find(END)
    if start < 0 or end < start:
        raise ValueError(f"no {BEGIN} ... {END} block")
    return doc[:start] + field_tables() + doc[end + len(END):]


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m messages.schema_export``."""
    parser = ArgumentParser(prog="python -m messages.schema_export", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=SCHEMA_DIR,
                        help="folder of the schema files (default: messages/schemas)")
    parser.add_argument("--doc", type=Path, help="also regenerate the field tables of this Markdown file")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if a file is out of date")
    args = parser.parse_args(argv)
    wanted = {args.out / name: text for name, text in generated_files().items()}
    if args.doc is not None:
        try:
            wanted[args.doc] = with_field_tables(args.doc.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            print(f"{parser.prog}: error: --doc {args.doc}: {getattr(err, 'strerror', None) or err}", file=sys.stderr)
            return 2
    stale = [p for p, text in wanted.items() if not p.is_file() or p.read_text(encoding="utf-8") != text]
    extra = sorted(p for p in args.out.glob("*.json") if p not in wanted) if args.out.is_dir() else []
    if args.check:
        for path in stale + extra:
            print(f"out of date: {path}" if path in wanted else f"not generated by the code: {path}")
        return 1 if stale or extra else 0
    args.out.mkdir(parents=True, exist_ok=True)
    for path in stale:
        path.write_text(wanted[path], encoding="utf-8")
    for path in extra:
        path.unlink()
    print(f"{len(stale)} of {len(wanted)} files written, {len(extra)} removed")
    return 0


if __name__ == "__main__":
    run_main(main)
