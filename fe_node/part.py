"""Scan plans of a real part: an STL sliced and hatched with PySLM (``pythonslm``), one plan per layer.

Each layer ``i`` is the part's cross-section at height ``(i + 1/2) * layer_m`` above its base,
scanned as PySLM's :class:`pyslm.hatching.Hatcher` lays it out:

* with ``contours``, first one contour per boundary of the slice (its outline, no spot
  compensation), each a closed path of tracks scanned without a jump;
* then the hatch: lines ``hatch_m`` apart at ``i * hatch_rotation_deg`` (mod 180°) counter-clockwise
  from +x, in alternating directions, clipped to the slice (with contours: inset by half a
  hatch distance from the contour);
* or, with ``island_width_m > 0``, the hatch in square islands of that side (PySLM's
  :class:`~pyslm.hatching.islandHatcher.IslandHatcher`, a checkerboard: the lines of neighbouring
  islands are perpendicular), the island grid turned by ``i * hatch_rotation_deg``; islands are
  scanned in rows, each island's lines in alternating directions.

Coordinates are centred on the part's plan-view bounding box and converted from PySLM's mm to
m; PySLM rounds them to 10 nm, so a hatch line's direction is within about 0.01° of its angle.

The example part :data:`EXAMPLE_STL` is a cylinder 1.5 mm across and 0.5 mm high (10 layers
of 50 µm); ``parts/block_5mm.stl`` is a 5 x 5 x 1.5 mm box (60 layers of 25 µm) and
``parts/l_bracket_3mm.stl`` an L-shaped bracket 3 mm across and 0.5 mm high (their generating
commands: docs/fe.md, "Parts in Foxglove and on the command line").  PySLM is an optional
dependency: ``pip install pythonslm``.
"""
from __future__ import annotations

import contextlib
import importlib.util
import logging
import math
from pathlib import Path

import numpy as np

from fe_node.scan import ScanPlan

EXAMPLE_STL = Path(__file__).parent / "parts" / "cylinder_d1.5_h0.5_mm.stl"
"""The shipped example part (``--scenario part``)."""


HATCH_ROTATION_DEG = 67.0
"""Default rotation of the hatch from one layer to the next [deg] (``hatch_rotation_deg``)."""

CONTOURS = True
"""Default: scan each slice's contour before its hatch (``contours``)."""

ISLAND_WIDTH_M = 0.0
"""Default island side [m] (``island_width_m``): 0, one hatch over the whole slice."""

MIN_TRACK_M = 1e-6
"""Shortest track kept [m]: shorter hatch lines are dropped, contour points closer than this to
the previous point are merged into it (PySLM's offsetting leaves sub-micrometre edges)."""

PYSLM_MISSING = "scenario part: needs PySLM (pip install pythonslm, or the project's [part] extra)"


def require_pyslm() -> None:
    """Raise ``ValueError`` (:data:`PYSLM_MISSING`, one line) when PySLM is not installed."""
    if importlib.util.find_spec("pyslm") is None:
        raise ValueError(PYSLM_MISSING)


def _contour_tracks(coords: np.ndarray) -> list:
    """Tracks [m] along a closed contour polyline (coordinates [m], first point repeated last),
    merging points closer than :data:`MIN_TRACK_M` to the previous one."""
    kept = [coords[0]]
    for p in coords[1:-1]:
        if np.hypot(*(p - kept[-1])) >= MIN_TRACK_M:
            kept.append(p)
    while len(kept) > 1 and np.hypot(*(kept[-1] - coords[-1])) < MIN_TRACK_M:
        kept.pop()
    kept.append(coords[-1])
    if len(kept) < 4:       # fewer than three distinct corners: no area to outline
        return []
    return [((float(a[0]), float(a[1])), (float(b[0]), float(b[1]))) for a, b in zip(kept[:-1], kept[1:])]


@contextlib.contextmanager
def _root_logging_kept():
    """Undo the handlers PySLM adds to the root logger (its module-level ``logging.info`` calls
    ``logging.basicConfig``), which would print every library's INFO records (Dask's among them) for the
    rest of the process."""
    root = logging.getLogger()
    handlers = list(root.handlers)
    try:
        yield
    finally:
        for handler in [h for h in root.handlers if h not in handlers]:
            root.removeHandler(handler)


def part_plans(stl_path: str | Path, layer_m: float, hatch_m: float, hatch_rotation_deg: float = HATCH_ROTATION_DEG,
               contours: bool = CONTOURS, island_width_m: float = ISLAND_WIDTH_M) -> tuple[ScanPlan, ...]:
    """Per-layer scan plans of the part in ``stl_path`` (module docstring).

    Parameters
    ----------
    stl_path : str or Path
        STL file, in mm (PySLM's unit).
    layer_m, hatch_m : float
        Layer thickness and hatch distance [m].
    hatch_rotation_deg : float
        Hatch angle of layer ``i`` is ``i`` times this [deg], counter-clockwise from +x.
    contours : bool
        Scan each slice's contour before its hatch.
    island_width_m : float
        Side of the square islands [m]; 0: no islands.

    Returns
    -------
    tuple of ScanPlan
        One plan per layer, bottom first [m].

    Raises
    ------
    ValueError
        Missing file, PySLM not installed, a part thinner than one layer, or islands narrower
        than the hatch distance.
    """
    with _root_logging_kept():
        return _slice(stl_path, layer_m, hatch_m, hatch_rotation_deg, contours, island_width_m)


def _slice(stl_path: str | Path, layer_m: float, hatch_m: float, hatch_rotation_deg: float = HATCH_ROTATION_DEG,
          contours: bool = CONTOURS, island_width_m: float = ISLAND_WIDTH_M) -> tuple[ScanPlan, ...]:
    """:func:`part_plans` without the logging guard."""
    if not (island_width_m == 0 or island_width_m >= hatch_m):
        raise ValueError(f"scenario part: island_width_m must be 0 (no islands) or at least hatch_m "
                         f"({hatch_m:g} m), got {island_width_m:g}")
    try:
        import pyslm
        from pyslm import hatching
        from pyslm.geometry import ContourGeometry, HatchGeometry
        from pyslm.hatching.islandHatcher import IslandHatcher
    except ImportError:
        raise ValueError(PYSLM_MISSING) from None
    path = Path(stl_path)
    if not path.is_file():
        raise ValueError(f"scenario part: no STL file {str(path)!r}")
    part = pyslm.Part(path.stem)
    try:
        part.setGeometry(str(path))
        part.dropToPlatform()
        x0, y0, _, x1, y1, z1 = (float(v) for v in part.boundingBox)
    except Exception as err:  # the mesh loader raises its own types for a file it cannot read
        raise ValueError(f"scenario part: cannot read {str(path)!r} as an STL mesh "
                         f"({type(err).__name__}: {' '.join(str(err).split())[:200]})") from None
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1, z1)) or not (x1 > x0 and y1 > y0 and z1 > 0):
        raise ValueError(f"scenario part: {str(path)!r} holds no solid (bounding box {x0:g}..{x1:g} x "
                         f"{y0:g}..{y1:g} x 0..{z1:g} mm)")
    centre = np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1)])
    hatcher = hatching.Hatcher() if island_width_m == 0 else IslandHatcher()
    if island_width_m > 0:
        hatcher.islandWidth, hatcher.islandOverlap = island_width_m * 1e3, 0.0
    hatcher.hatchDistance, hatcher.layerAngleIncrement = hatch_m * 1e3, 0.0
    hatcher.numInnerContours, hatcher.numOuterContours = 0, int(contours)
    hatcher.spotCompensation = hatcher.contourOffset = 0.0
    hatcher.volumeOffsetHatch = 0.5 * hatch_m * 1e3 if contours else 0.0
    hatcher.scanContourFirst = True
    hatcher.hatchSortMethod = hatching.AlternateSort()
    n_layers = int(np.floor(z1 / (layer_m * 1e3) + 1e-9))
    if n_layers < 1:
        raise ValueError(f"scenario part: {path.name} is thinner than one layer ({layer_m * 1e6:g} µm)")
    plans = []
    for i in range(n_layers):
        hatcher.hatchAngle = 90.0 + float(np.mod(i * hatch_rotation_deg, 180.0))   # PySLM's 90°: along +-x
        layer = hatcher.hatch(part.getVectorSlice((i + 0.5) * layer_m * 1e3))
        tracks = []
        for geometry in layer.geometry if layer is not None else ():
            coords = (np.asarray(geometry.coords)[:, :2] - centre) * 1e-3
            if isinstance(geometry, ContourGeometry):
                tracks += _contour_tracks(coords)
            elif isinstance(geometry, HatchGeometry):
                tracks += [((float(a[0]), float(a[1])), (float(b[0]), float(b[1])))
                           for a, b in coords.reshape(-1, 2, 2) if np.hypot(*(b - a)) >= MIN_TRACK_M]
        if not tracks:
            raise ValueError(f"scenario part: layer {i} of {path.name} has no scan path")
        plans.append(ScanPlan(tuple(tracks)))
    return tuple(plans)
