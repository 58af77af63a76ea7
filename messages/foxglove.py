"""Foxglove well-known schemas used by meltloop, JSON-encoded (bytes as base64 strings).

Field names and types follow https://docs.foxglove.dev/docs/visualization/message-schemas so
that Foxglove recognises the channels by schema name (``foxglove.Log``, ``foxglove.RawImage``)
and shows them in its Log and Image panels with no conversion.
"""

from __future__ import annotations

import enum
from typing import Annotated

import msgspec

from messages.base import Message


class LogLevel(enum.IntEnum):
    """``foxglove.LogLevel``."""

    UNKNOWN = 0
    DEBUG = 1
    INFO = 2
    WARNING = 3
    ERROR = 4
    FATAL = 5


class Timestamp(Message, frozen=True, kw_only=True):
    """``time``: seconds and nanoseconds (process time in meltloop)."""

    sec: Annotated[int, msgspec.Meta(ge=0, le=2**32 - 1)]
    nsec: Annotated[int, msgspec.Meta(ge=0, le=999_999_999)]

    @classmethod
    def from_seconds(cls, t_s: float) -> Timestamp:
        """Build from a time in seconds (``t_s >= 0``)."""
        ns = int(round(t_s * 1e9))
        return cls(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)

    def to_ns(self) -> int:
        """Nanoseconds since the epoch of the clock (process start for meltloop)."""
        return self.sec * 1_000_000_000 + self.nsec


class Log(Message, frozen=True, kw_only=True):
    """``foxglove.Log``: one log line of a node."""

    timestamp: Timestamp
    level: LogLevel
    message: Annotated[str, msgspec.Meta(max_length=8000)]
    name: Annotated[str, msgspec.Meta(max_length=64)]
    file: Annotated[str, msgspec.Meta(max_length=256)] = ""
    line: Annotated[int, msgspec.Meta(ge=0)] = 0


class RawImage(Message, frozen=True, kw_only=True):
    """``foxglove.RawImage``: an uncompressed image, e.g. the top-surface temperature map."""

    timestamp: Timestamp
    frame_id: Annotated[str, msgspec.Meta(max_length=64)]
    width: Annotated[int, msgspec.Meta(ge=1, le=4096)]
    height: Annotated[int, msgspec.Meta(ge=1, le=4096)]
    encoding: Annotated[str, msgspec.Meta(max_length=16)]
    step: Annotated[int, msgspec.Meta(ge=1)]
    data: bytes

    def __post_init__(self) -> None:
        super().__post_init__()
        if len(self.data) != self.step * self.height:
            raise ValueError(f"image data holds {len(self.data)} bytes, "
                             f"expected step*height = {self.step * self.height}")
