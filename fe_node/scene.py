"""The plant in Foxglove's 3D panel: the laser pose and the layer's scene (tracks, part).

Frame ``plate``: x and y as the scan plan, z up, 0 at the plate's top; metres (Foxglove's
3D unit).

* :func:`laser_pose`: ``foxglove.PoseInFrame`` of the spot on the current top surface, its x
  axis along the scan direction (``/plant/laser``, every state).
* :func:`scene_update`: ``foxglove.SceneUpdate`` with the entity ``scan_plan`` (the layer's
  tracks as a line list on the top surface) and, for a part, ``part`` (its STL, mm → m,
  placed as :func:`fe_node.part.part_plans` placed its scan paths: centred on its plan-view
  bounding box, its base on the plate) (``/plant/scene``, at the start and at each new layer).
"""
from __future__ import annotations

import functools
import math
from pathlib import Path

from fe_node.observe import Observation
from fe_node.scan import ScanPlan
from messages.foxglove import (
    IDENTITY,
    Color,
    LinePrimitive,
    LineType,
    ModelPrimitive,
    Pose,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    Timestamp,
    Vector3,
)

FRAME = "plate"
"""Frame of the scene and the laser pose."""

TRACK_COLOR = Color(r=0.2, g=0.6, b=1.0, a=1.0)
PART_COLOR = Color(r=0.75, g=0.75, b=0.78, a=0.35)


def laser_pose(obs: Observation) -> PoseInFrame:
    """The laser spot at ``obs`` on the top surface [m], heading along the scan direction."""
    heading = math.atan2(obs.direction[1], obs.direction[0])
    return PoseInFrame(timestamp=Timestamp.from_seconds(obs.time_s), frame_id=FRAME, pose=Pose(
        position=Vector3(x=obs.x_m, y=obs.y_m, z=obs.z_top_m), orientation=Quaternion.about_z(heading)))


def scene_update(plan: ScanPlan, obs: Observation, part_stl: Path | None = None) -> SceneUpdate:
    """The layer's scan tracks at the top surface and, if given, the part.

    Parameters
    ----------
    plan : ScanPlan
        The current layer's plan [m].
    obs : Observation
        The state the scene belongs to (time, layer, top height).
    part_stl : Path, optional
        The part's STL [mm] (needs ``trimesh``, installed with PySLM).
    """
    stamp = Timestamp.from_seconds(obs.time_s)
    points = [Vector3(x=float(x), y=float(y), z=obs.z_top_m) for track in plan.tracks for (x, y) in track]
    entities = [SceneEntity(timestamp=stamp, frame_id=FRAME, id="scan_plan", lines=[LinePrimitive(
        type=LineType.LINE_LIST, pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=IDENTITY),
        thickness=2.0, scale_invariant=True, points=points, color=TRACK_COLOR)])]
    if part_stl is not None:
        entities.append(SceneEntity(timestamp=stamp, frame_id=FRAME, id="part", models=[part_model(part_stl)]))
    return SceneUpdate(entities=entities)


@functools.lru_cache(maxsize=4)
def part_model(stl_path: Path) -> ModelPrimitive:
    """The STL as an embedded ``model/stl``, scaled mm → m and placed like its scan paths (read once
    per file: every layer's scene holds it)."""
    import trimesh

    (x0, y0, z0), (x1, y1, _) = trimesh.load(stl_path, file_type="stl").bounds.tolist()
    offset = Vector3(x=-0.5e-3 * (x0 + x1), y=-0.5e-3 * (y0 + y1), z=-1e-3 * z0)
    return ModelPrimitive(pose=Pose(position=offset, orientation=IDENTITY), scale=Vector3(x=1e-3, y=1e-3, z=1e-3),
                          color=PART_COLOR, override_color=True, media_type="model/stl",
                          data=Path(stl_path).read_bytes())
