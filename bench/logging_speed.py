"""Logging: leveler's LogWriter against the plain `mcap` Writer, in the same run.

Both get the same records: Sample objects from a short closed-loop simulation, encoded
with orjson exactly as LogWriter encodes them, zstd chunks of 1 MiB (LogWriter's default
chunk_size; also mcap.Writer's), one file each, finished and fsynced. The only difference
is the writer, and one that comes with it: LogWriter compresses at zstd level 1, mcap.Writer
at zstandard's default (level 3).

- sustained samples/s: the loop's hand-off (`LogWriter.sample`, pacing with `wait_drained`
  as `leveler sim` does) until close() returns, against a plain loop of
  `orjson.dumps` + `Writer.add_message` until finish() and fsync. Goal: >= 0.5x of raw.
- CPU at 1 kHz: samples fed at 1 kHz for a while; the writer thread's own CPU time
  (its pthread CPU clock) over the wall time. Goal: < 5 % of one core.
- bytes per sample: leveler's file size over the samples in it.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

import orjson
from common import REPO, at_least, bench_tmpdir, row  # beside this script
from mcap.writer import CompressionType, Writer

from leveler.log.reader import SAMPLE_TOPIC
from leveler.log.writer import LogWriter
from leveler.records import Event, Sample, Truth
from leveler.settings import load_config
from leveler.virtual import run_virtual

SECTION = "logging"
POOL = 20_000  # distinct samples, cycled; more than the ~3,500 in a 1 MiB chunk
_PACE_EVERY = 10_000  # as run_virtual: wait for the writer every so many samples
_PACE_BACKLOG = 20_000
_OPT = orjson.OPT_SERIALIZE_NUMPY  # LogWriter's option for samples


class _Collect:
    """A sink that keeps the loop's Sample records (duck-types the LogWriter run_virtual
    paces)."""

    def __init__(self) -> None:
        self.samples: list[Sample] = []

    def sample(self, s: Sample, log_time_ns: int) -> None:
        self.samples.append(s)

    def truth(self, t: Truth, log_time_ns: int) -> None:
        pass

    def event(self, e: Event, log_time_ns: int) -> None:
        pass

    def wait_drained(self, max_backlog: int = 0, timeout: float | None = None) -> bool:
        return True


def sample_pool(n: int = POOL) -> list[Sample]:
    """n samples of the closed loop on the default simulated stand."""
    cfg, _ = load_config(REPO / "config" / "sim.toml")
    sink = _Collect()
    run_virtual(cfg, n / cfg.loop.rate_hz, 1, engaged=True, writer=sink)  # type: ignore[arg-type]
    return sink.samples[:n]


def leveler_write(path: Path, pool: list[Sample], n: int) -> float:
    """Seconds for LogWriter to take n samples from the loop's side and finish the file."""
    m = len(pool)
    start = time.perf_counter()
    w = LogWriter(path)
    sample = w.sample
    t0 = time.time_ns()
    for k in range(n):
        sample(pool[k % m], t0 + k * 1_000_000)
        if k % _PACE_EVERY == 0:
            w.wait_drained(max_backlog=_PACE_BACKLOG)
    w.close()
    secs = time.perf_counter() - start
    if w.dropped:
        raise RuntimeError(f"LogWriter dropped {w.dropped} samples")
    return secs


def raw_write(path: Path, pool: list[Sample], n: int) -> float:
    """Seconds for mcap.Writer to write the same n samples, same JSON bytes, and finish."""
    m = len(pool)
    dumps = orjson.dumps
    start = time.perf_counter()
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=1 << 20, compression=CompressionType.ZSTD)
        w.start(library="bench raw mcap")
        schema = w.register_schema(name="leveler.Sample", encoding="jsonschema",
                                   data=b'{"type": "object"}')
        ch = w.register_channel(topic=SAMPLE_TOPIC, message_encoding="json", schema_id=schema)
        add = w.add_message
        t0 = time.time_ns()
        for k in range(n):
            s = pool[k % m]
            t = t0 + k * 1_000_000
            add(ch, log_time=t, data=dumps(s, option=_OPT), publish_time=t, sequence=s.seq)
        w.finish()
        f.flush()
        os.fsync(f.fileno())
    return time.perf_counter() - start


def _thread_cpu_s(thread: threading.Thread) -> float:
    assert thread.ident is not None
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


def paced_cpu(path: Path, pool: list[Sample], rate_hz: float,
              duration_s: float) -> dict[str, float]:
    """Feed samples at rate_hz for duration_s; the writer thread's CPU share after a
    one-second warm-up, and the whole process's (feeding loop included)."""
    m = len(pool)
    period = 1.0 / rate_hz
    n = round(duration_s * rate_hz)
    warm = round(rate_hz)
    with LogWriter(path) as w:
        name = f"logwriter {path.name}"
        thread = next(t for t in threading.enumerate() if t.name == name)
        t0 = time.time_ns()
        deadline = time.perf_counter()
        cpu0 = proc0 = wall0 = 0.0
        for k in range(n):
            if k == warm:
                cpu0, proc0, wall0 = _thread_cpu_s(thread), time.process_time(), time.perf_counter()
            w.sample(pool[k % m], t0 + int(k * period * 1e9))
            deadline += period
            left = deadline - time.perf_counter()
            if left > 0:
                time.sleep(left)
        cpu1, proc1, wall1 = _thread_cpu_s(thread), time.process_time(), time.perf_counter()
    wall = wall1 - wall0
    return {"writer_cpu_frac": (cpu1 - cpu0) / wall, "process_cpu_frac": (proc1 - proc0) / wall,
            "rate_hz": (n - warm) / wall, "dropped": w.dropped}


def run(quick: bool) -> list[dict[str, Any]]:
    n = 100_000 if quick else 300_000
    repeats = 1 if quick else 3
    paced_s = 6.0 if quick else 15.0
    pool = sample_pool()
    with bench_tmpdir() as tmp:
        lev_path, raw_path = Path(tmp) / "leveler.mcap", Path(tmp) / "raw.mcap"
        # Interleaved, best of each: both see the machine's load alike.
        lev_s: list[float] = []
        raw_s: list[float] = []
        for _ in range(repeats):
            raw_s.append(raw_write(raw_path, pool, n))
            lev_s.append(leveler_write(lev_path, pool, n))
        lev_bytes, raw_bytes = lev_path.stat().st_size, raw_path.stat().st_size
        cpu = paced_cpu(Path(tmp) / "paced.mcap", pool, 1000.0, paced_s)
    lev_rate, raw_rate = n / min(lev_s), n / min(raw_s)
    ratio = lev_rate / raw_rate
    best = "" if repeats == 1 else f", best of {repeats}"
    return [
        row(SECTION, "raw mcap.Writer, same JSON bytes (baseline)", raw_rate, "samples/s",
            note=f"{n} samples{best}; zstd level 3 (zstandard's default), 1 MiB chunks"),
        row(SECTION, "LogWriter, sustained", lev_rate, "samples/s",
            baseline="raw mcap.Writer", ratio=ratio, goal=">= 0.5x", met=at_least(ratio, 0.5),
            note=f"{n} samples{best}, hand-off to close(); zstd level 1, 1 MiB chunks, "
                 "a chunk closed at least every 1 s"),
        row(SECTION, "LogWriter CPU at 1 kHz (writer thread)", 100.0 * cpu["writer_cpu_frac"],
            "% of a core", goal="< 5 %", met=cpu["writer_cpu_frac"] < 0.05,
            note=f"{paced_s:g} s paced at {cpu['rate_hz']:.0f} samples/s; whole process "
                 f"incl. the feeding loop {100.0 * cpu['process_cpu_frac']:.1f} %"
                 + (f"; {cpu['dropped']} dropped" if cpu["dropped"] else "")),
        row(SECTION, "LogWriter bytes per sample", lev_bytes / n, "B/sample",
            note=f"raw mcap.Writer (zstd level 3): {raw_bytes / n:.1f} B/sample"),
    ]
