"""The controller node as a real process: answers states, drops bad input, follows the plant."""

from __future__ import annotations

import time

from messages import MeltPoolState
from messages.bus import BusSettings, NodeBus, StopFlag
from messages.topics import CONTROLLER_DIAGNOSTICS, LASER_COMMAND, PLANT_STATE, key_expr
from tests import forked_cli
from tests.conftest import finish, spawn


def state(run_id: str, step: int, area_mm2: float = 0.05) -> MeltPoolState:
    return MeltPoolState(
        run_id=run_id, step=step, time_s=step * 50e-6, laser_x_mm=0.04 * step, laser_y_mm=0.0, scan_dir_x=1.0,
        scan_dir_y=0.0, track=0, area_mm2=area_mm2, t_ahead_k=500.0, power_w=250.0, speed_mm_s=800.0,
    )


def test_pid_node_answers_each_state_and_exits_when_the_plant_goes(hub, run_id):
    node = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.07",
                 "--run-id", run_id, "--connect", hub)
    stop = StopFlag()
    with NodeBus("plant", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        commands = bus.inbox(LASER_COMMAND)
        diags = bus.inbox(CONTROLLER_DIAGNOSTICS)
        bus.wait_for_nodes(["controller"], stop, timeout_s=30)
        bus.ready()
        raw = bus.session.declare_publisher(key_expr(run_id, PLANT_STATE))
        pub = bus.publisher(PLANT_STATE)
        got = []
        for step in range(20):
            if step == 5:
                raw.put(b'{"garbage": true}')
                raw.put(b'{"run_id": "x", "step": 1, "area_mm2": NaN}')
            pub.put(state(run_id, step))
            cmd = commands.get(timeout=10)
            assert cmd is not None, f"no command for state {step}"
            got.append(cmd)
        raw.undeclare()
        assert [c.step for c in got] == list(range(1, 21))
        assert all(0.0 <= c.power_w <= 350.0 for c in got)
        assert got[-1].power_w > got[0].power_w  # area below the set point: PID raises the power
        last = None
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and (last is None or last.step < 20):
            last = diags.get(timeout=1) or last
        assert last.n_dropped == 2 and last.setpoint_mm2 == 0.07
    status, out = finish(node, timeout=20)  # the plant's token vanished: the node ends by itself
    assert status == 0, out
    assert "plant 'plant' ended" in out


def test_mpc_node_without_model_file_exits_2(tmp_path):
    run = forked_cli.run("-m", "controller_node", "--controller", "mpc", "--model", str(tmp_path / "missing.json"))
    assert run.returncode == 2
    assert run.stdout == "" and run.stderr.strip().count("\n") == 0 and "cannot load GP model" in run.stderr
