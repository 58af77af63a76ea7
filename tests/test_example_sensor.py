"""The example sensor node (free-running, hardware-shaped) against the real controller node."""

from __future__ import annotations

import json

from fe_node.commands import CommandPolicy
from messages.bus import BusSettings, NodeBus, StopFlag
from messages.topics import LASER_COMMAND, PLANT_STATE
from tests.conftest import finish, spawn


def test_example_sensor_closes_the_loop_with_the_controller_node(hub, run_id):
    common = ("--run-id", run_id, "--connect", hub)
    controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.07", *common)
    stop = StopFlag()
    with NodeBus("observer", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        states, commands = bus.inbox(PLANT_STATE), bus.inbox(LASER_COMMAND)
        bus.wait_for_nodes(["controller"], stop, timeout_s=30)
        sensor = spawn("fe_node.example_sensor", "--rate-hz", "500", "--max-steps", "400", "--require", "controller",
                       "--power-max-w", "300", "--json", *common)
        status, out = finish(sensor, timeout=30)
        assert status == 0, out
        stats = json.loads(out.strip().splitlines()[-1])
        seen_states = list(states.drain())
        seen_commands = list(commands.drain())
    assert [s.step for s in seen_states] == list(range(401))
    assert {s.source for s in seen_states} == {"sensor"}
    # states 0..400 each answered at most once (how many in time depends on the machine: bench_loop.py)
    assert 1 <= len(seen_commands) <= 401
    steps = [c.step for c in seen_commands]
    assert steps == sorted(set(steps)) and steps[0] >= 1
    # commands above the sensor's own 300 W bound are rejected (counted), never applied; one that
    # arrives after a newer command was applied (or after the last tick) is dropped as stale first
    above = sum(c.power_w > 300.0 for c in seen_commands)
    assert stats["steps"] == 400 and stats["rejected_commands"] <= above
    assert stats["commands"] + above >= 1 and stats["rtt_median_us"] > 0
    applied = {c.power_w for c in seen_commands if c.power_w <= 300.0} | {250.0}
    if stats["fallback_steps"]:  # a loaded host can leave it 0.5 s without a command: the default safe power
        applied.add(CommandPolicy().safe_power_w)
    assert all(s.power_w in applied for s in seen_states)  # the plant echoes an applied power
    assert seen_states[-1].power_w != 250.0  # the controller's commands were applied
    status, out = finish(controller, timeout=20)
    assert status == 0 and "plant 'plant' ended" in out, out
