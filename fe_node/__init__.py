"""fe_node: the FE thermal plant of meltloop (paper Sec. II.D) and its zenoh node.

Core API (no transport), here on a coarse mesh that builds at once:

>>> from fe_node import ThermalModel, scenario
>>> sc = scenario("single-track", h_fine_m=40e-6)
>>> model = ThermalModel(sc.settings, sc.plan)
>>> obs = model.step(*sc.profile.command(model.step_index))  # one step of the scenario's profile
>>> obs.step, obs.area_m2 > 0                                   # the melt pool's area [m²]
(1, True)

See docs/fe.md.
"""
from fe_node.material import Material
from fe_node.observe import Observation
from fe_node.scan import Profile, ScanPlan, Signal
from fe_node.scenarios import NAMES, Scenario, scenario
from fe_node.settings import Settings

__all__ = ["Material", "NAMES", "Observation", "Profile", "ScanPlan", "Scenario", "Settings",
           "Signal", "ThermalModel", "scenario"]


def __getattr__(name: str):
    """:class:`~fe_node.solver.ThermalModel` on first use: the solver brings scipy's sparse algebra, which
    a process that only checks a configuration (``launch.py``) does not load."""
    if name == "ThermalModel":
        from fe_node.solver import ThermalModel

        return ThermalModel
    raise AttributeError(f"module 'fe_node' has no attribute {name!r}")
