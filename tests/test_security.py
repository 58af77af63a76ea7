"""Security defaults and the example access-control configuration, with real sessions."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from messages import LaserCommand, Log, LogLevel, Timestamp
from messages.bus import DEFAULT_HUB, BusSettings, NodeBus, StopFlag, zenoh_config
from messages.topics import LASER_COMMAND, LOG, PLANT_STATE
from tests.conftest import REPO, finish, spawn
from tests.test_controller_node import state

ACL_FILE = REPO / "docs" / "zenoh-acl.json5"
PASSWORDS = {"plant": "pw-plant", "controller": "pw-controller", "recorder": "pw-recorder"}


def test_default_config_is_peer_on_loopback_without_multicast():
    config = zenoh_config(BusSettings())
    assert json.loads(config.get_json("mode")) == "peer"
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    listen = json.loads(config.get_json("listen/endpoints"))
    connect = json.loads(config.get_json("connect/endpoints"))
    assert listen == ["tcp/127.0.0.1:0"] and connect == [DEFAULT_HUB]
    assert all(e.split("/")[1].startswith("127.0.0.1:") for e in listen + connect)


def _socket_inodes(pid: int) -> set[str]:
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    return inodes


def _sockets(pid: int) -> dict[str, list[tuple[str, str]]]:
    """The process's inet sockets by table: (local address hex, state hex)."""
    mine = _socket_inodes(pid)
    found: dict[str, list[tuple[str, str]]] = {}
    for table in ("tcp", "tcp6", "udp", "udp6"):
        for line in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            cols = line.split()
            if cols[9] in mine:
                found.setdefault(table, []).append((cols[1], cols[3]))
    return found


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc")
def test_live_node_listens_on_loopback_only_and_opens_no_udp_socket(hub, run_id):
    node = spawn("controller_node", "--controller", "pid", "--run-id", run_id, "--connect", hub)
    with NodeBus("hub", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        bus.wait_for_nodes(["controller"], StopFlag(), timeout_s=30)
        sockets = _sockets(node.pid)
        links = list(bus.session.info.links())
    node.send_signal(signal.SIGINT)
    finish(node)
    listening = [addr for addr, st in sockets.get("tcp", []) + sockets.get("tcp6", []) if st == "0A"]
    assert listening, sockets
    loopback = ("0100007F:", "00000000000000000000000001000000:")  # 127.0.0.1, ::1
    assert all(addr.startswith(loopback) for addr in listening), listening
    assert "udp" not in sockets and "udp6" not in sockets  # no multicast scouting socket
    assert links and all(str(link.src).startswith("tcp/127.0.0.1:") and str(link.dst).startswith("tcp/127.0.0.1:")
                         for link in links)
    assert all(list(link.interfaces) == ["lo"] for link in links)


def node_config(tmp_path: Path, user: str, password: str | None = None) -> Path:
    """The shipped ACL example for ``user``, with this test's credential dictionary."""
    creds = tmp_path / "credentials.txt"
    creds.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    text = ACL_FILE.read_text()
    text = text.replace('user: "controller"', f'user: "{user}"')
    text = text.replace('password: "change-me-controller"', f'password: "{password or PASSWORDS[user]}"')
    text = text.replace("/etc/meltloop/zenoh-credentials.txt", str(creds))
    path = tmp_path / f"{user}.json5"
    path.write_text(text)
    return path


def test_acl_only_the_controller_session_may_command(tmp_path, hub, run_id):
    controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.063", "--run-id", run_id,
                       "--connect", hub, "--zenoh-config", str(node_config(tmp_path, "controller")))
    plant_settings = BusSettings(run_id=run_id, connect=(), listen=(hub,), zenoh_config=node_config(tmp_path, "plant"))
    rogue_settings = BusSettings(run_id=run_id, connect=(hub,), listen=("tcp/127.0.0.1:0",),
                                 zenoh_config=node_config(tmp_path, "recorder"))  # valid credentials, wrong role
    with NodeBus("plant", plant_settings) as plant:
        commands, logs = plant.inbox(LASER_COMMAND), plant.inbox(LOG)
        plant.wait_for_nodes(["controller"], StopFlag(), timeout_s=30)
        plant.ready()
        states = plant.publisher(PLANT_STATE)
        with NodeBus("rogue", rogue_settings) as rogue:
            time.sleep(0.5)
            states.put(state(run_id, 0))
            first = commands.get(timeout=10)
            assert first is not None and first.step == 1, "the controller's command must pass the ACL"
            rogue.publisher(LASER_COMMAND).put(LaserCommand(run_id=run_id, step=2, time_s=0.0, power_w=123.0,
                                                            speed_mm_s=800.0, controller="rogue"))
            rogue.publisher(LOG).put(Log(timestamp=Timestamp.from_seconds(0.0), level=LogLevel.INFO,
                                         message="rogue connected", name="rogue"))
            states.put(state(run_id, 1))
            time.sleep(1.0)
            rest = list(commands.drain())
            rogue_logs = [m.message for m in logs.drain()]
    status, out = finish(controller)
    assert "rogue connected" in rogue_logs  # the rogue was connected: only the command was filtered
    assert [(c.step, c.controller) for c in rest] == [(2, "pid")]
    assert status == 0, out


def test_wrong_password_cannot_connect(tmp_path, hub, run_id):
    plant_settings = BusSettings(run_id=run_id, connect=(), listen=(hub,), zenoh_config=node_config(tmp_path, "plant"))
    rogue_settings = BusSettings(run_id=run_id, connect=(hub,), listen=("tcp/127.0.0.1:0",),
                                 zenoh_config=node_config(tmp_path, "controller", password="guess"))
    with NodeBus("plant", plant_settings) as plant, NodeBus("controller", rogue_settings) as rogue:
        commands = plant.inbox(LASER_COMMAND)
        time.sleep(0.5)
        rogue.publisher(LASER_COMMAND).put(LaserCommand(run_id=run_id, step=1, time_s=0.0, power_w=123.0,
                                                        speed_mm_s=800.0, controller="rogue"))
        assert commands.get(timeout=1.0) is None
        assert not list(plant.session.info.links())
