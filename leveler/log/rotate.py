"""A log that is a sequence of MCAP files: rotated by time and size, and a full disk is a
logged fault rather than the end of the control loop.

The loop thread never touches the file system here. It hands each record to the current
LogWriter (a deque append) under a lock that is only ever held for a few attribute
updates. Opening a file (about 1 ms: header, schemas and metadata are written and
flushed) happens on an opener thread; finishing one (drain, summary, fsync: milliseconds
to seconds) and reporting faults on a closer thread. A new file replaces the old one in a
single step under the lock, so every sample lands in exactly one file and `seq` runs on
across files without a gap or a repeat.

A write error (ENOSPC, EIO, EROFS ...) kills only the current file: its closed chunks stay
readable, the samples that follow are counted as dropped, and every `retry_interval_s` a
fresh file is tried. The first events of the file that resumes logging say what was lost.

A file that leaves its place while written (deleted, its directory removed or moved) and a
rotation that cannot open a new file are log faults too: `healthy` turns False and a new
file is tried every `retry_interval_s` (the directory re-created where allowed) while
writing goes on into the open one. A deleted file is still readable through its open
descriptor: once finished it is copied back into the directory, so nothing is lost unless
that copy fails, and then its samples are counted as lost.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from functools import partial
from pathlib import Path
from queue import SimpleQueue
from typing import Literal

from leveler.log.reader import LogError
from leveler.log.writer import LogWriter
from leveler.records import Environment, Event, Sample, Truth
from leveler.rt import background_thread
from leveler.typed_config import positive


@dataclass(frozen=True, slots=True)
class LogConfig:
    """[log]: where files go, how often a chunk is closed (what a crash can lose), rotation."""

    dir: str = "logs"
    chunk_interval_s: float = positive(1.0)
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    rotate_interval_s: float = positive(86400.0)
    rotate_bytes: int = field(default=1 << 30, metadata={"ge": 1 << 16})
    retry_interval_s: float = positive(5.0)


_log = logging.getLogger(__name__)

_US = timedelta(microseconds=1)
_ROTATE_WAIT_S = 1.0  # rotate() runs on the loop thread in the daemon: bound its stall
_MAX_HELD_EVENTS = 1000  # events kept while the log is down, written when it resumes


def _utc(log_time_ns: int) -> str:
    return datetime.fromtimestamp(log_time_ns / 1e9, UTC).isoformat(timespec="milliseconds")


def _error_text(e: LogError) -> str:
    """The OS error behind a LogError ("[Errno 28] No space left on device") if there is one."""
    return str(e.__cause__ or e)


@dataclass
class _Loss:
    """Samples that never reached a file, and the time span they cover."""

    error: str
    file: str | None  # the file that failed; None if no file could be opened at all
    lost: int
    # log_time_ns where the gap starts: the newest record on disk, or if there is none
    # the first sample refused
    since: int | None
    until: tuple[float, int]  # (t_s, log_time_ns) of the newest lost sample
    events: list[tuple[Event, int]] = field(default_factory=list)  # held for the next file

    def event(self) -> Event:
        since, (t_s, until) = self.since or self.until[1], self.until
        reason = (f"log write failed: {self.error}; {self.lost} samples lost between "
                  f"{_utc(since)} and {_utc(until)}")
        return Event(t_s, "fault", reason, {
            "error": self.error, "file": self.file, "lost_samples": self.lost,
            "from_log_time_ns": since, "to_log_time_ns": until})


@dataclass
class _Retired:
    """A writer on its way to the closer, with what is needed to account for its end."""

    writer: LogWriter
    handed: int  # samples given to it
    last: tuple[float, int]  # (t_s, log_time_ns) when it was retired


class _Worker:
    """One thread running queued jobs in order, so slow file work stays off the loop.

    A daemon thread: a program that forgets close() must still exit; its LogWriters then
    finish their files by themselves.
    """

    def __init__(self, name: str) -> None:
        self._jobs: SimpleQueue[Callable[[], None] | None] = SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, job: Callable[[], None]) -> None:
        self._jobs.put(job)

    def stop(self) -> None:
        """Run what is queued, then end the thread."""
        self._jobs.put(None)
        self._thread.join()

    def _run(self) -> None:
        background_thread()  # below the loop; the writers it starts inherit this
        while (job := self._jobs.get()) is not None:
            try:
                job()
            except Exception:  # a bug here must not silently end all later closes
                _log.exception("%s: job failed", self._thread.name)
            del job  # else it keeps the last finished writer (and its index) until the next


class RotatingLog:
    """A Sink for the loop (sample/truth/event) that writes a sequence of MCAP files.

    Files are `<prefix>-<UTC start, YYYYmmddTHHMMSS.ffffff>Z.mcap`: unique, and their
    names sort in time order. sample(), truth() and event() never block and never raise
    for a write error. on_fault(message) is called once per write failure, from the
    closer thread (the constructor's own thread if the first file cannot be opened),
    instead of logging it as an error: keep it quick. `healthy`, `last_error` and
    `dropped` tell the rest.
    """

    def __init__(
        self,
        directory: Path,
        *,
        metadata: dict[str, str],
        truth: bool,
        environment: bool = False,
        chunk_interval_s: float = 1.0,
        compression: str = "zstd",
        rotate_interval_s: float = 86400.0,
        rotate_bytes: int = 1 << 30,
        retry_interval_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        prefix: str = "leveler",
        on_fault: Callable[[str], None] | None = None,
    ) -> None:
        """Open the first file now (before the loop runs). If that fails the log starts
        unhealthy and retries like after any write error; only bad arguments raise."""
        self.directory = Path(directory)
        self.prefix = prefix
        self.on_fault = on_fault
        self.files: list[Path] = []
        self.last_error: str | None = None
        self.faults = 0  # log faults since start; `last_fault` the newest, with its UTC time
        self.last_fault: str | None = None
        self._fault: str | None = None  # a fault while a file is still being written
        self._open_error = ""  # why the last attempt to open a file failed
        self._displaced_seen: LogWriter | None = None
        self._metadata = dict(metadata)
        self._truth = truth
        self._new_writer = partial(LogWriter, chunk_interval_s=chunk_interval_s,
                                   compression=compression, truth=truth,
                                   environment=environment)
        self._rotate_interval = rotate_interval_s
        self._rotate_bytes = rotate_bytes
        self._retry_interval = retry_interval_s
        self._clock = clock
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)  # an open attempt finished
        self._writer: LogWriter | None = None
        self._handed = 0  # samples given to the current writer
        self._written = 0  # samples in files that are finished (or failed: what is on disk)
        self._lost = 0  # samples of finished files and outages that are in no file
        self._retiring: list[_Retired] = []
        self._outage: _Loss | None = None
        self._opening = False  # an open is queued or under way
        self._reason = ""  # the first event of the file being opened
        self._opens = self._opened = 0  # open attempts finished, and succeeded
        self._rotate_at = math.inf  # clock() time of the next time-based rotation
        self._next_try = -math.inf  # no open is requested before this clock() time
        self._last = (0.0, time.time_ns())  # (t_s, log_time_ns) of the newest record
        self._last_start = datetime.min.replace(tzinfo=UTC)
        self._closed = False
        first = self._open()  # a bad argument raises here, before any thread starts
        self._closer = _Worker("logrotate close")
        self._opener = _Worker("logrotate open")
        with self._lock:
            if isinstance(first, LogWriter):
                self._install(first)
                return
            self._outage = _Loss(first, None, 0, None, self._last)
            self.last_error = first
            self._next_try = clock() + retry_interval_s
        self._report(f"cannot start logging: {first}; retrying every {retry_interval_s:g} s")

    # -- the loop thread ---------------------------------------------------------------

    @property
    def path(self) -> Path | None:
        """The file being written; None while logging is down."""
        w = self._writer
        return w.path if w is not None else None

    @property
    def healthy(self) -> bool:
        """False from a write error, a displaced file or a failed rotation until a new file
        is open; `last_error` says why. A new file clears `last_error`: a status that says
        healthy carries no stale error (`last_fault` and the log's events keep it)."""
        return self._outage is None and self._fault is None

    @property
    def samples_written(self) -> int:
        """Samples handed to a writer that are in a file (or will be once it closes)."""
        with self._lock:
            live = [r.writer for r in self._retiring] + [w for w in (self._writer,) if w]
            return self._written + sum(w.samples_written for w in live)

    @property
    def dropped(self) -> int:
        """Samples in no file: lost to write errors, refused while logging was down, or
        dropped by a writer whose backlog overflowed."""
        with self._lock:
            live = [r.writer for r in self._retiring] + [w for w in (self._writer,) if w]
            return self._lost + sum(w.dropped for w in live)

    def sample(self, s: Sample, log_time_ns: int) -> None:
        """Hand one sample on; rotate if the file is due. Never raises, never blocks."""
        with self._lock:
            self._last = (s.t_s, log_time_ns)
            w = self._writer
            if w is not None:
                try:
                    w.sample(s, log_time_ns)
                except LogError as e:
                    self._fail(w, e)
                else:
                    self._handed += 1
                    if not self._opening and (w.bytes_written >= self._rotate_bytes
                                              or self._clock() >= self._rotate_at
                                              or w.displaced is not None
                                              or self._fault is not None):
                        self._rotate_due(w)
                    return
            self._lost += 1
            outage = self._outage
            if outage is not None:
                outage.lost += 1
                outage.since = outage.since or log_time_ns
                outage.until = self._last
                self._maybe_retry()

    def truth(self, t: Truth, log_time_ns: int) -> None:
        """Hand one truth record on (simulation); lost silently while logging is down."""
        if not self._truth:
            raise LogError(f"{self.directory}: truth topic not enabled (truth=True)")
        self._optional(lambda w: w.truth(t, log_time_ns))

    def environment(self, e: Environment, log_time_ns: int) -> None:
        """Hand one environment record on (a thermometer reading); lost silently while
        logging is down, as truth is."""
        self._optional(lambda w: w.environment(e, log_time_ns))

    def _optional(self, put: Callable[[LogWriter], None]) -> None:
        """A record of an optional topic to the file being written, if any."""
        with self._lock:
            w = self._writer
            if w is not None:
                try:
                    put(w)
                except LogError as e:
                    self._fail(w, e)

    def event(self, e: Event, log_time_ns: int) -> None:
        """Hand one event on; while logging is down it is kept for the next file."""
        with self._lock:
            self._last = (e.t_s, log_time_ns)
            w = self._writer
            if w is not None:
                try:
                    w.event(e, log_time_ns)
                    return
                except LogError as err:
                    self._fail(w, err)
            if self._outage is not None:
                if len(self._outage.events) < _MAX_HELD_EVENTS:
                    self._outage.events.append((e, log_time_ns))
                self._maybe_retry()

    def rotate(self, reason: str = "requested") -> Path:
        """Finish the current file and continue in a new one; returns its path.

        Waits (at most about a second) for the opener thread; raises LogError if no new
        file could be opened, in which case logging goes on where it was, if anywhere.
        """
        with self._lock:
            if self._closed:
                raise LogError(f"{self.directory}: log is closed")
            opens, opened = self._opens, self._opened
            if self._opening:
                self._reason = f"rotated ({reason})"  # the open under way serves this request
            else:
                self._request(f"rotated ({reason})")
            if not self._changed.wait_for(lambda: self._opens > opens, _ROTATE_WAIT_S):
                raise LogError(f"{self.directory}: no new log file within {_ROTATE_WAIT_S:g} s;"
                               " it starts once the file system answers")
            if self._opened == opened or self._writer is None:
                raise LogError(f"cannot start a new log file: {self._open_error}")
            return self._writer.path

    def close(self) -> None:
        """Finish every file (summary, footer, fsync) and stop the threads. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            w, self._writer = self._writer, None
            if w is not None:
                self._retire(w)
            outage = self._outage
        self._opener.stop()  # an open under way ends; _open_next discards its file
        self._closer.stop()  # every retired file is finished when this returns
        if outage is not None:
            _log.error("%s: log closed while down: %d samples and %d events not written",
                       self.directory, outage.lost, len(outage.events))

    # -- under the lock, from any thread -----------------------------------------------

    def _rotate_due(self, w: LogWriter) -> None:
        if w.displaced is not None and self._displaced_seen is not w:
            self._displaced_seen = w
            self._set_fault(f"{w.displaced}; writing goes on into the open file until a new "
                            "one is open" + (", then it is copied back" if w.deleted else ""))
            self._closer.put(partial(self._report, self._fault or ""))
        if self._clock() >= self._next_try:
            self._request(f"rotated ({w.displaced})" if w.displaced is not None
                          else "rotated (size)" if w.bytes_written >= self._rotate_bytes
                          else "rotated (time)" if self._clock() >= self._rotate_at
                          else f"rotated (retry after: {self._fault})")

    def _set_fault(self, text: str) -> None:
        """A log fault while a file is still written; counted once until a new file opens."""
        if self._fault is None:
            self.faults += 1
        self._fault = self.last_error = text
        self.last_fault = f"{datetime.now(UTC):%Y-%m-%d %H:%M:%S} UTC: {text}"

    def _maybe_retry(self) -> None:
        if not self._opening and not self._closed and self._clock() >= self._next_try:
            self._request("logging resumed")

    def _request(self, reason: str) -> None:
        self._opening = True
        self._reason = reason
        self._opener.put(self._open_next)

    def _fail(self, w: LogWriter, e: LogError) -> None:
        """The current file hit a write error: stop using it, count what it lost."""
        samples, log_time_ns = w.flushed
        error = _error_text(e)
        self._writer = None
        self._written += samples
        self._lost += self._handed - samples
        self._outage = _Loss(error, w.path.name, self._handed - samples, log_time_ns or None,
                             self._last)
        self.last_error = error
        self._next_try = self._clock() + self._retry_interval
        self._closer.put(partial(self._report, f"{w.path}: log write failed: {error}; the "
                                 f"loop goes on, a new file is tried every "
                                 f"{self._retry_interval:g} s"))
        self._closer.put(partial(self._discard, w))

    def _install(self, new: LogWriter) -> None:
        """Make `new` the current file: one step, so no sample is lost or written twice."""
        old, outage = self._writer, self._outage
        t_s, log_time_ns = self._last
        name = new.path.name
        if old is not None:
            with contextlib.suppress(LogError):  # the closer reports a failed file
                old.event(Event(t_s, "log", f"continues in {name}",
                                {"next": name, "reason": self._reason}), log_time_ns)
            self._retire(old)
        if outage is not None:
            new.event(outage.event(), log_time_ns)
            new.event(Event(t_s, "log", "logging resumed", {"previous": outage.file}),
                      log_time_ns)
            for e, e_ns in outage.events:
                new.event(e, e_ns)
        elif self.files:
            new.event(Event(t_s, "log", self._reason,
                            {"previous": self.files[-1].name, "part": len(self.files) + 1}),
                      log_time_ns)
        self.files.append(new.path)
        self._writer, self._handed, self._outage, self._fault = new, 0, None, None
        self.last_error = None  # what failed before is in `new`'s events, not news now
        self._rotate_at = self._clock() + self._rotate_interval
        self._next_try = -math.inf

    def _retire(self, w: LogWriter) -> None:
        r = _Retired(w, self._handed, self._last)
        self._retiring.append(r)
        self._closer.put(partial(self._finish, r))

    # -- the opener thread -------------------------------------------------------------

    def _open(self) -> LogWriter | str:
        """Open the next file; on failure remove what was created and return the error."""
        metadata = self._metadata | {"part": str(len(self.files) + 1)}
        if self.files:
            metadata["previous"] = self.files[-1].name
        path = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)  # it may have been removed
            path = self._next_path()
            return self._new_writer(path, metadata=metadata)
        except (OSError, LogError) as e:
            if path is not None:
                with contextlib.suppress(OSError):
                    path.unlink(missing_ok=True)
            return str(e)

    def _next_path(self) -> Path:
        """Named by UTC start time to the microsecond, bumped if taken: unique, in order."""
        start = max(datetime.now(UTC), self._last_start + _US)
        while (path := self.directory / f"{self.prefix}-{start:%Y%m%dT%H%M%S.%f}Z.mcap").exists():
            start += _US
        self._last_start = start
        return path

    def _open_next(self) -> None:
        try:
            new = self._open()
        except Exception as e:  # a bad argument (ValueError) must not leave _opening set
            _log.exception("opening a log file failed")
            new = repr(e)
        still = resumed = unused = None
        with self._lock:
            self._opening = False
            self._opens += 1
            if isinstance(new, str):
                self.last_error = self._open_error = new
                self._next_try = self._clock() + self._retry_interval
                still = self.path  # None: logging is down, that was reported already
                if still is not None:  # a fault too: retried every retry_interval_s
                    w = self._writer
                    moved = f"{w.displaced}; " if w is not None and w.displaced else ""
                    self._set_fault(f"{moved}cannot start a new log file: {new}; still "
                                    f"writing {still.name}")
            elif self._closed:
                unused = new
            else:
                self._opened += 1
                resumed = self._outage
                self._install(new)
            self._changed.notify_all()
        if still is not None:
            _log.warning("log rotation failed, still writing %s: %s", still, new)
        if resumed is not None:
            _log.warning("%s: logging resumed; %d samples lost", self.path, resumed.lost)
        if unused is not None:  # close() came first: the file would hold nothing
            self._discard(unused)
            unused.path.unlink(missing_ok=True)

    # -- the closer thread ---------------------------------------------------------------

    def _finish(self, r: _Retired) -> None:
        """Close a retired file; if that fails, account for and report its lost tail. A file
        deleted while it was written is copied back from its descriptor once finished."""
        w = r.writer
        deleted = w.open_deleted() if w.deleted else None  # before close(): the only way back
        try:
            self._close_retired(r)
            if w.deleted and not self._restore(w, deleted):
                with self._lock:
                    self._written -= w.samples_written
                    self._lost += w.samples_written
                    self.files.remove(w.path)
        finally:
            if deleted is not None:
                os.close(deleted)

    def _restore(self, w: LogWriter, fd: int | None) -> bool:
        """Copy the deleted file behind `fd` back under its name (the directory re-created
        where allowed); False, reported, if that fails."""
        dest = self.directory / w.path.name
        if dest.exists():
            dest = dest.with_name(f"{dest.stem}.restored.mcap")
        tmp = dest.with_name(dest.name + ".new")
        try:
            if fd is None:
                raise OSError("no descriptor to read it through (is /proc mounted?)")
            self.directory.mkdir(parents=True, exist_ok=True)
            with open(fd, "rb", closefd=False) as src, open(tmp, "wb") as out:
                src.seek(0)
                shutil.copyfileobj(src, out, 1 << 20)
                out.flush()
                os.fsync(out.fileno())
            os.replace(tmp, dest)
            dir_fd = os.open(self.directory, os.O_RDONLY | os.O_DIRECTORY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
        except OSError as e:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            self._report(f"{w.path} was deleted while being written and cannot be restored: "
                         f"{e}; its {w.samples_written} samples are lost")
            return False
        text = (f"{w.path.name} was deleted while being written; restored from its open "
                f"descriptor into {dest} ({w.samples_written} samples)")
        with self._lock:
            self.files = [dest if f == w.path else f for f in self.files]
            self.last_fault = f"{datetime.now(UTC):%Y-%m-%d %H:%M:%S} UTC: {text}"
            if self._writer is not None:
                t_s, log_time_ns = self._last
                with contextlib.suppress(LogError):  # a failing writer reports itself
                    self._writer.event(Event(t_s, "log", text, {
                        "file": w.path.name, "restored_to": str(dest),
                        "samples": w.samples_written}), log_time_ns)
        _log.warning("%s", text)
        return True

    def _close_retired(self, r: _Retired) -> None:
        w = r.writer
        try:
            w.close()
        except LogError as e:
            samples, log_time_ns = w.flushed
            loss = _Loss(_error_text(e), w.path.name, r.handed - samples, log_time_ns or None,
                         r.last)
            with self._lock:
                self._retiring.remove(r)
                self._written += samples
                self._lost += loss.lost
                self.last_error = loss.error
                if self._outage is not None:
                    self._outage.lost += loss.lost
                elif self._writer is not None:
                    with contextlib.suppress(LogError):  # then that failure is reported
                        self._writer.event(loss.event(), self._last[1])
            self._report(f"{w.path}: {loss.event().reason}")
        else:
            with self._lock:
                self._retiring.remove(r)
                self._written += w.samples_written
                self._lost += w.dropped

    @staticmethod
    def _discard(w: LogWriter) -> None:
        with contextlib.suppress(LogError):  # already counted and reported
            w.close()

    def _report(self, message: str) -> None:
        """One report per failure: to on_fault if given (the daemon logs it there), else to
        the log as an error."""
        if self.on_fault is not None:
            self.on_fault(message)
        else:
            _log.error("%s", message)


__all__ = ["RotatingLog"]
