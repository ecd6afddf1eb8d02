"""Read leveler MCAP logs back as numpy columns, including logs cut short by a crash.

The writer closes a chunk every second, so a SIGKILL leaves a file without summary or
footer whose chunks up to the last second are intact. Reading is therefore *sequential*
(never looking for the summary) and the first unreadable record ends the data instead of
raising: a crashed run is still a run to analyse.

The scan is our own rather than mcap.stream_reader.StreamReader: that parses every message
and message-index entry with several Python calls (~14 us per message measured, 12 s for
a 15 min 1 kHz log); one struct.unpack_from per record keeps it to a few us. Records other
than messages are still parsed by mcap's record classes.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import MISSING, dataclass, field, fields
from io import BytesIO
from pathlib import Path
from typing import IO

import numpy as np
import orjson
import zstandard
from lz4 import frame as lz4_frame
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Header, McapRecord, Metadata, Schema, Statistics
from mcap.writer import CompressionType, Writer

from leveler.errors import LogError
from leveler.records import Environment, Event, Sample, ThrustStand, Truth

SAMPLE_TOPIC = "/leveler/sample"
TRUTH_TOPIC = "/leveler/truth"
ENVIRONMENT_TOPIC = "/leveler/environment"
THRUST_STAND_TOPIC = "/leveler/thrust_stand"
EVENT_TOPIC = "/leveler/event"
FOXGLOVE_LOG_TOPIC = "/leveler/log"  # the events again, as foxglove.Log for its Log panel
METADATA_NAME = "leveler"

_MAGIC = b"\x89MCAP0\r\n"
_RECORD = struct.Struct("<BQ")  # every record: opcode, body length
_MESSAGE = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time, then data
_RECORD_MESSAGE = struct.Struct("<BQHIQQ")
_CHUNK = struct.Struct("<16xQII")  # (time range), uncompressed size, crc, name length
_PARSED = {
    Opcode.HEADER: Header,
    Opcode.SCHEMA: Schema,
    Opcode.CHANNEL: Channel,
    Opcode.METADATA: Metadata,
    Opcode.ATTACHMENT: Attachment,
}
# What damaged bytes can raise while parsing a record whose length checked out (an
# OverflowError: a chunk's uncompressed size damaged to 2^63 or more).
_DAMAGE = (McapError, ValueError, struct.error, zstandard.ZstdError, RuntimeError, OverflowError)
_DTYPES = {"int": np.int64, "float": np.float64, "bool": np.bool_, "str": np.str_}
_BATCH = 8192  # messages decoded at once: bounds the memory of intermediate dicts


@dataclass
class LogData:
    """One log as columns; `complete`: the writer finished the file and all of it read."""

    samples: dict[str, np.ndarray]
    truth: dict[str, np.ndarray]
    events: list[dict]
    metadata: dict[str, dict[str, str]]
    complete: bool
    # Why the log is incomplete ("" when complete): tells a crash cut from corruption.
    stop_reason: str = ""
    environment: dict[str, np.ndarray] = field(default_factory=dict)
    thrust_stand: dict[str, np.ndarray] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)  # field -> unit, from the schemas
    live: bool = False  # a running writer holds the file: read up to its last whole chunk

    def per_sample(self, key: str) -> np.ndarray | None:
        """An environment column with one value per sample: a record holds from its
        cycle (seq) until the next one, as the daemon writes them at each thermometer
        reading; NaN before the first. None without that column."""
        env, seq = self.environment, self.samples.get("seq")
        if key not in env or seq is None or not len(env[key]):
            return None
        values = env[key].astype(float)
        if len(values) == len(seq):
            return values
        at = np.searchsorted(env["seq"], seq, side="right") - 1
        return np.where(at >= 0, values[np.maximum(at, 0)], np.nan)


def hold(f: IO[bytes]) -> None:
    """Mark `f` as being written, for as long as it stays open (the kernel drops the lock
    when the writer closes it or dies): readers tell a live log from one a crash cut short.
    A hint only: where the filesystem has no flock, a live log reads as a cut one."""
    with contextlib.suppress(OSError):
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


def _held(f: IO[bytes]) -> bool:
    """Whether a writer holds `f` (hold); probed without waiting and let go at once."""
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    return False


def _decompress(body: bytes) -> bytes:
    """The records inside a chunk, CRC-checked: corruption must not become data."""
    size, crc, name_len = _CHUNK.unpack_from(body)
    name = body[_CHUNK.size : _CHUNK.size + name_len].decode()
    pos = _CHUNK.size + name_len
    (data_len,) = struct.unpack_from("<Q", body, pos)
    data = body[pos + 8 : pos + 8 + data_len]
    if len(data) != data_len:
        raise ValueError("chunk data shorter than its length field")
    if name == "zstd":
        data = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    elif name == "lz4":
        data = lz4_frame.decompress(data)
    elif name:
        raise ValueError(f"unsupported chunk compression {name!r}")
    if crc and zlib.crc32(data) != crc:
        raise ValueError("chunk CRC mismatch")
    return data


# A message as (log time, data, publish time, sequence), grouped by channel id, a chunk at
# a time: a generator step, an object or a dispatch per message would cost more than all
# the rest of the read.
_Msg = tuple[int, bytes, int, int]
_Messages = dict[int, list[_Msg]]


class _Scan:
    """Yields a file's readable records in file order and notes how the file ended.

    Messages come out as _Messages (one per chunk), the records in _PARSED as mcap
    record objects; index records and the summary section are skipped (they repeat the
    data).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.complete = False
        self.stop_reason = ""
        self.summary_messages: int | None = None  # the count the writer put in the summary
        self.size = 0  # bytes in the file when the scan began
        self.live = False  # a writer held the file when the scan began
        self.position = 0  # bytes scanned so far: progress through a long log

    def records(self) -> Iterator[McapRecord | _Messages]:
        try:
            f = open(self.path, "rb")
        except OSError as e:
            raise LogError(f"{self.path}: cannot open: {e.strerror}") from e
        with f:
            head = f.read(len(_MAGIC))
            if head != _MAGIC:
                if not head:
                    what = "empty file"
                elif _MAGIC.startswith(head):
                    what = f"cut short at byte {len(head)}, inside the magic"
                else:
                    what = f"starts with {head!r}"
                raise LogError(f"{self.path}: not an MCAP file ({what}); give a log written "
                               "by `leveler run` or `leveler sim`")
            self.live = _held(f)
            self.size = os.fstat(f.fileno()).st_size
            yield from self._records(f, self.size)

    def _records(self, f: IO[bytes], size: int) -> Iterator[McapRecord | _Messages]:
        pos = len(_MAGIC)
        summary = False  # after Data End only the footer matters
        while True:
            head = f.read(_RECORD.size)
            if len(head) < _RECORD.size:
                self.stop_reason = f"no footer: file ends at byte {size}"
                return
            opcode, length = _RECORD.unpack(head)
            if length > size - pos - _RECORD.size:
                self.stop_reason = f"record at byte {pos} runs past the end of the file"
                return
            body = f.read(length)
            try:
                if summary and opcode != Opcode.FOOTER:
                    if opcode == Opcode.STATISTICS:
                        stream = ReadDataStream(BytesIO(body))
                        self.summary_messages = Statistics.read(stream).message_count
                elif opcode == Opcode.CHUNK:
                    yield from _split(_decompress(body))
                elif opcode == Opcode.MESSAGE:
                    channel_id, sequence, log_time, publish_time = _MESSAGE.unpack_from(body)
                    yield {channel_id: [(log_time, body[_MESSAGE.size :], publish_time, sequence)]}
                elif opcode in _PARSED:
                    yield _PARSED[opcode].read(ReadDataStream(BytesIO(body)))
                elif opcode == Opcode.DATA_END:
                    summary = True
                elif opcode == Opcode.FOOTER:
                    self.complete = f.read(len(_MAGIC)) == _MAGIC
                    self.stop_reason = "" if self.complete else "footer without closing magic"
                    return
            except _DAMAGE as e:
                self.stop_reason = f"record at byte {pos} unreadable: {str(e) or type(e).__name__}"
                return
            pos += _RECORD.size + length
            self.position = pos


def _split(data: bytes) -> Iterator[McapRecord | _Messages]:
    """The records of a decompressed chunk: any schema or channel, then its messages.

    Channels are declared before their messages (outside chunks or earlier in the chunk),
    so handing out the few other records first keeps every reference valid.
    """
    messages: _Messages = {}
    others: list[McapRecord] = []
    pos, end = 0, len(data)
    full, short = _RECORD_MESSAGE.unpack_from, _RECORD.unpack_from
    while pos < end:
        if end - pos >= _RECORD_MESSAGE.size:
            opcode, length, channel_id, sequence, log_time, publish_time = full(data, pos)
        else:  # too short to be a message
            opcode, length = short(data, pos)
        start = pos + _RECORD.size
        pos = start + length
        if pos > end:
            raise ValueError("record inside a chunk runs past the chunk")
        if opcode == Opcode.MESSAGE:
            msg = (log_time, data[start + _MESSAGE.size : pos], publish_time, sequence)
            if channel_id in messages:
                messages[channel_id].append(msg)
            else:
                messages[channel_id] = [msg]
        elif opcode in _PARSED:
            others.append(_PARSED[opcode].read(ReadDataStream(BytesIO(data[start:pos]))))
    yield from others
    yield messages


def _columns(
    payloads: list[bytes], times: list[int], types: dict[str, str],
    defaults: dict[str, object] | None = None,
) -> dict[str, np.ndarray]:
    """Turn a batch of JSON messages into numpy columns, typed by the record class.

    JSON has no NaN/Inf: orjson wrote them as null, which np.float64 reads back as NaN.
    A field the record class gives a default came later than the topic: a log written
    before it lacks it and reads as that default.
    """
    rows = orjson.loads(b"[" + b",".join(payloads) + b"]")
    defaults = defaults or {}
    missing = [k for k in types if k not in rows[0] and k not in defaults]
    if missing:  # (a later message lacking one is a KeyError below)
        raise ValueError(f"a message lacks {', '.join(missing)}")
    cols = {"log_time_ns": np.array(times, dtype=np.int64)}
    for key in rows[0]:
        cols[key] = np.array([r[key] for r in rows], dtype=_DTYPES.get(types.get(key, "")))
    for key, value in defaults.items():
        if key not in cols:
            cols[key] = np.full(len(rows), value, dtype=_DTYPES.get(types[key]))
    return cols


class _Table:
    """Accumulates one topic's messages and converts them to columns batch by batch."""

    def __init__(self, record_type: type) -> None:
        self.types = {f.name: str(f.type) for f in fields(record_type)}
        self.defaults = {f.name: f.default for f in fields(record_type)
                         if f.default is not MISSING}
        self.payloads: list[bytes] = []
        self.times: list[int] = []
        self.parts: list[dict[str, np.ndarray]] = []

    def convert(self, at_least: int = 1) -> None:
        if len(self.payloads) >= at_least:
            self.parts.append(_columns(self.payloads, self.times, self.types, self.defaults))
            self.payloads, self.times = [], []

    def result(self) -> dict[str, np.ndarray]:
        self.convert()
        if not self.parts:
            empty = {"log_time_ns": np.empty(0, np.int64)}
            return empty | {k: np.empty(0, _DTYPES.get(t)) for k, t in self.types.items()}
        return {k: np.concatenate([p[k] for p in self.parts]) for k in self.parts[0]}


_UNIT = re.compile(r"\[([^\[\]]+)\]")


def _schema_units(data: bytes) -> dict[str, str]:
    """Each property's unit, the last [bracketed] part of its description (writer.py)."""
    try:
        props = orjson.loads(data).get("properties", {})
    except (orjson.JSONDecodeError, AttributeError):
        return {}
    out = {}
    for name, spec in props.items():
        found = _UNIT.findall(str(spec.get("description", ""))) if isinstance(spec, dict) else []
        if found:
            out[name] = found[-1]
    return out


def read_log(path: str | Path, progress: Callable[[float], None] | None = None) -> LogData:
    """Read every readable message of a log; a truncated file gives complete=False.
    `progress` is told the fraction of the file read, a chunk at a time."""
    scan = _Scan(path)
    tables = {SAMPLE_TOPIC: _Table(Sample), TRUTH_TOPIC: _Table(Truth), EVENT_TOPIC: _Table(Event),
              ENVIRONMENT_TOPIC: _Table(Environment), THRUST_STAND_TOPIC: _Table(ThrustStand)}
    by_channel: dict[int, _Table] = {}
    metadata: dict[str, dict[str, str]] = {}
    units: dict[str, str] = {}
    read = 0
    try:
        for record in scan.records():
            if type(record) is dict:
                for channel_id, messages in record.items():
                    read += len(messages)
                    table = by_channel.get(channel_id)
                    if table is not None:
                        table.times += [m[0] for m in messages]
                        table.payloads += [m[1] for m in messages]
                tables[SAMPLE_TOPIC].convert(_BATCH)
                tables[TRUTH_TOPIC].convert(_BATCH)
                if progress is not None:
                    progress(scan.position / scan.size)
            elif isinstance(record, Channel) and record.topic in tables:
                by_channel[record.id] = tables[record.topic]
            elif isinstance(record, Metadata):
                metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Schema):
                units |= _schema_units(record.data)
        if progress is not None:
            progress(1.0)
        events = tables[EVENT_TOPIC]
        event_list = [
            {"log_time_ns": t} | orjson.loads(data)
            for t, data in zip(events.times, events.payloads, strict=True)
        ]
        samples = tables[SAMPLE_TOPIC].result()
        truth, env = tables[TRUTH_TOPIC], tables[ENVIRONMENT_TOPIC]
        truth_cols = truth.result() if truth in by_channel.values() else {}
        env_cols = env.result() if env in by_channel.values() else {}
        stand = tables[THRUST_STAND_TOPIC]
        stand_cols = stand.result() if stand in by_channel.values() else {}
    except orjson.JSONDecodeError as e:
        raise LogError(f"{scan.path}: a message is not valid JSON: {e}") from e
    except (KeyError, TypeError, ValueError) as e:  # checksums passed: not what we write
        raise LogError(f"{scan.path}: messages are not as leveler writes them "
                       f"({type(e).__name__}: {e}); is this a leveler log?") from e
    complete, reason = scan.complete, scan.stop_reason
    if complete and scan.summary_messages is not None and read < scan.summary_messages:
        # a record with a damaged opcode reads as one of a later MCAP version and is
        # skipped; the writer's count is what tells
        complete = False
        reason = (f"{scan.summary_messages - read} of its {scan.summary_messages} messages "
                  "unreadable")
    return LogData(
        samples=samples,
        truth=truth_cols,
        events=event_list,
        metadata=metadata,
        complete=complete,
        stop_reason=reason,
        environment=env_cols,
        thrust_stand=stand_cols,
        units=units,
        live=scan.live and not complete,
    )


def partial_note(path: str | Path, stop_reason: str, samples: int, live: bool = False) -> str:
    """What a command says when it used an incomplete log: one still being written, read
    as a stream, or one cut short or damaged."""
    if live:
        return (f"note: {path} is still being written (a running leveler holds it); read as "
                f"a stream up to its last complete chunk: {samples} samples")
    return (f"note: {path} is incomplete ({stop_reason}); used its {samples} readable "
            f"samples. `leveler recover {path} --out FIXED.mcap` copies them into a complete "
            "file")


def recover(src: str | Path, dst: str | Path) -> int:
    """Copy everything readable from `src` (e.g. cut by a crash) into a finished file `dst`.

    The result has a summary and indexes, so seeking readers and Foxglove open it fast.
    Returns the number of messages copied.
    """
    src, dst = Path(src), Path(dst)
    if dst.exists() and dst.resolve() == src.resolve():
        raise LogError(f"{dst}: recover would overwrite its own source")
    records = _Scan(src).records()
    first = next(records, None)  # raises LogError before dst is created if src isn't MCAP
    schemas: dict[int, int] = {0: 0}
    channels: dict[int, int] = {}
    copied = 0
    with open(dst, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        if isinstance(first, Header):
            writer.start(first.profile, first.library)
        else:
            writer.start()
        for record in records:
            if type(record) is dict:
                for channel_id, messages in record.items():
                    for log_time, data, publish_time, sequence in messages:
                        writer.add_message(
                            channels[channel_id], log_time, data, publish_time, sequence
                        )
                    copied += len(messages)
            elif isinstance(record, Schema):
                schemas[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel):
                channels[record.id] = writer.register_channel(
                    record.topic,
                    record.message_encoding,
                    schemas[record.schema_id],
                    record.metadata,
                )
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Attachment):
                writer.add_attachment(
                    record.create_time,
                    record.log_time,
                    record.name,
                    record.media_type,
                    record.data,
                )
        writer.finish()
        out.flush()
        os.fsync(out.fileno())
    return copied


__all__ = [
    "ENVIRONMENT_TOPIC",
    "EVENT_TOPIC",
    "FOXGLOVE_LOG_TOPIC",
    "METADATA_NAME",
    "SAMPLE_TOPIC",
    "THRUST_STAND_TOPIC",
    "TRUTH_TOPIC",
    "LogData",
    "LogError",
    "hold",
    "partial_note",
    "read_log",
    "recover",
]
