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


Finite = Annotated[float, msgspec.Meta(ge=-1.0e6, le=1.0e6)]
"""A coordinate or component, finite and bounded (the plant's frame is metres)."""
Unit = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]


class Vector3(Message, frozen=True, kw_only=True):
    """``foxglove.Vector3`` (also used for ``foxglove.Point3``: same fields)."""

    x: Finite
    y: Finite
    z: Finite


class Quaternion(Message, frozen=True, kw_only=True):
    """``foxglove.Quaternion``, unit length (checked)."""

    x: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)]
    y: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)]
    z: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)]
    w: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)]

    def __post_init__(self) -> None:
        super().__post_init__()
        norm = self.x**2 + self.y**2 + self.z**2 + self.w**2
        if abs(norm - 1.0) > 1e-6:
            raise ValueError(f"quaternion is not unit length (|q|² = {norm:.6g})")

    @classmethod
    def about_z(cls, angle_rad: float) -> Quaternion:
        """Rotation by ``angle_rad`` about +z (the scan direction's heading in the plate frame)."""
        import math

        return cls(x=0.0, y=0.0, z=math.sin(angle_rad / 2), w=math.cos(angle_rad / 2))


IDENTITY = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


class Pose(Message, frozen=True, kw_only=True):
    """``foxglove.Pose``: position [m] and orientation in the parent frame."""

    position: Vector3
    orientation: Quaternion


class PoseInFrame(Message, frozen=True, kw_only=True):
    """``foxglove.PoseInFrame``: the laser spot, x axis along the scan direction."""

    timestamp: Timestamp
    frame_id: Annotated[str, msgspec.Meta(max_length=64)]
    pose: Pose


class Color(Message, frozen=True, kw_only=True):
    """``foxglove.Color``, RGBA in [0, 1]."""

    r: Unit
    g: Unit
    b: Unit
    a: Unit


class Duration(Message, frozen=True, kw_only=True):
    """``duration``; zero = forever."""

    sec: Annotated[int, msgspec.Meta(ge=0, le=2**31 - 1)] = 0
    nsec: Annotated[int, msgspec.Meta(ge=0, le=999_999_999)] = 0


class LineType(enum.IntEnum):
    """``foxglove.LineType``."""

    LINE_STRIP = 0
    LINE_LOOP = 1
    LINE_LIST = 2


class LinePrimitive(Message, frozen=True, kw_only=True):
    """``foxglove.LinePrimitive``: e.g. the layer's scan tracks (``LINE_LIST``: pairs of points)."""

    type: LineType
    pose: Pose
    thickness: Annotated[float, msgspec.Meta(ge=0.0, le=1.0e3)]
    scale_invariant: bool
    points: Annotated[list[Vector3], msgspec.Meta(max_length=200_000)]
    color: Color
    colors: list[Color] = []
    indices: list[int] = []


class ModelPrimitive(Message, frozen=True, kw_only=True):
    """``foxglove.ModelPrimitive``: a mesh embedded as bytes (the part's STL, ``model/stl``)."""

    pose: Pose
    scale: Vector3
    color: Color
    override_color: bool
    url: Annotated[str, msgspec.Meta(max_length=1024)] = ""
    media_type: Annotated[str, msgspec.Meta(max_length=64)] = ""
    data: bytes = b""


class Nothing(Message, frozen=True, kw_only=True):
    """Never present: the item type of an always empty list."""


Unused = Annotated[list[Nothing], msgspec.Meta(max_length=0, description="Always empty in meltloop.")]
"""A field of a Foxglove schema that meltloop does not use: present (Foxglove's JSON schema lists
every field) and empty. Its items are typed (an empty object), so a hostile payload nested
thousands deep in it is a type error at the first level, not a recursion."""


class SceneEntity(Message, frozen=True, kw_only=True):
    """``foxglove.SceneEntity``; meltloop draws lines and models, the other primitive lists stay empty."""

    timestamp: Timestamp
    frame_id: Annotated[str, msgspec.Meta(max_length=64)]
    id: Annotated[str, msgspec.Meta(max_length=64)]
    lifetime: Duration = Duration()
    frame_locked: bool = False
    metadata: Unused = []
    arrows: Unused = []
    cubes: Unused = []
    spheres: Unused = []
    cylinders: Unused = []
    lines: list[LinePrimitive] = []
    triangles: Unused = []
    texts: Unused = []
    models: list[ModelPrimitive] = []


class SceneUpdate(Message, frozen=True, kw_only=True):
    """``foxglove.SceneUpdate``: entities replace earlier ones of the same id (no deletions)."""

    deletions: Unused = []
    entities: Annotated[list[SceneEntity], msgspec.Meta(min_length=1, max_length=64)]
