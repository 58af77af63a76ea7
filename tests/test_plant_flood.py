"""A rogue publisher floods the lockstep plant with schema-valid commands it must not apply.

Two short runs of the FE plant (real processes) side by side: a clean one under the PID controller
node, and a flooded one whose commands the test sends itself — at each state, first a burst of
``LaserCommand`` forgeries on the run's command key (2 000 in all; ``-m slow``: 10 000), then the
clean controller's command for that step. The forgeries are the awaited step with another run's
id, steps ahead of anything the plant can wait for (up to 2³¹ − 1), the stale step 0, and the
awaited step with a power or speed outside the plant's bounds. The flooded plant listens to the
test alone, over one link, so it reads every burst before the command that follows it: the outcome
does not depend on timing. The flooded run must give exactly the clean states, and after every
step the plant must have dropped and counted every forgery sent so far, each for its reason.
"""

from __future__ import annotations

import re
import subprocess

import msgspec
import pytest

from messages import LaserCommand
from messages.bus import BusSettings, NodeBus
from messages.topics import LASER_COMMAND, PLANT_DIAGNOSTICS, PLANT_STATE
from messages.types import MAX_STEP
from tests.conftest import finish, free_endpoint, spawn
from tests.plants import BARE_ARGS

STEPS = 60
N_FORGED = 2000


def forgery(i: int, run_id: str, k: int) -> LaserCommand:
    """The ``i``-th forged command, sent at state ``k`` (the plant waits for step k + 1)."""
    kind = i % 4
    if kind == 0:  # the awaited step, another run's id
        return LaserCommand(run_id="other-run", step=k + 1, time_s=0.0, power_w=123.0, speed_mm_s=800.0,
                            controller="pid")
    if kind == 1:  # ahead of anything the plant can wait for in this run
        step = MAX_STEP if i % 8 == 1 else STEPS + 2 + i * 1000
        return LaserCommand(run_id=run_id, step=step, time_s=0.0, power_w=123.0, speed_mm_s=800.0, controller="pid")
    if kind == 2:  # stale: the plant never waits for step 0
        return LaserCommand(run_id=run_id, step=0, time_s=0.0, power_w=123.0, speed_mm_s=800.0, controller="pid")
    # the awaited step, power or speed outside the plant's bounds
    return LaserCommand(run_id=run_id, step=k + 1, time_s=0.0, power_w=1e5 if i % 8 == 3 else 123.0,
                        speed_mm_s=800.0 if i % 8 == 3 else 1e5, controller="pid")


def plant(run_id: str, endpoint: str, controller: str) -> subprocess.Popen[str]:
    """The plant of one run, connected to ``endpoint``, following the liveliness of ``controller``
    (and waiting for it and for the test's ``observer``)."""
    waits = [arg for node in dict.fromkeys((controller, "observer")) for arg in ("--require", node)]
    return spawn("fe_node", "--scenario", "single-track", "--h-um", "40", *BARE_ARGS, "--max-steps", str(STEPS),
                 "--command-timeout-s", "20", "--controller", controller, *waits, "--run-id", run_id,
                 "--connect", endpoint)


@pytest.mark.parametrize("n_forged", [N_FORGED, pytest.param(10_000, marks=pytest.mark.slow)])
def test_forged_commands_are_dropped_and_counted_and_change_nothing(hub, run_id, n_forged):
    clean_id, flood_id, flood_hub = run_id + "c", run_id + "f", free_endpoint()
    with (NodeBus("observer", BusSettings(run_id=clean_id, connect=(), listen=(hub,))) as clean,
          NodeBus("observer", BusSettings(run_id=flood_id, connect=(), listen=(flood_hub,))) as rogue):
        clean_states, clean_commands = clean.inbox(PLANT_STATE), clean.inbox(LASER_COMMAND)
        states, diagnostics = rogue.inbox(PLANT_STATE), rogue.inbox(PLANT_DIAGNOSTICS)
        commands = rogue.publisher(LASER_COMMAND)  # one publisher, one link: the plant reads in this order
        clean.ready()
        rogue.ready()
        controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.063",
                           "--run-id", clean_id, "--connect", hub)
        processes = [controller, plant(clean_id, hub, "controller"), plant(flood_id, flood_hub, "observer")]
        flooded, sent, sent_by_step = [], 0, {}
        while (state := states.get(timeout=60)) is not None:
            flooded.append(state)
            if state.step == STEPS:
                break
            end = n_forged * (state.step + 1) // STEPS  # one burst per state: the flood runs along with the loop
            for i in range(sent, end):
                commands.put(forgery(i, flood_id, state.step))
            sent = sent_by_step[state.step + 1] = end
            command = clean_commands.get(timeout=60)  # the clean controller's answer to the same state
            assert command is not None and command.step == state.step + 1, command
            commands.put(msgspec.structs.replace(command, run_id=flood_id))
        outputs = [finish(p, timeout=60) for p in processes]
        clean_trace = list(clean_states.drain())
        diagnosed = list(diagnostics.drain())
    for status, out in outputs:
        assert status == 0 and "Traceback" not in out, out
    assert sent == n_forged

    def trace(seen):
        return [(s.step, s.power_w, s.speed_mm_s, s.area_mm2) for s in seen]

    assert [s.step for s in clean_trace] == list(range(STEPS + 1))
    assert trace(flooded) == trace(clean_trace)
    assert len({s.power_w for s in flooded}) > 5  # the controller did steer
    assert {d.step: d.n_dropped for d in diagnosed} == sent_by_step  # each burst counted before its step
    assert all(d.n_fallbacks == 0 and d.command_source == "controller" for d in diagnosed)
    plant_out = outputs[2][1]
    m = re.search(r"(\d+) dropped commands \((\d+) stale, (\d+) ahead, (\d+) out of bounds, (\d+) invalid\)", plant_out)
    assert m, plant_out
    print(f"flooded plant: {m.group(0)}")
    assert [int(g) for g in m.groups()] == [n_forged, *[n_forged // 4] * 4]
    assert "0 dropped commands" in outputs[1][1]  # the clean plant dropped nothing
