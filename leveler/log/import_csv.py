"""Import another system's recording (CSV) into a leveler MCAP log.

replay, diagnose and asd only read leveler logs; converting once lets them analyse data from
other stands without each learning a new format. The input is checked completely before the
output is created, because a silently shifted or gappy time base would corrupt every spectrum
computed from it. Real files come in days, counts and degrees, with their own column names
and delimiters, stray rows and a jittery clock: `ImportOptions` maps and converts them to SI
as they are read, and `--resample` (`leveler.log.resample`) puts a nearly uniform time base on
an exact one, reporting every row it moved, dropped or filled in. Format:
docs/log-format.md, "Importing other systems' data (CSV)".
"""

from __future__ import annotations

import contextlib
import datetime
import math
import os
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from leveler import __version__
from leveler.errors import LogError
from leveler.log.resample import Resampling, resample
from leveler.log.writer import LogWriter
from leveler.records import Environment, Event, Sample, ThrustStand

#: What each column is for, and the header name sought for it unless `--column` says.
ROLES = ("t", "actuator", "sensor", "temperature", "thrust", "displacement", "tilt")
DEFAULT_NAMES = {"t": "t_s", "actuator": "actuator_V", "sensor": "sensor_m",
                 "temperature": "temperature_K", "thrust": "thrust_N",
                 "displacement": "displacement_m", "tilt": "tilt_rad"}
UNITS = {"actuator": "V", "sensor": "m", "temperature": "K", "thrust": "N", "displacement": "m",
         "tilt": "rad"}
#: The columns that make a log: the leveler's loop (its samples), or a torsion-pendulum thrust
#: stand's (`leveler analyze stiffness LOG`); a file needs one pair or both.
LEVELER_PAIR = ("actuator", "sensor")
STAND_PAIR = ("thrust", "displacement")
#: Seconds per unit of the time column (`--time-unit`); "iso" is an ISO 8601 date-time.
TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "min": 60.0, "h": 3600.0, "days": 86400.0}
DELIMITERS = {"comma": ",", "semicolon": ";", "tab": "\t", "space": None}
MIN_ROWS = 16
#: With --resample, a row may be out of order by at most this many rows (a swapped pair, a
#: late flush); one further back is a stray row, not a sample (a clock reset, a test line).
MAX_ROWS_BACK = 10
UNIFORM_TOLERANCE = 0.01  # largest relative deviation of an interval from the median
MAX_LISTED = 20  # bad rows named one by one in a message
_DRAIN_EVERY = 10_000  # rows between waits for the writer thread
_MAX_BACKLOG = 20_000  # well under LogWriter's drop threshold, so nothing is ever dropped
_MAX_LOG_TIME_NS = 2**63  # MCAP log times are uint64; stay clear of the top bit


@dataclass(frozen=True)
class ImportOptions:
    """How to read a file that is not in leveler's own column names and units.

    Each value becomes SI as `raw * scale + offset` (`scale`, `offset` per role): counts to
    metres, degrees Celsius to kelvin."""

    columns: dict[str, str] = field(default_factory=dict)  # role -> header name
    time_unit: str = "s"  # a key of TIME_UNITS_S, or "iso"
    scale: dict[str, float] = field(default_factory=dict)
    offset: dict[str, float] = field(default_factory=dict)
    delimiter: str = "auto"  # a key of DELIMITERS, or "auto": sniffed from the header
    resample: bool = False
    max_gap_s: float | None = None  # longest gap --resample fills (None: 60 intervals)

    def __post_init__(self) -> None:
        for what, roles in (("--column", self.columns), ("--scale", self.scale),
                            ("--offset", self.offset)):
            for role in roles:
                if role not in ROLES:
                    raise LogError(f"{what} {role}=...: unknown column role {role!r} (roles: "
                                   f"{', '.join(ROLES)})")
        for what, roles in (("--scale", self.scale), ("--offset", self.offset)):
            if "t" in roles:
                raise LogError(f"{what} t=...: the time column is converted by --time-unit "
                               f"({', '.join([*TIME_UNITS_S, 'iso'])})")
            for role, value in roles.items():
                if not math.isfinite(value) or (what == "--scale" and value == 0):
                    raise LogError(f"{what} {role}={value!r}: must be a finite"
                                   f"{' non-zero' if what == '--scale' else ''} number")
        names = [self.name(role).lower() for role in ROLES]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise LogError(f"--column: {', '.join(map(repr, twice))} named for two roles; each "
                           "role needs its own column")
        if self.time_unit not in TIME_UNITS_S and self.time_unit != "iso":
            raise LogError(f"--time-unit {self.time_unit!r}: use one of "
                           f"{', '.join([*TIME_UNITS_S, 'iso'])}")
        if self.delimiter != "auto" and self.delimiter not in DELIMITERS:
            raise LogError(f"--delimiter {self.delimiter!r}: use auto or one of "
                           f"{', '.join(DELIMITERS)}")
        if self.max_gap_s is not None and not (self.max_gap_s > 0 and self.resample):
            raise LogError("--max-gap needs --resample and a positive duration")

    def name(self, role: str) -> str:
        return self.columns.get(role, DEFAULT_NAMES[role])

    def converted(self, role: str) -> bool:
        return role in self.scale or role in self.offset

    def describe(self) -> str:
        """The conversions, as the summary and the log's metadata state them."""
        parts = [f"time in {self.time_unit}"]
        for role in ROLES[1:]:
            if self.converted(role):
                parts.append(f"{role} x {self.scale.get(role, 1.0):g} "
                             f"{self.offset.get(role, 0.0):+g} {UNITS[role]}")
        return ", ".join(parts)


def parse_assignments(items: list[str] | None, option: str, *,
                      numeric: bool) -> dict[str, float] | dict[str, str]:
    """`ROLE=VALUE` items of a repeated option, e.g. `--scale sensor=1.75e-6`."""
    out: dict = {}
    for item in items or []:
        role, eq, value = item.partition("=")
        role = role.strip().lower()
        if not eq or not role or not value.strip():
            raise LogError(f"{option} {item!r}: write ROLE=VALUE, e.g. "
                           f"{option} {'sensor=1.75e-9' if numeric else 'sensor=tilt_counts'}")
        if role in out:
            raise LogError(f"{option} {role}=...: given twice")
        if numeric:
            try:
                out[role] = float(value)
            except ValueError:
                raise LogError(f"{option} {item!r}: {value.strip()!r} is not a number") from None
        else:
            out[role] = value.strip()
    return out


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
    options: ImportOptions = field(default_factory=ImportOptions)
    t_s: array = field(default_factory=lambda: array("d"))
    values: dict[str, array] = field(default_factory=dict)  # role -> SI column, as found
    lines: array = field(default_factory=lambda: array("q"))  # line number of each row
    bad: list[BadRow] = field(default_factory=list)
    headers_repeated: list[int] = field(default_factory=list)  # lines repeating the header
    interval_s: float = math.nan  # median sampling interval
    resampling: Resampling | None = None  # what --resample moved, dropped and filled in

    @property
    def rows(self) -> int:
        return len(self.t_s)

    @property
    def duration_s(self) -> float:
        return self.t_s[-1] - self.t_s[0] if self.rows else 0.0

    def column(self, role: str) -> array | None:
        return self.values.get(role)


@dataclass
class _Columns:
    """Where the needed values sit in a row, and how a row is split and its time read."""

    count: int
    t: int
    index: dict[str, int]  # value role -> field index, in ROLES order
    ignored: list[str]
    sep: str | None  # str.split's separator (None: runs of whitespace)
    time: Callable[[str], float]  # the time field as a number (days, s, ... as written)


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


def _iso_seconds(text: str) -> float:
    """An ISO 8601 date-time as seconds since 1970 (UTC unless it carries an offset)."""
    when = datetime.datetime.fromisoformat(text.strip())
    if when.tzinfo is None:
        when = when.replace(tzinfo=datetime.UTC)
    return when.timestamp()


def _separator(path: Path, lineno: int, header: str, options: ImportOptions) -> str | None:
    """The delimiter: as told, or the first of tab, semicolon, comma the header holds."""
    if options.delimiter != "auto":
        return DELIMITERS[options.delimiter]
    for sep in ("\t", ";", ","):
        if sep in header:
            return sep
    if len(header.split()) > 1:
        return None
    raise LogError(f"{path}: line {lineno}: the header {header.strip()!r} has one column; "
                   "columns are separated by commas, semicolons, tabs or spaces (--delimiter)")


def _columns(path: Path, lineno: int, header: str, options: ImportOptions) -> _Columns:
    """Locate the needed columns by name: case-insensitive, any order, extras ignored."""
    sep = _separator(path, lineno, header, options)
    names = [n.strip().strip('"').strip() for n in header.split(sep)]
    wanted = {options.name(role).lower(): role for role in ROLES}
    found: dict[str, int] = {}
    ignored = []
    for i, name in enumerate(names):
        role = wanted.get(name.lower())
        if role is not None:
            if role in found:
                raise LogError(f"{path}: line {lineno}: column {name!r} appears twice in the "
                               f"header {header.strip()!r}")
            found[role] = i
        else:
            ignored.append(name or f"(unnamed column {i + 1})")
    missing = [options.name(r) for r in _needed(found) if r not in found]
    missing += [options.name(r) for r in options.columns if r not in found]
    if missing:
        missing = list(dict.fromkeys(missing))
        raise LogError(
            f"{path}: line {lineno}: column{'s' if len(missing) > 1 else ''} "
            f"{', '.join(missing)} missing; the header found is {header.strip()!r} (needed: "
            "a time column and the leveler's actuator and sensor columns, or a thrust "
            "stand's thrust and displacement columns, or both; named t_s, actuator_V, "
            "sensor_m, thrust_N, displacement_m unless --column t=NAME etc. says; see "
            "docs/log-format.md)")
    if "tilt" in found and "thrust" not in found:
        raise LogError(f"{path}: line {lineno}: a tilt column ({options.name('tilt')}) goes "
                       "with a thrust stand's thrust and displacement columns, which the "
                       f"header {header.strip()!r} lacks")
    time = _iso_seconds if options.time_unit == "iso" else float
    index = {role: found[role] for role in ROLES[1:] if role in found}
    return _Columns(len(names), found["t"], index, ignored, sep, time)


def _needed(found: dict[str, int]) -> tuple[str, ...]:
    """The time and whichever pair the header has begun (the leveler's when neither)."""
    stand = any(r in found for r in STAND_PAIR)
    leveler = any(r in found for r in LEVELER_PAIR) or not stand
    return ("t", *(LEVELER_PAIR if leveler else ()), *(STAND_PAIR if stand else ()))


def _field_count(n: int, ncols: int) -> str:
    return f"{n} field{'s' if n != 1 else ''}, the header has {ncols}"


def _why_bad(parts: list[str], cols: _Columns, options: ImportOptions) -> str:
    """Why a row that failed the fast path was refused (slow; only for bad rows)."""
    for role, i in [("t", cols.t), *cols.index.items()]:
        name, text = options.name(role), parts[i].strip()
        try:
            value = cols.time(text) if role == "t" else float(text)
        except ValueError:
            if not text:
                return f"{name} is empty"
            form = "an ISO 8601 date-time" if role == "t" and cols.time is _iso_seconds \
                else "a number"
            return f"{name} is not {form}: {text!r}"
        if not math.isfinite(value):
            return f"{name} is {text!r} (not finite)"
    return "unreadable row"  # pragma: no cover - the fast path accepted every field


def _parse_rows(data: CsvData, lines: Iterator[tuple[int, str]], cols: _Columns,
                header: str) -> None:
    """The hot loop: one split and a few float() per line, rows appended to typed arrays.

    A row whose time is not after the last accepted row's is refused, so the accepted
    rows are strictly increasing whatever was skipped; with --resample a row up to
    MAX_ROWS_BACK rows out of order is kept (the resampling sorts it in and reports it).
    A line repeating the header (a logger restarted) is skipped and noted.
    """
    ncols, it, sep, time = cols.count, cols.t, cols.sep, cols.time
    index = list(cols.index.values())
    appends = [data.values[role].append for role in cols.index]
    ts, ls = data.t_s, data.lines
    bad = data.bad
    isfinite = math.isfinite
    tname = data.options.name("t")
    reorder = data.options.resample
    header = header.strip()
    last_t, last_line, last_text = -math.inf, 0, ""
    for lineno, line in lines:
        c = line[:1]
        if c == "#" or (c in " \t" and _skippable(line)):
            continue
        parts = line.split(sep)
        if len(parts) != ncols:
            if not _skippable(line):
                bad.append(BadRow(lineno, _field_count(len(parts), ncols)))
            continue
        try:
            t = time(parts[it])
            values = [float(parts[i]) for i in index]
        except ValueError:
            if line.strip() == header:
                data.headers_repeated.append(lineno)
            elif not _skippable(line):
                bad.append(BadRow(lineno, _why_bad(parts, cols, data.options)))
            continue
        if not (isfinite(t) and all(map(isfinite, values))):
            bad.append(BadRow(lineno, _why_bad(parts, cols, data.options)))
            continue
        if t <= last_t:
            if not (reorder and t >= ts[max(len(ts) - MAX_ROWS_BACK, 0)]):
                more = (f"; more than {MAX_ROWS_BACK} rows out of order for --resample"
                        if reorder else " (--resample sorts rows a little out of order in)")
                bad.append(BadRow(lineno, f"{tname} {parts[it].strip()} is not after "
                                  f"{last_text} (line {last_line}): time must increase{more}"))
                continue
        else:
            last_t, last_line, last_text = t, lineno, parts[it].strip()
        ts.append(t)
        for append, value in zip(appends, values, strict=True):
            append(value)
        ls.append(lineno)


def listing(bad: list[BadRow]) -> str:
    """The bad rows, one a line, at most MAX_LISTED of them."""
    shown = "\n".join(f"  {b}" for b in bad[:MAX_LISTED])
    more = f"\n  ... and {len(bad) - MAX_LISTED} more" if len(bad) > MAX_LISTED else ""
    return f"{shown}{more}"


def _to_si(data: CsvData) -> None:
    """Time to seconds and each value to SI, in place, as the options say."""
    opts = data.options
    if opts.time_unit != "iso" and opts.time_unit != "s":
        t = np.frombuffer(data.t_s, dtype=np.float64)
        t *= TIME_UNITS_S[opts.time_unit]
    for role, column in data.values.items():
        if opts.converted(role):
            x = np.frombuffer(column, dtype=np.float64)
            x *= opts.scale.get(role, 1.0)
            x += opts.offset.get(role, 0.0)


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
            "jitter would corrupt replay: --resample interpolates onto a uniform time base "
            "(reporting every gap it fills), or resample the data yourself.")
    data.interval_s = median


def read_csv(path: str | Path, *, skip_bad: bool = False,
             options: ImportOptions | None = None) -> CsvData:
    """Parse, convert and check a whole CSV file; raises LogError for anything that cannot
    be imported.

    With skip_bad, bad rows are left out and listed in the result's `bad`; without it any
    bad row is an error listing the first MAX_LISTED of them by line number.
    """
    path, options = Path(path), options or ImportOptions()
    lines = _lines(path)
    for lineno, line in lines:
        if not _skippable(line):
            cols = _columns(path, lineno, line, options)
            header = line.strip()
            break
    else:
        raise LogError(f"{path}: no header line (the file is empty or only comments)")
    data = CsvData(path, header, cols.ignored, options,
                   values={role: array("d") for role in cols.index})
    _parse_rows(data, lines, cols, header)
    if data.bad and not skip_bad:
        raise LogError(f"{path}: {len(data.bad)} bad row{'s' if len(data.bad) > 1 else ''} "
                       f"(fix them, or --skip-bad to leave them out):\n{listing(data.bad)}")
    if data.rows < MIN_ROWS:
        what = "no data rows" if not data.rows else f"only {data.rows} good data rows"
        raise LogError(f"{path}: {what} after the header; at least {MIN_ROWS} are needed")
    _to_si(data)
    if options.resample:
        _resample(data)
    else:
        _check_uniform(data)
    return data


def _resample(data: CsvData) -> None:
    """Replace the rows by their resampling (`leveler.log.resample`) and keep its report."""
    grid, out, report = resample(
        np.frombuffer(data.t_s, dtype=np.float64),
        {k: np.frombuffer(v, dtype=np.float64) for k, v in data.values.items()},
        np.frombuffer(data.lines, dtype=np.int64), data.options.max_gap_s, str(data.path))
    data.t_s = array("d", grid.tobytes())
    data.values = {k: array("d", v.tobytes()) for k, v in out.items()}
    data.lines = array("q")  # rows of the file no longer map onto samples one to one
    data.interval_s = report.interval_s
    data.resampling = report


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
        "conversion": data.options.describe(),
    }
    report = data.resampling
    if report is not None:
        metadata["resampled"] = report.summary()
    times = _log_times(np.frombuffer(data.t_s, dtype=np.float64), data.path)
    ks, vs, ss = data.column("temperature"), data.column("actuator"), data.column("sensor")
    fs, xs, tilts = data.column("thrust"), data.column("displacement"), data.column("tilt")
    writer = LogWriter(dest, environment=ks is not None, thrust_stand=fs is not None,
                       metadata=metadata)
    try:
        writer.event(Event(data.t_s[0], "start", "import-csv", {"csv": path}), times[0])
        gaps = report.gaps if report is not None else []
        for gap in gaps:  # at the gap's start, so a reader meets it in time order
            at = round((gap.t_s - data.t_s[0]) / data.interval_s)
            ns = times[min(at, len(times) - 1)]
            writer.event(Event(gap.t_s, "gap", "import-csv --resample", {
                "after_line": gap.after_line, "before_line": gap.before_line,
                "length_s": gap.length_s, "samples_interpolated": gap.filled}), ns)
        filled = report.filled if report is not None else np.zeros(data.rows, bool)
        sample, environment, wait = writer.sample, writer.environment, writer.wait_drained
        stand = writer.thrust_stand
        for i, (t, ns, made) in enumerate(zip(data.t_s, times, filled.tolist(), strict=True)):
            if ss is not None:
                v, s = vs[i], ss[i]
                state = "interpolated" if made else "imported"
                sample(Sample(i, t, 0, s, 0, 0.0, -s, 0.0, 0.0, 0.0, v, v, False, state), ns)
            if ks is not None:
                environment(Environment(i, t, ks[i]), ns)
            if fs is not None:
                stand(ThrustStand(i, t, fs[i], xs[i], math.nan if tilts is None else tilts[i]),
                      ns)
            if i % _DRAIN_EVERY == _DRAIN_EVERY - 1:
                wait(max_backlog=_MAX_BACKLOG)
        writer.event(Event(data.t_s[-1], "stop", "import-csv", {"csv": path, "rows": data.rows}),
                     times[-1])
    finally:
        writer.close()
    expected = data.rows if ss is not None else 0
    if writer.dropped or writer.samples_written != expected:
        raise LogError(f"{out}: {writer.dropped} records dropped, {writer.samples_written} of "
                       f"{expected} samples written")


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
               force: bool = False, options: ImportOptions | None = None) -> CsvData:
    """Read, check and convert one CSV file; returns what was imported."""
    data = read_csv(path, skip_bad=skip_bad, options=options)
    write_log(data, out, force=force)
    return data


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds:.6g} s ({seconds / 3600:.3g} h)"
    return f"{seconds:.6g} s"


def summary(data: CsvData, out: str | Path) -> str:
    """One line saying what the log holds, how it was converted and what was left out."""
    temperature = "yes" if data.column("temperature") is not None else "no"
    stand = ("thrust stand: " + ", ".join(r for r in (*STAND_PAIR, "tilt") if r in data.values)
             + ", " if "thrust" in data.values else "")
    ignored = ", ".join(data.ignored) or "none"
    rows = data.resampling.rows_in if data.resampling is not None else data.rows
    resampled = f"; {data.resampling.summary()}" if data.resampling is not None else ""
    return (f"imported {rows} rows from {data.path} into {out}: "
            f"{_duration(data.duration_s)} at {1.0 / data.interval_s:.6g} Hz, "
            f"{data.options.describe()}, temperature: {temperature}, {stand}ignored columns: "
            f"{ignored}, skipped bad rows: {len(data.bad)}, repeated headers skipped: "
            f"{len(data.headers_repeated)}{resampled}")


def details(data: CsvData) -> str:
    """What the summary only counts, line by line (stderr): rows moved, dropped, gaps."""
    out = []
    if data.headers_repeated:
        out.append("repeated header lines skipped (a logger restart?): "
                   + ", ".join(map(str, data.headers_repeated[:MAX_LISTED])))
    r = data.resampling
    if r is not None:
        for what, lines in (("rows out of order, sorted in", r.moved),
                            ("rows repeating the one before, dropped", r.duplicates),
                            ("rows with a time already taken and other values, dropped",
                             r.conflicts)):
            if lines:
                out.append(f"{what}: line{'s' if len(lines) > 1 else ''} "
                           f"{', '.join(map(str, lines[:MAX_LISTED]))}"
                           + (f" and {len(lines) - MAX_LISTED} more" if len(lines) > MAX_LISTED
                              else ""))
        out += [f"gap after line {g.after_line}: {g.length_s:.6g} s to line {g.before_line}, "
                f"{g.filled} sample{'s' if g.filled != 1 else ''} interpolated (state "
                "'interpolated' in the log)"
                for g in r.gaps[:MAX_LISTED]]
        if len(r.gaps) > MAX_LISTED:
            out.append(f"... and {len(r.gaps) - MAX_LISTED} more gaps")
    return "\n".join(out)


def rate_doubt(data: CsvData) -> str:
    """A warning when the time unit looks wrong (2 Hz in days reads as 172,800 Hz)."""
    rate = 1.0 / data.interval_s
    if rate > 1e5 or rate < 1e-3:
        return (f"the time base gives {rate:.6g} Hz: is the time column in "
                f"{data.options.time_unit}? (--time-unit {', '.join(TIME_UNITS_S)} or iso)")
    return ""


__all__ = ["BadRow", "CsvData", "ImportOptions", "details", "import_csv", "listing",
           "parse_assignments", "rate_doubt", "read_csv", "summary", "write_log"]
