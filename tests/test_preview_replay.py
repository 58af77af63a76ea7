"""The preview MPC's control law is kept: a recorded sequence of states replayed through the
controller gives the commands and plans recorded in ``tests/data/preview_replay.npz``.

The states are those of a closed loop of the preview MPC with the bare plate's model on its FE
double track (two 5 mm tracks, 250 states), then the same states again as a second layer with one
state missing (a gap); each replayed state carries the power the replaying controller commanded
before it, as the plant would.
Three controllers replay them: the node's (prepare after each command: the real-time iteration), one
without preparation (every update full), and one with bound tightening and a tight upper area bound
(variance of every row, DAQP where a bound binds). The recording is that of the controller before
its stages were made named objects; regenerate it (``python tests/test_preview_replay.py``) only for
a deliberate change of the control law.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from controller_node.preview import PreviewMPC
from controller_node.settings import ControllerSettings
from controller_node.types import Measurement
from gp_model.narx import NarxGPModel
from gp_model.shipped import PLATE_MODEL_PATH
from tests.plants import BARE

FIXTURE = Path(__file__).resolve().parent / "data" / "preview_replay.npz"
SP = 0.063e-6
GAP_AT = 380
"""Index of the replayed state left out of the second layer."""
VARIANTS = ("prepared", "full", "tightened")
FIELDS = ("time_s", "area_m2", "t_ahead_k", "track", "track_elapsed_s", "track_remaining_s", "next_track")


def _settings(variant: str) -> ControllerSettings:
    base = ControllerSettings(set_point_m2=SP)
    if variant != "tightened":
        return base
    return dataclasses.replace(base, preview=dataclasses.replace(base.preview, uncertainty_z=1.0,
                                                                  area_max_m2=1.08 * SP))


def _record_fe_states() -> dict[str, np.ndarray]:
    """The states of a closed loop of the preview MPC on the bare plate's FE double track (as arrays)."""
    from fe_node.scenarios import scenario
    from fe_node.solver import ThermalModel

    sc = scenario("double-track", preset=BARE)
    ctrl = PreviewMPC(_settings("prepared"), NarxGPModel.load(PLATE_MODEL_PATH))
    plant = ThermalModel(sc.settings, sc.plan)
    obs, rows = plant.initial_observation(), []
    while not plant.done:
        speed = obs.speed_m_s or 0.8
        m = Measurement(step=obs.step, time_s=obs.time_s, area_m2=obs.area_m2, t_ahead_k=obs.t_ahead_k,
                        power_w=obs.power_w, speed_m_s=speed, track=obs.track,
                        track_elapsed_s=obs.track_travelled_m / speed,
                        track_remaining_s=obs.track_remaining_m / speed, next_track=obs.next_track)
        rows.append([getattr(m, name) for name in FIELDS])
        cmd, _ = ctrl.update(m)
        ctrl.prepare()
        obs = plant.step(cmd.power_w, 0.8)
    return {name: np.array(column, dtype=float) for name, column in zip(FIELDS, zip(*rows, strict=True), strict=True)}


def _replay(states: dict[str, np.ndarray], variant: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The commands [W], plans (n, H) [W], QP iterations (0: the kernel's unconstrained step) and
    feedback updates of a controller fed ``states`` twice (layers 0 and 1, state ``GAP_AT`` of the
    sequence left out), each with its previous command."""
    ctrl = PreviewMPC(_settings(variant), NarxGPModel.load(PLATE_MODEL_PATH))
    n, period = states["time_s"].size, float(states["time_s"][1] - states["time_s"][0])
    power, commands, plans, iterations = 0.0, [], [], []
    for k in range(2 * n):
        if k == GAP_AT:
            continue
        i = k % n
        m = Measurement(step=k, time_s=k * period, area_m2=float(states["area_m2"][i]),
                        t_ahead_k=float(states["t_ahead_k"][i]), power_w=power, speed_m_s=0.8,
                        track=int(states["track"][i]), track_elapsed_s=float(states["track_elapsed_s"][i]),
                        track_remaining_s=float(states["track_remaining_s"][i]),
                        next_track=bool(states["next_track"][i]), layer=k // n)
        cmd, diag = ctrl.update(m)
        if variant != "full":
            ctrl.prepare()
        power = cmd.power_w
        commands.append(power)
        plans.append(diag.predicted_power_w or (np.nan,) * ctrl.settings.preview.horizon)
        iterations.append(diag.solver_iterations)
    return np.array(commands), np.array(plans), np.array(iterations), ctrl.n_feedback


@pytest.fixture(scope="module")
def recorded() -> dict[str, np.ndarray]:
    with np.load(FIXTURE) as data:
        return dict(data)


@pytest.mark.parametrize("variant", VARIANTS)
def test_the_replayed_states_get_the_recorded_commands(recorded, variant):
    """Every command and the last planned power p[k+H−1] within 1e-9 W of the recording, the same
    updates taking the feedback phase and the same QPs solved beyond the kernel's step."""
    states = {name: recorded[name] for name in FIELDS}
    commands, plans, iterations, n_feedback = _replay(states, variant)
    assert n_feedback == int(recorded[f"{variant}_n_feedback"])
    assert np.array_equal(iterations, recorded[f"{variant}_iterations"])
    assert np.max(np.abs(commands - recorded[f"{variant}_commands_w"])) <= 1e-9
    assert np.allclose(plans[:, -1], recorded[f"{variant}_plan_ends_w"], rtol=0.0, atol=1e-9, equal_nan=True)


def test_the_recording_covers_the_paths_of_the_law(recorded):
    """Both tracks of both layers, the feedback phase and the full update, the kernel's step and
    (with the tight area bound) the QPs solved beyond it."""
    assert set(recorded["track"].astype(int)) == {0, 1}
    assert 200 < int(recorded["prepared_n_feedback"]) < 2 * recorded["track"].size - 5   # the full update at
    # the first states, the turns, the new layer and the gap
    assert int(recorded["full_n_feedback"]) == 0
    iterations = recorded["tightened_iterations"]
    assert 20 < np.count_nonzero(iterations) < iterations.size - 20


def main() -> None:
    """Record the states and the commands of every variant into :data:`FIXTURE`."""
    states = _record_fe_states()
    out = dict(states)
    for variant in VARIANTS:
        (out[f"{variant}_commands_w"], plans, out[f"{variant}_iterations"],
         out[f"{variant}_n_feedback"]) = _replay(states, variant)
        out[f"{variant}_plan_ends_w"] = plans[:, -1]
    FIXTURE.parent.mkdir(exist_ok=True)
    np.savez_compressed(FIXTURE, **out)
    print({v: (int(out[f"{v}_n_feedback"]), int(np.count_nonzero(out[f"{v}_iterations"]))) for v in VARIANTS},
          FIXTURE.stat().st_size, "bytes")


if __name__ == "__main__":
    main()
