"""A rogue publisher floods the lockstep plant with schema-valid commands it must not apply.

Two short closed-loop runs (FE plant + PID controller, real processes) side by side: a clean
one, and one during which the test publishes 2 000 (``-m slow``: 10 000) schema-valid
``LaserCommand`` messages on the run's command key — the awaited step with another run's id,
steps ahead of anything the plant can wait for (up to 2³¹ − 1), the stale step 0, and the
awaited step with a power or speed outside the plant's bounds. The lockstep result does not
depend on timing, so the flooded run must give exactly the clean states, and every forged
command must be dropped and counted.
"""

from __future__ import annotations

import re

import pytest

from messages import LaserCommand
from messages.bus import BusSettings, NodeBus
from messages.topics import LASER_COMMAND, PLANT_DIAGNOSTICS, PLANT_STATE
from messages.types import MAX_STEP
from tests.conftest import finish, spawn
from tests.plants import BARE_ARGS

STEPS = 60
SLACK = 25  # steps after the last burst, for the plant to read every forged command (a loaded machine delays them)
N_FORGED = 2000


def forgery(i: int, run_id: str, k: int) -> LaserCommand:
    """The ``i``-th forged command, sent when state ``k`` was seen (the plant waits for step k + 1 or k + 2)."""
    kind = i % 4
    if kind == 0:  # the awaited step, another run's id
        return LaserCommand(run_id="other-run", step=k + 1, time_s=0.0, power_w=123.0, speed_mm_s=800.0,
                            controller="pid")
    if kind == 1:  # ahead of anything the plant can wait for in this run
        step = MAX_STEP if i % 8 == 1 else STEPS + 2 + i * 1000
        return LaserCommand(run_id=run_id, step=step, time_s=0.0, power_w=123.0, speed_mm_s=800.0, controller="pid")
    if kind == 2:  # stale: the plant never waits for step 0
        return LaserCommand(run_id=run_id, step=0, time_s=0.0, power_w=123.0, speed_mm_s=800.0, controller="pid")
    # the awaited step, power or speed outside the plant's bounds (stale if the controller's came first)
    return LaserCommand(run_id=run_id, step=k + 1, time_s=0.0, power_w=1e5 if i % 8 == 3 else 123.0,
                        speed_mm_s=800.0 if i % 8 == 3 else 1e5, controller="pid")


def start(run_id: str, hub: str) -> tuple:
    common = ("--run-id", run_id, "--connect", hub)
    controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.063", *common)
    plant = spawn("fe_node", "--scenario", "single-track", "--h-um", "40", *BARE_ARGS, "--max-steps", str(STEPS),
                  "--command-timeout-s", "20", "--require", "controller", "--require", "observer", *common)
    return controller, plant


@pytest.mark.parametrize("n_forged", [N_FORGED, pytest.param(10_000, marks=pytest.mark.slow)])
def test_forged_commands_are_dropped_and_counted_and_change_nothing(hub, run_id, n_forged):
    clean_id, flood_id = run_id + "c", run_id + "f"
    with (NodeBus("observer", BusSettings(run_id=clean_id, connect=(), listen=(hub,))) as clean,
          NodeBus("observer", BusSettings(run_id=flood_id, connect=(hub,), listen=())) as rogue):
        clean_states = clean.inbox(PLANT_STATE)
        states, diagnostics = rogue.inbox(PLANT_STATE), rogue.inbox(PLANT_DIAGNOSTICS)
        commands = rogue.publisher(LASER_COMMAND)
        clean.ready()
        rogue.ready()
        processes = [*start(clean_id, hub), *start(flood_id, hub)]
        flooded, sent = [], 0
        while (state := states.get(timeout=60)) is not None:
            flooded.append(state)
            if 1 <= state.step < STEPS - SLACK:  # one burst per state: the flood runs along with the loop
                end = n_forged * state.step // (STEPS - SLACK - 1)
                for i in range(sent, end):
                    commands.put(forgery(i, flood_id, state.step))
                sent = end
            if state.step == STEPS:
                break
        outputs = [finish(p, timeout=60) for p in processes]
        clean_trace = list(clean_states.drain())
        last = list(diagnostics.drain())[-1]
    for status, out in outputs:
        assert status == 0 and "Traceback" not in out, out
    assert sent == n_forged

    def trace(seen):
        return [(s.step, s.power_w, s.speed_mm_s, s.area_mm2) for s in seen]

    assert [s.step for s in clean_trace] == list(range(STEPS + 1))
    assert trace(flooded) == trace(clean_trace)
    assert len({s.power_w for s in flooded}) > 5  # the controller did steer
    assert last.step == STEPS and last.n_fallbacks == 0 and last.command_source == "controller"
    assert last.n_dropped == n_forged and last.n_stale_commands >= n_forged // 4
    plant_out = outputs[3][1]
    m = re.search(r"(\d+) dropped commands \((\d+) stale, (\d+) ahead, (\d+) out of bounds, (\d+) invalid\)", plant_out)
    assert m, plant_out
    dropped, stale, ahead, out_of_bounds, invalid = (int(g) for g in m.groups())
    print(f"flooded plant: {m.group(0)}")
    assert dropped == n_forged and invalid == n_forged // 4 and ahead == n_forged // 4
    assert stale + out_of_bounds == n_forged // 2 and stale >= n_forged // 4
    assert "0 dropped commands" in outputs[1][1]  # the clean plant dropped nothing
