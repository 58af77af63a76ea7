"""Off-design suite: each controller on cases of geometry, speed, preheat, plant mismatch and set point.

Every case is one ``python launch.py --config CASE.toml --controller C --json`` run on the default
(physical) plant, with the case's ``[plant]`` overrides, a layer case on the models' training mesh
(:data:`fe_node.scenarios.TRAINING_MESH`, the uniform reference: no figure depends on how well the default
layer's multi-level mesh holds on another plan), the part case on a part's default mesh; the figures are
launch's, on its common window (from 1 ms after laser-on). A case is *in-sample* when one of
the model's training runs (``provenance.runs`` of the model) scanned the same plan (tracks, track length,
hatch) on the same process (no speed, preheat or absorptivity override but those of the model's own
``[plant]`` table): its figure is then not a test of generalisation, and the record says so.

The cases (:data:`CASES`):

* ``default-layer``: 4 x 10 mm at 100 µm hatch, 0.063 mm² (the shipped model's training includes
  runs on this plan: in-sample);
* geometry: ``tight-6x4mm-h80``, ``short-8x2mm``, ``wide-2x10mm-h120``;
* speed: ``speed-0.6``, ``speed-1.0``, each on the model learned at its speed
  (``gp_model/models/in625_narx_gp_0.6mps.json``, ``..._1.0mps.json``: ``python -m gp_trainer learn
  --config docs/physical-0.6mps.toml`` and ``...-1.0mps.toml``), the PID on that model's process record
  (a model learned at another speed refuses them: exit 2, and the record carries the refusal);
* preheat: ``preheat-500K``;
* plant mismatch: ``absorptivity+10pct``, ``absorptivity-10pct`` (dense and powder absorptivity
  both scaled; the model was learned on the calibrated plant);
* set point: ``setpoint-0.05``, ``setpoint-0.09``;
* ``part-2-layers``: the example part's first two layers (``--scenario part --layers 2``).
* ``l-bracket-3-layers``: the first three layers of the L-shaped bracket, a part no model was trained on
  (``--scenario part --part fe_node/parts/l_bracket_3mm.stl --layers 3``).

Prints one table, writes one JSON record per case and controller to ``--out-dir`` and, as the last
line, ``{"cases": [{"case", "controller", "status", "overshoot_pct", "undershoot_pct", "rmse_pct",
"rmse_turnaround_pct", "rmse_along_pct", "in_sample", "layers", "track_length_m", "hatch_m",
"speed_m_s", "setpoint_mm2", "wall_s", "refused"}, ...]}``. The runs on the delay-aware model (preview MPC,
scan-feedforward) also carry how well that model predicts their own recording one step ahead, with the measured
T ahead and powers (:func:`gp_trainer.narx_fit.evaluate_model`, as ``python -m gp_trainer evaluate --runs``):
``model_mape_turnaround_pct``, ``model_bias_turnaround_pct`` (mean signed error, model minus plant; by bins of
5 states after the turn: ``model_bias_after_turn_pct``),
``model_mape_along_pct``, ``model_bias_along_pct``. With ``--bound`` each record also carries
the case's learning bound, ``bound_rmse_pct`` and ``bound_iteration`` (:mod:`learning_bound`: iterative
learning control of the open-loop power against the FE plant, the best that power alone reached).
The bound needs ``provenance.controller.pid.fopdt`` in the model (``python -m gp_trainer tune-pid``).

Usage: ``python benchmarks/bench_suite.py [--cases NAME ...] [--controllers preview-mpc pid scan-feedforward]
[--max-steps N] [--out-dir DIR] [--bound [--bound-iterations 8] [--bound-gain 0.5]] [--json]``
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from learning_bound import BoundSettings, learning_bound  # noqa: E402

from fe_node.scenarios import TRAINING_MESH, scenario  # noqa: E402
from gp_model.files import read_document  # noqa: E402
from gp_model.narx import NarxGPModel, series_from_states  # noqa: E402
from gp_model.shipped import DEFAULT_MODEL_PATH  # noqa: E402
from gp_trainer.dataset import read_states  # noqa: E402
from gp_trainer.narx_fit import evaluate_model  # noqa: E402
from gp_trainer.pid_tuning import Fopdt  # noqa: E402
from launch import RunOptions, plant_model  # noqa: E402
from messages.recording import run_config  # noqa: E402

LAYER_PLAN = (4, 10e-3, 1e-4)
"""(tracks, track length [m], hatch [m]) of the ``layer`` scenario."""
SCENARIO_PLANS = {"layer": LAYER_PLAN, "double-track": (2, 5e-3, 1e-4)}
"""The plans of the scenarios the identification runs use (``ident-<scenario>`` and controller runs)."""
EXAMPLE_PART = "example-part"
""":func:`training_plans`' entry for a run on the shipped example part (``ident-part-p100-s12``,
``ident-pid-part-a0.063``: :data:`gp_trainer.campaign.IDENT_PART_RUNS`, each over its first 4 layers)."""
CONTROLLERS = ("preview-mpc", "pid", "scan-feedforward")
"""The controllers the suite runs: the preview MPC and its two baselines, PID (tuned on the model's
training staircases, ``gp_trainer.pid_tuning``) and the scan-plan feed-forward (the same model and
plan with no feedback, :mod:`controller_node.scan_feedforward`)."""



@dataclass(frozen=True)
class Case:
    """One off-design case: the ``layer`` scenario (or the part) with ``[plant]`` overrides.

    Attributes
    ----------
    name : str
        Case name (the record's ``case``).
    plant : dict
        ``[plant]`` overrides of the case (SI: ``track_length_m`` [m], ``speed_m_s`` [m/s], ``t0_k`` [K]).
    setpoint_mm2 : float
        Area set point [mm²].
    scenario : str
        ``layer`` or ``part``.
    layers : int
        Layers built (``part``; 1 otherwise).
    model : str or None
        The model learned on the case's process (repository path, ``python -m gp_trainer learn``): the
        preview MPC's and the scan-plan feed-forward's model and the PID's process record (``--process``)
        unless ``--model`` is given; None: launch's model of the plant.
    """

    name: str
    plant: dict[str, Any] = field(default_factory=dict)
    setpoint_mm2: float = 0.063
    scenario: str = "layer"
    layers: int = 1
    model: str | None = None

    def plant_table(self) -> dict[str, Any]:
        """The run's ``[plant]`` table: the case's overrides, on :data:`~fe_node.scenarios.TRAINING_MESH` for a
        layer case."""
        return ({"mesh": TRAINING_MESH} if self.scenario == "layer" else {}) | self.plant

    def plan(self) -> tuple[int, float, float] | None:
        """(tracks, track length [m], hatch [m]) of the case's plan; None for a part."""
        if self.scenario != "layer":
            return None
        n, length, hatch = LAYER_PLAN
        return (int(self.plant.get("n_tracks", n)), float(self.plant.get("track_length_m", length)),
                float(self.plant.get("hatch_m", hatch)))


def _absorptivity(scale: float) -> dict[str, float]:
    """The ``[plant]`` absorptivities (dense and powder) of the default plant scaled by ``scale``."""
    settings = scenario("layer").settings
    return {"absorptivity": round(settings.absorptivity * scale, 4),
            "powder_absorptivity": round(settings.powder_absorptivity * scale, 4)}


CASES = (
    Case("default-layer"),
    Case("tight-6x4mm-h80", {"n_tracks": 6, "track_length_m": 4e-3, "hatch_m": 80e-6}),
    Case("short-8x2mm", {"n_tracks": 8, "track_length_m": 2e-3}),
    Case("wide-2x10mm-h120", {"n_tracks": 2, "hatch_m": 120e-6}),
    Case("speed-0.6", {"speed_m_s": 0.6}, model="gp_model/models/in625_narx_gp_0.6mps.json"),
    Case("speed-1.0", {"speed_m_s": 1.0}, model="gp_model/models/in625_narx_gp_1.0mps.json"),
    Case("preheat-500K", {"t0_k": 500.0}),
    Case("absorptivity+10pct", _absorptivity(1.1)),
    Case("absorptivity-10pct", _absorptivity(0.9)),
    Case("setpoint-0.05", setpoint_mm2=0.05),
    Case("setpoint-0.09", setpoint_mm2=0.09),
    Case("part-2-layers", scenario="part", layers=2),
    Case("l-bracket-3-layers", {"part_stl": "fe_node/parts/l_bracket_3mm.stl"}, scenario="part", layers=3),
)


def training_plans(runs: list[str]) -> set[tuple[int, float, float] | str]:
    """The plans (tracks, length [m], hatch [m]) the named training runs scanned, from their names
    (``ident-layer-p174-s2``, ``ident-preview-mpc-layer-a0.061-h110um-450K``, ``ident-layer-8x5mm-p174-s7``),
    and :data:`EXAMPLE_PART` if one built the example part (``ident-part-p60-s11``, ``ident-pid-part-a0.063``),
    ``part:<stem>`` if one built another part (``ident-part-block_5mm-p60-s21``,
    ``ident-pid-part-l_bracket_3mm-a0.063``: its STL's stem)."""
    plans = set()
    for run in runs:
        if re.search(r"-part(-|$)", run):
            m = re.search(r"-part(?:-(.+?))?-(?:p[\d.]+-s\d+|a[\d.]+)", run)
            plans.add(EXAMPLE_PART if m is None or m.group(1) is None else f"part:{m.group(1)}")
            continue
        scenario = next((s for s in SCENARIO_PLANS if re.search(rf"-{s}(-|$)", run)), None)
        if scenario is None:
            continue
        n, length, hatch = SCENARIO_PLANS[scenario]
        if (m := re.search(r"-(\d+)x([\d.]+)mm", run)) is not None:
            n, length = int(m.group(1)), float(m.group(2)) * 1e-3
        if (m := re.search(r"-h(\d+)um", run)) is not None:
            hatch = int(m.group(1)) * 1e-6
        plans.add((n, round(length, 9), round(hatch, 9)))
    return plans


PROCESS_KEYS = ("speed_m_s", "t0_k", "absorptivity", "powder_absorptivity")
"""``[plant]`` keys that change the process away from the one the model was learned on."""


def in_sample(case: Case, plans: set[tuple[int, float, float] | str], process: dict[str, Any] | None = None) -> bool:
    """Whether a training run scanned the case's plan (for a part: built that part, whose first layers every
    part run scans) on the model's own process: no :data:`PROCESS_KEYS` override other than the model's
    ``[plant]`` table ``process`` sets alike."""
    process = process or {}
    if case.scenario == "part":
        stl = case.plant.get("part_stl")
        trained = (EXAMPLE_PART if stl is None else f"part:{Path(stl).stem}") in plans
    else:
        plan = case.plan()
        trained = (plan[0], round(plan[1], 9), round(plan[2], 9)) in plans
    return trained and all(case.plant[key] == process.get(key) for key in PROCESS_KEYS if key in case.plant)


def case_config(case: Case, out_dir: Path) -> Path:
    """The case's ``--config`` file in ``out_dir``: its ``[plant]`` table (:meth:`Case.plant_table`)."""
    config = out_dir / f"{case.name}.toml"
    lines = ["[plant]"] + [f"{k} = {json.dumps(v)}" for k, v in sorted(case.plant_table().items())]
    config.write_text("\n".join(lines) + "\n")
    return config


def shipped_model(case: Case, out_dir: Path) -> Path:
    """The model launch.py gives the case's plant when none is named (:func:`launch.plant_model`)."""
    layers = case.layers if case.scenario == "part" else None
    model = plant_model(RunOptions(scenario=case.scenario, config=case_config(case, out_dir), layers=layers))
    if model is None:
        raise ValueError(f"case {case.name}: launch.py refuses its [plant] table")
    return model


def case_model(case: Case, model: Path | None) -> Path | None:
    """The model a case runs on: ``model`` (``--model``), else the case's learned model, else None (launch's)."""
    return model or (None if case.model is None else REPO / case.model)


MODEL_CONTROLLERS = ("preview-mpc", "scan-feedforward")
"""The controllers of :data:`CONTROLLERS` that run on the delay-aware model (``--model``)."""


def run_case(case: Case, controller: str, out_dir: Path, max_steps: int | None,
             model: Path | None = None) -> dict[str, Any]:
    """One launch.py run of ``case`` under ``controller`` (on ``model`` for :data:`MODEL_CONTROLLERS`, the
    PID on its process record; None: launch's model of the plant); launch's JSON summary (or the refusal)."""
    config = case_config(case, out_dir)
    cmd = [sys.executable, "launch.py", "--config", str(config), "--scenario", case.scenario,
           "--controller", controller, "--setpoint-mm2", str(case.setpoint_mm2), "--json", "--no-progress",
           "--out", str(out_dir / f"{case.name}-{controller}.mcap"), "--overwrite"]
    if case.scenario == "part":
        cmd += ["--layers", str(case.layers)]
    if max_steps is not None:
        cmd += ["--max-steps", str(max_steps)]
    if model is not None:
        cmd += ["--model" if controller in MODEL_CONTROLLERS else "--process", str(model)]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    last = (done.stdout.strip().splitlines() or [""])[-1]
    try:
        summary = json.loads(last)
    except json.JSONDecodeError:
        error = (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
        return {"status": done.returncode, "refused": error}
    return summary


MODEL_FIT_KEYS = ("mape_turnaround_pct", "bias_turnaround_pct", "mape_along_pct", "bias_along_pct",
                  "bias_after_turn_pct")
"""The keys of :func:`gp_trainer.narx_fit.evaluate_model` a model controller's record carries (``model_`` first)."""


def model_fit(recording: Path) -> dict[str, float | None]:
    """How the model the run's controller used (its configuration in ``recording``) predicts the run one step
    ahead: :data:`MODEL_FIT_KEYS`, each ``model_``-prefixed."""
    model = NarxGPModel.load(run_config(recording)["controller"]["model"])
    fit = evaluate_model(model, [series_from_states(read_states(recording), recording.stem)])
    return {f"model_{key}": fit[key] for key in MODEL_FIT_KEYS}


def record(case: Case, controller: str, summary: dict[str, Any], plans: set, process: dict[str, Any] | None = None
           ) -> dict[str, Any]:
    """The suite's record of one run (launch's figures, the case's plan and whether it is in-sample on the
    model's training ``plans`` and ``[plant]`` table ``process``)."""
    plan = case.plan() or (None, None, float(case.plant.get("hatch_m", 1e-4)))
    return {"case": case.name, "controller": controller, "status": summary.get("status"),
            "overshoot_pct": summary.get("overshoot_pct"), "undershoot_pct": summary.get("undershoot_pct"),
            "rmse_pct": summary.get("steady_rmse_pct"), "rmse_turnaround_pct": summary.get("rmse_turnaround_pct"),
            "rmse_along_pct": summary.get("rmse_along_pct"), "in_sample": in_sample(case, plans, process),
            "layers": case.layers, "track_length_m": plan[1], "hatch_m": plan[2],
            "speed_m_s": float(case.plant.get("speed_m_s", 0.8)), "setpoint_mm2": case.setpoint_mm2,
            "wall_s": summary.get("wall_s"), "refused": summary.get("refused")}


def bound_from(provenance: dict[str, Any], args: argparse.Namespace, model: Path | None = None) -> BoundSettings:
    """The learning bound's settings: the process's FOPDT gain and dead time (``provenance.controller.pid.fopdt``
    of the model ``model``, ``python -m gp_trainer tune-pid``) and operating power; exits 2 naming what is
    missing."""
    controller = provenance.get("controller") or {}
    fopdt = (controller.get("pid") or {}).get("fopdt") or {}
    needed = ("gain_m2_per_w", "delay_steps", "time_constant_s", "sample_period_s")
    if any(key not in fopdt for key in needed) or "nominal_power_w" not in controller:
        sys.exit(f"bench_suite.py: error: --bound: {model or DEFAULT_MODEL_PATH} records no "
                 "provenance.controller.pid.fopdt (run python -m gp_trainer tune-pid --model on it)")
    try:
        return BoundSettings(iterations=args.bound_iterations, gain=args.bound_gain, process=Fopdt(**fopdt),
                             start_power_w=float(controller["nominal_power_w"]))
    except (TypeError, ValueError) as err:
        sys.exit(f"bench_suite.py: error: --bound: {err}")


def case_bound(case: Case, settings: BoundSettings, max_steps: int | None) -> dict[str, Any]:
    """``bound_rmse_pct`` and ``bound_iteration`` of ``case`` (:func:`learning_bound.learning_bound`)."""
    overrides = case.plant_table() | ({"n_layers": case.layers} if case.scenario == "part" else {})
    result = learning_bound(scenario(case.scenario, **overrides), case.setpoint_mm2 * 1e-6, settings, max_steps)
    return {"bound_rmse_pct": result["bound_rmse_pct"], "bound_iteration": result["bound_iteration"]}


def _cell(value: Any) -> str:
    return "-" if value is None else f"{value:.2f}" if isinstance(value, float) else str(value)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", choices=[c.name for c in CASES], help="cases to run (default: all)")
    parser.add_argument("--controllers", nargs="+", default=list(CONTROLLERS), choices=CONTROLLERS)
    parser.add_argument("--max-steps", type=int, help="end each run after this many plant steps (a quick check)")
    parser.add_argument("--model", type=Path,
                        help="the model of preview-mpc and scan-feedforward and the PID's process record, whose "
                             "training runs decide in_sample (default: the case's learned model if it names one, "
                             "else the shipped model of each case's plant; in_sample from the physical plate's)")
    parser.add_argument("--out-dir", type=Path, help="recordings, configs and JSON records (default: a temp folder)")
    parser.add_argument("--json", action="store_true", help="print the records as JSON on the last line")
    parser.add_argument("--bound", action="store_true",
                        help="also each case's learning bound (ILC of the open-loop power, learning_bound.py)")
    parser.add_argument("--bound-iterations", type=int, default=8, help="FE runs of the bound (default %(default)s)")
    parser.add_argument("--bound-gain", type=float, default=0.5, help="its learning gain (default %(default)s)")
    args = parser.parse_args()
    cases = [c for c in CASES if args.cases is None or c.name in args.cases]
    if args.bound:                                  # a model without the FOPDT fails before any run
        for model in {case_model(c, args.model) for c in cases}:
            bound_from(read_document(model or DEFAULT_MODEL_PATH).get("provenance", {}), args, model)
    with tempfile.TemporaryDirectory() as tmp:
        out_dir = args.out_dir or Path(tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        records = []
        print(f"{'case':22s} {'controller':12s} {'over %':>7s} {'under %':>7s} {'RMSE %':>7s} {'turn %':>7s} "
              f"{'along %':>7s}  in-sample", flush=True)
        for case in cases:
            model = case_model(case, args.model)
            learned = read_document(model or shipped_model(case, out_dir)).get("provenance", {})
            bound = case_bound(case, bound_from(learned, args, model), args.max_steps) if args.bound else {}
            plans, process = training_plans(list(learned.get("runs", []))), (learned.get("process") or {}).get("plant")
            for controller in args.controllers:
                summary = run_case(case, controller, out_dir, args.max_steps, model)
                rec = record(case, controller, summary, plans, process) | bound
                if controller in MODEL_CONTROLLERS and summary.get("status") == 0:
                    rec |= model_fit(Path(summary["recording"]))
                (out_dir / f"{case.name}-{controller}.json").write_text(json.dumps(rec, indent=1) + "\n")
                records.append(rec)
                figures = " ".join(f"{_cell(rec[k]):>7s}" for k in ("overshoot_pct", "undershoot_pct", "rmse_pct",
                                                                      "rmse_turnaround_pct", "rmse_along_pct"))
                note = f"  refused: {rec['refused']}" if rec["refused"] else ""
                print(f"{case.name:22s} {controller:12s} {figures}  {rec['in_sample']}{note}", flush=True)
    if args.json:
        print(json.dumps({"cases": records}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
