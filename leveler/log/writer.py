"""Log every loop sample to MCAP without ever making the loop wait for the disk.

The loop thread only appends records to a deque (thread-safe, ~50 ns). A writer thread
encodes them with orjson and writes them into MCAP chunks, closing a chunk every
`chunk_interval_s` of wall time: a chunk is only readable once closed, so this bounds what
a SIGKILL or power cut can lose to about one second at any sample rate (at 10 Hz a 1 MiB
chunk would otherwise stay open for minutes). See docs/log-format.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import logging
import os
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Iterator
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np
import orjson
import zstandard
from lz4 import frame as lz4_frame
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from leveler.log.reader import (
    ENVIRONMENT_TOPIC,
    EVENT_TOPIC,
    FOXGLOVE_LOG_TOPIC,
    METADATA_NAME,
    SAMPLE_TOPIC,
    THRUST_STAND_TOPIC,
    TRUTH_TOPIC,
    LogError,
    hold,
)
from leveler.records import Environment, Event, Sample, ThrustStand, Truth
from leveler.rt import background_thread

_log = logging.getLogger(__name__)

_MAGIC = b"\x89MCAP0\r\n"
# Compressor factories: a ZstdCompressor must not be shared between threads. Level 1:
# on sample-like JSON it compressed better than the default level 3 (6.0x vs 5.2x,
# measured) in half the time.
_COMPRESSION = {
    "zstd": lambda: zstandard.ZstdCompressor(level=1).compress,
    "lz4": lambda: lz4_frame.compress,
    "none": lambda: bytes,
}
# One message record's header: opcode, record length, channel, sequence, log/publish time.
_MESSAGE = struct.Struct("<BQHIQQ")
_OP_MESSAGE = int(Opcode.MESSAGE)
_MESSAGE_INDEX = struct.Struct("<BQHI")
_POLL_S = 0.025  # writer wake-up period: latency from sample() to the open chunk
# Records queued at which sample() wakes the writer at once (16 cycles at 1 kHz with truth):
# its work then starts just after a loop cycle, while the loop sleeps, instead of at any
# moment of the period, where it would hold the GIL as the loop wakes (measured at 1 kHz:
# ~0.5% of cycles woke during a drain and waited ~150 us for the lock).
_WAKE_BACKLOG = 32
_BATCH = 64  # messages (~0.3 ms of encoding) between GIL hand-backs
_YIELD_BELOW = 2048  # backlog above which the writer stops handing the GIL back
_SEQ_MASK = 0xFFFF_FFFF  # MCAP sequence is uint32 (wraps after 49 days at 1 kHz)
# Samples/truth: typed records, an unencodable value is a bug and must surface.
# Events: free-form detail, anything unknown is logged as its str() rather than lost.
_RECORD_OPT = orjson.OPT_SERIALIZE_NUMPY
_EVENT_OPT = orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS

_NULL = " (null when not finite)"
_SAMPLE_FIELDS: dict[str, tuple[str, str]] = {
    "seq": ("integer", "cycle number, contiguous from 0"),
    "t_s": ("number", "loop time since start [s]"),
    "raw_counts": ("integer", "sensor ADC reading [counts]"),
    "sensor_m": ("number", "displacement at the inverted pendulum end [m]" + _NULL),
    "status": ("integer", "sensor status: 0 OK, 1 TIMEOUT, 2 INVALID, 3 RAILED, 4 FAULT"),
    "setpoint_m": ("number", "displacement setpoint [m]"),
    "error_m": ("number", "setpoint_m - sensor_m [m]" + _NULL),
    "p_v": ("number", "PID proportional term [V]"),
    "i_v": ("number", "PID integral term, and the resonant terms when configured [V]"),
    "d_v": ("number", "PID derivative term [V]"),
    "command_v": ("number", "controller output [V]"),
    "applied_v": ("number", "voltage the actuator actually applied [V]"),
    "saturated": ("boolean", "output railed or slew-limited this cycle"),
    "state": ("string", "controller state: idle, engaged or fault"),
}
_TRUTH_FIELDS: dict[str, tuple[str, str]] = {
    "seq": ("integer", "cycle number of the matching sample"),
    "t_s": ("number", "loop time since start [s]"),
    "tilt_rad": ("number", "true platform tilt [rad]"),
    "thermal_tilt_rad": ("number", "tilt contribution of thermal gradients [rad]"),
    "cooler_tilt_rad": ("number", "tilt contribution of the cooler [rad]"),
    "piezo_tilt_rad": ("number", "tilt contribution of the piezo actuator [rad]"),
    "pendulum_rad": ("number", "inverted-pendulum deflection relative to the platform [rad]"),
    "temperature_k": ("number", "plate temperature [K]"),
    "sensor_drift_m": ("number", "sensor zero drift [m]"),
}
_ENVIRONMENT_FIELDS: dict[str, tuple[str, str]] = {
    "seq": ("integer", "cycle number of the matching sample"),
    "t_s": ("number", "loop time since start [s]"),
    "temperature_k": ("number", "measured table temperature [K]" + _NULL),
    "feedforward_v": ("number", "temperature feedforward added to the command while "
                      "engaged, from this record on [V]" + _NULL),
}
_THRUST_STAND_FIELDS: dict[str, tuple[str, str]] = {
    "seq": ("integer", "row number of the recording"),
    "t_s": ("number", "time since start [s]"),
    "thrust_n": ("number", "thrust or calibration force on the torsion pendulum [N]" + _NULL),
    "displacement_m": ("number", "torsion-pendulum displacement at the sensor [m]" + _NULL),
    "tilt_rad": ("number", "base pitch tilt [rad] (null when not recorded)"),
}
_EVENT_FIELDS: dict[str, tuple[str, str]] = {
    "t_s": ("number", "loop time since start [s]"),
    "kind": ("string", "event class, e.g. start, stop, gain, fault, state, log"),
    "reason": ("string", "human-readable cause"),
    "detail": ("object", "kind-specific values"),
}


# Each event again as a foxglove.Log message (the schema Foxglove's Log panel shows, with
# its severity levels): the field names and types of foxglove-sdk's schemas/jsonschema/Log.
_FOXGLOVE_LOG_SCHEMA = json.dumps({
    "title": "foxglove.Log",
    "description": "A log message",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "title": "time",
                      "properties": {"sec": {"type": "integer", "minimum": 0},
                                     "nsec": {"type": "integer", "minimum": 0,
                                              "maximum": 999999999}},
                      "description": "Timestamp of log message"},
        "level": {"title": "foxglove.LogLevel", "description": "Log level", "type": "integer",
                  "oneOf": [{"title": n, "const": v} for n, v in (
                      ("UNKNOWN", 0), ("DEBUG", 1), ("INFO", 2), ("WARNING", 3), ("ERROR", 4),
                      ("FATAL", 5))]},
        "message": {"type": "string", "description": "Log message"},
        "name": {"type": "string", "description": "Process or node name"},
        "file": {"type": "string", "description": "Filename"},
        "line": {"type": "integer", "minimum": 0, "description": "Line number in the file"},
    },
}, indent=1).encode()
_WARNING_KINDS = frozenset({"bad_reading", "reconnect", "clock", "stability", "log", "gap"})
_ERROR_KINDS = frozenset({"fault", "driver_error"})


def encode(record: Sample | Truth | Environment | ThrustStand) -> bytes:
    """A record's JSON as the log holds it (NaN and infinities as null)."""
    return orjson.dumps(record, option=_RECORD_OPT)


class Columns:
    """n consecutive cycles' samples (and truth) as columns, queued as one item: a producer
    that makes records far faster than one call each can carry (the virtual loop's kernel)
    hands them over in bulk, and the writer encodes each as `encode` would, byte for byte.
    A column is a sequence of n values (numbers or bools) or one value for all n."""

    __slots__ = ("log_time_ns", "n", "sample", "t_s", "truth")

    def __init__(self, sample: dict[str, Any], truth: dict[str, Any] | None,
                 log_time_ns: list[int]) -> None:
        self.n = len(log_time_ns)
        for kind, cols, keys in (("sample", sample, _SAMPLE_KEYS), ("truth", truth, _TRUTH_KEYS)):
            if cols is None:
                continue
            if list(cols) != keys:
                raise ValueError(f"{kind} columns must be {keys}, got {list(cols)}")
            for key, col in cols.items():
                if not isinstance(col, np.ndarray | list):
                    continue
                if len(col) != self.n:
                    raise ValueError(f"{kind} column {key} has {len(col)} values, not {self.n}")
                if np.asarray(col).dtype.kind not in "biuf":
                    raise ValueError(f"{kind} column {key}: only numbers and bools as columns")
        self.sample, self.truth, self.log_time_ns = sample, truth, log_time_ns
        t = sample["t_s"]
        self.t_s = float(t[-1] if isinstance(t, np.ndarray | list) else t) if self.n else 0.0

    def rows(self, which: str) -> Iterator[tuple[bytes, ...]]:
        """Each cycle's JSON tokens in field order: a float column is encoded by one
        orjson call on the whole list (the same shortest round-trip form a record gets)."""
        cols = self.sample if which == "sample" else self.truth
        assert cols is not None
        tokens = []
        for col in cols.values():
            if isinstance(col, np.ndarray | list):
                values = col.tolist() if isinstance(col, np.ndarray) else col
                tokens.append(orjson.dumps(values, option=_RECORD_OPT)[1:-1].split(b","))
            else:
                tokens.append(itertools.repeat(orjson.dumps(col, option=_RECORD_OPT), self.n))
        return zip(*tokens, strict=False)


def _template(keys: list[str]) -> bytes:
    """`%b` template of a record's JSON object, keys in the dataclass's order."""
    return b"{" + b",".join(orjson.dumps(k) + b":%b" for k in keys) + b"}"


_SAMPLE_KEYS = [f.name for f in dataclasses.fields(Sample)]
_TRUTH_KEYS = [f.name for f in dataclasses.fields(Truth)]
_SAMPLE_TEMPLATE = _template(_SAMPLE_KEYS)
_TRUTH_TEMPLATE = _template(_TRUTH_KEYS)
_COLUMNS = -1  # the queue's channel slot for a Columns item
_COLUMN_BATCH = 4096  # cycles of a Columns item written between flush checks


def encode_event(event: Event) -> bytes:
    """An event's JSON as the log holds it (numpy values and anything else made plain)."""
    return orjson.dumps(event, default=str, option=_EVENT_OPT)


def foxglove_log(event: Event, log_time_ns: int) -> dict[str, Any]:
    """`event` as a foxglove.Log message: its kind and reason as the text, a fault (or a
    state change into one) as ERROR, trouble the loop rides out as WARNING, else INFO."""
    detail = event.detail if isinstance(event.detail, dict) else {}
    if event.kind in _ERROR_KINDS or (event.kind == "state" and detail.get("new") == "fault"):
        level = 4
    else:
        level = 3 if event.kind in _WARNING_KINDS else 2
    return {"timestamp": {"sec": log_time_ns // 1_000_000_000,
                          "nsec": log_time_ns % 1_000_000_000},
            "level": level, "message": f"{event.kind}: {event.reason}", "name": "leveler",
            "file": "", "line": 0}


def _schema(title: str, props: dict[str, tuple[str, str]]) -> bytes:
    """A JSON Schema of type object: what Foxglove needs to offer the fields for plotting."""
    return json.dumps(
        {
            "title": title,
            "type": "object",
            "properties": {k: {"type": t, "description": d} for k, (t, d) in props.items()},
            "required": list(props),
        },
        indent=1,
    ).encode()


#: every topic's (schema name, JSON Schema): the log's channels, and the live stream's
#: (leveler.live), which publishes the same topics in the same form
SCHEMAS: dict[str, tuple[str, bytes]] = {
    topic: (name, _schema(name, props)) for topic, name, props in (
        (SAMPLE_TOPIC, "leveler.Sample", _SAMPLE_FIELDS),
        (TRUTH_TOPIC, "leveler.Truth", _TRUTH_FIELDS),
        (ENVIRONMENT_TOPIC, "leveler.Environment", _ENVIRONMENT_FIELDS),
        (THRUST_STAND_TOPIC, "leveler.ThrustStand", _THRUST_STAND_FIELDS),
        (EVENT_TOPIC, "leveler.Event", _EVENT_FIELDS))
} | {FOXGLOVE_LOG_TOPIC: ("foxglove.Log", _FOXGLOVE_LOG_SCHEMA)}


def _library() -> str:
    try:
        return f"leveler {version('lab-leveler')}"
    except PackageNotFoundError:  # running from a source tree that isn't installed
        return "leveler (uninstalled)"


class _McapFile:
    """The part of an MCAP writer this log needs, with a fast path for messages.

    mcap.Writer.add_message costs 5-10 us of pure Python per message (measured), more
    than the whole per-sample budget; here a message is one struct.pack into the open
    chunk and two index appends. Records other than messages are rare and written with
    mcap's own record classes. Schemas, channels and metadata go to the data section
    before any chunk, so a crashed file still describes its topics.
    """

    def __init__(self, f: IO[bytes], library: str, compression: str, chunk_size: int) -> None:
        self._f = f
        self._pos = 0
        self._compress = _COMPRESSION[compression]()
        self._compression = "" if compression == "none" else compression
        self._chunk_size = chunk_size
        self._chunk = bytearray()
        self._index: dict[int, list[int]] = {}  # channel -> [log_time, offset, ...]
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        # The summary's chunk indexes, serialized as each chunk closes: about 100 bytes a
        # chunk instead of a ~700-byte ChunkIndex object. At a chunk a second that is what
        # the daemon's memory grew by, 2.3 MiB/h, until the file rotated.
        self._chunk_index_bytes = bytearray()
        self._chunk_count = 0
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = {}
        self._time_range: tuple[int, int] | None = None
        # (end offset, messages per channel, newest log time) of each chunk since the last
        # flush: after a failed write, the file's size tells which of them are whole.
        self.unflushed: list[tuple[int, dict[int, int], int]] = []
        self._write(_MAGIC)
        self._record(Header(profile="", library=library))

    def _write(self, data: bytes) -> None:
        self._f.write(data)
        self._pos += len(data)

    def _record(self, record: McapRecord) -> int:
        """Write one record outside chunks; returns its length."""
        rb = RecordBuilder()
        record.write(rb)
        data = rb.end()
        self._write(data)
        return len(data)

    def channel(self, topic: str, schema_name: str, schema: bytes) -> int:
        s = Schema(id=len(self._schemas) + 1, data=schema, encoding="jsonschema", name=schema_name)
        c = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding="json",
            metadata={},
            schema_id=s.id,
        )
        self._record(s)
        self._record(c)
        self._schemas.append(s)
        self._channels.append(c)
        self._index[c.id] = []
        self._counts[c.id] = 0
        return c.id

    def metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._pos
        length = self._record(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add(self, channel: int, log_time: int, data: bytes, sequence: int) -> None:
        chunk = self._chunk
        index = self._index[channel]
        index.append(log_time)
        index.append(len(chunk))
        chunk += _MESSAGE.pack(_OP_MESSAGE, 22 + len(data), channel, sequence, log_time, log_time)
        chunk += data
        if len(chunk) >= self._chunk_size:
            self.close_chunk()

    def close_chunk(self) -> None:
        """Write the open chunk and its message indexes; from here on it survives a crash."""
        if not self._chunk:
            return
        data = bytes(self._chunk)
        compressed = self._compress(data)  # zstd and lz4 release the GIL meanwhile
        times = np.concatenate([np.asarray(ix[0::2], np.uint64) for ix in self._index.values()])
        start, end = int(times.min()), int(times.max())
        chunk_offset = self._pos
        chunk_length = self._record(
            Chunk(
                compression=self._compression,
                data=compressed,
                message_start_time=start,
                message_end_time=end,
                uncompressed_crc=zlib.crc32(data),
                uncompressed_size=len(data),
            )
        )
        counts = {ch: self._counts[ch] + len(ix) // 2 for ch, ix in self._index.items()}
        self.unflushed.append((self._pos, counts, end))
        index_start = self._pos
        offsets = {}
        for ch, ix in self._index.items():
            if ix:
                offsets[ch] = self._pos
                self._write(
                    _MESSAGE_INDEX.pack(Opcode.MESSAGE_INDEX, 6 + 8 * len(ix), ch, 8 * len(ix))
                )
                self._write(np.asarray(ix, "<u8").tobytes())
                self._counts[ch] += len(ix) // 2
                ix.clear()
        rb = RecordBuilder()
        ChunkIndex(
            message_start_time=start,
            message_end_time=end,
            chunk_start_offset=chunk_offset,
            chunk_length=chunk_length,
            message_index_offsets=offsets,
            message_index_length=self._pos - index_start,
            compression=self._compression,
            compressed_size=len(compressed),
            uncompressed_size=len(data),
        ).write(rb)
        self._chunk_index_bytes += rb.end()
        self._chunk_count += 1
        if self._time_range is not None:
            start, end = min(start, self._time_range[0]), max(end, self._time_range[1])
        self._time_range = (start, end)
        self._chunk.clear()

    def flush(self) -> None:
        self.close_chunk()
        self._f.flush()
        self.unflushed.clear()

    def finish(self) -> None:
        """Write the summary section and footer that seeking readers (Foxglove) rely on."""
        self.close_chunk()
        self._record(DataEnd(data_section_crc=0))
        start, end = self._time_range or (0, 0)
        groups: list[tuple[Opcode, list[McapRecord] | bytes]] = [
            (Opcode.SCHEMA, list(self._schemas)),
            (Opcode.CHANNEL, list(self._channels)),
            (
                Opcode.STATISTICS,
                [
                    Statistics(
                        message_count=sum(self._counts.values()),
                        schema_count=len(self._schemas),
                        channel_count=len(self._channels),
                        attachment_count=0,
                        metadata_count=len(self._metadata_indexes),
                        chunk_count=self._chunk_count,
                        message_start_time=start,
                        message_end_time=end,
                        channel_message_counts={c: n for c, n in self._counts.items() if n},
                    )
                ],
            ),
            (Opcode.CHUNK_INDEX, bytes(self._chunk_index_bytes)),
            (Opcode.METADATA_INDEX, list(self._metadata_indexes)),
        ]
        summary_start = self._pos
        rb = RecordBuilder()
        offsets = []
        for opcode, records in groups:
            group_start = rb.count
            if isinstance(records, bytes):
                rb.write(records)
            else:
                for record in records:
                    record.write(rb)
            offsets.append(
                SummaryOffset(opcode, summary_start + group_start, rb.count - group_start)
            )
        summary_offset_start = summary_start + rb.count
        for offset in offsets:
            offset.write(rb)
        summary = rb.end()
        footer_prefix = struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start)
        self._write(summary)
        self._record(
            Footer(
                summary_start=summary_start,
                summary_offset_start=summary_offset_start,
                summary_crc=zlib.crc32(footer_prefix, zlib.crc32(summary)),
            )
        )
        self._write(_MAGIC)
        self._f.flush()


class LogWriter:
    """Writes samples, truth and events to one MCAP file from a background thread.

    Producer methods may be called from one thread (the loop); they never block. The
    file is readable up to the last closed chunk at any moment; close() finishes it.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        metadata: dict[str, str] | None = None,
        chunk_interval_s: float = 1.0,
        compression: str = "zstd",
        truth: bool = False,
        environment: bool = False,
        thrust_stand: bool = False,
        chunk_size: int = 1 << 20,
        max_backlog: int = 600_000,
    ) -> None:
        """Open `path` and start the writer thread.

        chunk_size bounds chunks at high rates (memory, Foxglove seeking);
        max_backlog (default: 10 min at 1 kHz) bounds memory if the disk stalls.
        """
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}")
        meta = dict(metadata or {})
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in meta.items()):
            raise TypeError("metadata keys and values must be str")
        self._path = Path(path)
        # Written under another name and renamed once the header, topics and metadata are
        # in it: a kill between creating the file and that flush would otherwise leave an
        # empty `path` that no reader (nor `leveler recover`) can open. A kill before the
        # rename leaves only `<path>.new`.
        new = self._path.with_name(self._path.name + ".new")
        try:
            self._file = open(new, "wb")  # owned by the writer thread from here on
            hold(self._file)
            self._mcap = _McapFile(self._file, _library(), compression, chunk_size)
            self._sample_ch = self._channel(SAMPLE_TOPIC)
            self._truth_ch = self._channel(TRUTH_TOPIC) if truth else None
            self._env_ch = self._channel(ENVIRONMENT_TOPIC) if environment else None
            self._stand_ch = self._channel(THRUST_STAND_TOPIC) if thrust_stand else None
            self._event_ch = self._channel(EVENT_TOPIC)
            self._log_ch = self._channel(FOXGLOVE_LOG_TOPIC)
            self._mcap.metadata(METADATA_NAME, meta)
            self._file.flush()  # header, topics and metadata reach the OS even if we die now
            os.replace(new, self._path)
        except OSError as e:
            if hasattr(self, "_file"):
                with contextlib.suppress(OSError):  # the buffered header fails again (ENOSPC)
                    self._file.close()
                with contextlib.suppress(OSError):
                    new.unlink(missing_ok=True)
            raise LogError(f"{self._path}: cannot create log: {e.strerror}") from e

        self._interval = chunk_interval_s
        self._max_backlog = max_backlog
        self._queue: deque[tuple[int, Any, int]] = deque()
        self._in_flight = 0  # records popped by the writer thread, not yet written
        self._dropped = 0
        self._dropped_logged = 0
        self._samples_written = 0
        self._event_seq = 0
        self._last = (0.0, 0)  # (t_s, log_time_ns) of the newest written record
        self._flushed = (0, 0)  # (samples, newest log_time_ns) known to be in the file
        self._last_flush = time.monotonic()
        self._error: BaseException | None = None
        self._displaced: str | None = None
        self._deleted = False  # displaced because its last link went
        self._closed = False
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._progress = threading.Condition()
        self._thread = threading.Thread(
            target=self._run, name=f"logwriter {self._path.name}", daemon=False
        )
        self._thread.start()

    def _channel(self, topic: str) -> int:
        return self._mcap.channel(topic, *SCHEMAS[topic])

    # -- producer side: the loop thread ------------------------------------------------

    @property
    def path(self) -> Path:
        return self._path

    @property
    def samples_written(self) -> int:
        """Samples handed to the MCAP writer (on disk after the next chunk flush)."""
        return self._samples_written

    @property
    def bytes_written(self) -> int:
        """Bytes in the file so far (closed chunks; the open one is still in memory):
        cheap enough to read every sample, which is what size-based rotation needs."""
        return self._mcap._pos

    @property
    def flushed(self) -> tuple[int, int]:
        """(samples, log_time_ns of the newest record) in the file as of the last flush to
        the OS or, once the writer failed, in the chunks that reached the file whole: what
        a write error (disk full) cannot take back."""
        return self._flushed

    @property
    def dropped(self) -> int:
        """Samples and truth records refused because the backlog was full; should stay 0."""
        return self._dropped

    @property
    def displaced(self) -> str | None:
        """Why the file being written is no longer at its path (deleted, its directory
        removed or moved, or another file in its place), or None. Checked by the writer
        thread at every chunk; writing goes on into the open file either way."""
        return self._displaced

    @property
    def deleted(self) -> bool:
        """Displaced because the file was deleted (not moved): only its descriptor holds it."""
        return self._deleted

    def open_deleted(self) -> int | None:
        """A read-only descriptor of the deleted file (call before close()), or None if there
        is no /proc or the file is closed: what it holds stays readable through /proc while
        it is open, so it can be copied back."""
        try:
            return os.open(f"/proc/self/fd/{self._file.fileno()}", os.O_RDONLY | os.O_CLOEXEC)
        except (OSError, ValueError):  # ValueError: the writer thread closed the file
            return None

    @property
    def backlog(self) -> int:
        """Records waiting for the writer thread."""
        return len(self._queue) + self._in_flight

    def sample(self, s: Sample, log_time_ns: int) -> None:
        """Queue one loop sample; raises LogError if the writer thread has failed."""
        if self._error is not None or self._closed:
            self._raise()
        q = self._queue
        if len(q) >= self._max_backlog:
            self._dropped += 1
            return
        q.append((self._sample_ch, s, log_time_ns))
        if len(q) >= _WAKE_BACKLOG and not self._wake.is_set():
            self._wake.set()

    def truth(self, t: Truth, log_time_ns: int) -> None:
        """Queue one simulation truth record (needs truth=True)."""
        self._put(self._truth_ch, t, log_time_ns)

    def environment(self, e: Environment, log_time_ns: int) -> None:
        """Queue one environment record (needs environment=True)."""
        self._put(self._env_ch, e, log_time_ns)

    def thrust_stand(self, r: ThrustStand, log_time_ns: int) -> None:
        """Queue one thrust-stand record (needs thrust_stand=True)."""
        self._put(self._stand_ch, r, log_time_ns)

    def _put(self, channel: int | None, record: object, log_time_ns: int) -> None:
        """An optional topic's record: dropped (and counted) only when the backlog is full."""
        if self._error is not None or self._closed or channel is None:
            self._raise()
        if len(self._queue) >= self._max_backlog:
            self._dropped += 1
            return
        self._queue.append((channel, record, log_time_ns))

    def columns(self, cols: Columns) -> None:
        """Queue many cycles' records at once. It waits while an earlier item is still
        queued: a bulk producer is never real-time, and pacing it here bounds the memory a
        fast one could otherwise fill (`sample`'s backlog limit counts items, not cycles)."""
        if self._error is not None or self._closed:
            self._raise()
        if cols.truth is not None and self._truth_ch is None:
            self._raise()
        self.wait_drained(max_backlog=1)
        if cols.n:
            self._queue.append((_COLUMNS, cols, cols.log_time_ns[-1]))
            self._wake.set()

    def event(self, e: Event, log_time_ns: int) -> None:
        """Queue one event; events are rare and never dropped."""
        if self._error is not None or self._closed:
            self._raise()
        self._queue.append((self._event_ch, e, log_time_ns))

    def wait_drained(self, max_backlog: int = 0, timeout: float | None = None) -> bool:
        """Block until at most `max_backlog` records wait; lets a faster-than-real-time
        producer (the simulator) pace itself to the writer. Returns False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._progress:
            # Queue length first, then the batch in flight: read in this order the sum
            # never misses a record the writer has popped but not yet written.
            while len(self._queue) + self._in_flight > max_backlog:
                if self._error is not None or self._closed:
                    self._raise()
                self._wake.set()
                left = _POLL_S if deadline is None else min(_POLL_S, deadline - time.monotonic())
                if left <= 0:
                    return False
                self._progress.wait(left)
        return True

    def close(self) -> None:
        """Write everything queued, finish the file (summary, footer), fsync it. Idempotent;
        raises LogError if the writer thread failed."""
        if not self._closed:
            self._closed = True
            self._stop.set()
            self._wake.set()
            self._thread.join()
            if self._error is not None:
                self._raise()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _raise(self) -> None:
        if self._error is not None:
            raise LogError(f"{self._path}: log writer failed: {self._error!r}") from self._error
        if self._closed:
            raise LogError(f"{self._path}: log is closed")
        raise LogError(f"{self._path}: topic not enabled (LogWriter(truth=True), "
                       "environment=True or thrust_stand=True)")

    # -- consumer side: the writer thread ----------------------------------------------

    def _run(self) -> None:
        background_thread()  # below the loop, above ordinary load (it shares the GIL)
        try:
            while True:
                # Decide before draining, so the final drain sees every record queued
                # before close() (or before the program's threads ended).
                stopping = self._stop.is_set() or self._abandoned()
                self._drain()
                if stopping:
                    break
                self._maybe_flush()
                self._wake.wait(_POLL_S)
                self._wake.clear()
            self._mcap.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._flushed = (self._samples_written, self._last[1])
        except BaseException as e:  # stored, re-raised on the producer side
            self._count_whole_chunks()  # before the error is seen: `flushed` is final then
            self._error = e
        finally:
            try:
                self._file.close()
            except OSError as e:  # after a failed write it retries the buffered tail (ENOSPC)
                self._error = self._error or e  # closed regardless; the first error matters
            with self._progress:
                self._progress.notify_all()

    def _abandoned(self) -> bool:
        """True once nothing can call close() any more: the main thread and every other
        non-daemon thread (except other log writers) have ended. Without this a forgotten
        close() would keep a non-daemon writer thread, and the process, alive forever."""
        if threading.main_thread().is_alive():
            return False
        return not any(
            t.is_alive() and not t.daemon and not t.name.startswith("logwriter ")
            for t in threading.enumerate()
            if t is not threading.current_thread()
        )

    def _drain(self) -> None:
        """Encode and write everything queued, in batches that hand the GIL back."""
        q = self._queue
        popleft = q.popleft
        add = self._mcap.add
        dumps = orjson.dumps
        sample_ch, event_ch = self._sample_ch, self._event_ch
        while q:
            n_samples = 0
            n = self._in_flight = min(len(q), _BATCH)
            for _ in range(n):
                ch, rec, t = popleft()
                if ch == event_ch:
                    self._put_event(rec, t)
                elif ch == _COLUMNS:
                    self._put_columns(rec)
                else:
                    add(ch, t, dumps(rec, option=_RECORD_OPT), rec.seq & _SEQ_MASK)
                    n_samples += ch == sample_ch
            self._samples_written += n_samples
            self._in_flight = 0
            self._last = (rec.t_s, t)
            if self._dropped != self._dropped_logged:
                self._log_drops()
            with self._progress:
                self._progress.notify_all()
            # A producer faster than the writer keeps the queue non-empty: still close
            # chunks on time, so the crash-loss bound holds during a backlog too.
            self._maybe_flush()
            # Hand the GIL back between batches, so a real-time loop waiting for it runs
            # now rather than after the 5 ms switch interval. Not while a backlog builds
            # (a simulator outrunning real time): every hand-back then costs the writer a
            # whole switch interval to get the GIL back, and it would never catch up.
            if len(q) < _YIELD_BELOW:
                os.sched_yield()

    def _maybe_flush(self) -> None:
        if time.monotonic() - self._last_flush >= self._interval:
            self._mcap.flush()  # closes the chunk and flushes the file to the OS
            self._flushed = (self._samples_written, self._last[1])
            self._last_flush = time.monotonic()
            if self._displaced is None:
                self._check_in_place()

    def _check_in_place(self) -> None:
        """Notice a file that was deleted, or whose directory was removed or moved: writes
        to it succeed and `status` would say healthy while nothing reaches the log."""
        fd_st = os.fstat(self._file.fileno())
        if self._noticed_deleted(fd_st):
            return
        try:
            path_st = os.stat(self._path)
        except (FileNotFoundError, NotADirectoryError):
            # Unlinked between the two calls? Then its link count is 0 by now: deleted,
            # not moved (a test's rm landed there about every other run).
            if self._noticed_deleted(os.fstat(self._file.fileno())):
                return
            path_st = None
        except OSError:  # e.g. the directory made unreadable: the file may still be there
            return
        if path_st is None or not os.path.samestat(path_st, fd_st):
            self._displaced = (f"{self._path} is no longer at its path (its directory was "
                               "moved or the file renamed or replaced); what it holds is "
                               "wherever it went")

    def _noticed_deleted(self, fd_st: os.stat_result) -> bool:
        if fd_st.st_nlink != 0:
            return False
        gone = "" if self._path.parent.is_dir() else " (its directory is gone)"
        self._deleted = True
        self._displaced = f"{self._path} was deleted while being written{gone}"
        return True

    def _count_whole_chunks(self) -> None:
        """A chunk that reached the file whole is readable even if the flush after it (or
        its message index) failed: count it, so a reported loss is the real gap."""
        with contextlib.suppress(OSError):
            size = os.fstat(self._file.fileno()).st_size
            for end, counts, log_time in reversed(self._mcap.unflushed):
                if end <= size:
                    self._flushed = (counts[self._sample_ch], log_time)
                    break

    def _log_drops(self) -> None:
        dropped = self._dropped
        t_s, log_time = self._last
        event = Event(
            t_s=t_s,
            kind="log",
            reason="log backlog full: records dropped",
            detail={"dropped_total": dropped, "max_backlog": self._max_backlog},
        )
        _log.warning("%s: %d records dropped (backlog full)", self._path, dropped)
        self._put_event(event, log_time)
        self._dropped_logged = dropped

    def _put_columns(self, cols: Columns) -> None:
        """A Columns item's records, sample then truth per cycle as `sample`/`truth` queue
        them, closing chunks on time as a long backlog does."""
        add, mask = self._mcap.add, _SEQ_MASK
        sample_ch, truth_ch = self._sample_ch, self._truth_ch
        samples = cols.rows("sample")
        truths = cols.rows("truth") if cols.truth is not None else None
        seq_at, t_at = _SAMPLE_KEYS.index("seq"), _SAMPLE_KEYS.index("t_s")
        for j, (t, row) in enumerate(zip(cols.log_time_ns, samples, strict=True)):
            seq = int(row[seq_at]) & mask
            add(sample_ch, t, _SAMPLE_TEMPLATE % row, seq)
            if truths is not None:
                add(truth_ch, t, _TRUTH_TEMPLATE % next(truths), seq)
            if j % _COLUMN_BATCH == _COLUMN_BATCH - 1:
                self._samples_written += _COLUMN_BATCH
                self._last = (float(row[t_at]), t)
                self._maybe_flush()
        self._samples_written += cols.n % _COLUMN_BATCH

    def _put_event(self, event: Event, log_time: int) -> None:
        """An event on /leveler/event and, for Foxglove's Log panel, on /leveler/log."""
        seq = self._event_seq
        self._mcap.add(self._event_ch, log_time, encode_event(event), seq)
        self._mcap.add(self._log_ch, log_time, orjson.dumps(foxglove_log(event, log_time)), seq)
        self._event_seq += 1


__all__ = ["Columns", "LogError", "LogWriter"]
