"""Reading meltloop recordings back: validated messages per channel, metadata, completeness.

Used by the GP dataset builder, the report and the tests, so that everything downstream of a
run depends on the message contract only — a recording from a hardware node reads the same.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader

from messages.codec import MessageError, decode
from messages.topics import TOPICS, Topic


class RecordingError(ValueError):
    """A recording that is missing, empty, truncated or not a meltloop MCAP (one-line reason)."""


def _topic(channel_or_topic: str | Topic) -> Topic:
    if isinstance(channel_or_topic, Topic):
        return channel_or_topic
    topic = TOPICS.get(channel_or_topic.lstrip("/"))
    if topic is None:
        raise KeyError(f"unknown channel {channel_or_topic!r}")
    return topic


def _open(path: Path):
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"recording not found: {path}")
    if path.stat().st_size == 0:
        raise RecordingError(f"recording is empty: {path}")
    return path.open("rb")


def read_messages(path: str | Path, channel: str | Topic) -> Iterator[Any]:
    """Yield the decoded, validated messages of one channel (e.g. ``"/plant/state"``), in file order.

    Raises
    ------
    RecordingError
        Missing, empty or truncated file, or a message that fails validation.
    """
    topic = _topic(channel)
    with _open(Path(path)) as stream:
        try:
            for _schema, _channel, message in make_reader(stream).iter_messages(topics=[topic.channel]):
                yield decode(topic, message.data)
        except (McapError, EOFError, ValueError, KeyError, AssertionError) as err:
            if isinstance(err, MessageError):
                raise RecordingError(f"{path}: invalid message: {err}") from None
            raise RecordingError(f"{path}: unreadable or truncated MCAP ({type(err).__name__}: {err})") from None


def metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The file's metadata records by name (``meltloop``, ``meltloop.counts``)."""
    with _open(Path(path)) as stream:
        try:
            return {m.name: dict(m.metadata) for m in make_reader(stream).iter_metadata()}
        except (McapError, EOFError, ValueError, AssertionError) as err:
            raise RecordingError(f"{path}: unreadable or truncated MCAP ({type(err).__name__})") from None


def attachments(path: str | Path) -> dict[str, bytes]:
    """The file's attachments by name (``config/<node>.json``)."""
    with _open(Path(path)) as stream:
        try:
            return {a.name: a.data for a in make_reader(stream).iter_attachments()}
        except (McapError, EOFError, ValueError, AssertionError) as err:
            raise RecordingError(f"{path}: unreadable or truncated MCAP ({type(err).__name__})") from None


def is_complete(path: str | Path) -> bool:
    """True if the recorder finished the file and found no message missing."""
    try:
        return metadata(path).get("meltloop.counts", {}).get("complete") == "true"
    except RecordingError:
        return False


def run_config(path: str | Path) -> dict[str, Any]:
    """Each node's resolved configuration recorded in the file, by node name."""
    return {
        name.removeprefix("config/").removesuffix(".json"): json.loads(data)
        for name, data in attachments(path).items()
        if name.startswith("config/")
    }
