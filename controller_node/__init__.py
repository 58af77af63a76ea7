"""Melt-pool controllers (GP-MPC of the paper's eq. 7-8 and baselines), transport-free.

Functional core: ``controller.update(measurement) -> (command, diagnostics)``; build
controllers with :func:`make_controller`.  The zenoh wrapper lives in ``node.py``.
"""

from .base import Controller, Proposal
from .model import DynamicsModel, Linearisation, linearise
from .registry import CONTROLLERS, make_controller
from .settings import ControllerSettings, FeedForwardSettings, MPCSettings, PIDSettings
from .types import Command, Diagnostics, Measurement

__all__ = [
    "CONTROLLERS",
    "Command",
    "Controller",
    "ControllerSettings",
    "Diagnostics",
    "DynamicsModel",
    "FeedForwardSettings",
    "Linearisation",
    "MPCSettings",
    "Measurement",
    "PIDSettings",
    "Proposal",
    "linearise",
    "make_controller",
]
