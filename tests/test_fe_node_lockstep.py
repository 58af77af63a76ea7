"""The FE node in lockstep with a scripted command publisher in another process (this test)."""

from __future__ import annotations

from messages import LaserCommand
from messages.bus import BusSettings, NodeBus
from messages.topics import LASER_COMMAND, PLANT_DIAGNOSTICS, PLANT_STATE
from tests.conftest import finish, spawn
from tests.plants import BARE_ARGS


def command(run_id: str, step: int, power_w: float) -> LaserCommand:
    return LaserCommand(run_id=run_id, step=step, time_s=0.0, power_w=power_w, speed_mm_s=800.0, controller="script")


def test_plant_applies_only_the_matching_in_bounds_command(hub, run_id):
    plant = spawn("fe_node", "--scenario", "single-track", "--h-um", "40", *BARE_ARGS, "--max-steps", "6",
                  "--power-max-w", "300", "--run-id", run_id, "--connect", hub)
    with NodeBus("controller", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        states, diags = bus.inbox(PLANT_STATE), bus.inbox(PLANT_DIAGNOSTICS)
        commands = bus.publisher(LASER_COMMAND)
        bus.ready()
        applied = []
        state = states.get(timeout=60)
        assert state is not None and state.step == 0
        while state.step < 6:
            k = state.step
            commands.put(command(run_id, k, 111.0))          # stale: answers an old step
            commands.put(command(run_id, k + 1, 320.0))      # above the plant's 300 W bound: never applied
            commands.put(command(run_id, k + 1, 150.0 + 10 * k))
            state = states.get(timeout=30)
            assert state is not None and state.step == k + 1
            applied.append(state.power_w)
        diag = None
        while (d := diags.get(timeout=2)) is not None:
            diag = d
    status, out = finish(plant, timeout=30)
    assert status == 0, out
    assert applied == [150.0 + 10 * k for k in range(6)]
    assert diag.n_stale_commands == 6 and diag.n_dropped == 12 and diag.n_fallbacks == 0  # stale + out of bounds


def test_missing_commands_trigger_the_safe_fallback_and_are_logged(hub, run_id):
    plant = spawn("fe_node", "--scenario", "single-track", "--h-um", "40", *BARE_ARGS, "--max-steps", "3",
                  "--command-timeout-s", "0.2", "--safe-power-w", "20", "--run-id", run_id, "--connect", hub)
    with NodeBus("controller", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        states = bus.inbox(PLANT_STATE)
        bus.ready()
        seen = [states.get(timeout=60) for _ in range(4)]
    status, out = finish(plant, timeout=30)
    assert status == 0, out  # the controller (this test) is still present: fallback, not failure
    assert [s.power_w for s in seen[1:]] == [20.0, 20.0, 20.0]
    assert out.count("no command for step") == 3 and "applying fallback-safe 20.0 W" in out
