"""Hostile input within bounds: deeply nested JSON and MCAP files that declare huge sizes give a
one-line error (exit status 1 from the tools), never a RecursionError, MemoryError or traceback."""

from __future__ import annotations

import struct
import subprocess
import sys
import time

import msgspec
import pytest
from mcap.opcode import Opcode

from messages.codec import MessageError, decode, encode, loads
from messages.recorder import McapRecorder
from messages.recording import (
    _RECORD_HEAD,
    MAGIC,
    MAX_CHUNK_BYTES,
    RecordingLimitError,
    attachments,
    metadata,
    read_messages,
    read_recording,
)
from messages.topics import PLANT_SCENE, PLANT_STATE, RUN_EVENTS, Topic
from tests.conftest import REPO
from tests.samples import sample_messages
from tests.test_recorder_rules import RUN, event, state

DEEP = b"[" * 1200 + b"]" * 1200


def test_a_scene_nested_1200_deep_is_an_invalid_message():
    scene = encode(dict(sample_messages(RUN))[PLANT_SCENE])
    for nested in (b'[{"key":' + DEEP + b"}]", b"[" + DEEP + b"]"):
        payload = scene.replace(b'"deletions":[]', b'"deletions":' + nested)
        assert len(payload) < 4000
        with pytest.raises(MessageError, match="/plant/scene: "):
            decode(PLANT_SCENE, payload)


class Free(msgspec.Struct):
    anything: list[dict] = []


def test_decode_turns_a_recursion_into_a_message_error_and_loads_bounds_free_json():
    topic = Topic("test/free", Free, "test.Free", 64 * 1024)
    assert decode(topic, b'{"anything": [{"a": [1]}]}') == Free([{"a": [1]}])
    with pytest.raises(MessageError, match="test/free: nested too deeply"):
        decode(topic, b'{"anything": [{"a": ' + DEEP * 2 + b"}]}")
    with pytest.raises(MessageError, match="config: JSON nested too deeply"):
        loads(b"[" * 100_000 + b"]" * 100_000, "config")
    with pytest.raises(MessageError, match="exceed the"):
        loads(b" " * (2 * 1024 * 1024) + b"{}", "config")


def records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, offset, length) of a finished MCAP's top-level records."""
    found, offset = [], len(MAGIC)
    while offset < len(data) - len(MAGIC):
        opcode, length = _RECORD_HEAD.unpack_from(data, offset)
        found.append((opcode, offset, length))
        offset += _RECORD_HEAD.size + length
    return found


def recording(tmp_path, finished: bool = True):
    out = tmp_path / "run.mcap"
    recorder = McapRecorder(out, RUN, out.open("wb"))
    recorder.write(RUN_EVENTS, encode(event("plant", "start")), event("plant", "start"), time.time_ns())
    recorder.attach("config/plant.json", b"{}")
    for step in range(50):
        recorder.write(PLANT_STATE, encode(state(step)), state(step), time.time_ns())
    recorder.flush()
    if not finished:
        return out
    recorder.finish({"complete": "true"})
    return out


def patched(path, opcode: int, at: int, value: int, occurrence: int = 0):
    """``path`` with the u64 at byte ``at`` of the body of the ``occurrence``-th record ``opcode`` set to ``value``."""
    data = bytearray(path.read_bytes())
    _, offset, _ = [r for r in records(bytes(data)) if r[0] == opcode][occurrence]
    struct.pack_into("<Q", data, offset + _RECORD_HEAD.size + at, value)
    path.write_bytes(bytes(data))
    return path


HUGE = 2**62


def hostile_chunk(uncompressed_size: int) -> bytes:
    """A CHUNK record declaring ``uncompressed_size`` whose zstd frame does not say its size (the
    decompressor then allocates what the chunk declares)."""
    import zstandard

    frame = zstandard.ZstdCompressor(write_content_size=False).compress(b"\0" * 1000)
    body = struct.pack("<QQQII", 0, 0, uncompressed_size, 0, 4) + b"zstd" + struct.pack("<Q", len(frame)) + frame
    return _RECORD_HEAD.pack(Opcode.CHUNK, len(body)) + body


def with_hostile_chunk(tmp_path):
    """An unfinished recording (as of a killed recorder) whose last chunk declares 2^62 bytes."""
    path = recording(tmp_path, finished=False)
    path.write_bytes(path.read_bytes() + hostile_chunk(HUGE))
    return path


def test_a_chunk_declaring_2_62_bytes_uncompressed_is_refused(tmp_path):
    path = with_hostile_chunk(tmp_path)
    assert path.stat().st_size < 50_000  # a small file
    with pytest.raises(RecordingLimitError, match=f"declares {HUGE} bytes uncompressed, more than the "
                                                  f"{MAX_CHUNK_BYTES}-byte limit"):
        read_recording(path)
    with pytest.raises(RecordingLimitError):
        list(read_messages(path, PLANT_STATE))


def test_a_finished_file_whose_chunk_declares_2_62_bytes_is_refused(tmp_path):
    path = patched(recording(tmp_path), Opcode.CHUNK, 16, HUGE)
    with pytest.raises(RecordingLimitError, match="more than the"):
        list(read_messages(path, PLANT_STATE))
    with pytest.raises(RecordingLimitError, match="more than the"):
        read_recording(path)


def test_a_zstd_frame_larger_than_its_chunk_declares_is_refused(tmp_path):
    path = recording(tmp_path)
    data = bytearray(path.read_bytes())
    _, offset, _ = [r for r in records(bytes(data)) if r[0] == Opcode.CHUNK][0]
    frame_at = offset + _RECORD_HEAD.size + 28 + 4 + 4 + 8  # the chunk head, "zstd", the records' length
    import zstandard

    frame = zstandard.compress(b"\0" * (MAX_CHUNK_BYTES + 1))  # declares its content size
    data[frame_at:frame_at + len(frame)] = frame
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingLimitError, match="holds a zstd frame of"):
        read_recording(path)


@pytest.mark.parametrize("opcode, at, what", [
    (Opcode.CHUNK_INDEX, 16, "not at a CHUNK"),  # chunk_start_offset
    (Opcode.METADATA_INDEX, 0, "not at a METADATA"),
    (Opcode.ATTACHMENT_INDEX, 0, "not at a ATTACHMENT"),
    (Opcode.FOOTER, 0, "not at a record"),  # summary_start
])
def test_indexes_of_a_finished_file_must_point_at_their_records(tmp_path, opcode, at, what):
    path = recording(tmp_path)
    data = path.read_bytes()
    attachment = [r for r in records(data) if r[0] == Opcode.ATTACHMENT][0][1]
    patched(path, opcode, at, attachment + 1 if opcode == Opcode.FOOTER else
            attachment if opcode != Opcode.ATTACHMENT_INDEX else len(MAGIC))
    with pytest.raises(RecordingLimitError, match=what):
        metadata(path)
    with pytest.raises(RecordingLimitError):
        attachments(path)


def test_a_field_length_past_the_end_of_the_file_allocates_nothing(tmp_path):
    path = recording(tmp_path)
    data = bytearray(path.read_bytes())
    _, offset, _ = [r for r in records(bytes(data)) if r[0] == Opcode.ATTACHMENT][0]
    at = offset + _RECORD_HEAD.size + 16  # past log and create time: the name, the media type, the data
    for _ in range(2):
        at += 4 + struct.unpack_from("<I", data, at)[0]
    struct.pack_into("<Q", data, at, HUGE)  # the data's length
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="unreadable MCAP"):  # a RecordingError, not a MemoryError
        attachments(path)


@pytest.mark.parametrize("command", [
    ["-m", "controller_node.report", "{path}"],
    ["launch.py", "--report", "{path}"],
    ["-m", "messages.conformance", "{path}"],
    ["-m", "messages.recording", "recover", "{path}", "--out", "{out}"],
])
def test_the_tools_report_a_hostile_recording_in_one_line_with_status_1(tmp_path, command):
    path = with_hostile_chunk(tmp_path)
    args = [a.format(path=path, out=tmp_path / "fixed.mcap") for a in command]
    done = subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    assert "more than the" in done.stderr and done.stderr.count("\n") == 1, done.stderr
    assert "Traceback" not in done.stderr
