"""Named plant configurations, chosen with the ``preset`` key of ``[plant]`` (or ``preset=`` of
:func:`fe_node.scenarios.scenario`; :data:`DEFAULT` without one); the table's other keys override
the preset's values. A preset is a set of overrides of :class:`~fe_node.settings.Settings`, whose
own defaults are the bare physics (the ``bare-plate`` preset).

* ``physical`` (the default plant): a 25 µm powder layer that consolidates to dense metal, evaporative cooling,
  keyhole onset (:mod:`fe_node.keyhole`), absorptivity by surface (powder, dense, keyhole) and an
  anisotropic effective liquid conductivity for Marangoni flow, with the absorptivities and
  conductivity factors fitted to the AM-Bench tracks by ``python -m fe_node calibrate``
  (:data:`CALIBRATION_PATH`).
* ``bare-plate``: a dense IN625 plate, conduction only, the paper's Table 1 (absorptivity 0.4):
  :class:`~fe_node.settings.Settings` as it is, the plant the shipped GP models were trained on.
"""
from __future__ import annotations

import json
from pathlib import Path

CALIBRATION_PATH = Path(__file__).with_name("calibration.json")
"""The shipped calibration record (written by ``python -m fe_node calibrate``, :mod:`fe_node.calibrate`)."""

PHYSICAL = {"powder_layer_m": 25e-6, "evaporation": True, "keyhole": True, "fine_depth_m": 250e-6}
"""The physics of the ``physical`` preset besides the calibrated values: a layer thickness (the
platform's drop per layer) of 25 µm, an assumption within the 20-50 µm of LPBF practice, chosen for
the explicit step's cost and the mesh check: 40 µm meshes as two 20 µm elements, whose stability
limit with the fitted vertical liquid factor needs 5 sub-steps instead of 3 (1.67x the step cost),
and 50 µm (two 25 µm elements) is 3 % off at half the element size (``validate``'s
``mesh_convergence_pct``); and the fine band 250 µm deep, below the keyhole of the paper's process
(as in the calibration runs, :data:`fe_node.am_bench.FINE_DEPTH_M`)."""
NAMES = ("bare-plate", "physical")
DEFAULT = "physical"
"""The preset of every plant built without one (``launch.py``, ``python -m fe_node``, the campaigns)."""


def calibrated() -> dict:
    """The fitted settings of the shipped calibration record."""
    return dict(json.loads(CALIBRATION_PATH.read_text())["fitted"])


def preset(name: object) -> dict:
    """The :class:`~fe_node.settings.Settings` overrides of preset ``name`` (ValueError naming the choices)."""
    if name == "bare-plate":
        return {}
    if name == "physical":
        return {**PHYSICAL, **calibrated()}
    raise ValueError(f"preset must be one of {', '.join(NAMES)}, got {name!r}")
