"""Controllers by name: :func:`make_controller`."""

from __future__ import annotations

from pathlib import Path

from gp_model import model as one_step
from gp_model import narx

from .base import Controller
from .baselines import OpenLoopController
from .feedforward import FeedForwardController
from .model import DynamicsModel
from .mpc import MPCController
from .pid import PIDController
from .preview import PreviewMPC
from .settings import ControllerSettings

__all__ = ["CONTROLLERS", "MODELS", "make_controller"]

CONTROLLERS: tuple[str, ...] = ("open-loop", "pid", "feedforward", "mpc", "preview-mpc")
"""Every controller by name, in the order of launch.py's comparison."""
MODELS: dict[str, tuple[type, Path]] = {
    "feedforward": (one_step.GPModel, one_step.DEFAULT_MODEL_PATH),
    "mpc": (one_step.GPModel, one_step.DEFAULT_MODEL_PATH),
    "preview-mpc": (narx.NarxGPModel, narx.DEFAULT_MODEL_PATH),
}
"""The model class and shipped model file of each controller that runs a model (the others run none)."""


def make_controller(
    name: str, settings: ControllerSettings | None = None, model: DynamicsModel | None = None
) -> Controller:
    """Build a controller by name.

    Parameters
    ----------
    name : {"open-loop", "pid", "feedforward", "mpc", "preview-mpc"}
        Controller kind.
    settings : ControllerSettings, optional
        Defaults to ``ControllerSettings()``.
    model : DynamicsModel or gp_model.narx.NarxGPModel, optional
        Required by ``"mpc"`` (one-step model), by ``"preview-mpc"`` (delay-aware model), and by
        ``"feedforward"`` unless ``settings.feedforward.gain_w_per_k`` is set; ignored otherwise.

    Returns
    -------
    Controller

    Raises
    ------
    ValueError
        Unknown name or missing model.
    """
    settings = ControllerSettings() if settings is None else settings
    if name == "open-loop":
        return OpenLoopController(settings)
    if name == "pid":
        return PIDController(settings)
    if name == "feedforward":
        return FeedForwardController(settings, model)
    if name == "mpc":
        if model is None:
            raise ValueError("the 'mpc' controller needs a model")
        return MPCController(settings, model)
    if name == "preview-mpc":
        if model is None or not hasattr(model, "turn_profile_k"):
            raise ValueError("the 'preview-mpc' controller needs a delay-aware model (gp_model.narx.NarxGPModel)")
        return PreviewMPC(settings, model)
    raise ValueError(f"unknown controller {name!r}; choose one of {', '.join(CONTROLLERS)}")
