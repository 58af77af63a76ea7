"""Scan plans of a real part: an STL sliced and hatched with PySLM (``pythonslm``), one plan per layer.

Each layer ``i`` is the part's cross-section at height ``(i + 1/2) * layer_m`` above its base,
hatched by :class:`pyslm.hatching.Hatcher` with lines along x (hatch angle 90°, the plant's
tracks are parallel to x), alternating direction, no contours and no offsets.  Coordinates
are centred on the part's plan-view bounding box and converted from PySLM's mm to m.

The example part :data:`EXAMPLE_STL` is a cylinder 1.5 mm across and 0.5 mm high (10 layers
of 50 µm).  PySLM is an optional dependency: ``pip install pythonslm``.
"""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np

from fe_node.scan import ScanPlan

EXAMPLE_STL = Path(__file__).parent / "parts" / "cylinder_d1.5_h0.5_mm.stl"
"""The shipped example part (``--scenario part``)."""


PYSLM_MISSING = "scenario part: needs PySLM (pip install pythonslm, or the project's [part] extra)"


def require_pyslm() -> None:
    """Raise ``ValueError`` (:data:`PYSLM_MISSING`, one line) when PySLM is not installed."""
    if importlib.util.find_spec("pyslm") is None:
        raise ValueError(PYSLM_MISSING)


def part_plans(stl_path: str | Path, layer_m: float, hatch_m: float) -> tuple[ScanPlan, ...]:
    """Per-layer scan plans of the part in ``stl_path``.

    Parameters
    ----------
    stl_path : str or Path
        STL file, in mm (PySLM's unit).
    layer_m, hatch_m : float
        Layer thickness and hatch distance [m].

    Returns
    -------
    tuple of ScanPlan
        One plan per layer, bottom first [m].

    Raises
    ------
    ValueError
        Missing file, PySLM not installed, or a part thinner than one layer.
    """
    try:
        import pyslm
        from pyslm import hatching
        from pyslm.geometry import HatchGeometry
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
    hatcher = hatching.Hatcher()
    hatcher.hatchAngle, hatcher.layerAngleIncrement, hatcher.hatchDistance = 90.0, 0.0, hatch_m * 1e3
    hatcher.numInnerContours = hatcher.numOuterContours = 0
    hatcher.spotCompensation = hatcher.volumeOffsetHatch = 0.0
    hatcher.hatchSortMethod = hatching.AlternateSort()
    n_layers = int(np.floor(z1 / (layer_m * 1e3) + 1e-9))
    if n_layers < 1:
        raise ValueError(f"scenario part: {path.name} is thinner than one layer ({layer_m * 1e6:g} µm)")
    plans = []
    for i in range(n_layers):
        layer = hatcher.hatch(part.getVectorSlice((i + 0.5) * layer_m * 1e3))
        coords = [g.coords for g in layer.geometry if isinstance(g, HatchGeometry)]
        segments = (np.concatenate(coords) - centre).reshape(-1, 2, 2) * 1e-3 if coords else np.empty((0, 2, 2))
        tracks = tuple(((float(a[0]), float(0.5 * (a[1] + b[1]))), (float(b[0]), float(0.5 * (a[1] + b[1]))))
                       for a, b in segments if abs(b[0] - a[0]) > 1e-6)
        if not tracks:
            raise ValueError(f"scenario part: layer {i} of {path.name} has no hatch")
        plans.append(ScanPlan(tracks))
    return tuple(plans)
