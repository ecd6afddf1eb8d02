"""The MCAP log: exact round trip, compatibility with mcap's own readers, the crash-loss
bound under a real SIGKILL, damaged files, and failures that must not pass silently."""

from __future__ import annotations

import json
import math
import os
import random
import re
import signal
import struct
import subprocess
import sys
import time
import tracemalloc
import zlib
from collections import deque
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.reader import SeekingReader, make_reader
from mcap.records import MessageIndex
from mcap.stream_reader import StreamReader

from leveler.log import writer as logwriter
from leveler.log.reader import LogError, read_log, recover
from leveler.log.writer import LogWriter
from leveler.records import Event, Sample, Truth

ROOT = Path(__file__).resolve().parents[1]
T0_NS = 1_700_000_000_000_000_000
STATES = ("idle", "engaged", "fault")


def make_sample(seq: int, rng: random.Random) -> Sample:
    return Sample(
        seq=seq,
        t_s=seq * 1e-3,
        raw_counts=rng.randrange(-32768, 32768),
        sensor_m=rng.gauss(0, 1e-6),
        status=rng.randrange(5),
        setpoint_m=rng.choice((0.0, 1.5e-7)),
        error_m=rng.gauss(0, 1e-6),
        p_v=rng.gauss(0, 0.1),
        i_v=rng.gauss(0, 0.1),
        d_v=rng.gauss(0, 0.1),
        command_v=rng.uniform(-10, 10),
        applied_v=rng.uniform(-10, 10),
        saturated=rng.random() < 0.5,
        state=rng.choice(STATES),
    )


def make_truth(seq: int, rng: random.Random) -> Truth:
    return Truth(
        seq,
        seq * 1e-3,
        *(rng.gauss(0, 1e-6) for _ in range(4)),
        rng.gauss(0, 1e-3),
        293.15 + rng.gauss(0, 0.01),
        rng.gauss(0, 1e-9),
    )


def write_log(path: Path, n: int, **kwargs: object) -> tuple[list[Sample], list[Truth]]:
    rng = random.Random(1)
    samples = [make_sample(i, rng) for i in range(n)]
    truths = [make_truth(i, rng) for i in range(n)]
    with LogWriter(path, truth=True, **kwargs) as w:
        for s, t in zip(samples, truths, strict=True):
            w.sample(s, T0_NS + s.seq * 1_000_000)
            w.truth(t, T0_NS + t.seq * 1_000_000)
    assert w.dropped == 0
    return samples, truths


def assert_columns(cols: dict[str, np.ndarray], records: list, kind: type) -> None:
    names = [f.name for f in fields(kind)]
    assert set(cols) == {"log_time_ns", *names}
    np.testing.assert_array_equal(cols["log_time_ns"], [T0_NS + r.seq * 1_000_000 for r in records])
    for name in names:
        expected = np.array([getattr(r, name) for r in records])
        assert cols[name].dtype.kind == expected.dtype.kind, name
        np.testing.assert_array_equal(cols[name], expected, err_msg=name)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_round_trip_is_exact(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "run.mcap"
    rng = random.Random(1)
    samples = [make_sample(i, rng) for i in range(3000)]
    truths = [make_truth(i, rng) for i in range(3000)]
    events = [
        Event(0.0, "start", "daemon started", {"config": "config/lab.toml"}),
        Event(1.2345, "gain", "operator", {"kp": 1.5, "nested": {"ki": [1, 2.5, None]}}),
        Event(2.999, "fault", "sensor railed – ±10 V", {"count": 3, "ok": False}),
    ]
    metadata = {"config": "[loop]\nrate_hz = 1000\n", "version": "0.1.0", "started_utc": "x"}
    with LogWriter(
        path, metadata=metadata, truth=True, compression=compression, chunk_size=64 * 1024
    ) as w:
        for i, (s, t) in enumerate(zip(samples, truths, strict=True)):
            w.sample(s, T0_NS + i * 1_000_000)
            w.truth(t, T0_NS + i * 1_000_000)
            if i % 1000 == 0:
                e = events[i // 1000]
                w.event(e, T0_NS + round(e.t_s * 1e9))
    assert w.samples_written == 3000 and w.dropped == 0

    log = read_log(path)
    assert log.complete and log.stop_reason == ""
    assert_columns(log.samples, samples, Sample)
    assert_columns(log.truth, truths, Truth)
    assert log.samples["state"].dtype.kind == "U" and log.samples["saturated"].dtype == bool
    assert log.events == [
        {
            "log_time_ns": T0_NS + round(e.t_s * 1e9),
            "t_s": e.t_s,
            "kind": e.kind,
            "reason": e.reason,
            "detail": e.detail,
        }
        for e in events
    ]
    assert log.metadata == {"leveler": metadata}


def test_non_finite_floats_come_back_as_nan(tmp_path: Path) -> None:
    rng = random.Random(2)
    s = make_sample(0, rng)
    s.sensor_m, s.error_m, s.applied_v = math.nan, math.inf, np.float64(-math.inf)
    s.raw_counts, s.saturated = np.int64(7), np.bool_(True)  # numpy scalars encode too
    with LogWriter(tmp_path / "nan.mcap") as w:
        w.sample(s, T0_NS)
    cols = read_log(tmp_path / "nan.mcap").samples
    assert np.isnan(cols["sensor_m"][0]) and np.isnan(cols["error_m"][0])
    assert np.isnan(cols["applied_v"][0])
    assert cols["raw_counts"][0] == 7 and cols["saturated"][0]


def test_no_truth_and_no_samples_give_empty_tables(tmp_path: Path) -> None:
    with LogWriter(tmp_path / "empty.mcap"):
        pass
    log = read_log(tmp_path / "empty.mcap")
    assert log.complete and log.truth == {} and log.events == []
    assert set(log.samples) == {"log_time_ns", *Sample.__slots__}
    assert all(len(v) == 0 for v in log.samples.values())
    assert log.samples["t_s"].dtype == np.float64


def test_mcap_seeking_reader_opens_it(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    samples, _ = write_log(path, 5000, chunk_size=32 * 1024, metadata={"version": "9"})
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert isinstance(reader, SeekingReader)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = {c.id: c.topic for c in summary.channels.values()}
        counts = {topics[c]: n for c, n in summary.statistics.channel_message_counts.items()}
        assert counts == {"/leveler/sample": 5000, "/leveler/truth": 5000}
        assert summary.statistics.message_count == 10000
        assert summary.statistics.message_start_time == T0_NS
        assert summary.statistics.message_end_time == T0_NS + 4999 * 1_000_000
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count > 10
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            doc = json.loads(schema.data)
            assert doc["type"] == "object"
            assert all(p["type"] and p["description"] for p in doc["properties"].values())
        assert reader.get_header().library.startswith("leveler ")
        assert [m.metadata for m in reader.iter_metadata()] == [{"version": "9"}]
        seqs = [m.sequence for _, c, m in reader.iter_messages(topics=["/leveler/sample"])]
        assert seqs == list(range(5000))
        seen = [json.loads(m.data) for _, _, m in reader.iter_messages(log_time_order=False)]
        assert len(seen) == 10000 and seen[0] == json.loads(
            json.dumps({f: getattr(samples[0], f) for f in Sample.__slots__})
        )
        # Message indexes (which mcap's Python reader skips) must point at the messages.
        indexed = 0
        for ci in summary.chunk_indexes:
            f.seek(ci.chunk_start_offset + 9 + 8 * 3 + 4)
            name = f.read(int.from_bytes(f.read(4), "little")).decode()
            data = f.read(int.from_bytes(f.read(8), "little"))
            chunk = zstandard.ZstdDecompressor().decompress(data, ci.uncompressed_size)
            assert name == "zstd"
            for offset in ci.message_index_offsets.values():
                f.seek(offset + 9)
                for log_time, pos in MessageIndex.read(ReadDataStream(f)).records:
                    assert chunk[pos] == 0x05  # a Message record starts there
                    assert int.from_bytes(chunk[pos + 15 : pos + 23], "little") == log_time
                    indexed += 1
        assert indexed == 10000
    # Footer CRC per the spec: summary section through the footer's summary_offset_start.
    raw = path.read_bytes()
    summary_start, _, summary_crc = struct.unpack("<QQI", raw[-8 - 20 : -8])
    assert zlib.crc32(raw[summary_start : -8 - 4]) == summary_crc
    # mcap's streaming reader with CRC checks walks the whole file without complaint.
    with open(path, "rb") as f:
        assert sum(1 for _ in StreamReader(f, validate_crcs=True).records) > 10000


def test_schemas_and_docs_cover_every_record_field() -> None:
    docs = (ROOT / "docs" / "log-format.md").read_text()
    for kind, described in [
        (Sample, logwriter._SAMPLE_FIELDS),
        (Truth, logwriter._TRUTH_FIELDS),
        (Event, logwriter._EVENT_FIELDS),
    ]:
        assert list(described) == [f.name for f in fields(kind)]
        for name in described:
            assert f"`{name}`" in docs, f"docs/log-format.md does not describe {name}"


CHILD = """
import sys, time
from leveler.log.writer import LogWriter
from leveler.records import Sample
path, rate = sys.argv[1], float(sys.argv[2])
w = LogWriter(path, chunk_interval_s=1.0)
out = open(sys.argv[3], "w")
t0 = time.monotonic()
for seq in range(10**9):
    delay = t0 + seq / rate - time.monotonic()
    if delay > 0:
        time.sleep(delay)
    w.sample(Sample(seq, seq / rate, 0, 1e-6, 0, 0.0, -1e-6, 0.1, 0.2, 0.3, 0.6, 0.6, False,
                    "engaged"), time.time_ns())
    out.write(f"{seq + 1}\\n")
    out.flush()
"""


def test_sigkill_loses_at_most_about_one_second(tmp_path: Path) -> None:
    """Real crash: SIGKILL writers paced in real time, then recover what they left."""
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    rates = (10.0, 100.0, 1000.0)
    runs = []
    for rate in rates:
        log, count = tmp_path / f"{rate:g}.mcap", tmp_path / f"{rate:g}.count"
        proc = subprocess.Popen(
            [sys.executable, str(script), str(log), str(rate), str(count)], env=env
        )
        runs.append((rate, log, count, proc))
    try:
        deadline = time.monotonic() + 20
        while not all(c.exists() and c.read_text() for _, _, c, _ in runs):
            assert time.monotonic() < deadline, "writers did not start"
            assert all(p.poll() is None for *_, p in runs), "a writer died"
            time.sleep(0.05)
        time.sleep(3.0)
    finally:
        for *_, proc in runs:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
    for rate, log, count, proc in runs:
        assert proc.returncode == -signal.SIGKILL
        handed = int(count.read_text().split()[-1])
        data = read_log(log)
        got = len(data.samples["seq"])
        lost = handed - got
        print(
            f"{rate:g} Hz: handed {handed}, readable {got}, lost {lost} "
            f"({lost / rate:.2f} s); {data.stop_reason}"
        )
        assert not data.complete and data.stop_reason
        np.testing.assert_array_equal(data.samples["seq"], np.arange(got))
        assert handed >= 2.5 * rate  # really ran ~3 s
        assert -1 <= lost <= 1.5 * rate, f"{rate} Hz: lost {lost} samples"

        fixed = tmp_path / f"{rate:g}-recovered.mcap"
        assert recover(log, fixed) == got
        again = read_log(fixed)
        assert again.complete
        np.testing.assert_array_equal(again.samples["seq"], np.arange(got))
        np.testing.assert_array_equal(again.samples["t_s"], data.samples["t_s"])
        with open(fixed, "rb") as f:
            stats = make_reader(f).get_summary().statistics
            assert stats.message_count == got


def test_data_is_readable_while_the_writer_runs(tmp_path: Path) -> None:
    """The in-process face of the crash bound: closed chunks are on disk without close()."""
    path = tmp_path / "live.mcap"
    rng = random.Random(3)
    with LogWriter(path, chunk_interval_s=0.2) as w:
        for i in range(5):
            w.sample(make_sample(i, rng), T0_NS + i)
        time.sleep(0.5)
        live = read_log(path)
        assert not live.complete
        np.testing.assert_array_equal(live.samples["seq"], np.arange(5))
    assert read_log(path).complete


def test_not_mcap_raises_log_error(tmp_path: Path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("this is not a log\n")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    for path in (text, empty):
        with pytest.raises(LogError, match=re.escape(f"{path}: not an MCAP file")):
            read_log(path)
    with pytest.raises(LogError, match="not an MCAP file"):
        recover(text, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()
    with pytest.raises(LogError, match="cannot open"):
        read_log(tmp_path / "missing.mcap")
    with pytest.raises(LogError, match="cannot create log"):
        LogWriter(tmp_path / "no" / "such" / "dir.mcap")


def test_truncated_and_corrupted_files_read_up_to_the_damage(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    write_log(path, 20000, chunk_size=64 * 1024)
    whole = path.read_bytes()
    with open(path, "rb") as f:
        chunk_offsets = [c.chunk_start_offset for c in make_reader(f).get_summary().chunk_indexes]
    cases = {
        "half": whole[: len(whole) // 2],
        "in chunk header": whole[: chunk_offsets[5] + 12],
        "before first chunk": whole[: chunk_offsets[0] - 3],
        "in summary": whole[: len(whole) - 200],
        "header only": whole[:20],
        "flipped byte": bytearray(whole),
    }
    cases["flipped byte"][chunk_offsets[10] + 500] ^= 0xFF
    for name, data in cases.items():
        cut = tmp_path / f"{name}.mcap"
        cut.write_bytes(bytes(data))
        log = read_log(cut)
        n = len(log.samples["seq"])
        assert not log.complete and log.stop_reason, name
        np.testing.assert_array_equal(log.samples["seq"], np.arange(n), err_msg=name)
        np.testing.assert_array_equal(
            log.truth.get("seq", []), np.arange(len(log.truth.get("seq", [])))
        )
        expected = {"in summary": 20000, "header only": 0, "before first chunk": 0}
        if name in expected:
            assert n == expected[name], name
        else:
            assert 0 < n < 20000, name
        assert recover(cut, tmp_path / f"{name}-fixed.mcap") >= n


def test_writer_thread_failure_surfaces_as_log_error(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    w = LogWriter(path)
    bad = make_sample(0, random.Random(4))
    bad.state = object()  # type: ignore[assignment]  # orjson cannot encode it
    w.sample(bad, T0_NS)
    with pytest.raises(LogError, match=re.escape(f"{path}: log writer failed")) as err:
        w.wait_drained(0, timeout=10)
    assert isinstance(err.value.__cause__, TypeError)  # orjson's error, chained
    assert "not JSON serializable" in str(err.value)
    with pytest.raises(LogError, match="log writer failed"):
        w.sample(make_sample(1, random.Random(4)), T0_NS)
    with pytest.raises(LogError, match="log writer failed"):
        w.close()
    w.close()  # idempotent once reported
    assert not w._thread.is_alive()


def test_closed_log_and_disabled_truth_refuse(tmp_path: Path) -> None:
    w = LogWriter(tmp_path / "a.mcap")
    with pytest.raises(LogError, match="topic not enabled"):
        w.truth(make_truth(0, random.Random(5)), T0_NS)
    w.close()
    with pytest.raises(LogError, match="closed"):
        w.sample(make_sample(0, random.Random(5)), T0_NS)
    with pytest.raises(ValueError, match="compression"):
        LogWriter(tmp_path / "b.mcap", compression="gzip")


def test_full_backlog_drops_counts_and_logs_it(tmp_path: Path) -> None:
    path = tmp_path / "drops.mcap"
    rng = random.Random(6)
    samples = [make_sample(i, rng) for i in range(50000)]
    with LogWriter(path, max_backlog=100) as w:
        for s in samples:  # far faster than the writer encodes
            w.sample(s, T0_NS + s.seq)
    assert w.dropped > 0 and w.samples_written + w.dropped == 50000
    log = read_log(path)
    assert len(log.samples["seq"]) == w.samples_written
    assert np.all(np.diff(log.samples["seq"]) > 0)
    drops = [e for e in log.events if e["kind"] == "log"]
    assert drops and drops[-1]["detail"]["dropped_total"] == w.dropped


def test_wait_drained_paces_a_fast_producer(tmp_path: Path) -> None:
    rng = random.Random(7)
    samples = [make_sample(i, rng) for i in range(20000)]
    with LogWriter(tmp_path / "sim.mcap", max_backlog=1000) as w:
        for s in samples:
            if w.backlog > 500:
                assert w.wait_drained(100, timeout=10)
            w.sample(s, T0_NS + s.seq)
        assert w.wait_drained(0, timeout=10) and w.backlog == 0
    assert w.dropped == 0 and w.samples_written == 20000


ABANDON = """
import sys, threading, time
from leveler.log.writer import LogWriter
from leveler.records import Sample
w = LogWriter(sys.argv[1])
def worker():  # keeps logging after the main thread has returned; nobody calls close()
    for seq in range(50):
        w.sample(Sample(seq, seq * 0.01, 0, 0.0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False,
                        "idle"), time.time_ns())
        time.sleep(0.01)
threading.Thread(target=worker).start()
"""


def test_forgotten_close_still_finishes_the_file_and_exits(tmp_path: Path) -> None:
    script, path = tmp_path / "abandon.py", tmp_path / "abandon.mcap"
    script.write_text(ABANDON)
    done = subprocess.run(
        [sys.executable, str(script), str(path)],
        timeout=20,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )
    assert done.returncode == 0
    log = read_log(path)
    assert log.complete
    np.testing.assert_array_equal(log.samples["seq"], np.arange(50))


def test_recover_refuses_to_overwrite_its_source(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    write_log(path, 10)
    with pytest.raises(LogError, match="overwrite"):
        recover(path, path)
    assert read_log(path).complete


def test_read_is_fast_enough(tmp_path: Path) -> None:
    """Guards against an accidental per-message slow path (mcap's parser: ~14 us/msg)."""
    path = tmp_path / "big.mcap"
    write_log(path, 30000)
    t = time.perf_counter()
    log = read_log(path)
    per_msg = (time.perf_counter() - t) / 60000
    assert len(log.samples["seq"]) == 30000
    assert per_msg < 40e-6, f"{per_msg * 1e6:.1f} us per message"


def test_sample_is_a_cheap_hand_off(tmp_path: Path) -> None:
    """The loop thread's cost per sample(): a deque append, not an encode or a write.
    Timed against a bare append measured in the same run (best of five each, so a busy
    machine slows both): sample() is ~2x that, an encode would be 20x and more."""
    s = make_sample(0, random.Random(8))
    bare: deque[tuple[Sample, int]] = deque()

    def best(call: Callable[[], None]) -> float:
        times = []
        for _ in range(5):
            t = time.perf_counter()
            for _ in range(2000):
                call()
            times.append(time.perf_counter() - t)
        return min(times) / 2000

    with LogWriter(tmp_path / "cheap.mcap") as w:
        per_call = best(lambda: w.sample(s, T0_NS))
        baseline = best(lambda: bare.append((s, T0_NS)))
    assert w.samples_written == 10000
    assert per_call < 10 * baseline, (f"{per_call * 1e6:.2f} us per sample(), "
                                      f"{baseline * 1e6:.2f} us per bare append")


def test_an_open_file_holds_about_a_hundred_bytes_per_chunk_in_memory(tmp_path: Path) -> None:
    """The summary's chunk indexes stay in memory until the file is finished: at a chunk a
    second, a day's file. As ChunkIndex objects that was ~700 bytes a chunk (2.3 MiB/h of
    daemon growth in the 1 kHz soak); serialized, it is the bytes the summary will hold."""
    from leveler.log.writer import _McapFile

    out = (tmp_path / "x.mcap").open("wb")
    f = _McapFile(out, "test", "zstd", 1 << 20)
    ch = f.channel("/t", "t", b"{}")
    f.add(ch, 0, b"{}", 0)
    f.flush()  # warm-up: first-use allocations are not per chunk
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for i in range(1, 2001):
            f.add(ch, i, b'{"x": 1}', i)
            f.flush()  # as the writer does every chunk_interval_s
        per_chunk = (tracemalloc.get_traced_memory()[0] - before) / 2000
    finally:
        tracemalloc.stop()
        out.close()
    assert per_chunk < 150, f"{per_chunk:.0f} bytes retained per chunk"
