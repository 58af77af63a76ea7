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
test; on the multi-level mesh, :data:`LAYER_MESH`), all at 250 W, 800 mm/s.

Identification scenarios (GP training data beyond Table 2): ``ident-layer`` (the ``layer``
geometry) and ``ident-double-track`` (the ``double-track`` geometry) play a seeded random
power staircase at a constant 800 mm/s. Each level holds for a uniform random 3-30 steps of
``dt_s`` and is uniform in ``[ident_mean_w - ident_amplitude_w, ident_mean_w + ident_amplitude_w]``
(defaults 250 +- 60 W); ``ident_seed`` (default 0) seeds ``numpy.random.default_rng``, so the
same seed gives the same profile. The levels are not clipped to the 150-300 W window above.

``part``: a real part built layer by layer, 100 W at 800 mm/s: the STL ``part_stl`` (default
the shipped 1.5 mm x 0.5 mm cylinder, :data:`fe_node.part.EXAMPLE_STL`) sliced every
``powder_layer_m`` (the preset's: 25 µm on ``physical``; 50 µm on ``bare-plate``) and hatched every
``hatch_m`` (default 0.1 mm) by PySLM (:mod:`fe_node.part`, needs ``pythonslm``); ``n_layers``
defaults to all the part's layers; on the multi-level mesh (:data:`PART_MESH`), with
:data:`PART_DWELL_S` between layers.
``hatch_rotation_deg`` (default 67) turns the hatch from one layer to the next; ``contours``
(default true) scans each slice's outline before its hatch; ``island_width_m`` > 0 hatches in
square islands of that side (default 0: no islands).
``ident-part``: the same part under a seeded random power staircase (the ``ident_*`` overrides
above; the powder and the small part need far less power than the bare plate, so its
identification runs choose lower means, :data:`gp_trainer.campaign.IDENT_PART_RUNS`).
"""
from __future__ import annotations

import json
import math
import numbers
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from fe_node.grid_size import check_grid_size
from fe_node.part import CONTOURS, EXAMPLE_STL, HATCH_ROTATION_DEG, ISLAND_WIDTH_M, part_plans
from fe_node.presets import DEFAULT as DEFAULT_PRESET
from fe_node.presets import preset
from fe_node.scan import Profile, ScanPlan, Signal
from fe_node.settings import Settings, check_type
from messages.types import CONFIG_JSON_MAX_CHARS

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
    # power None: a seeded random staircase (ident_power), built once the plan and dt are known
    "ident-layer": (4, 10e-3, 1e-4, None, S_CONST),
    "ident-double-track": (2, 5e-3, 1e-4, None, S_CONST),
}
PART_NAMES = ("part", "ident-part")
NAMES = (*_TABLE, *PART_NAMES)
DEFAULT = "layer"

# identification overrides and their defaults (ident-* scenarios only)
IDENT_DEFAULTS = {"ident_seed": 0, "ident_mean_w": 250.0, "ident_amplitude_w": 60.0}
PART_MESH = "multilevel"
"""The mesh of the ``part`` and ``ident-part`` scenarios unless ``[plant] mesh`` names another: the
multi-level mesh that moves with the laser (:mod:`fe_node.multilevel`), whose cost per step does not
grow with the part's size or its layers (docs/fe-scale.md); ``mesh = "uniform"`` is the reference.
"""

PART_DWELL_S = 10.0
"""The ``part`` and ``ident-part`` scenarios' time between layers [s] (``dwell_s``) unless ``[plant] dwell_s``
sets it: the recoater's pass and the platform's move with the laser off, during which the part cools. The
inter-layer time changes a part's heat accumulation and melt pools (Mohr, Altenburg, Hilgenberg, Additive
Manufacturing 32 (2020) 101080); 10 s is this project's choice of a short single-laser recoating cycle. Set
it to the machine's layer time: at 0 s a part's layers follow each other within milliseconds and it heats
layer after layer as no machine builds it.
"""

LAYER_MESH = {"mesh": "multilevel", "fine_box_m": 3.2e-3}
"""The ``layer`` scenario's mesh unless ``[plant] mesh`` names one: the multi-level mesh with a 3.2 mm
fine box, which matches the uniform mesh there (``benchmarks/bench_fe_scale.py``: area trace within
1 % rms and 3 % at most; the preview MPC's closed loop within 0.2 points, docs/fe-scale.md) at 2.4-2.6
times less cost per step. The box side was chosen on that comparison (2.4 mm, the part default, put the
overshoot 0.38 points below the uniform mesh's); ``mesh = "uniform"`` is the reference.
"""

TRAINING_MESH = "uniform"
"""The mesh of the plate models' training runs: the identification staircases' (the plate scenarios'
default) and, in place of :data:`LAYER_MESH`, that of a learning campaign's closed-loop runs on the ``layer``
(``gp_trainer.campaign``), so that all of a model's training runs are on one mesh. The off-design suite's
layer cases and the sensitivity benchmarks run the plant on it too.
"""

PART_POWER_W = 100.0
"""Open-loop power of the ``part`` scenario [W]; ``launch.py`` starts every controller from it on a part.
On a 50 µm powder layer over the small part, 250 W (the bare plate's) gives 3-4× the bare plate's
area and PID settles near 75 W for 0.063 mm² (docs/controller.md, "Parts")."""
IDENT_HOLD_STEPS = (3, 30)  # each power level holds this many steps (inclusive, uniform)


def _ident_options(name: str, given: dict) -> dict:
    """Validated ``ident_*`` overrides of scenario ``name`` merged into the defaults."""
    if given and name != "ident-part" and _TABLE[name][3] is not None:
        key = sorted(given)[0]
        raise ValueError(f"scenario override {key!r} is only valid for ident-* scenarios, not {name!r}")
    opts = {**IDENT_DEFAULTS, **given}
    seed = opts["ident_seed"]
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"scenario override 'ident_seed' must be an integer >= 0, got {seed!r}")
    for key in ("ident_mean_w", "ident_amplitude_w"):
        value = opts[key]
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
            raise ValueError(f"scenario override {key!r} must be a finite number, got {value!r}")
    mean, amplitude = float(opts["ident_mean_w"]), float(opts["ident_amplitude_w"])
    if amplitude < 0:
        raise ValueError(f"scenario override 'ident_amplitude_w' must be >= 0, got {amplitude:g}")
    if mean - amplitude < 0:
        raise ValueError(f"scenario override 'ident_mean_w' minus ident_amplitude_w must be >= 0 W, "
                         f"got {mean:g} - {amplitude:g}")
    return {"ident_seed": int(seed), "ident_mean_w": mean, "ident_amplitude_w": amplitude}


def ident_power(seed: int, mean_w: float, amplitude_w: float, n_steps: int, dt_s: float) -> Signal:
    """Seeded random power staircase covering at least ``n_steps`` steps of ``dt_s``.

    Levels and holds are drawn in turn (hold, level, hold, level, ...) from
    ``numpy.random.default_rng(seed)``, so a longer run extends a shorter one's profile.
    Hold lengths are integers in :data:`IDENT_HOLD_STEPS`; a level starts at ``k * dt_s``, the
    time the plant commands step ``k`` (:meth:`~fe_node.scan.Profile.command`).
    """
    rng = np.random.default_rng(seed)
    lo, hi = IDENT_HOLD_STEPS
    starts, levels, k = [], [], 0
    while k < max(int(n_steps), 1):
        hold = int(rng.integers(lo, hi + 1))
        starts.append(k)
        levels.append(float(rng.uniform(mean_w - amplitude_w, mean_w + amplitude_w)))
        k += hold
    return Signal(times_s=tuple(i * dt_s for i in starts), values=tuple(levels))


@dataclass(frozen=True)
class Scenario:
    """A runnable case: ``plant_model(sc.settings, sc.plan, sc.layer_plans)`` (:mod:`fe_node.multilevel`)
    driven by ``sc.profile``."""

    name: str
    settings: Settings
    plan: ScanPlan
    profile: Profile
    layer_plans: tuple[ScanPlan, ...] | None = None
    """One plan per layer (``part``); ``plan`` is the first.  ``None``: ``plan`` in every layer."""
    part_stl: Path | None = None
    """The part's STL (``part``; shown in Foxglove by :mod:`fe_node.scene`)."""


_PLAN_KINDS = {"n_tracks": "int", "track_length_m": "float", "hatch_m": "float", "bidirectional": "bool"}
"""The plan overrides of :func:`scenario` and their kinds (:func:`fe_node.settings.check_type`)."""


def _constant(key: str, value: object) -> float:
    """A constant power (``power_w`` >= 0 W) or speed (``speed_m_s`` > 0 m/s) override as a float
    (ValueError naming the key otherwise)."""
    check_type(f"scenario override {key!r}", value, "float")
    if not (value > 0 if key == "speed_m_s" else value >= 0):
        raise ValueError(f"scenario override {key!r} must be {'> 0' if key == 'speed_m_s' else '>= 0'}, got {value!r}")
    return float(value)


def scenario(name: str = DEFAULT, **overrides) -> Scenario:
    """Build a named scenario.

    Parameters
    ----------
    name : str
        One of :data:`NAMES`.
    **overrides
        ``preset`` (:mod:`fe_node.presets`; default :data:`fe_node.presets.DEFAULT`) and any
        :class:`~fe_node.settings.Settings` field, which overrides the preset's; ``n_tracks``, ``track_length_m``,
        ``hatch_m``, ``bidirectional`` for the plan; ``power_w`` and/or ``speed_m_s``
        replace the open-loop signal by a constant. ``ident_seed`` (int >= 0),
        ``ident_mean_w`` and ``ident_amplitude_w`` [W] shape the random power staircase of
        the ``ident-*`` scenarios (error for any other scenario, or together with ``power_w``).

    Raises
    ------
    ValueError
        Unknown name or override, or invalid values.
    """
    overrides = {**preset(overrides.pop("preset", DEFAULT_PRESET)), **overrides}
    if name in PART_NAMES:
        return _part(name, **overrides)
    if name not in _TABLE:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(NAMES)}")
    n, length, hatch, power, speed = _TABLE[name]
    plan_kw = dict(n_tracks=n, length_m=length, hatch_m=hatch, bidirectional=True)
    keys = {"n_tracks": "n_tracks", "track_length_m": "length_m", "hatch_m": "hatch_m",
            "bidirectional": "bidirectional"}
    settings_kw, ident_kw = {}, {}
    for key, value in overrides.items():
        if key in IDENT_DEFAULTS:
            ident_kw[key] = value
        elif key in keys:
            check_type(f"scenario override {key!r}", value, _PLAN_KINDS[key])
            plan_kw[keys[key]] = value
        elif key == "power_w":
            power = Signal(_constant(key, value))
        elif key == "speed_m_s":
            speed = Signal(_constant(key, value))
        elif key in Settings.field_names():
            settings_kw[key] = value
        else:
            raise ValueError(f"unknown scenario override {key!r}")
    ident = _ident_options(name, ident_kw)
    if name == "layer":
        settings_kw = _default_mesh(name, settings_kw, LAYER_MESH)
    settings = replace(Settings(), **settings_kw)
    plan = ScanPlan.layer(**plan_kw)
    if "power_w" in overrides and ident_kw:
        raise ValueError(f"scenario override {sorted(ident_kw)[0]!r} conflicts with 'power_w' (a constant power)")
    if power is None:
        v_min = speed.range()[0]
        if not v_min > 0:
            raise ValueError(f"profile: speed must be > 0, got min {v_min} m/s")
        n_steps = math.ceil(plan.total_length / (v_min * settings.dt_s) - 1e-9) * settings.n_layers
        power = ident_power(ident["ident_seed"], ident["ident_mean_w"], ident["ident_amplitude_w"],
                            n_steps, settings.dt_s)
    check_grid_size(settings, plan)
    return Scenario(name=name, settings=settings, plan=plan, profile=Profile(power, speed, settings.dt_s))


DESCRIPTION_ROOM_CHARS = 4096
"""Characters of a start event's configuration left for the plant node's own entries beside the
scenario's description (:func:`check_description`)."""


def describe(scenario: Scenario) -> dict:
    """JSON-able description of a scenario (recorded as the plant's configuration)."""
    return json.loads(json.dumps(
        {"scenario": scenario.name, "settings": asdict(scenario.settings),
         "plan": asdict(scenario.plan), "profile": asdict(scenario.profile)},
        default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def check_description(scenario: Scenario) -> None:
    """``ValueError`` (one line) if the scenario's description (:func:`describe`), which the plant
    records in its start event, is longer than that event carries
    (:data:`messages.types.CONFIG_JSON_MAX_CHARS`): a plan of thousands of tracks."""
    n = len(json.dumps(describe(scenario), sort_keys=True))
    limit = CONFIG_JSON_MAX_CHARS - DESCRIPTION_ROOM_CHARS
    if n > limit:
        raise ValueError(f"the scenario's description ({len(scenario.plan.tracks)} tracks) would take {n:,} "
                         f"characters of the plant's start event, more than {limit:,}: shorten the scan plan "
                         "(n_tracks, track_length_m)")


def _default_mesh(name: str, settings_kw: dict, default: dict) -> dict:
    """``settings_kw`` with the scenario's ``default`` multi-level mesh settings under it, unless it
    names a mesh; ``ValueError`` (one line) if it sets an option of the uniform mesh only
    (``window_m``, ``operator``) without naming the mesh."""
    if "mesh" in settings_kw:
        return settings_kw
    for key, value in (("window_m", 0.0), ("operator", "tensor")):
        given = settings_kw.get(key, value)
        if given != value and isinstance(given, type(value)):     # (a value of another kind: Settings names it)
            what = "a part's" if name in PART_NAMES else f"the {name} scenario's"
            raise ValueError(f"scenario {name}: {key} = {settings_kw[key]!r} needs mesh = 'uniform' "
                             f"({what} default mesh is {default['mesh']!r})")
    return {**default, **settings_kw}


def _part(name: str, part_stl: str | None = None, hatch_m: float = 1e-4, power_w: float | None = None,
          speed_m_s: float = 0.8, hatch_rotation_deg: float = HATCH_ROTATION_DEG, contours: bool = CONTOURS,
          island_width_m: float = ISLAND_WIDTH_M, **settings_kw) -> Scenario:
    """The ``part`` and ``ident-part`` scenarios (module docstring); ``settings_kw`` are
    :class:`Settings` fields and, for ``ident-part``, the ``ident_*`` overrides."""
    ident_kw = {k: settings_kw.pop(k) for k in list(settings_kw) if k in IDENT_DEFAULTS}
    unknown = set(settings_kw) - Settings.field_names()
    if unknown:
        raise ValueError(f"unknown scenario override {sorted(unknown)[0]!r} for {name!r}")
    if ident_kw and name == "part":
        raise ValueError(f"scenario override {sorted(ident_kw)[0]!r} is only valid for ident-* scenarios, not 'part'")
    if ident_kw and power_w is not None:
        raise ValueError(f"scenario override {sorted(ident_kw)[0]!r} conflicts with 'power_w' (a constant power)")
    check_type("scenario override 'hatch_rotation_deg'", hatch_rotation_deg, "float")
    check_type("scenario override 'contours'", contours, "bool")
    check_type("scenario override 'island_width_m'", island_width_m, "float")
    layer_m = settings_kw.setdefault("powder_layer_m", 50e-6)
    settings_kw.setdefault("dwell_s", PART_DWELL_S)
    settings_kw.update(_default_mesh(name, settings_kw, {"mesh": PART_MESH}))
    stl = Path(EXAMPLE_STL if part_stl is None else part_stl)
    plans = part_plans(stl, layer_m, hatch_m, float(hatch_rotation_deg), contours, float(island_width_m))
    n = settings_kw.setdefault("n_layers", len(plans))
    if not 1 <= n <= len(plans):
        raise ValueError(f"scenario {name}: n_layers must be in [1, {len(plans)}] for this part, got {n}")
    settings = replace(Settings(), **settings_kw)
    if name == "ident-part" and power_w is None:
        ident = _ident_options(name, ident_kw)
        n_steps = sum(math.ceil(plan.total_length / (speed_m_s * settings.dt_s) - 1e-9) for plan in plans[:n])
        power = ident_power(ident["ident_seed"], ident["ident_mean_w"], ident["ident_amplitude_w"],
                            n_steps, settings.dt_s)
    else:
        power = Signal(PART_POWER_W if power_w is None else _constant("power_w", power_w))
    profile = Profile(power, Signal(_constant("speed_m_s", speed_m_s)), settings.dt_s)
    check_grid_size(settings, plans[0], plans[:n])
    return Scenario(name=name, settings=settings, plan=plans[0], profile=profile, layer_plans=plans[:n],
                    part_stl=stl)
