"""Resource bounds: the recorder's backlog and each node's log rate are bounded and their drops
counted; a message over its topic's limit is refused where it is published; a part too large for
the scene topic is simplified to fit."""

from __future__ import annotations

import io
import json
import time
from types import SimpleNamespace

import msgspec
import pytest

from fe_node.part import EXAMPLE_STL
from fe_node.scene import decimated_stl, fitted_scene, scene_update
from messages.bus import TopicPublisher
from messages.codec import MessageError, decode, encode
from messages.recorder import LOG_BURST, LOG_RATE_PER_S, QUEUED_OVERHEAD_BYTES, Arrivals
from messages.recording import metadata
from messages.topics import LOG, PLANT_SCENE, PLANT_STATE, RUN_EVENTS, key_expr
from tests.samples import sample_messages
from tests.test_recorder_rules import RUN, event, plant_run, run_recorder


def test_the_backlog_is_bounded_and_what_it_drops_is_counted():
    box = Arrivals(RUN, max_bytes=10 * (100 + QUEUED_OVERHEAD_BYTES))
    for k in range(15):
        box.put(key_expr(RUN, PLANT_STATE), bytes(100), k)
    assert [item[2] for item in box.take(0.0)] == list(range(10))
    assert box.take_dropped() == {("queue_full", ""): 5} and box.take_dropped() == {}
    box.put(key_expr(RUN, PLANT_STATE), bytes(100), 99)  # room again once taken
    assert len(box.take(0.0)) == 1


def test_each_node_has_its_own_log_rate():
    now = [0.0]
    box = Arrivals(RUN, clock=lambda: now[0])
    for _ in range(3 * LOG_BURST):
        box.put(key_expr(RUN, LOG, "evil"), b"{}", 0)
    box.put(key_expr(RUN, LOG, "plant"), b"{}", 0)
    box.put(key_expr(RUN, PLANT_STATE), b"{}", 0)  # other topics have no rate
    taken = box.take(0.0)
    assert len(taken) == LOG_BURST + 2 and taken[-2][0].endswith("/log/plant")
    assert box.take_dropped() == {("log_rate", "evil"): 2 * LOG_BURST}
    now[0] += 10 / LOG_RATE_PER_S  # the bucket refills: 10 more
    for _ in range(20):
        box.put(key_expr(RUN, LOG, "evil"), b"{}", 0)
    assert len(box.take(0.0)) == 10


def test_a_log_flood_of_one_node_is_dropped_and_counted_and_the_plant_still_reconciles(tmp_path):
    line = msgspec.structs.replace(dict(sample_messages(RUN))[LOG], name="evil", message="x" * 8000)
    n = 2 * LOG_BURST

    def forge(bus, step):
        if step == 0:
            bus.send(RUN_EVENTS, event("evil", "start"))
            for _ in range(n):
                bus.send(LOG, line)
            bus.send(RUN_EVENTS, event("evil", "end", {"run/events": 2, "log": n}))
            time.sleep(0.05)
            bus.leave("evil")

    status, out = run_recorder(tmp_path, plant_run(20, forge))
    counts = metadata(out)["meltloop.counts"]
    dropped = json.loads(counts["dropped"])
    assert dropped["log_rate"] > 0, dropped  # (fewer than n - LOG_BURST: the bucket refills while the flood is sent)
    assert json.loads(counts["missing"]) == {"log/evil": dropped["log_rate"]}  # only its own key
    assert counts["complete"] == "false" and status == 1


class FakePublisher:
    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.sent.append(payload)


def test_a_message_over_its_topic_limit_is_refused_by_the_publisher():
    bus = SimpleNamespace(max_payload_bytes=float("inf"), published={})
    zenoh_pub = FakePublisher()
    pub = TopicPublisher(bus, LOG, zenoh_pub)
    line = dict(sample_messages(RUN))[LOG]
    pub.put(line)
    with pytest.raises(MessageError, match=r"/log: a \d+-byte message exceeds the topic's 32768-byte limit"):
        pub.put(msgspec.structs.replace(line, message="\x01" * 8000))  # 8000 characters, 6 bytes each in JSON
    assert len(zenoh_pub.sent) == 1 and bus.published == {"log": 1}


OBS = SimpleNamespace(time_s=0.0, z_top_m=50e-6, layer=0)
PLAN = SimpleNamespace(tracks=[[(-1e-3, k * 1e-4), (1e-3, k * 1e-4)] for k in range(-10, 10)])


def test_a_part_too_large_for_the_scene_topic_is_decimated_to_fit(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    big = tmp_path / "sphere.stl"
    trimesh.creation.icosphere(subdivisions=6, radius=2.0).export(big)  # mm; 81,920 triangles, 4 MB
    assert len(encode(scene_update(PLAN, OBS, big))) > PLANT_SCENE.max_bytes  # what every receiver dropped
    scene, notes = fitted_scene(PLAN, OBS, big)
    payload = encode(scene)
    assert len(payload) <= PLANT_SCENE.max_bytes
    model = decode(PLANT_SCENE, payload).entities[1].models[0]
    mesh = trimesh.load(io.BytesIO(model.data), file_type="stl")
    assert 10_000 < len(mesh.faces) < 81_920
    assert mesh.bounds.ravel() == pytest.approx([-2.0] * 3 + [2.0] * 3, abs=0.05)
    assert len(notes) == 1 and f"part sphere.stl ({big.stat().st_size} bytes) decimated to {len(mesh.faces)} " \
                               "triangles" in notes[0]
    for n in (100, 1):  # down to one triangle, or none: a cell larger than the mesh leaves nothing
        assert len(decimated_stl(mesh.vertices, mesh.faces, n)) <= 84 + 50 * n


def test_a_part_that_fits_is_embedded_as_it_is_and_too_many_tracks_are_thinned():
    pytest.importorskip("trimesh")
    scene, notes = fitted_scene(PLAN, OBS, EXAMPLE_STL)
    assert notes == [] and scene.entities[1].models[0].data == EXAMPLE_STL.read_bytes()
    many = SimpleNamespace(tracks=[[(-1e-3, k * 1e-6), (1e-3, k * 1e-6)] for k in range(2000)])
    scene, notes = fitted_scene(many, OBS, max_bytes=64 * 1024)
    assert len(encode(scene)) <= 64 * 1024 and 0 < len(scene.entities[0].lines[0].points) < 2 * 2000
    assert len(notes) == 1 and "of its 2000 tracks drawn" in notes[0]
