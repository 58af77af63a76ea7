"""Controllers by name: :func:`make_controller`."""

from __future__ import annotations

import importlib
from pathlib import Path

from gp_model.shipped import DEFAULT_MODEL_PATH, ONE_STEP_MODEL_PATH

from .base import Controller
from .model import DynamicsModel
from .settings import ControllerSettings

__all__ = ["CONTROLLERS", "MODELS", "PREVIEW_CONTROLLERS", "make_controller", "model_class"]

CLASSES: dict[str, str] = {
    "open-loop": "controller_node.baselines:OpenLoopController",
    "pid": "controller_node.pid:PIDController",
    "feedforward": "controller_node.feedforward:FeedForwardController",
    "mpc": "controller_node.mpc:MPCController",
    "preview-mpc": "controller_node.preview:PreviewMPC",
    "scan-feedforward": "controller_node.scan_feedforward:ScanFeedForward",
}
"""Every controller by name (``module:class``), in the order of launch.py's comparison. A class is
imported when it is built, so a node loads only its own controller's numerics (a PID node loads no
scipy, numba or cvxpy)."""
CONTROLLERS: tuple[str, ...] = tuple(CLASSES)
PREVIEW_CONTROLLERS = ("preview-mpc", "scan-feedforward")
"""The controllers on the delay-aware model and the scan-plan preview (checked against its process)."""
MODELS: dict[str, tuple[str, Path]] = {
    "feedforward": ("gp_model.model:GPModel", ONE_STEP_MODEL_PATH),
    "mpc": ("gp_model.model:GPModel", ONE_STEP_MODEL_PATH),
    "preview-mpc": ("gp_model.narx:NarxGPModel", DEFAULT_MODEL_PATH),
    "scan-feedforward": ("gp_model.narx:NarxGPModel", DEFAULT_MODEL_PATH),
}
"""The model class (``module:class``) and shipped model file of each controller that runs a model (the
others run none)."""


def _resolve(spec: str) -> type:
    """The class named by ``spec`` (``module:class``), importing its module."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def model_class(name: str) -> type:
    """The model class of controller ``name`` (a key of :data:`MODELS`)."""
    return _resolve(MODELS[name][0])


def make_controller(
    name: str, settings: ControllerSettings | None = None, model: DynamicsModel | None = None
) -> Controller:
    """Build a controller by name.

    Parameters
    ----------
    name : {"open-loop", "pid", "feedforward", "mpc", "preview-mpc", "scan-feedforward"}
        Controller kind.
    settings : ControllerSettings, optional
        Defaults to ``ControllerSettings()``.
    model : DynamicsModel or gp_model.narx.NarxGPModel, optional
        Required by ``"mpc"`` (one-step model), by ``"preview-mpc"`` and ``"scan-feedforward"`` (delay-aware
        model), and by ``"feedforward"`` unless ``settings.feedforward.gain_w_per_k`` is set; ignored otherwise.

    Returns
    -------
    Controller

    Raises
    ------
    ValueError
        Unknown name or missing model.
    """
    settings = ControllerSettings() if settings is None else settings
    if name not in CLASSES:
        raise ValueError(f"unknown controller {name!r}; choose one of {', '.join(CONTROLLERS)}")
    controller_class = _resolve(CLASSES[name])
    if name not in MODELS:                      # a controller that runs no model
        return controller_class(settings)
    if name == "mpc" and model is None:
        raise ValueError("the 'mpc' controller needs a model")
    if name in PREVIEW_CONTROLLERS and (model is None or not hasattr(model, "turn_profile_k")):
        raise ValueError(f"the {name!r} controller needs a delay-aware model (gp_model.narx.NarxGPModel)")
    return controller_class(settings, model)
