"""Import another system's recording (CSV) into a leveler MCAP log.

replay, diagnose and asd only read leveler logs; converting once lets them analyse data from
other stands without each learning a new format. The input is checked completely before the
output is created, because a silently shifted or gappy time base would corrupt every spectrum
computed from it. Format: docs/log-format.md, "Importing other systems' data (CSV)".
"""

from __future__ import annotations

import contextlib
import math
import os
from array import array
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from leveler import __version__
from leveler.errors import LogError
from leveler.log.writer import LogWriter
from leveler.records import Environment, Event, Sample

T_S, ACTUATOR_V, SENSOR_M, TEMPERATURE_K = "t_s", "actuator_v", "sensor_m", "temperature_k"
REQUIRED = (T_S, ACTUATOR_V, SENSOR_M)
MIN_ROWS = 16
UNIFORM_TOLERANCE = 0.01  # largest relative deviation of an interval from the median
MAX_LISTED = 20  # bad rows named one by one in a message
_DRAIN_EVERY = 10_000  # rows between waits for the writer thread
_MAX_BACKLOG = 20_000  # well under LogWriter's drop threshold, so nothing is ever dropped
_MAX_LOG_TIME_NS = 2**63  # MCAP log times are uint64; stay clear of the top bit


@dataclass
class BadRow:
    line: int  # 1-based line number in the file
    reason: str

    def __str__(self) -> str:
        return f"line {self.line}: {self.reason}"


@dataclass
class CsvData:
    """The accepted rows of a CSV file as columns, plus what was left out and why."""

    path: Path
    header: str  # the header line as found
    ignored: list[str]  # names of columns not imported
    t_s: array = field(default_factory=lambda: array("d"))
    actuator_v: array = field(default_factory=lambda: array("d"))
    sensor_m: array = field(default_factory=lambda: array("d"))
    temperature_k: array | None = None
    lines: array = field(default_factory=lambda: array("q"))  # line number of each row
    bad: list[BadRow] = field(default_factory=list)
    interval_s: float = math.nan  # median sampling interval

    @property
    def rows(self) -> int:
        return len(self.t_s)

    @property
    def duration_s(self) -> float:
        return self.t_s[-1] - self.t_s[0] if self.rows else 0.0


@dataclass
class _Columns:
    """Where the needed values sit in a row."""

    count: int
    t: int
    v: int
    s: int
    k: int | None
    ignored: list[str]


def _lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number, text) of every line; undecodable bytes become a LogError naming the line.

    Streams the file: a day at 1 kHz does not have to fit in memory as text.
    """
    try:
        f = open(path, encoding="utf-8-sig", newline="")  # -sig: drop a BOM (spreadsheets)
    except FileNotFoundError:
        raise LogError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise LogError(f"{path}: is a directory, not a CSV file") from None
    except OSError as e:
        raise LogError(f"{path}: cannot open: {e.strerror}") from None
    lineno = 0
    with f:
        try:
            for lineno, line in enumerate(f, 1):
                yield lineno, line
        except UnicodeDecodeError:
            raise LogError(f"{path}: line {_first_bad_utf8(path, lineno)}: not UTF-8 "
                           "text") from None
        except OSError as e:
            raise LogError(f"{path}: cannot read after line {lineno}: {e.strerror}") from None


def _first_bad_utf8(path: Path, after: int) -> int:
    """The line holding the first invalid UTF-8 (text mode decodes ahead in blocks)."""
    with open(path, "rb") as f:
        for lineno, raw in enumerate(f, 1):
            if lineno > after:
                try:
                    raw.decode("utf-8")
                except UnicodeDecodeError:
                    return lineno
    return after + 1


def _skippable(line: str) -> bool:
    """Blank lines and comments (first non-blank character '#') carry no data."""
    s = line.strip()
    return not s or s[0] == "#"


def _columns(path: Path, lineno: int, header: str) -> _Columns:
    """Locate the needed columns by name: case-insensitive, any order, extras ignored."""
    names = [n.strip().strip('"').strip() for n in header.split(",")]
    found: dict[str, int] = {}
    ignored = []
    for i, name in enumerate(names):
        key = name.lower()
        if key in (*REQUIRED, TEMPERATURE_K):
            if key in found:
                raise LogError(f"{path}: line {lineno}: column {name!r} appears twice in the "
                               f"header {header.strip()!r}")
            found[key] = i
        else:
            ignored.append(name or f"(unnamed column {i + 1})")
    missing = [n for n in ("t_s", "actuator_V", "sensor_m") if n.lower() not in found]
    if missing:
        raise LogError(
            f"{path}: line {lineno}: required column{'s' if len(missing) > 1 else ''} "
            f"{', '.join(missing)} missing; the header found is {header.strip()!r} (needed: "
            "t_s, actuator_V, sensor_m, optional temperature_K; see docs/log-format.md)")
    return _Columns(len(names), found[T_S], found[ACTUATOR_V], found[SENSOR_M],
                    found.get(TEMPERATURE_K), ignored)


def _field_count(n: int, ncols: int) -> str:
    return f"{n} field{'s' if n != 1 else ''}, the header has {ncols}"


def _why_bad(parts: list[str], cols: _Columns) -> str:
    """Why a row that failed the fast path was refused (slow; only for bad rows)."""
    named = [(T_S, cols.t), ("actuator_V", cols.v), ("sensor_m", cols.s)]
    if cols.k is not None:
        named.append(("temperature_K", cols.k))
    for name, i in named:
        text = parts[i].strip()
        try:
            value = float(text)
        except ValueError:
            return f"{name} is not a number: {text!r}" if text else f"{name} is empty"
        if not math.isfinite(value):
            return f"{name} is {text!r} (not finite)"
    return "unreadable row"  # pragma: no cover - the fast path accepted every field


def _parse_rows(data: CsvData, lines: Iterator[tuple[int, str]], cols: _Columns) -> None:
    """The hot loop: one split and a few float() per line, rows appended to typed arrays.

    A row whose time is not after the last accepted row's is refused, so the accepted
    rows are strictly increasing whatever was skipped.
    """
    ncols, it, iv, is_, ik = cols.count, cols.t, cols.v, cols.s, cols.k
    ts, vs, ss, ls = data.t_s, data.actuator_v, data.sensor_m, data.lines
    ks = data.temperature_k if data.temperature_k is not None else array("d")
    bad = data.bad
    isfinite = math.isfinite
    last_t, last_line = -math.inf, 0
    for lineno, line in lines:
        c = line[:1]
        if c == "#" or (c in " \t" and _skippable(line)):
            continue
        parts = line.split(",")
        if len(parts) != ncols:
            if not _skippable(line):
                bad.append(BadRow(lineno, _field_count(len(parts), ncols)))
            continue
        try:
            t = float(parts[it])
            v = float(parts[iv])
            s = float(parts[is_])
            k = 0.0 if ik is None else float(parts[ik])
        except ValueError:
            if not _skippable(line):
                bad.append(BadRow(lineno, _why_bad(parts, cols)))
            continue
        if not (isfinite(t) and isfinite(v) and isfinite(s) and isfinite(k)):
            bad.append(BadRow(lineno, _why_bad(parts, cols)))
            continue
        if t <= last_t:
            bad.append(BadRow(lineno, f"t_s {t!r} is not after {last_t!r} (line {last_line}): "
                              "time must increase strictly"))
            continue
        last_t, last_line = t, lineno
        ts.append(t)
        vs.append(v)
        ss.append(s)
        ls.append(lineno)
        if ik is not None:
            ks.append(k)


def listing(bad: list[BadRow]) -> str:
    """The bad rows, one a line, at most MAX_LISTED of them."""
    shown = "\n".join(f"  {b}" for b in bad[:MAX_LISTED])
    more = f"\n  ... and {len(bad) - MAX_LISTED} more" if len(bad) > MAX_LISTED else ""
    return f"{shown}{more}"


def _check_uniform(data: CsvData) -> None:
    """Refuse gaps and jitter: replay and the spectra assume one constant sample interval."""
    t = np.frombuffer(data.t_s, dtype=np.float64)
    dt = np.diff(t)
    median = float(np.median(dt))
    off = np.abs(dt - median) > UNIFORM_TOLERANCE * median
    if off.any():
        i = int(np.argmax(off))
        hint = f" ({len(data.bad)} skipped bad rows leave gaps too)" if data.bad else ""
        raise LogError(
            f"{data.path}: line {data.lines[i + 1]}: sampling is not uniform: {dt[i]:.9g} s "
            f"since line {data.lines[i]}, median interval {median:.9g} s; {int(off.sum())} of "
            f"{len(dt)} intervals are more than {UNIFORM_TOLERANCE:.0%} off{hint}. Gaps or "
            "jitter would corrupt replay; resample the data to a uniform time base first.")
    data.interval_s = median


def read_csv(path: str | Path, *, skip_bad: bool = False) -> CsvData:
    """Parse and check a whole CSV file; raises LogError for anything that cannot be imported.

    With skip_bad, bad rows are left out and listed in the result's `bad`; without it any
    bad row is an error listing the first MAX_LISTED of them by line number.
    """
    path = Path(path)
    lines = _lines(path)
    for lineno, line in lines:
        if not _skippable(line):
            cols = _columns(path, lineno, line)
            header = line.strip()
            break
    else:
        raise LogError(f"{path}: no header line (the file is empty or only comments)")
    data = CsvData(path, header, cols.ignored)
    if cols.k is not None:
        data.temperature_k = array("d")
    _parse_rows(data, lines, cols)
    if data.bad and not skip_bad:
        raise LogError(f"{path}: {len(data.bad)} bad row{'s' if len(data.bad) > 1 else ''} "
                       f"(fix them, or --skip-bad to leave them out):\n{listing(data.bad)}")
    if data.rows < MIN_ROWS:
        what = "no data rows" if not data.rows else f"only {data.rows} good data rows"
        raise LogError(f"{path}: {what} after the header; at least {MIN_ROWS} are needed")
    _check_uniform(data)
    return data


def _log_times(t: np.ndarray, path: Path) -> list[int]:
    """MCAP log times (ns, unsigned): t_s as is, or from the first row if t_s goes negative."""
    offset = min(float(t[0]), 0.0)
    ns = np.rint((t - offset) * 1e9)
    if ns[-1] >= _MAX_LOG_TIME_NS:
        raise LogError(f"{path}: t_s up to {t[-1]:.9g} s does not fit an MCAP log time "
                       "(nanoseconds, 64 bit); subtract a start time first")
    return ns.astype(np.int64).tolist()


def _write(data: CsvData, dest: Path, out: Path) -> None:
    """Write every row to `dest`, pacing ourselves to the writer thread so nothing drops."""
    path = str(data.path.resolve())
    metadata = {
        "source": "import-csv",
        "csv": path,
        "rows": str(data.rows),
        "version": __version__,
        "columns": data.header,
        "skipped_rows": str(len(data.bad)),
    }
    times = _log_times(np.frombuffer(data.t_s, dtype=np.float64), data.path)
    ks = data.temperature_k
    writer = LogWriter(dest, environment=ks is not None, metadata=metadata)
    try:
        writer.event(Event(data.t_s[0], "start", "import-csv", {"csv": path}), times[0])
        sample, environment, wait = writer.sample, writer.environment, writer.wait_drained
        rows = zip(data.t_s, data.actuator_v, data.sensor_m, times, strict=True)
        for i, (t, v, s, ns) in enumerate(rows):
            sample(Sample(i, t, 0, s, 0, 0.0, -s, 0.0, 0.0, 0.0, v, v, False, "imported"), ns)
            if ks is not None:
                environment(Environment(i, t, ks[i]), ns)
            if i % _DRAIN_EVERY == _DRAIN_EVERY - 1:
                wait(max_backlog=_MAX_BACKLOG)
        writer.event(Event(data.t_s[-1], "stop", "import-csv", {"csv": path, "rows": data.rows}),
                     times[-1])
    finally:
        writer.close()
    if writer.dropped or writer.samples_written != data.rows:
        raise LogError(f"{out}: {writer.dropped} records dropped, {writer.samples_written} of "
                       f"{data.rows} samples written")


def write_log(data: CsvData, out: str | Path, *, force: bool = False) -> None:
    """Write `data` to `out` atomically: a crash or error never leaves a partial log there."""
    out = Path(out)
    if out.is_dir():
        raise LogError(f"{out}: is a directory")
    if not out.parent.is_dir():
        raise LogError(f"{out}: directory {out.parent} does not exist")
    if out.exists():
        if out.resolve() == data.path.resolve():
            raise LogError(f"{out}: is the CSV file itself")
        if not force:
            raise LogError(f"{out}: already exists (--force replaces it)")
    partial = out.with_name(out.name + ".partial")
    try:
        _write(data, partial, out)
        os.replace(partial, out)
    except BaseException as e:
        with contextlib.suppress(OSError):
            partial.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise LogError(f"{out}: cannot write: {e.strerror or e}") from None
        raise


def import_csv(path: str | Path, out: str | Path, *, skip_bad: bool = False,
               force: bool = False) -> CsvData:
    """Read, check and convert one CSV file; returns what was imported."""
    data = read_csv(path, skip_bad=skip_bad)
    write_log(data, out, force=force)
    return data


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds:.6g} s ({seconds / 3600:.3g} h)"
    return f"{seconds:.6g} s"


def summary(data: CsvData, out: str | Path) -> str:
    """One line saying what the log holds and what was left out."""
    temperature = "yes" if data.temperature_k is not None else "no"
    ignored = ", ".join(data.ignored) or "none"
    return (f"imported {data.rows} rows from {data.path} into {out}: "
            f"{_duration(data.duration_s)} at {1.0 / data.interval_s:.6g} Hz, "
            f"temperature: {temperature}, ignored columns: {ignored}, "
            f"skipped bad rows: {len(data.bad)}")


__all__ = ["BadRow", "CsvData", "import_csv", "listing", "read_csv", "summary", "write_log"]
