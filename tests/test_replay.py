"""The replay node: a recording's states drive the unchanged controller node."""

from __future__ import annotations

import subprocess
import sys
import time

import msgspec
import pytest

from fe_node.replay import schedule
from messages.bus import BusSettings, NodeBus, StopFlag
from messages.recording import read_messages
from messages.topics import LASER_COMMAND, PLANT_STATE
from tests import forked_cli
from tests.conftest import REPO, finish, spawn
from tests.plants import BARE_ARGS


@pytest.fixture(scope="module")
def fe_recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("replay") / "fe.mcap"
    run = subprocess.run([sys.executable, "launch.py", "--controller", "none", "--h-um", "40", *BARE_ARGS,
                          "--max-steps", "12", "--out", str(out), "--no-progress"], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    return out


def test_schedule_scales_process_time():
    s = [msgspec.structs.replace(_dummy(), time_s=t) for t in (1.0, 1.5, 3.0)]
    assert schedule(s, 0.5) == [0.0, 1.0, 4.0]


def _dummy():
    from tests.test_controller_node import state

    return state("r", 0)


def test_replay_drives_the_controller_node(fe_recording, hub, run_id):
    original = list(read_messages(fe_recording, "/plant/state"))
    common = ("--run-id", run_id, "--connect", hub)
    controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.063", *common)
    stop = StopFlag()
    with NodeBus("observer", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        states, commands = bus.inbox(PLANT_STATE), bus.inbox(LASER_COMMAND)
        bus.wait_for_nodes(["controller"], stop, timeout_s=30)
        node = spawn("fe_node.replay", str(fe_recording), "--rate-scale", "0.0005", "--require", "controller", *common)
        status, out = finish(node, timeout=30)
        assert status == 0, out
        replayed = list(states.drain())
        answered = list(commands.drain())
        deadline = time.monotonic() + 5.0  # the observer may see the last answer after the replay node did
        while len(answered) < len(original) and (cmd := commands.get(timeout=deadline - time.monotonic())):
            answered.append(cmd)
    assert len(replayed) == len(original) == 13
    for got, want in zip(replayed, original):
        assert got.source == "replay" and got.run_id == run_id
        assert msgspec.structs.replace(got, run_id=want.run_id, source=want.source) == want
    assert [c.step for c in answered] == [s.step + 1 for s in original]  # 100 ms apart: every state answered
    assert "replayed 13 of 13 states; 13 commands received" in out
    status, out = finish(controller, timeout=20)
    assert status == 0 and "plant 'plant' ended" in out, out


@pytest.mark.parametrize("args, message", [
    (["missing.mcap"], "recording not found"),
    (["README.md"], "not an MCAP file"),
    (["X", "--rate-scale", "0"], "--rate-scale must be finite and > 0"),
    (["X", "--rate-scale", "nan"], "--rate-scale must be finite and > 0"),
])
def test_replay_bad_input_exit_2(args, message, fe_recording):
    args = [str(fe_recording) if a == "X" else a for a in args]
    run = forked_cli.run("-m", "fe_node.replay", *args)
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and message in run.stderr, run.stderr
