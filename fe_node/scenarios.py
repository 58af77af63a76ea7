"""Named scenarios: scan plan + open-loop profile + settings.

Paper Table 2 (GP training data, 5 mm tracks, commands inside the process window
150-300 W, 600-1000 mm/s; the paper gives no amplitudes or periods, these are ours):

=====  ======  ===========================  ===========================  =====
case   tracks  power                        speed                        hatch
=====  ======  ===========================  ===========================  =====
1      1       250 W                        800 mm/s                     -
2      1       225 +- 75 W, period 2 ms     800 mm/s                     -
3      1       250 W                        800 +- 200 mm/s, period 2.5 ms  -
4      1       225 +- 75 W, period 2 ms     800 +- 200 mm/s, period 3 ms  -
5      2       250 W                        800 mm/s                     0.10
6      2       250 W                        800 mm/s                     0.15
7      2       250 W                        800 mm/s                     0.05
8      2       225 +- 75 W, period 2 ms     profile S                    0.10
9      2       profile P                    profile S                    0.10
=====  ======  ===========================  ===========================  =====

Profile S (speed, mm/s, 2 ms each): 800, 1000, 700, 900, 600, 850, repeating the last.
Profile P (power, W, 1.5 ms each): 250, 180, 300, 200, 275, 150, 225, repeating the last.
Double tracks are bidirectional.  Other names: ``single-track`` (5 mm), ``double-track``
(2 x 5 mm, hatch 0.1 mm), ``layer`` (default; 4 x 10 mm, hatch 0.1 mm, the paper's MPC
test), all at 250 W, 800 mm/s.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

from fe_node.scan import Profile, ScanPlan, Signal
from fe_node.settings import Settings

P_SINE = Signal(mean=225.0, amplitude=75.0, period_s=2e-3)
P_PROFILE = Signal(times_s=tuple(i * 1.5e-3 for i in range(7)),
                   values=(250.0, 180.0, 300.0, 200.0, 275.0, 150.0, 225.0))
S_PROFILE = Signal(times_s=tuple(i * 2e-3 for i in range(6)),
                   values=(0.8, 1.0, 0.7, 0.9, 0.6, 0.85))
P_CONST, S_CONST = Signal(250.0), Signal(0.8)

# name: (n_tracks, track_length_m, hatch_m, power signal, speed signal)
_TABLE = {
    "single-track": (1, 5e-3, 1e-4, P_CONST, S_CONST),
    "double-track": (2, 5e-3, 1e-4, P_CONST, S_CONST),
    "layer": (4, 10e-3, 1e-4, P_CONST, S_CONST),
    "table2-case1": (1, 5e-3, 1e-4, P_CONST, S_CONST),
    "table2-case2": (1, 5e-3, 1e-4, P_SINE, S_CONST),
    "table2-case3": (1, 5e-3, 1e-4, P_CONST, Signal(0.8, 0.2, 2.5e-3)),
    "table2-case4": (1, 5e-3, 1e-4, P_SINE, Signal(0.8, 0.2, 3e-3)),
    "table2-case5": (2, 5e-3, 1e-4, P_CONST, S_CONST),
    "table2-case6": (2, 5e-3, 1.5e-4, P_CONST, S_CONST),
    "table2-case7": (2, 5e-3, 0.5e-4, P_CONST, S_CONST),
    "table2-case8": (2, 5e-3, 1e-4, P_SINE, S_PROFILE),
    "table2-case9": (2, 5e-3, 1e-4, P_PROFILE, S_PROFILE),
}
NAMES = tuple(_TABLE)
DEFAULT = "layer"


@dataclass(frozen=True)
class Scenario:
    """A runnable case: ``ThermalModel(sc.settings, sc.plan)`` driven by ``sc.profile``."""

    name: str
    settings: Settings
    plan: ScanPlan
    profile: Profile


def scenario(name: str = DEFAULT, **overrides) -> Scenario:
    """Build a named scenario.

    Parameters
    ----------
    name : str
        One of :data:`NAMES`.
    **overrides
        Any :class:`~fe_node.settings.Settings` field; ``n_tracks``, ``track_length_m``,
        ``hatch_m``, ``bidirectional`` for the plan; ``power_w`` and/or ``speed_m_s``
        replace the open-loop signal by a constant.

    Raises
    ------
    ValueError
        Unknown name or override, or invalid values.
    """
    if name not in _TABLE:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(NAMES)}")
    n, length, hatch, power, speed = _TABLE[name]
    plan_kw = dict(n_tracks=n, length_m=length, hatch_m=hatch, bidirectional=True)
    keys = {"n_tracks": "n_tracks", "track_length_m": "length_m", "hatch_m": "hatch_m",
            "bidirectional": "bidirectional"}
    settings_kw = {}
    for key, value in overrides.items():
        if key in keys:
            plan_kw[keys[key]] = value
        elif key == "power_w":
            power = Signal(float(value))
        elif key == "speed_m_s":
            speed = Signal(float(value))
        elif key in Settings.field_names():
            settings_kw[key] = value
        else:
            raise ValueError(f"unknown scenario override {key!r}")
    settings = replace(Settings(), **settings_kw)
    return Scenario(name=name, settings=settings, plan=ScanPlan.layer(**plan_kw),
                    profile=Profile(power, speed, settings.dt_s))
