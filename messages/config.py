"""TOML run configuration → frozen settings dataclasses, with one-line errors.

``launch.py --config FILE`` hands the same TOML file to every node; each node reads its own
table (``[plant]``, ``[controller]``) into its settings dataclasses, whose field names (with
units in the names, SI inside) are the TOML keys. Unknown keys, wrong types and values the
dataclass rejects raise :class:`~messages.cli.UsageError` naming the key.
"""

from __future__ import annotations

import dataclasses
import tomllib
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from messages.cli import UsageError

T = TypeVar("T")


def load_toml(path: Path | None) -> dict[str, Any]:
    """The parsed TOML file (``{}`` for ``None``); :class:`UsageError` if missing or invalid, or if
    its ``[plant]`` or ``[controller]`` is not a table (e.g. ``[[plant]]``, an array of tables)."""
    if path is None:
        return {}
    try:
        data = tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UsageError(f"config file not found: {path}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise UsageError(f"{path}: invalid TOML: {err}") from None
    for table in ("plant", "controller"):
        if table in data and not isinstance(data[table], dict):
            raise UsageError(f"{path}: [{table}] must be a table, got {type(data[table]).__name__}")
    return data


def build(cls: type[T], data: Mapping[str, Any], where: str, **overrides: Any) -> T:
    """Construct dataclass ``cls`` from ``data`` (nested tables → nested dataclasses).

    Parameters
    ----------
    cls : dataclass type
        The (frozen) settings class.
    data : mapping
        TOML table.
    where : str
        Its location, for messages (e.g. ``[controller]``).
    overrides : Any
        Field values that take precedence (e.g. from the command line); ``None`` is ignored.
    """
    if not isinstance(data, Mapping):
        raise UsageError(f"{where} must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = set(data) - set(fields)
    if unknown:
        raise UsageError(f"{where}: unknown key(s) {', '.join(sorted(unknown))}; known: {', '.join(fields)}")
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            kwargs[name] = build(hint, value, f"{where}.{name}")
        else:
            kwargs[name] = tuple(value) if isinstance(value, list) else value
    kwargs.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as err:
        raise UsageError(f"{where}: {err}") from None


def as_dict(settings: Any) -> dict[str, Any]:
    """Plain, JSON-able dictionary of a settings dataclass (what the node records as its config)."""
    return dataclasses.asdict(settings)
