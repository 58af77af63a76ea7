"""Melt-pool controllers (GP-MPC of the paper's eq. 7-8 and baselines), transport-free.

Functional core: ``controller.update(measurement) -> (command, diagnostics)``; build
controllers with :func:`make_controller`.  The zenoh wrapper lives in ``node.py``.

>>> from controller_node import ControllerSettings, Measurement, make_controller
>>> pid = make_controller("pid", ControllerSettings())
>>> state = Measurement(step=0, time_s=0.0, area_m2=0.05e-6, t_ahead_k=500.0, power_w=200.0, speed_m_s=0.8, track=0)
>>> command, diagnostics = pid.update(state)                 # SI: m², K, W, m/s
>>> command.step, command.power_w, diagnostics.status
(1, 250.0, 'ok')
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
