"""Topic registry: key expressions, MCAP channel names, types and size limits, in one place.

Every key is namespaced by run id: ``meltloop/<run_id>/<suffix>``; the MCAP channel of a topic
is ``/<suffix>``. Topics every node publishes (run events, log) carry the publishing node's name
as a last key segment, ``meltloop/<run_id>/run/events/<node>``, so that access control can let
each node publish only its own. Liveliness tokens (readiness and presence of each node) live at
``meltloop/<run_id>/alive/<node>`` in zenoh's separate liveliness space.
"""

from __future__ import annotations

from dataclasses import dataclass

from messages.foxglove import Log, PoseInFrame, RawImage, SceneUpdate
from messages.types import ControllerDiagnostics, LaserCommand, MeltPoolState, PlantDiagnostics, RunEvent

PREFIX = "meltloop"


@dataclass(frozen=True)
class Topic:
    """One stream of the contract.

    Attributes
    ----------
    suffix : str
        Key suffix after ``meltloop/<run_id>/``, e.g. ``plant/state``.
    type : type
        Message class carried on it.
    schema_name : str
        MCAP schema name (Foxglove recognises ``foxglove.*`` names).
    max_bytes : int
        Largest payload accepted; larger ones are rejected before parsing.
    per_node : bool
        Published by every node under its own key ``<suffix>/<node>``; the message names the
        node (``node`` or ``name`` field) and must match that segment.
    """

    suffix: str
    type: type
    schema_name: str
    max_bytes: int
    per_node: bool = False

    @property
    def channel(self) -> str:
        """MCAP channel / Foxglove topic name, e.g. ``/plant/state``."""
        return "/" + self.suffix


PLANT_STATE = Topic("plant/state", MeltPoolState, "meltloop.MeltPoolState", 16 * 1024)
PLANT_DIAGNOSTICS = Topic("plant/diagnostics", PlantDiagnostics, "meltloop.PlantDiagnostics", 16 * 1024)
PLANT_TEMPERATURE = Topic("plant/temperature", RawImage, "foxglove.RawImage", 4 * 1024 * 1024)
PLANT_LASER = Topic("plant/laser", PoseInFrame, "foxglove.PoseInFrame", 4 * 1024)
PLANT_SCENE = Topic("plant/scene", SceneUpdate, "foxglove.SceneUpdate", 4 * 1024 * 1024)
LASER_COMMAND = Topic("controller/command", LaserCommand, "meltloop.LaserCommand", 16 * 1024)
CONTROLLER_DIAGNOSTICS = Topic(
    "controller/diagnostics", ControllerDiagnostics, "meltloop.ControllerDiagnostics", 64 * 1024
)
RUN_EVENTS = Topic("run/events", RunEvent, "meltloop.RunEvent", 512 * 1024, per_node=True)
LOG = Topic("log", Log, "foxglove.Log", 32 * 1024, per_node=True)

TOPICS: dict[str, Topic] = {
    t.suffix: t
    for t in (PLANT_STATE, PLANT_DIAGNOSTICS, PLANT_TEMPERATURE, PLANT_LASER, PLANT_SCENE, LASER_COMMAND,
              CONTROLLER_DIAGNOSTICS, RUN_EVENTS, LOG)
}


def key_expr(run_id: str, topic: Topic, node: str = "*") -> str:
    """Zenoh key expression of ``topic`` in run ``run_id``.

    For a per-node topic, ``node`` is the publishing node (``*``: every node, to subscribe).
    """
    if topic.per_node:
        return f"{PREFIX}/{run_id}/{topic.suffix}/{node}"
    return f"{PREFIX}/{run_id}/{topic.suffix}"


def message_node(msg: object) -> str | None:
    """The node a per-node message says it comes from (``RunEvent.node``, ``Log.name``)."""
    return getattr(msg, "node", getattr(msg, "name", None))


def key_suffix(topic: Topic, node: str | None) -> str:
    """A message's key after ``meltloop/<run_id>/``: ``topic.suffix``, plus ``/<node>`` for a per-node topic."""
    return f"{topic.suffix}/{node}" if topic.per_node else topic.suffix


def run_prefix(run_id: str) -> str:
    """Key expression matching every topic of a run (what the recorder subscribes to)."""
    return f"{PREFIX}/{run_id}/**"


def liveliness_key(run_id: str, node: str = "*") -> str:
    """Liveliness token key of ``node`` (``*`` matches every node of the run)."""
    return f"{PREFIX}/{run_id}/alive/{node}"


def split_key(run_id: str, key: str) -> tuple[Topic, str | None] | None:
    """The registered topic of a received key and, for a per-node topic, the node segment;
    ``None`` if the key is not part of the run's contract."""
    head = f"{PREFIX}/{run_id}/"
    if not key.startswith(head):
        return None
    suffix = key[len(head):]
    if suffix in TOPICS and not TOPICS[suffix].per_node:
        return TOPICS[suffix], None
    base, _, node = suffix.rpartition("/")
    topic = TOPICS.get(base)
    if topic is None or not topic.per_node or not node or node == "*":
        return None
    return topic, node


def topic_for_key(run_id: str, key: str) -> Topic | None:
    """The registered topic of a received key, or ``None`` if it is not part of the contract."""
    found = split_key(run_id, key)
    return None if found is None else found[0]
