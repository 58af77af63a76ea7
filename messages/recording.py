"""Reading meltloop recordings back: validated messages per channel, metadata, completeness.

Used by the GP dataset builder, the report and the tests, so that everything downstream of a
run depends on the message contract only — a recording from a hardware node reads the same.

A finished file is read through its summary (``mcap``'s seeking reader). A file the recorder
never finished (killed, disk full: no footer) is read record by record up to the last complete
one: :func:`read_messages`, :func:`metadata` and :func:`attachments` then return what its
complete chunks hold, and :func:`read_recording` says so (``truncated``, ``detail``).

``python -m messages.recording recover FILE --out FIXED.mcap`` writes such a file's schemas,
channels, metadata, attachments and every message of its complete chunks into a finished MCAP,
with ``meltloop.counts`` saying ``complete = "false"``, ``stopped_by = "recovered"``; an
existing ``--out`` only with ``--overwrite``. Exit status 2 for a bad command line, a missing
file or one that is not MCAP; 1 if nothing is recoverable or the output cannot be written.

Recordings are created with mode :data:`RECORDING_MODE` (0600, whatever the umask): they hold
every node's configuration.

Any file is read within bounds: no record may extend past the end of the file, no read
allocates more than the file holds, a chunk may declare at most :data:`MAX_CHUNK_BYTES`
uncompressed (zstd or none), and the indexes of a finished file must point at records of their
kind. A file that breaks a bound raises :class:`RecordingLimitError` (one line), which the
command-line tools report with exit status 1.
"""

from __future__ import annotations

import json
import os
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Footer, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from messages.cli import ArgumentParser, UsageError, exit_error, exit_usage, run_main
from messages.codec import MessageError, decode, loads
from messages.topics import TOPICS, Topic

MAGIC = b"\x89MCAP0\r\n"
MAX_CHUNK_BYTES = 64 * 1024 * 1024
"""Largest uncompressed chunk a recording may declare [bytes], the reader's allocation bound (the
recorder's chunks hold about 1 MiB and at most one message more, which is at most 4 MiB)."""
_CHUNK_HEAD = struct.Struct("<QQQII")  # message start and end time, uncompressed size and CRC, compression length
RECORDING_MODE = 0o600
"""File mode of a recording: owner read/write only, whatever the umask."""
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, record length


class RecordingError(ValueError):
    """A recording that is missing, empty, truncated or not a meltloop MCAP (one-line reason)."""


class RecordingLimitError(RecordingError):
    """A recording that declares more than the reader allocates, or whose indexes point elsewhere
    than at records of their kind: hostile or corrupt (one-line reason)."""


class _Bounded:
    """A file whose reads never ask for more than it holds (a hostile length field would otherwise
    make ``read(n)`` allocate ``n`` bytes first)."""

    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream
        self._size = stream.seek(0, os.SEEK_END)
        stream.seek(0)

    def read(self, n: int | None = -1) -> bytes:
        left = max(0, self._size - self._stream.tell())
        return self._stream.read(left if n is None or n < 0 else min(n, left))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _chunk_problem(body: bytes) -> str | None:
    """Why decompressing a chunk record (its body, or at least the first 64 bytes of it) would
    allocate beyond :data:`MAX_CHUNK_BYTES`, or ``None``."""
    if len(body) < _CHUNK_HEAD.size:
        return None  # too short to decompress anything: the parser finds it corrupt
    *_, uncompressed, _crc, n = _CHUNK_HEAD.unpack_from(body)
    compression = body[_CHUNK_HEAD.size:_CHUNK_HEAD.size + min(n, 16)]
    if n > 16 or compression not in (b"", b"zstd"):
        return f"compression {compression.decode(errors='replace')!r} is not read (zstd or none)"
    if uncompressed > MAX_CHUNK_BYTES:
        return f"declares {uncompressed} bytes uncompressed, more than the {MAX_CHUNK_BYTES}-byte limit"
    frame = body[_CHUNK_HEAD.size + n + 8:]
    if compression == b"zstd" and frame:
        try:
            declared = zstandard.frame_content_size(frame)
        except zstandard.ZstdError:
            return None  # not a zstd frame: the parser finds it corrupt
        if declared > uncompressed:
            return f"holds a zstd frame of {declared} bytes, more than the {uncompressed} it declares"
    return None


_INDEX_TARGETS = {Opcode.CHUNK_INDEX: (16, Opcode.CHUNK), Opcode.ATTACHMENT_INDEX: (0, Opcode.ATTACHMENT),
                  Opcode.METADATA_INDEX: (0, Opcode.METADATA)}
"""Index record -> (byte position of the target offset in its body, opcode of the target)."""


def _check_structure(stream: BinaryIO, path: Path) -> None:
    """Walk a finished file's records by their headers (no payload is read): each must end inside
    the file, each chunk within :func:`_chunk_problem`'s bounds, each index and the footer must
    point at a record of their kind. Raises :class:`RecordingLimitError`."""
    size = stream.seek(0, os.SEEK_END)
    starts: dict[int, int] = {}
    targets: list[tuple[int, int, int]] = []  # (index record offset, target offset, target opcode)
    offset, end = len(MAGIC), size - len(MAGIC)
    while True:
        stream.seek(offset)
        head = stream.read(_RECORD_HEAD.size)
        if len(head) < _RECORD_HEAD.size:
            raise RecordingLimitError(f"{path}: record header past the end of the file at byte {offset}")
        opcode, length = _RECORD_HEAD.unpack(head)
        if length > end - offset - _RECORD_HEAD.size:
            raise RecordingLimitError(f"{path}: {_opcode_name(opcode)} record at byte {offset} declares {length} "
                                      "bytes, past the end of the file")
        starts[offset] = opcode
        if opcode == Opcode.CHUNK and (problem := _chunk_problem(stream.read(min(length, 64)))):
            raise RecordingLimitError(f"{path}: CHUNK record at byte {offset} {problem}")
        if opcode in _INDEX_TARGETS:
            at, kind = _INDEX_TARGETS[opcode]
            body = stream.read(min(length, at + 8))
            targets.append((offset, struct.unpack_from("<Q", body, at)[0] if len(body) == at + 8 else -1, kind))
        offset += _RECORD_HEAD.size + length
        if opcode == Opcode.FOOTER:
            summary_start, summary_offsets = struct.unpack_from("<QQ", stream.read(16) + bytes(16))
            targets += [(offset, o, -1) for o in (summary_start, summary_offsets) if o]
            break
    if offset != end:
        raise RecordingLimitError(f"{path}: the footer is not the last record")
    for at, target, kind in targets:
        if target not in starts or kind not in (-1, starts[target]):
            raise RecordingLimitError(f"{path}: the index record at byte {at} points at byte {target}, "
                                      f"not at a {_opcode_name(kind) if kind >= 0 else 'record'}")


def create_recording(path: str | Path, overwrite: bool) -> BinaryIO:
    """Open ``path`` for writing a recording, created with mode :data:`RECORDING_MODE`; an
    existing file only with ``overwrite`` (truncated, its mode set to :data:`RECORDING_MODE`).

    Raises
    ------
    FileExistsError
        ``path`` exists and ``overwrite`` is false.
    OSError
        It cannot be created.
    """
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL), RECORDING_MODE)
    os.fchmod(fd, RECORDING_MODE)
    return os.fdopen(fd, "wb")


def _topic(channel_or_topic: str | Topic) -> Topic:
    if isinstance(channel_or_topic, Topic):
        return channel_or_topic
    topic = TOPICS.get(channel_or_topic.lstrip("/"))
    if topic is None:
        raise KeyError(f"unknown channel {channel_or_topic!r}")
    return topic


def _open(path: Path) -> BinaryIO:
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"recording not found: {path}")
    if path.stat().st_size == 0:
        raise RecordingError(f"recording is empty: {path}")
    stream = path.open("rb")
    if stream.read(len(MAGIC)) != MAGIC:
        stream.close()
        raise RecordingError(f"not an MCAP file: {path}")
    stream.seek(0)
    return stream


def _finished(stream: BinaryIO) -> bool:
    """Whether the file ends with a footer and the closing magic (the recorder finished it)."""
    size = stream.seek(0, os.SEEK_END)
    footer_at = size - len(MAGIC) - _RECORD_HEAD.size - 20
    if footer_at < len(MAGIC):
        return False
    stream.seek(footer_at)
    tail = stream.read()
    stream.seek(0)
    return tail[0] == Opcode.FOOTER and tail.endswith(MAGIC)


def is_finished(path: str | Path) -> bool:
    """Whether the recorder finished the file (footer present); ``False`` for a truncated one.

    Raises
    ------
    RecordingError
        Missing, empty or non-MCAP file.
    """
    with _open(Path(path)) as stream:
        return _finished(stream)


@dataclass
class Recording:
    """Everything readable from one MCAP file, finished or truncated.

    Attributes
    ----------
    path : Path
        The file read.
    schemas, channels : dict
        MCAP schema and channel records by id.
    messages : list of mcap.records.Message
        Raw messages in file order (of complete chunks only, for a truncated file).
    metadata : dict
        Metadata records by name.
    attachments : list of mcap.records.Attachment
        Attachments in file order.
    truncated : bool
        True if the file has no footer: the recorder did not finish it.
    detail : str
        For a truncated file, where reading stopped and why; empty otherwise.
    """

    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[McapMessage] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: list[Attachment] = field(default_factory=list)
    truncated: bool = False
    detail: str = ""

    def decoded(self, channel: str | Topic) -> Iterator[Any]:
        """The validated messages of one channel, in file order (:class:`RecordingError` if one is invalid)."""
        topic = _topic(channel)
        ids = {i for i, c in self.channels.items() if c.topic == topic.channel}
        for message in self.messages:
            if message.channel_id in ids:
                try:
                    yield decode(topic, message.data)
                except MessageError as err:
                    raise RecordingError(f"{self.path}: invalid message: {err}") from None

    def counts(self) -> Counter[str]:
        """Messages per channel suffix (``plant/state``, ...)."""
        return Counter(self.channels[m.channel_id].topic.lstrip("/") for m in self.messages)

    def _take(self, record: Any) -> None:
        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
        elif isinstance(record, McapMessage):
            self.messages.append(record)
        elif isinstance(record, Attachment):
            self.attachments.append(record)
        elif isinstance(record, Metadata):
            self.metadata[record.name] = dict(record.metadata)


def read_recording(path: str | Path) -> Recording:
    """Read a whole recording record by record, tolerating a missing end.

    Reading stops at the footer, or at the first incomplete or corrupt record of a file the
    recorder did not finish; ``truncated`` and ``detail`` of the result say which.

    Raises
    ------
    RecordingError
        Missing, empty or non-MCAP file.
    """
    path = Path(path)
    result = Recording(path)
    with _open(path) as stream:
        size = stream.seek(0, os.SEEK_END)
        stream.seek(len(MAGIC))
        while True:
            offset = stream.tell()
            head = stream.read(_RECORD_HEAD.size)
            if len(head) < _RECORD_HEAD.size:
                stop = "no footer" if not head else f"ends inside a record header at byte {offset}"
                break
            opcode, length = _RECORD_HEAD.unpack(head)
            if length > size - stream.tell():
                stop = f"ends inside a {_opcode_name(opcode)} record at byte {offset}"
                break
            body = stream.read(length)
            if opcode == Opcode.CHUNK and (problem := _chunk_problem(body)):
                raise RecordingLimitError(f"{path}: CHUNK record at byte {offset} {problem}")
            records = _parse_record(head + body)
            if records is None:
                stop = f"corrupt {_opcode_name(opcode)} record at byte {offset}"
                break
            for record in records:
                result._take(record)
            if records and isinstance(records[-1], Footer):
                return result
    result.truncated = True
    result.detail = (f"{path}: truncated recording ({stop}, {size} bytes): "
                     f"read {len(result.messages)} messages of its complete chunks")
    return result


def _parse_record(data: bytes) -> list[Any] | None:
    """The records of one complete top-level record (a chunk's content for a chunk), ``None`` if corrupt."""
    buffer = BytesIO(data)
    records: list[Any] = []
    try:
        for record in StreamReader(buffer, skip_magic=True, validate_crcs=True).records:
            records.append(record)
    except EndOfFile:  # the reader asks for the next record (or the closing magic) past our one
        if records and buffer.tell() == len(data):
            return records
    except (McapError, ValueError, struct.error, zstandard.ZstdError):
        pass
    return None


def _reader(stream: BinaryIO, path: str | Path) -> Any:
    """``mcap``'s seeking reader of a finished file, after :func:`_check_structure`, on reads bounded by the file."""
    _check_structure(stream, Path(path))
    return make_reader(_Bounded(stream))


_READ_ERRORS = (McapError, EOFError, ValueError, KeyError, AssertionError, struct.error, zstandard.ZstdError)
"""What ``mcap``'s reader raises on a malformed file that passed :func:`_check_structure`."""


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name
    except ValueError:
        return f"unknown (opcode {opcode:#x})"


def read_messages(path: str | Path, channel: str | Topic) -> Iterator[Any]:
    """Yield the decoded, validated messages of one channel (e.g. ``"/plant/state"``), in file order.

    Of a file the recorder did not finish, the messages of its complete chunks
    (:func:`read_recording` tells it is truncated; :func:`is_complete` is false).

    Raises
    ------
    RecordingError
        Missing, empty or non-MCAP file, or a message that fails validation.
    """
    topic = _topic(channel)
    with _open(Path(path)) as stream:
        if not _finished(stream):
            yield from read_recording(path).decoded(topic)
            return
        reader = _reader(stream, path)
        try:
            for _schema, _channel, message in reader.iter_messages(topics=[topic.channel]):
                yield decode(topic, message.data)
        except _READ_ERRORS as err:
            if isinstance(err, MessageError):
                raise RecordingError(f"{path}: invalid message: {err}") from None
            raise RecordingError(f"{path}: unreadable MCAP ({type(err).__name__}: {err})") from None


def read_all(path: str | Path, channel: str | Topic, *, finished: bool = False) -> list[Any]:
    """Every message of one channel, as :func:`read_messages`, in a list that is never empty.

    Parameters
    ----------
    path : str or Path
        The recording.
    channel : str or Topic
        E.g. ``"/plant/state"``.
    finished : bool
        Refuse a file the recorder did not finish (default: read its complete chunks).

    Raises
    ------
    RecordingError
        As :func:`read_messages`; no message on the channel; with ``finished``, a truncated file
        (the message says how to recover it).
    """
    topic = _topic(channel)
    if finished and not is_finished(path):
        raise RecordingError(f"{path}: truncated recording (the recorder did not finish it); to use its complete "
                             "chunks, recover it first: python -m messages.recording recover FILE --out FIXED.mcap")
    found = list(read_messages(path, topic))
    if not found:
        raise RecordingError(f"{path}: no {topic.channel} messages")
    return found


def metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The file's metadata records by name (``meltloop``, ``meltloop.counts``)."""
    with _open(Path(path)) as stream:
        if not _finished(stream):
            return read_recording(path).metadata
        reader = _reader(stream, path)
        try:
            return {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except _READ_ERRORS as err:
            raise RecordingError(f"{path}: unreadable MCAP ({type(err).__name__})") from None


def attachments(path: str | Path) -> dict[str, bytes]:
    """The file's attachments by name (``config/<node>.json``)."""
    with _open(Path(path)) as stream:
        if not _finished(stream):
            return {a.name: a.data for a in read_recording(path).attachments}
        reader = _reader(stream, path)
        try:
            return {a.name: a.data for a in reader.iter_attachments()}
        except _READ_ERRORS as err:
            raise RecordingError(f"{path}: unreadable MCAP ({type(err).__name__})") from None


def is_complete(path: str | Path) -> bool:
    """True if the recorder finished the file (footer present) and found no message missing or
    extra; ``False`` for a truncated, missing or unreadable file, whatever metadata it holds."""
    try:
        return is_finished(path) and metadata(path).get("meltloop.counts", {}).get("complete") == "true"
    except RecordingError:
        return False


def run_config(path: str | Path) -> dict[str, Any]:
    """Each node's resolved configuration recorded in the file, by node name.

    Raises
    ------
    RecordingError
        As :func:`attachments`, or a configuration that is not JSON within :func:`messages.codec.loads`' limits.
    """
    try:
        return {
            name.removeprefix("config/").removesuffix(".json"): loads(data, f"{path}: attachment {name}")
            for name, data in attachments(path).items()
            if name.startswith("config/")
        }
    except MessageError as err:
        raise RecordingError(str(err)) from None


def recover(path: str | Path, out: str | Path) -> Recording:
    """Write what is readable of ``path`` into a finished MCAP ``out`` (replaced if it exists); returns what was read.

    Schemas, channels, metadata (but the source's ``meltloop.counts``), attachments and every
    message with its original times and sequence; then ``meltloop.counts`` with
    ``complete = "false"``, ``stopped_by = "recovered"``, the per-channel counts and the
    truncation detail.

    Raises
    ------
    RecordingError
        ``path`` missing, empty, not MCAP, or without a single complete message.
    OSError
        ``out`` cannot be written.
    """
    source = read_recording(path)
    if not source.messages:
        raise RecordingError(f"nothing recoverable in {path}: no complete chunk with messages"
                             + (f" ({source.detail})" if source.detail else ""))
    with create_recording(out, overwrite=True) as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="meltloop recover")
        schema_ids = {i: writer.register_schema(name=s.name, encoding=s.encoding, data=s.data)
                      for i, s in source.schemas.items()}
        channel_ids = {i: writer.register_channel(topic=c.topic, message_encoding=c.message_encoding,
                                                  schema_id=schema_ids.get(c.schema_id, 0), metadata=dict(c.metadata))
                       for i, c in source.channels.items()}
        for name, data in source.metadata.items():
            if name != "meltloop.counts":
                writer.add_metadata(name, data)
        for a in source.attachments:
            writer.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                                  media_type=a.media_type, data=a.data)
        for m in source.messages:
            writer.add_message(channel_id=channel_ids[m.channel_id], log_time=m.log_time, data=m.data,
                               publish_time=m.publish_time, sequence=m.sequence)
        writer.add_metadata("meltloop.counts", {
            "complete": "false",
            "stopped_by": "recovered",
            "incomplete_reason": source.detail or f"recovered from {path}",
            "recorded": json.dumps(dict(source.counts()), sort_keys=True),
            "recovered_from": str(path),
        })
        writer.finish()
    return source


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m messages.recording``."""
    parser = ArgumentParser(prog="python -m messages.recording", description="Tools for meltloop recordings.")
    commands = parser.add_subparsers(dest="command", required=True)
    rec = commands.add_parser("recover", help="write what is readable of an unfinished recording into a valid MCAP")
    rec.add_argument("file", type=Path, help="recording to recover (e.g. of a killed recorder)")
    rec.add_argument("--out", type=Path, required=True, help="finished MCAP to write")
    rec.add_argument("--overwrite", action="store_true", help="replace --out if it exists (else refused)")
    args = parser.parse_args(argv)
    prog = f"{parser.prog} {args.command}"
    try:
        if args.out.resolve() == args.file.resolve():
            raise UsageError("--out must differ from FILE")
        if args.out.exists() and not args.overwrite:
            raise UsageError(f"--out {args.out}: exists; give --overwrite to replace it")
        with _open(args.file):
            pass
    except (UsageError, RecordingError) as err:
        return exit_usage(prog, err)
    try:
        source = recover(args.file, args.out)
    except RecordingError as err:
        return exit_error(prog, err)
    except OSError as err:
        return exit_error(prog, RecordingError(f"cannot write {args.out}: {err.strerror or err}"))
    state = "truncated" if source.truncated else "finished"
    print(f"recovered {len(source.messages)} messages of {state} {args.file} into {args.out}")
    if source.truncated:
        print(source.detail)
    return 0


if __name__ == "__main__":
    run_main(main)
