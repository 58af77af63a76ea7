"""The live node serves a running loop over the Foxglove WebSocket protocol: a real WebSocket
client subscribes, decodes the binary message frames and compares channels with the recorder's."""

from __future__ import annotations

import io
import json
import re
import socket
import struct
import threading
import time
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from messages import MeltPoolState, RawImage, Timestamp
from messages.bus import BusSettings, NodeBus, StopFlag
from messages.live import DropOldestQueue, RateGate
from messages.recorder import McapRecorder
from messages.topics import PLANT_STATE, PLANT_TEMPERATURE, RUN_EVENTS, TOPICS
from tests import forked_cli
from tests.conftest import finish, spawn
from tests.plants import BARE_ARGS

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # foxglove-sdk >= 0.x speaks the first
N_STATES = 400
RATE_HZ = 250.0


def recorder_channels(tmp_path: Path, run_id: str) -> dict[str, dict]:
    """The channels and schemas the MCAP recorder writes, read back from a file it made."""
    path = tmp_path / "channels.mcap"
    recorder = McapRecorder(path, run_id, path.open("wb"))
    recorder.finish({})
    summary = make_reader(io.BytesIO(path.read_bytes())).get_summary()
    return {ch.topic: {"encoding": ch.message_encoding, "schemaName": summary.schemas[ch.schema_id].name,
                       "schemaEncoding": summary.schemas[ch.schema_id].encoding,
                       "schema": summary.schemas[ch.schema_id].data.decode()}
            for ch in summary.channels.values()}


def state(run_id: str, step: int) -> MeltPoolState:
    return MeltPoolState(run_id=run_id, step=step, time_s=step * 50e-6, laser_x_mm=step * 0.04, laser_y_mm=0.0,
                         scan_dir_x=1.0, scan_dir_y=0.0, track=0, area_mm2=0.07, t_ahead_k=400.0, power_w=250.0,
                         speed_mm_s=800.0)


def image(step: int) -> RawImage:
    width, height = 32, 16
    return RawImage(timestamp=Timestamp.from_seconds(step * 50e-6), frame_id="top_surface", width=width,
                    height=height, encoding="rgb8", step=3 * width, data=bytes([step % 256]) * (3 * width * height))


def read_frames(ws, subs: dict[int, str], received: dict[str, list]) -> None:
    """Collect decoded binary MessageData frames (receipt time, log time, message) until the connection closes."""
    while True:
        try:
            frame = ws.recv(timeout=20)
        except (ConnectionClosed, TimeoutError):
            return
        if isinstance(frame, str):
            continue  # status or (un)advertise
        assert frame[0] == 0x01, "binary MessageData frame"
        sid, log_time = struct.unpack_from("<IQ", frame, 1)
        received[subs[sid]].append((time.monotonic(), log_time, json.loads(frame[13:])))


def serving_port(proc) -> int:
    """The port the live node prints once it is ready."""
    lines = []
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        lines.append(line)
        if found := re.search(r"serving run \S+ on ws://127\.0\.0\.1:(\d+)", line):
            return int(found.group(1))
        if not line and proc.poll() is not None:
            break
    raise AssertionError("live node never said where it serves:\n" + "".join(lines))


def test_client_receives_every_state_images_at_most_30_hz_and_the_recorders_channels(tmp_path, hub, run_id):
    expected = recorder_channels(tmp_path, run_id)
    stop = StopFlag()
    with NodeBus("tester", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as tester:
        events = tester.inbox(RUN_EVENTS)
        live = spawn("messages.live", "--run-id", run_id, "--connect", hub, "--port", "0", "--image-max-hz", "30")
        tester.wait_for_nodes(["live"], stop, timeout_s=20)
        port = serving_port(live)
        with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=10,
                     max_size=None) as ws:
            server_info = json.loads(ws.recv(timeout=5))
            assert server_info["op"] == "serverInfo"
            advertised = {}
            while len(advertised) < len(TOPICS):
                msg = json.loads(ws.recv(timeout=5))
                assert msg["op"] == "advertise"
                advertised.update({ch["topic"]: ch for ch in msg["channels"]})
            # the same channel names, schema names, schema bytes and encodings as the MCAP recording
            assert {t: {k: ch[k] for k in ("encoding", "schemaName", "schemaEncoding", "schema")}
                    for t, ch in advertised.items()} == expected
            subs = {1: PLANT_STATE.channel, 2: PLANT_TEMPERATURE.channel}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": sid, "channelId": advertised[topic]["id"]} for sid, topic in subs.items()]}))
            received: dict[str, list[tuple[float, int, dict]]] = {topic: [] for topic in subs.values()}
            reader = threading.Thread(target=read_frames, args=(ws, subs, received), daemon=True)
            reader.start()  # like Foxglove: read while the run goes on
            time.sleep(0.5)  # the subscription reaches the server before the plant starts

            with NodeBus("plant", BusSettings(run_id=run_id, connect=(hub,), listen=(), require=("live",))) as plant:
                states, images = plant.publisher(PLANT_STATE), plant.publisher(PLANT_TEMPERATURE)
                plant.ready(stop=stop)
                t0 = time.monotonic()
                for step in range(N_STATES):
                    states.put(state(run_id, step))
                    images.put(image(step))
                    time.sleep(1 / RATE_HZ)
                publish_s = time.monotonic() - t0
            reader.join(timeout=15)  # the live node closes the connection when it ends
        status, output = finish(live, timeout=15)
        end = [e for e in events.drain() if e.node == "live" and e.event == "end"]

    assert status == 0, output
    got_states = received[PLANT_STATE.channel]
    assert [m["step"] for _, _, m in got_states] == list(range(N_STATES)), output
    # log time = the message's process time, as in the recording
    assert all(log_time == round(m["time_s"] * 1e9) for _, log_time, m in got_states)
    state_schema, image_schema = (json.loads(expected[t]["schema"]) for t in subs.values())
    jsonschema.validate(got_states[-1][2], state_schema)
    got_images = received[PLANT_TEMPERATURE.channel]
    jsonschema.validate(got_images[-1][2], image_schema)
    assert all(log_time == m["timestamp"]["sec"] * 10**9 + m["timestamp"]["nsec"] for _, log_time, m in got_images)
    # images decimated to <= 30 Hz of wall clock while N_STATES arrived at RATE_HZ
    assert 2 <= len(got_images) <= 30 * publish_s + 2, (len(got_images), publish_s)
    assert len(got_images) < len(got_states)  # (N_STATES / publish_s is far above 30 Hz, however slow the host)
    assert end and "images decimated" in end[0].detail and "0 dropped" in end[0].detail, end
    assert "went away" in output


def test_port_in_use_is_a_one_line_usage_error(run_id, hub):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc = spawn("messages.live", "--run-id", run_id, "--connect", hub, "--port", str(port))
        status, output = finish(proc, timeout=20)
    assert status == 2, output
    assert output.count("\n") == 1 and "--port" in output and "in use" in output, output


def test_bad_options_are_usage_errors(run_id):
    run = forked_cli.run("-m", "messages.live", "--run-id", run_id, "--image-max-hz", "0")
    assert run.returncode == 2 and "--image-max-hz" in run.stderr, run.stderr


def test_queue_drops_oldest_and_counts():
    queue = DropOldestQueue(3)
    for i in range(5):
        queue.put(i)
    assert queue.dropped == 2
    assert queue.take_all(0) == [2, 3, 4]
    assert queue.dropped == 2 and queue.take_all(0.01) == []


def test_rate_gate_admits_at_most_one_per_period():
    now = [0.0]
    gate = RateGate(30.0, clock=lambda: now[0])
    admitted = 0
    for _ in range(1000):  # 1000 events over 1 s
        admitted += gate.admit()
        now[0] += 1e-3
    assert 29 <= admitted <= 30 and admitted + gate.n_skipped == 1000



def test_shipped_layout_uses_only_served_channels_and_fields():
    """Every plot path and the image topic of docs/foxglove-layout.json is a live channel and schema field."""
    from messages.codec import json_schema
    from messages.topics import PLANT_TEMPERATURE as IMAGES

    layout = json.loads((Path(__file__).resolve().parent.parent / "docs" / "foxglove-layout.json").read_text())
    channels = {t.channel: t for t in TOPICS.values()}
    paths = [p["value"] for panel in layout["configById"].values() for p in panel.get("paths", [])]
    assert paths
    for path in paths:
        channel, _, field = path.partition(".")
        assert channel in channels, path
        assert field.split("[")[0] in json_schema(channels[channel])["properties"], path
    images = [panel["imageMode"]["imageTopic"] for panel in layout["configById"].values() if "imageMode" in panel]
    assert images == [IMAGES.channel]
    scene_topics = {t for panel in layout["configById"].values() for t in panel.get("topics", {})}
    assert scene_topics == {"/plant/scene", "/plant/laser"} and scene_topics <= set(channels)


def test_launch_live_serves_the_default_nodes_run(tmp_path):
    """``launch.py --live PORT``: a client subscribed to /plant/state receives the run's states, in order, from
    its subscription to the last (150 steps: the client connects while the run goes on)."""
    import subprocess
    import sys

    from tests.conftest import REPO, free_endpoint

    port = int(free_endpoint().rsplit(":", 1)[1])
    out = tmp_path / "live.mcap"
    proc = subprocess.Popen([sys.executable, "launch.py", "--live", str(port), "--max-steps", "150", "--h-um", "40",
                             *BARE_ARGS, "--controller", "pid", "--out", str(out), "--no-progress"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    steps, statuses, started, subscribed_s = [], [], time.monotonic(), None
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"])
                break
            except OSError:
                time.sleep(0.05)
        with ws:
            channels = {}
            while "/plant/state" not in channels:
                frame = ws.recv(timeout=30)
                if isinstance(frame, str) and json.loads(frame).get("op") == "advertise":
                    channels |= {c["topic"]: c["id"] for c in json.loads(frame)["channels"]}
            subscription = {"id": 1, "channelId": channels["/plant/state"]}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [subscription]}))
            subscribed_s = time.monotonic() - started
            while True:
                try:
                    frame = ws.recv(timeout=30)
                except (ConnectionClosed, TimeoutError):
                    break
                if isinstance(frame, bytes) and frame[0] == 1:  # message data: op, subscription, log time, payload
                    steps.append(json.loads(frame[13:])["step"])
                elif isinstance(frame, str) and json.loads(frame).get("op") == "status":
                    statuses.append(json.loads(frame)["message"])
    finally:
        status, output = finish(proc, timeout=120)
    assert status == 0, output
    live = [line for line in output.splitlines() if line.startswith(("[live]", "[plant]"))]
    assert steps and steps == sorted(steps) and steps[-1] == 150, (steps[:5], steps[-5:], subscribed_s, statuses, live)


def test_with_a_token_only_a_client_that_gives_it_is_served(monkeypatch):
    """``MELTLOOP_LIVE_TOKEN``: a client must open ``ws://HOST:PORT/?token=TOKEN``; without it, or
    with another one, the upgrade is refused (HTTP 401) before any byte of the run is sent."""
    from websockets.exceptions import InvalidStatus

    from messages.live import LiveServer, LiveSettings

    server = LiveServer(LiveSettings(port=0, token="s3cret"), "token test")
    try:
        for url in (f"ws://127.0.0.1:{server.port}", f"ws://127.0.0.1:{server.port}/?token=guess"):
            with pytest.raises(InvalidStatus) as refused:
                connect(url, subprotocols=SUBPROTOCOLS, open_timeout=10)
            assert refused.value.response.status_code == 401
        with connect(f"ws://127.0.0.1:{server.port}/?token=s3cret", subprotocols=SUBPROTOCOLS,
                     open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=5))["op"] == "serverInfo"
    finally:
        server.stop()


def test_a_host_other_machines_can_reach_needs_a_token():
    from messages.cli import UsageError
    from messages.live import LiveSettings

    for host in ("0.0.0.0", "192.0.2.1", "viewer.example"):
        with pytest.raises(UsageError, match=f"--host {host}: other machines can reach the view, so it needs a token"):
            LiveSettings(host=host)
    assert LiveSettings(host="0.0.0.0", token="s3cret").host == "0.0.0.0"
    assert LiveSettings(host="::1").host == "::1"
