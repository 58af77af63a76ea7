"""Faults with real processes: a killed controller, a killed plant, and a run that loses nothing."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time

from messages.bus import BusSettings, NodeBus, StopFlag
from messages.recording import is_complete, metadata, read_messages
from messages.topics import LOG, PLANT_DIAGNOSTICS, PLANT_STATE
from tests.conftest import RECORDER_NODE, controller_node, finish, spawn, start_node_list
from tests.plants import BARE_ARGS

FE = ("--h-um", "40", *BARE_ARGS)
TIMEOUT_S = 2.0


def wait_for(inbox, predicate, timeout_s: float):
    """The first message of ``inbox`` satisfying ``predicate`` within ``timeout_s`` (or ``None``)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = inbox.get(timeout=0.1)
        if msg is not None and predicate(msg):
            return msg
    return None


def test_controller_killed_plant_applies_the_safe_power_on_the_liveliness_loss(tmp_path, hub, run_id):
    """The kill's wall time vs the wall time the plant logs for its first safe-power step (an upper bound of
    the delay after the liveliness loss) is under half the command timeout (2 s), and the timeout never
    fired: the liveliness path acted. How fast it acts is a figure of the machine's load (11-19 ms on a
    quiet one, ``docs/node-contract.md``), not a pass mark."""
    out = tmp_path / "fault.mcap"
    common = ("--run-id", run_id, "--connect", hub)
    with NodeBus("observer", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        states, diagnostics, logs = bus.inbox(PLANT_STATE), bus.inbox(PLANT_DIAGNOSTICS), bus.inbox(LOG)
        recorder = spawn("messages.recorder", "--out", str(out), "--expect", "plant", "--expect", "controller", *common)
        controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.063", "--require", "recorder",
                           *common)
        bus.wait_for_nodes(["recorder", "controller"], StopFlag(), timeout_s=60)
        plant = spawn("fe_node", *FE, "--max-steps", "2000", "--command-timeout-s", str(TIMEOUT_S),
                      "--safe-power-w", "40", "--require", "recorder", "--require", "controller", *common)
        assert wait_for(states, lambda s: s.step >= 5, 60) is not None, "plant did not start stepping"
        killed_wall = time.time()
        controller.send_signal(signal.SIGKILL)
        fallback = wait_for(logs, lambda m: "gone (liveliness lost)" in m.message, 10)
        status, plant_out = finish(plant, timeout=30)
        last_state = None
        for s in states.drain():
            last_state = s
        last_diagnostics = list(diagnostics.drain())[-1]
        recorder.send_signal(signal.SIGINT)  # the controller never ends: stop the recorder by hand
        finish(recorder, timeout=60)
    finish(controller)
    assert fallback is not None, plant_out
    m = re.search(r"applying fallback-safe 40.0 W to step (\d+) at wall ([\d.]+) s", fallback.message)
    assert m, fallback.message
    delay_s = float(m.group(2)) - killed_wall
    print(f"controller SIGKILL -> safe power applied: {delay_s * 1e3:.1f} ms")
    assert 0 <= delay_s < 0.5 * TIMEOUT_S, f"safe power {delay_s * 1e3:.0f} ms after the kill"
    assert plant_out.count("gone (liveliness lost)") == 1 and "no command for step" not in plant_out, plant_out
    assert status == 1 and "aborted at step" in plant_out and "controller lost" in plant_out, plant_out
    assert last_state.step == int(m.group(1)) and last_state.power_w == 40.0  # the safe power, echoed
    assert last_diagnostics.step == last_state.step and last_diagnostics.command_source == "fallback-safe"
    recorded = list(read_messages(out, "/plant/state"))  # readable up to the fault
    assert [s.step for s in recorded] == list(range(last_state.step + 1))
    assert any("fallback-safe" in m.message for m in read_messages(out, "/log"))
    assert not is_complete(out)


def launch_nodes(tmp_path, plant_args: list[str], controller: str = "pid") -> tuple[subprocess.Popen[str], object]:
    plant = f"""
[[node]]
name = "plant"
module = "fe_node"
args = {json.dumps([*FE, "--require", "recorder", "--require", "controller", *plant_args])}
main = true
"""
    return start_node_list(tmp_path, "run", RECORDER_NODE + controller_node(controller) + plant)


def test_controller_killed_under_launch_ends_the_run_nonzero(tmp_path):
    proc, out = launch_nodes(tmp_path, ["--max-steps", "2000", "--command-timeout-s", str(TIMEOUT_S)])
    lines, pid = [], None
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        lines.append(proc.stdout.readline())
        if m := re.search(r"started controller \(pid (\d+)\)", lines[-1]):
            pid = int(m.group(1))
        if "[plant] info: layer:" in lines[-1]:
            break
    assert pid is not None, "".join(lines)
    time.sleep(0.5)
    subprocess.run(["kill", "-KILL", str(pid)], check=True)
    status, rest = finish(proc, timeout=60)
    output = "".join(lines) + rest
    assert status == 1, output
    assert "error: node controller exited with status -9; stopping the run" in output
    assert len(list(read_messages(out, "/plant/state"))) >= 1  # readable up to the fault


def test_plant_killed_controller_notices_and_stops(hub, run_id):
    common = ("--run-id", run_id, "--connect", hub)
    with NodeBus("observer", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        states = bus.inbox(PLANT_STATE)
        controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.063", *common)
        bus.wait_for_nodes(["controller"], StopFlag(), timeout_s=30)
        plant = spawn("fe_node.example_sensor", "--rate-hz", "200", "--require", "controller", *common)
        assert wait_for(states, lambda s: s.step >= 20, 30) is not None
        plant.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        status, out = finish(controller, timeout=15)
        finish(plant)
    assert status == 1 and "plant 'plant' lost (no end event)" in out, out
    assert time.monotonic() - killed < 5


def test_full_run_loses_no_message(tmp_path):
    proc, out = launch_nodes(tmp_path, ["--max-steps", "25"], controller="mpc")
    status, output = finish(proc, timeout=120)
    assert status == 0, output
    counts = metadata(out)["meltloop.counts"]
    published, recorded = json.loads(counts["published"]), json.loads(counts["recorded"])
    assert counts["complete"] == "true" and json.loads(counts["invalid_dropped"]) == {}
    assert published["plant/state"] == 26 and published["controller/command"] == 26
    recorded["run/events"] -= 1  # the recorder's own start event (it does not count itself)
    assert recorded == published
