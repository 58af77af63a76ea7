"""The plant in Foxglove's 3D panel: the laser pose and the layer's scene (tracks, part).

Frame ``plate``: x and y as the scan plan, z up, 0 at the plate's top; metres (Foxglove's
3D unit).

* :func:`laser_pose`: ``foxglove.PoseInFrame`` of the spot on the current top surface, its x
  axis along the scan direction (``/plant/laser``, every state).
* :func:`scene_update`: ``foxglove.SceneUpdate`` with the entity ``scan_plan`` (the layer's
  tracks as a line list on the top surface) and, for a part, ``part`` (its STL, mm → m,
  placed as :func:`fe_node.part.part_plans` placed its scan paths: centred on its plan-view
  bounding box, its base on the plate) (``/plant/scene``, at the start and at each new layer).
* :func:`fitted_scene`: that scene simplified until it fits the topic's size limit
  (``PLANT_SCENE.max_bytes``): the part's mesh decimated by vertex clustering, then, if the
  tracks alone are too many, every k-th track drawn; with notes saying what was simplified.
"""
from __future__ import annotations

import functools
import math
import struct
from pathlib import Path

import numpy as np

from fe_node.observe import Observation
from fe_node.scan import ScanPlan
from messages.codec import encode
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
from messages.topics import PLANT_SCENE

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
    return _scene(plan.tracks, obs, None if part_stl is None else part_model(part_stl))


def _scene(tracks: list, obs: Observation, part: ModelPrimitive | None) -> SceneUpdate:
    stamp = Timestamp.from_seconds(obs.time_s)
    points = [Vector3(x=float(x), y=float(y), z=obs.z_top_m) for track in tracks for (x, y) in track]
    entities = [SceneEntity(timestamp=stamp, frame_id=FRAME, id="scan_plan", lines=[LinePrimitive(
        type=LineType.LINE_LIST, pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=IDENTITY),
        thickness=2.0, scale_invariant=True, points=points, color=TRACK_COLOR)])]
    if part is not None:
        entities.append(SceneEntity(timestamp=stamp, frame_id=FRAME, id="part", models=[part]))
    return SceneUpdate(entities=entities)


@functools.lru_cache(maxsize=4)
def part_model(stl_path: Path, max_data_bytes: int | None = None) -> ModelPrimitive:
    """The STL as an embedded ``model/stl``, scaled mm → m and placed like its scan paths (read once
    per file: every layer's scene holds it); if the file is larger than ``max_data_bytes``, its
    mesh decimated (:func:`decimated_stl`) to fit."""
    import trimesh

    mesh = trimesh.load(stl_path, file_type="stl")
    (x0, y0, z0), (x1, y1, _) = mesh.bounds.tolist()
    offset = Vector3(x=-0.5e-3 * (x0 + x1), y=-0.5e-3 * (y0 + y1), z=-1e-3 * z0)
    data = Path(stl_path).read_bytes()
    if max_data_bytes is not None and len(data) > max_data_bytes:
        data = decimated_stl(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                             max(1, (max_data_bytes - _STL_HEAD) // _STL_FACET))
    return ModelPrimitive(pose=Pose(position=offset, orientation=IDENTITY), scale=Vector3(x=1e-3, y=1e-3, z=1e-3),
                          color=PART_COLOR, override_color=True, media_type="model/stl", data=data)


_STL_HEAD, _STL_FACET = 84, 50
"""Bytes of a binary STL's header (80 bytes and the triangle count) and of each triangle."""
_STL_DTYPE = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])


def decimated_stl(vertices: np.ndarray, faces: np.ndarray, max_triangles: int) -> bytes:
    """A binary STL of the mesh with at most ``max_triangles`` triangles, by vertex clustering.

    Vertices are merged per cubic cell of a grid from the mesh's lowest corner (their mean),
    triangles that lose a corner are dropped;
    the cell starts at half the mean edge length scaled by the square root of the reduction
    wanted and grows by 1.25 until few enough triangles remain.

    Parameters
    ----------
    vertices : ndarray (n, 3)
        Vertex coordinates (the STL's unit).
    faces : ndarray (m, 3)
        Vertex indices of each triangle.
    max_triangles : int
        At most this many triangles (>= 1).
    """
    edge = float(np.linalg.norm(vertices[faces[:, 1]] - vertices[faces[:, 0]], axis=1).mean())
    cell = 0.5 * (edge or 1.0) * math.sqrt(max(1.0, len(faces) / max_triangles))
    points, triangles, low = vertices, faces, vertices.min(axis=0)
    while len(triangles) > max_triangles:  # ends: a cell larger than the mesh leaves no triangle
        cells, inverse = np.unique(np.floor((vertices - low) / cell).astype(np.int64), axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        points = np.zeros((len(cells), 3))
        np.add.at(points, inverse, vertices)
        points /= np.bincount(inverse, minlength=len(cells))[:, None]
        merged = inverse[faces]
        whole = (merged[:, 0] != merged[:, 1]) & (merged[:, 1] != merged[:, 2]) & (merged[:, 0] != merged[:, 2])
        triangles = np.unique(merged[whole], axis=0)  # a triangle found twice after merging is drawn once
        cell *= 1.25
    corners = points[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    records = np.zeros(len(triangles), dtype=_STL_DTYPE)
    records["normal"] = np.divide(normals, lengths, out=np.zeros_like(normals), where=lengths > 0)
    records["vertices"] = corners
    return b"meltloop: decimated by vertex clustering".ljust(80) + struct.pack("<I", len(triangles)) + records.tobytes()


def fitted_scene(plan: ScanPlan, obs: Observation, part_stl: Path | None = None,
                 max_bytes: int = PLANT_SCENE.max_bytes) -> tuple[SceneUpdate, list[str]]:
    """:func:`scene_update`, simplified until its message takes at most ``max_bytes``, and notes
    saying what was simplified (none if nothing was).

    If the tracks take more than half of ``max_bytes``, only every k-th is drawn; then the part's
    mesh is decimated to the room the tracks leave (its bytes travel base64-encoded: 4 characters
    per 3 bytes).
    """
    tracks = list(plan.tracks)
    part = None if part_stl is None else part_model(part_stl)
    scene = _scene(tracks, obs, part)
    if len(encode(scene)) <= max_bytes:
        return scene, []
    notes = []
    tracks_bytes = len(encode(_scene(tracks, obs, None)))
    if tracks_bytes > max_bytes // 2:
        every = math.ceil(tracks_bytes / (max_bytes // 2))
        notes.append(f"{PLANT_SCENE.channel}: layer {obs.layer}: every {every}th of its {len(tracks)} tracks drawn "
                     f"to fit the topic's {max_bytes}-byte limit")
        tracks = tracks[::every]
        tracks_bytes = len(encode(_scene(tracks, obs, None)))
    if part_stl is not None and len(encode(_scene(tracks, obs, part))) > max_bytes:
        part = part_model(part_stl, (max_bytes - tracks_bytes - 4096) * 3 // 4)  # 4 KiB: the entity's other fields
        notes.append(f"{PLANT_SCENE.channel}: part {part_stl.name} ({part_stl.stat().st_size} bytes) decimated to "
                     f"{(len(part.data) - _STL_HEAD) // _STL_FACET} triangles ({len(part.data)} bytes) to fit the "
                     f"topic's {max_bytes}-byte limit")
    return _scene(tracks, obs, part), notes
