"""Security defaults and the example access-control configuration, with real sessions."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from pathlib import Path

import msgspec
import pytest

from messages import LaserCommand, LogLevel, RunEvent, encode
from messages.auth import PASSWORD_ENV, USER_ENV, RunCredentials
from messages.bus import DEFAULT_HUB, BusSettings, NodeBus, StopFlag, zenoh_config
from messages.topics import LASER_COMMAND, LOG, PLANT_STATE, RUN_EVENTS, key_expr, liveliness_key, run_prefix
from tests.conftest import finish, spawn
from tests.test_controller_node import state


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


def _hub(credentials: RunCredentials, endpoint: str):
    """The run's authenticating hub, as launch.py opens it."""
    import zenoh

    from messages.hub import router_config

    return zenoh.open(router_config(credentials, endpoint))


def _node(monkeypatch, credentials: RunCredentials, name: str, endpoint: str, password: str | None = None) -> NodeBus:
    monkeypatch.setenv(USER_ENV, name)
    monkeypatch.setenv(PASSWORD_ENV, password or credentials.passwords[name])
    return NodeBus(name, BusSettings(run_id=credentials.run_id, connect=(endpoint,)))


ROLES = {"plant": ("plant",), "controller": ("controller",), "recorder": ("recorder",), "probe": ()}


def test_generated_access_control_lets_each_node_publish_only_its_own_keys(monkeypatch, hub, run_id):
    with RunCredentials(run_id, ROLES) as creds, _hub(creds, hub):
        with _node(monkeypatch, creds, "plant", hub) as plant, _node(monkeypatch, creds, "controller", hub) as ctl, \
                _node(monkeypatch, creds, "recorder", hub) as rec, _node(monkeypatch, creds, "probe", hub) as probe:
            commands, events, logs, states = rec.inbox(LASER_COMMAND), rec.inbox(RUN_EVENTS), rec.inbox(LOG), \
                rec.inbox(PLANT_STATE)
            plant_commands = plant.inbox(LASER_COMMAND)
            assert plant.routed and ctl.routed  # clients: every message crosses the hub
            gone = plant.watch_presence("controller")
            time.sleep(0.5)
            command = LaserCommand(run_id=run_id, step=1, time_s=0.0, power_w=200.0, speed_mm_s=800.0, controller="pid")
            ctl.publisher(LASER_COMMAND).put(command)
            probe.publisher(LASER_COMMAND).put(msgspec.structs.replace(command, power_w=123.0))  # no role
            probe.publisher(PLANT_STATE).put(state(run_id, 0))  # no role
            rec.publisher(PLANT_STATE).put(state(run_id, 1))  # reads everything, publishes no topic
            probe.log(LogLevel.INFO, "probe connected")  # its own log: allowed
            forged_end = RunEvent(run_id=run_id, node="plant", event="end", time_s=0.0)
            probe.session.put(key_expr(run_id, RUN_EVENTS, "plant"), encode(forged_end))  # another node's key
            token = probe.session.liveliness().declare_token(liveliness_key(run_id, "controller"))
            time.sleep(1.0)
            received = [c.power_w for c in commands.drain()]
            applied = [c.power_w for c in plant_commands.drain()]
            seen_events = [(e.node, e.event) for e in events.drain()]
            seen_logs = [(m.name, m.message) for m in logs.drain()]
            seen_states = [s.step for s in states.drain()]
            token.undeclare()
    assert received == applied == [200.0]
    assert ("plant", "end") not in seen_events
    assert ("probe", "probe connected") in seen_logs  # connected: only the forgeries were filtered
    assert seen_states == [1]  # the recorder's own, delivered in its session; nothing crossed the hub
    assert not gone.is_set()


def test_each_node_receives_only_what_its_role_reads(monkeypatch, hub, run_id):
    """The plant receives the commands, the controller the plant state and run events, the
    recorder everything, a node without a role nothing but liveliness; no queryable is served."""
    topics = (PLANT_STATE, LASER_COMMAND, RUN_EVENTS, LOG)
    with RunCredentials(run_id, ROLES) as creds, _hub(creds, hub):
        with contextlib.ExitStack() as stack:
            buses = {name: stack.enter_context(_node(monkeypatch, creds, name, hub)) for name in ROLES}
            boxes = {name: {t.suffix: bus.inbox(t) for t in topics} for name, bus in buses.items()}
            everything: dict[str, list[str]] = {name: [] for name in buses}
            for name, bus in buses.items():
                bus.subscribe_raw(run_prefix(run_id), lambda s, seen=everything[name]: seen.append(str(s.key_expr)))
            queryable = buses["probe"].session.declare_queryable(
                key_expr(run_id, PLANT_STATE), lambda query: query.reply(query.key_expr, b"forged"))
            presence = buses["probe"].watch_presence("plant")
            time.sleep(0.5)     # the subscriptions reach the hub before the plant's start event is sent
            buses["plant"].ready()
            buses["probe"].wait_for_nodes(["plant"], StopFlag(), timeout_s=10)  # liveliness: everyone
            time.sleep(0.5)
            buses["plant"].publisher(PLANT_STATE).put(state(run_id, 0))
            buses["plant"].log(LogLevel.INFO, "plant log")
            buses["controller"].publisher(LASER_COMMAND).put(
                LaserCommand(run_id=run_id, step=1, time_s=0.0, power_w=200.0, speed_mm_s=800.0, controller="pid"))
            time.sleep(1.0)
            replies = list(buses["controller"].session.get(key_expr(run_id, PLANT_STATE), timeout=1.0))
            from_others = {
                name: sorted(suffix for suffix, box in named.items() for msg in box.drain()
                             if getattr(msg, "node", getattr(msg, "name", None)) != name
                             and not (suffix == PLANT_STATE.suffix and name == "plant")
                             and not (suffix == LASER_COMMAND.suffix and name == "controller"))
                for name, named in boxes.items()}
            queryable.undeclare()
            buses["plant"].__exit__(None, None, None)
            time.sleep(0.5)
            assert presence.is_set()
    assert from_others == {
        "plant": ["controller/command"],
        "controller": ["plant/state", "run/events"],
        "recorder": ["controller/command", "log", "plant/state", "run/events"],
        "probe": [],
    }
    assert not [key for key in everything["probe"] if not key.endswith("/probe")]  # only its own
    suffixes = {key.removeprefix(f"meltloop/{run_id}/") for key in everything["recorder"]}
    assert {"plant/state", "controller/command", "log/plant", "run/events/plant"} <= suffixes
    assert replies == []


def test_wrong_or_missing_credentials_get_no_session(monkeypatch, hub, run_id, capsys):
    with RunCredentials(run_id, ROLES) as creds, _hub(creds, hub):
        with pytest.raises(ConnectionError, match="refused or unreachable"):
            with _node(monkeypatch, creds, "controller", hub, password="guess"):
                pass
        monkeypatch.delenv(USER_ENV)
        monkeypatch.delenv(PASSWORD_ENV)
        bus = NodeBus("rogue", BusSettings(run_id=run_id, connect=(hub,), listen=("tcp/127.0.0.1:0",)))
        with bus:
            assert not list(bus.session.info.peers_zid()) and not list(bus.session.info.routers_zid())
    assert "this zenoh session is unauthenticated" in capsys.readouterr().out


def test_run_credentials_are_private_and_removed():
    with RunCredentials("r", ROLES) as creds:
        folder = creds.folder
        assert oct(folder.stat().st_mode & 0o777) == "0o700"
        assert oct(creds.dictionary_file.stat().st_mode & 0o777) == "0o600"
        assert len({*creds.passwords.values()}) == len(ROLES)
        assert creds.env("plant") == {USER_ENV: "plant", PASSWORD_ENV: creds.passwords["plant"]}
    assert not folder.exists()


def test_launch_gives_credentials_by_environment_never_argv(tmp_path):
    from messages.launch.node import NodeProcess, NodeSpec

    lines = []
    node = NodeProcess.spawn(NodeSpec("probe", "tests.nodes.ticker", ("--steps", "1")), "r", "tcp/127.0.0.1:9",
                             {USER_ENV: "probe", PASSWORD_ENV: "s3cret"}, lines.append, lines.append)
    argv = " ".join(node.process.args)
    node.stop()
    assert "s3cret" not in argv and "s3cret" not in " ".join(lines)


def test_the_credentials_of_a_killed_run_are_removed_at_the_next_start(tmp_path, monkeypatch):
    """A run killed with SIGKILL leaves its folder; the next run removes it, but not a running run's."""
    import subprocess
    import sys
    import tempfile

    from messages.auth import FOLDER_PREFIX

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f"{FOLDER_PREFIX}{int(dead.stdout)}-abc123"
    alive = tmp_path / f"{FOLDER_PREFIX}{os.getppid()}-def456"
    for folder in (stale, alive):
        folder.mkdir(mode=0o700)
        (folder / "credentials.txt").write_text("plant:secret\n")
    with RunCredentials("r", ROLES) as creds:
        assert creds.folder.parent == tmp_path and creds.folder.name.startswith(f"{FOLDER_PREFIX}{os.getpid()}-")
        assert not stale.exists()
        assert (alive / "credentials.txt").exists()
    assert sorted(tmp_path.iterdir()) == [alive]


def test_no_hop_passes_a_large_message_through_shared_memory(monkeypatch, tmp_path, hub, run_id):
    """A 40 kB payload (a temperature image's size) from the plant to the recorder through the run's
    hub travels over the sockets: no zenoh shared-memory segment is mapped into this process, which
    holds both nodes and the hub (with zenoh's default one is, and a receiver descheduled at the
    wrong moment loses the message silently: messages.bus.SHARED_MEMORY). The configurations the
    hub writes for other nodes keep it off too."""

    from messages.hub import write_node_configs
    from messages.topics import PLANT_TEMPERATURE

    received = []
    key = key_expr(run_id, PLANT_TEMPERATURE, "plant")
    with RunCredentials(run_id, ROLES) as creds, _hub(creds, hub):
        with _node(monkeypatch, creds, "plant", hub) as plant, _node(monkeypatch, creds, "recorder", hub) as rec:
            rec.session.declare_subscriber(key, lambda s: received.append(len(s.payload.to_bytes())))
            deadline = time.monotonic() + 10
            while not received and time.monotonic() < deadline:
                plant.session.put(key, bytes(40_000))
                time.sleep(0.1)
            with open("/proc/self/maps") as maps:
                shared = [line for line in maps if line.rstrip().endswith(".zenoh")]
        paths = write_node_configs(creds, hub, tmp_path, None)
    assert received and received[0] == 40_000
    assert shared == []
    assert all(json.loads(p.read_text())["transport"]["shared_memory"]["enabled"] is False for p in paths)
