"""Recordings that cannot be lost: chunks reach disk every period, write errors end the recorder in
one line with the data kept, a truncated file reads and recovers into an MCAP the seeking reader opens."""

from __future__ import annotations

import errno
import io
import json
import os
import signal
import stat
import time

import pytest
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.writer import Writer

from messages import recorder as recorder_module
from messages.bus import BusSettings, NodeBus, StopFlag
from messages.codec import encode
from messages.recorder import FLUSH_PERIOD_S, McapRecorder, RunTracker, record
from messages.recording import (
    _RECORD_HEAD,
    MAGIC,
    attachments,
    is_complete,
    metadata,
    read_messages,
    read_recording,
    recover,
)
from messages.topics import PLANT_STATE, RUN_EVENTS
from tests import forked_cli
from tests.conftest import finish, spawn
from tests.plants import BARE_ARGS
from tests.test_recorder_rules import RUN, FakeBus, FakeStop, event, plant_run, state


class CountingStream(io.BytesIO):
    """An in-memory stream that counts its flushes."""

    flushes = 0

    def flush(self) -> None:
        self.flushes += 1
        super().flush()


class FullDisk:
    """A file whose device fills up after ``budget`` bytes: the write that crosses it raises ENOSPC."""

    def __init__(self, stream, budget: int) -> None:
        self._stream, self._budget = stream, budget

    def write(self, data: bytes) -> int:
        if self._stream.tell() + len(data) > self._budget:
            raise OSError(errno.ENOSPC, "No space left on device")
        return self._stream.write(data)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def test_mcap_writer_flush_ends_the_chunk_and_flushes_the_stream(tmp_path):
    """What :meth:`McapRecorder.flush` relies on; fails if the ``mcap`` package changes it."""
    stream = CountingStream()
    writer = Writer(stream)
    writer.start()
    channel = writer.register_channel("/a", "json", writer.register_schema("s", "jsonschema", b"{}"))
    writer.add_message(channel, log_time=1, data=b"{}", publish_time=1)
    path = tmp_path / "x.mcap"
    path.write_bytes(stream.getvalue())
    assert read_recording(path).messages == []  # still in the open chunk
    writer.flush()
    assert stream.flushes >= 1
    path.write_bytes(stream.getvalue())
    read = read_recording(path)
    assert read.truncated and len(read.messages) == 1 and read.channels[channel].topic == "/a"


def test_recorder_puts_data_on_disk_every_period_while_running(tmp_path):
    """Read the file from outside while the recorder runs: what arrived a period ago is there."""
    seen = {}
    out = tmp_path / "live.mcap"

    def script(bus):
        bus.send(RUN_EVENTS, event("plant", "start"))
        for step in range(5):
            bus.send(PLANT_STATE, state(step))
        time.sleep(FLUSH_PERIOD_S + 0.3)  # idle: the idle tick flushes
        seen["idle"] = [s.step for s in read_messages(out, PLANT_STATE)]
        t0 = time.monotonic()
        step = 5
        while time.monotonic() - t0 < 2.5 * FLUSH_PERIOD_S:  # busy: flushes keep coming
            bus.send(PLANT_STATE, state(step))
            step += 1
            time.sleep(0.01)
        seen["busy"] = len(list(read_messages(out, PLANT_STATE)))
        seen["sent"] = step
        bus.send(RUN_EVENTS, event("plant", "end", {"plant/state": step, "run/events": 2}))
        bus.leave("plant")

    recorder, stop = McapRecorder(out, RUN, out.open("wb")), FakeStop()
    assert record(recorder, FakeBus(script, stop), stop, RunTracker(("plant",), 0.3), 0.3, {}) == 0
    assert stop.signal_name is None
    assert seen["idle"] == [0, 1, 2, 3, 4]
    assert seen["busy"] >= seen["sent"] - FLUSH_PERIOD_S / 0.01 - 5, seen


def test_full_disk_ends_the_recorder_in_one_line_with_the_data_kept(tmp_path, capsys):
    out = tmp_path / "full.mcap"
    stream = FullDisk(out.open("wb"), budget=60_000)

    def script(bus):
        plant_run(100_000)(bus)  # more than fits

    recorder, stop = McapRecorder(out, RUN, stream), FakeStop()
    status = record(recorder, FakeBus(script, stop), stop, RunTracker(("plant",), 0.3), 0.3, {})
    err = capsys.readouterr().err
    assert status == 1
    assert err == f"error: cannot write {out}: No space left on device\n"
    kept = read_recording(out)
    assert kept.truncated and len(kept.messages) > 10
    steps = [s.step for s in kept.decoded(PLANT_STATE)]
    assert steps == list(range(len(steps)))
    recover(out, tmp_path / "fixed.mcap")
    assert [s.step for s in read_messages(tmp_path / "fixed.mcap", PLANT_STATE)] == steps


def test_unwritable_output_folder_is_a_usage_error_naming_out(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert recorder_module.main(["--out", str(blocker / "run.mcap")]) == 2
    line = capsys.readouterr().err
    assert line.count("\n") == 1 and f"--out {blocker / 'run.mcap'}: cannot write" in line
    try:
        open("/sys/meltloop-test.mcap", "wb").close()
    except OSError:
        assert recorder_module.main(["--out", "/sys/meltloop-test.mcap"]) == 2
        assert "--out /sys/meltloop-test.mcap: cannot write: " in capsys.readouterr().err


def truncated_recording(tmp_path):
    """A recording cut in its last chunk, with an attachment; returns (path, steps in complete chunks)."""
    out = tmp_path / "cut.mcap"
    recorder = McapRecorder(out, RUN, out.open("wb"))
    msg = event("plant", "start")
    recorder.write(RUN_EVENTS, encode(msg), msg, time.time_ns())
    recorder.attach("config/plant.json", b'{"h_um": 40}')
    for step in range(30):
        recorder.write(PLANT_STATE, encode(state(step)), state(step), time.time_ns())
    recorder.flush()
    on_disk = out.stat().st_size
    for step in range(30, 40):
        recorder.write(PLANT_STATE, encode(state(step)), state(step), time.time_ns())
    recorder.flush()
    out.write_bytes(out.read_bytes()[:on_disk + 40])  # killed while writing the second chunk
    return out, list(range(30))


def test_truncated_file_reads_its_complete_chunks_and_says_so(tmp_path):
    path, steps = truncated_recording(tmp_path)
    read = read_recording(path)
    assert read.truncated and "truncated recording" in read.detail and "ends inside a CHUNK record" in read.detail
    assert [s.step for s in read_messages(path, PLANT_STATE)] == steps
    assert metadata(path)["meltloop"]["run_id"] == RUN
    assert attachments(path) == {"config/plant.json": b'{"h_um": 40}'}


def run_recover(*args):
    return forked_cli.run("-m", "messages.recording", "recover", *args)


def test_recover_writes_an_mcap_the_seeking_reader_opens(tmp_path):
    path, steps = truncated_recording(tmp_path)
    fixed = tmp_path / "fixed.mcap"
    done = run_recover(str(path), "--out", str(fixed))
    assert done.returncode == 0, done.stderr
    with fixed.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == len(steps) + 1
        topics = [channel.topic for _s, channel, _m in reader.iter_messages()]
    assert topics.count("/plant/state") == len(steps)
    counts = metadata(fixed)["meltloop.counts"]
    assert counts["complete"] == "false" and counts["stopped_by"] == "recovered"
    assert json.loads(counts["recorded"]) == {"plant/state": 30, "run/events": 1}
    assert not read_recording(fixed).truncated and read_recording(fixed).detail == ""
    assert metadata(fixed)["meltloop"]["run_id"] == RUN
    assert attachments(fixed) == {"config/plant.json": b'{"h_um": 40}'}


@pytest.mark.parametrize("case, status, text", [
    ("missing", 2, "recording not found"),
    ("not-mcap", 2, "not an MCAP file"),
    ("header-only", 1, "nothing recoverable"),
    ("no-out", 2, "required: --out"),
])
def test_recover_errors_are_one_line(tmp_path, case, status, text):
    path = tmp_path / "in.mcap"
    if case == "not-mcap":
        path.write_text("hello\n")
    if case == "header-only":
        path.write_bytes(truncated_recording(tmp_path)[0].read_bytes()[:200])
    args = [str(path)] if case == "no-out" else [str(path), "--out", str(tmp_path / "out.mcap")]
    done = run_recover(*args)
    assert done.returncode == status, done.stderr
    assert text in done.stderr and done.stderr.count("\n") == 1 and "Traceback" not in done.stderr


def test_recorder_killed_loses_at_most_a_second(tmp_path, hub, run_id):
    """SIGKILL the recorder of a real run after >= 2 s of recording; the recovered file holds the
    states received up to within 1 s (recorder wall clock) of the kill."""
    out = tmp_path / "killed.mcap"
    common = ("--run-id", run_id, "--connect", hub)
    with NodeBus("observer", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        states = bus.inbox(PLANT_STATE)
        recorder = spawn("messages.recorder", "--out", str(out), "--expect", "plant", *common)
        bus.wait_for_nodes(["recorder"], StopFlag(), timeout_s=60)
        plant = spawn("fe_node", "--h-um", "40", *BARE_ARGS, "--open-loop", "--max-steps", "3000", "--require",
                      "recorder", "--image-every", "100000", *common)  # no images: chunks would fill up without a flush
        assert states.get(timeout=60) is not None, "plant did not start stepping"
        time.sleep(2.5)
        recorder.send_signal(signal.SIGKILL)
        killed_ns = time.time_ns()
        plant.send_signal(signal.SIGINT)
        finish(plant, timeout=30)
        finish(recorder, timeout=10)
    fixed = tmp_path / "fixed.mcap"
    done = run_recover(str(out), "--out", str(fixed))
    assert done.returncode == 0, done.stderr
    with fixed.open("rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None
        last = max(m.publish_time for _s, c, m in reader.iter_messages() if c.topic == "/plant/state")
    assert killed_ns - last < 1e9, f"last recovered state {(killed_ns - last) / 1e9:.2f} s before the kill"
    steps = [s.step for s in read_messages(fixed, PLANT_STATE)]
    assert len(steps) >= 10 and steps == list(range(len(steps)))


def test_runs_started_in_the_same_second_get_their_own_recording(tmp_path, monkeypatch):
    """Default names are stamped to the second: a second run then gets ``-2``, a folder too, never
    the first run's file (two launches in one second wrote one MCAP, unreadable, before)."""
    from messages.launch.service import new_recording

    first, second = new_recording(tmp_path / "run.mcap"), new_recording(tmp_path / "run.mcap")
    assert (first.name, second.name) == ("run.mcap", "run-2.mcap") and first.exists() and second.exists()
    assert new_recording(tmp_path / "cmp").name == "cmp" and new_recording(tmp_path / "cmp").name == "cmp-2"
    monkeypatch.chdir(tmp_path)
    names = {recorder_module.default_path("r").name for _ in range(3)}
    assert len(names) == 3


def test_completeness_is_written_after_the_last_message_and_a_cut_file_is_never_complete(tmp_path):
    out = tmp_path / "cut.mcap"
    recorder = McapRecorder(out, RUN, out.open("wb"))
    for step in range(2000):
        recorder.write(PLANT_STATE, encode(state(step)), state(step), time.time_ns())
    recorder.finish({"complete": "true"})
    data = out.read_bytes()
    records, offset = [], len(MAGIC)
    while offset < len(data) - len(MAGIC):
        opcode, length = _RECORD_HEAD.unpack_from(data, offset)
        offset += _RECORD_HEAD.size + length
        records.append((Opcode(opcode), offset))
    counts_end = next(end for opcode, end in records
                      if opcode == Opcode.METADATA and b"meltloop.counts" in data[end - 200:end])
    assert max(end for opcode, end in records if opcode == Opcode.CHUNK) < counts_end
    assert is_complete(out)
    out.write_bytes(data[:counts_end])  # cut right after the completeness record
    assert len(list(read_messages(out, PLANT_STATE))) == 2000 and not is_complete(out)
    for opcode, end in records:  # and anywhere before it
        if opcode == Opcode.CHUNK:
            out.write_bytes(data[:end])
            assert not is_complete(out)


def test_the_periodic_flush_fsyncs_the_file_and_no_message_does(tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr(recorder_module.os, "fsync", synced.append)
    out = tmp_path / "sync.mcap"
    stream = out.open("wb")
    recorder = McapRecorder(out, RUN, stream)
    assert synced == [stream.fileno()]  # the header, once
    for step in range(100):
        recorder.write(PLANT_STATE, encode(state(step)), state(step), time.time_ns())
    assert len(synced) == 1
    recorder.flush_due(time.monotonic() + FLUSH_PERIOD_S)
    assert synced == [stream.fileno()] * 2
    recorder.finish({"complete": "true"})
    assert len(synced) == 3  # and once when finished
    memory = McapRecorder(out, RUN, io.BytesIO())  # a stream without a file descriptor is only flushed
    memory.flush()
    assert len(synced) == 3


def test_a_recorder_killed_before_its_first_periodic_flush_leaves_a_readable_recording(tmp_path):
    """The header, the channels and the run's metadata are on disk as soon as the recorder exists: a
    recorder killed at once (never flushed again, never finished) leaves a recording that reads, with its
    run id and no messages, not an empty file (which ``launch.py`` removes as never written)."""
    out = tmp_path / "killed.mcap"
    stream = out.open("wb")
    McapRecorder(out, RUN, stream)             # then nothing: the process is gone
    recording = read_recording(out)
    assert recording.truncated and list(read_messages(out, "/plant/state")) == []
    assert metadata(out)["meltloop"]["run_id"] == RUN and not is_complete(out)
    stream.close()


def test_recordings_are_created_0600_whatever_the_umask(tmp_path):
    from messages.launch.service import new_recording, reserve_recording

    old = os.umask(0)
    try:
        made = [recorder_module.open_output(tmp_path / "a.mcap", overwrite=False), new_recording(tmp_path / "b.mcap"),
                reserve_recording(tmp_path / "c.mcap", overwrite=False)]
        (tmp_path / "d.mcap").write_bytes(b"old")
        os.chmod(tmp_path / "d.mcap", 0o666)
        made.append(recorder_module.open_output(tmp_path / "d.mcap", overwrite=True))
        path, _ = truncated_recording(tmp_path)
        recover(path, tmp_path / "e.mcap")
    finally:
        os.umask(old)
    for name in "abcde":
        assert stat.S_IMODE((tmp_path / f"{name}.mcap").stat().st_mode) == 0o600, name
    assert (tmp_path / "d.mcap").stat().st_size == 0


@pytest.mark.parametrize("command", [
    ["-m", "messages.recorder", "--out", "{out}"],
    ["launch.py", "--out", "{out}"],
    ["launch.py", "--compare", "--out", "{folder}"],
    ["-m", "messages.recording", "recover", "{other}", "--out", "{out}"],
])
def test_out_refuses_an_existing_recording_without_overwrite(tmp_path, command):
    out = tmp_path / "layer-pid.mcap"
    out.write_bytes(b"a recording")
    other = tmp_path / "other.mcap"
    other.write_bytes(MAGIC)
    args = [a.format(out=out, folder=tmp_path, other=other) for a in command]
    done = forked_cli.run(*args)
    assert done.returncode == 2, done.stderr
    assert f"--out {out}: exists; give --overwrite to replace it" in done.stderr
    assert done.stderr.count("\n") == 1 and out.read_bytes() == b"a recording"

