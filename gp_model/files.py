"""Model files: versioned JSON documents, read with one-line errors and written atomically."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from gp_model.atomic import atomic_write_bytes
from gp_model.errors import GPError, ModelFormatError
from messages.cli import UsageError


def read_document(path: str | os.PathLike[str]) -> Any:
    """The JSON document of the model file ``path``.

    Raises
    ------
    ModelFormatError
        The file is missing, unreadable or not JSON.
    """
    try:
        return json.loads(Path(path).read_bytes())
    except OSError as exc:
        raise ModelFormatError(f"cannot read model file {path}: {exc.strerror or exc}") from exc
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelFormatError(f"model file {path} is not valid JSON ({exc})") from exc


def is_format(doc: Any, format_name: str) -> bool:
    """True if ``doc`` is a model document of ``format_name`` (any version)."""
    return isinstance(doc, dict) and doc.get("format") == format_name


def is_model_file(path: str | os.PathLike[str], format_name: str) -> bool:
    """True if ``path`` is a readable JSON file of ``format_name`` (any version)."""
    try:
        return is_format(read_document(path), format_name)
    except ModelFormatError:
        return False


def write_document(path: str | os.PathLike[str], doc: dict[str, Any]) -> Path:
    """Write ``doc`` as sorted, indented JSON, atomically (temporary file + ``os.replace``); the written path."""
    text = json.dumps(doc, indent=1, sort_keys=True, allow_nan=False) + "\n"
    return atomic_write_bytes(path, text.encode("utf-8"))


def load_for_node(model_class: Any, path: Path) -> Any:
    """``model_class.load(path)`` for a node's command line: :class:`~messages.cli.UsageError` with a
    one-line reason if the file cannot be loaded."""
    try:
        return model_class.load(path)
    except (GPError, OSError, ValueError) as err:
        raise UsageError(f"cannot load GP model {path}: {' '.join(str(err).split())}") from None
