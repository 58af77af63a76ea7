"""The one contract between meltloop processes.

Typed message definitions (:mod:`messages.types`, :mod:`messages.foxglove`), the topic
registry and zenoh key expressions (:mod:`messages.topics`), the JSON codec that validates
everything it decodes (:mod:`messages.codec`), the shared zenoh session helper
(:mod:`messages.bus`), the MCAP recorder (:mod:`messages.recorder`) and the recording reader
(:mod:`messages.recording`).

Nothing else crosses a process boundary: a hardware node that publishes these messages on
these keys can replace the FE node without any change to the controller.

>>> from messages import LaserCommand, decode, encode
>>> from messages.topics import LASER_COMMAND
>>> command = LaserCommand(run_id="demo", step=1, time_s=50e-6, power_w=200.0, speed_mm_s=800.0, controller="pid")
>>> decode(LASER_COMMAND, encode(command)) == command  # JSON on the wire, validated on the way in
True
"""

from messages.codec import MessageError, decode, encode, json_schema
from messages.foxglove import Log, LogLevel, RawImage, Timestamp
from messages.topics import TOPICS, Topic, key_expr, liveliness_key, topic_for_key
from messages.types import (
    ControllerDiagnostics,
    LaserCommand,
    MeltPoolState,
    PlantDiagnostics,
    RunEvent,
)

__all__ = [
    "ControllerDiagnostics",
    "LaserCommand",
    "Log",
    "LogLevel",
    "MeltPoolState",
    "MessageError",
    "PlantDiagnostics",
    "RawImage",
    "RunEvent",
    "TOPICS",
    "Timestamp",
    "Topic",
    "decode",
    "encode",
    "json_schema",
    "key_expr",
    "liveliness_key",
    "topic_for_key",
]
