"""The client side of the control socket, and the CLI verbs built on it."""

from __future__ import annotations

import contextlib
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import orjson

from leveler.daemon.protocol import (
    MAX_LINE_BYTES,
    VERSION,
    client_socket_candidates,
    socket_problem,
)


class ClientError(Exception):
    """No daemon, no access, or the daemon said no; the message says which."""


def _may_exist(path: Path) -> bool:
    """True if the socket is there, or hidden from us by permissions (connect will say)."""
    try:
        return path.exists()
    except PermissionError:
        return True


class Client:
    """One connection to a running daemon."""

    def __init__(self, path: str | Path | None = None, timeout_s: float = 5.0) -> None:
        candidates = [Path(path)] if path else client_socket_candidates()
        found = next((p for p in candidates if _may_exist(p)), None)
        if found is None:
            tried = ", ".join(str(p) for p in candidates)
            raise ClientError(f"no leveler daemon is running (no control socket at {tried}); "
                              "start one with `systemctl start leveler` or "
                              "`leveler run --config FILE`")
        self.path = found
        why = socket_problem(found)
        if why is not None:
            raise ClientError(f"refusing to talk to {found}: {why}; nothing was sent")
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        try:
            self._connect(found, timeout_s)
        except PermissionError:
            self._sock.close()
            raise ClientError(f"access denied to {found}: the daemon's group may use it; "
                              f"ask to be added (`ls -l {found}` shows which)") from None
        except (ConnectionRefusedError, FileNotFoundError):
            self._sock.close()
            raise ClientError(f"no daemon is listening on {found} (left behind by one that "
                              "stopped?)") from None
        self._reader = self._sock.makefile("rb")

    def _connect(self, path: Path, timeout_s: float) -> None:
        """connect(), retried while the daemon's queue of pending connections is full
        (a Unix socket then says EAGAIN at once rather than waiting)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self._sock.connect(str(path))
                return
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    self._sock.close()
                    raise ClientError(f"the daemon on {path} is busy (its queue of pending "
                                      "connections stayed full); try later") from None
                time.sleep(0.05)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._reader.close()
            self._sock.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _read(self) -> dict[str, Any]:
        try:
            line = self._reader.readline(MAX_LINE_BYTES * 16)
        except TimeoutError:
            raise ClientError(f"the daemon on {self.path} did not answer in time") from None
        except OSError as exc:
            raise ClientError(f"reading from {self.path} failed: {exc}") from None
        if not line:
            raise ClientError(f"the daemon on {self.path} closed the connection")
        try:
            reply = orjson.loads(line)
        except orjson.JSONDecodeError:
            raise ClientError(f"{self.path} answered something that is not JSON: not a "
                              "leveler daemon?") from None
        if not isinstance(reply, dict):
            raise ClientError(f"{self.path} answered a JSON {type(reply).__name__}, not an "
                              "object: not a leveler daemon?")
        if not reply.get("ok", False):
            raise ClientError(str(reply.get("error", "request refused")))
        return reply

    @contextlib.contextmanager
    def reading(self) -> Iterator[None]:
        """Around code that reads a reply's fields: a reply without them (another program,
        or another version, on the socket) is one line, not a traceback."""
        try:
            yield
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            raise ClientError(f"the daemon on {self.path} sent a reply this leveler cannot "
                              f"read ({type(exc).__name__}: {exc}): another version, or not "
                              "a leveler daemon?") from None

    def request(self, verb: str, **args: Any) -> dict[str, Any]:
        """Send one request and return the daemon's (successful) reply."""
        try:
            self._sock.sendall(orjson.dumps({"v": VERSION, "verb": verb, **args}) + b"\n")
        except OSError as exc:
            # A daemon that refuses the connection (too many clients) answers at once and
            # closes: its reason is waiting to be read, and says more than EPIPE.
            refusal = self._pending_refusal()
            raise ClientError(refusal or f"sending to {self.path} failed: {exc}") from None
        return self._read()

    def _pending_refusal(self) -> str | None:
        """The error a daemon sent before closing the connection, if there is one."""
        try:
            self._sock.settimeout(0.5)
            line = self._reader.readline(MAX_LINE_BYTES)
            reply = orjson.loads(line) if line else None
        except (OSError, ValueError):
            return None
        if isinstance(reply, dict) and reply.get("ok") is False and reply.get("error"):
            return str(reply["error"])
        return None

    def watch(self, rate_hz: float) -> Iterator[dict[str, Any]]:
        """Samples streamed by the daemon, as dicts, until it stops or we do."""
        self.request("watch", rate_hz=rate_hz)
        self._sock.settimeout(None)
        while True:
            line = self._reader.readline(MAX_LINE_BYTES)
            if not line:
                return
            yield orjson.loads(line)["sample"]


_BARS = " ▁▂▃▄▅▆▇█"


def sparkline(values: list[float]) -> str:
    """A small trend: one block character per value, scaled to the window's range."""
    if not values:
        return ""
    lo, hi = min(values), max(values)
    span = hi - lo or 1.0
    return "".join(_BARS[round((v - lo) / span * (len(_BARS) - 1))] for v in values)


def _limit(value: float | None) -> str:
    """A rate limit from JSON, where infinity (no limit) arrives as null."""
    return "none" if value is None else f"{value:g}"


def _driver_errors(counts: dict[str, int] | None) -> str:
    if counts is None:  # a daemon older than the count
        return "errors      (driver errors not reported by this daemon)"
    total = sum(counts.values())
    parts = ", ".join(f"{device} {n}" for device, n in counts.items())
    return f"errors      {total} driver errors since start ({parts})"


def _log_line(log: dict[str, Any]) -> str:
    where = log["path"] if log["path"] else "no file open (logging is down; retrying)"
    health = "healthy" if log["healthy"] else f"FAULT: {log['error']}"
    faults = log.get("faults", 0)  # a daemon older than the count has none
    return (f"log         {where}, {log['samples_written']} samples, {health}"
            + (f", {log['dropped']} dropped" if log["dropped"] else "")
            + (f"\n            {faults} log fault(s) since start; last: {log['last_fault']}"
               if faults else ""))


def format_status(st: dict[str, Any]) -> str:
    s = st.get("sample") or {}
    c, lp, log = st["controller"], st["loop"], st["log"]
    lines = [
        f"leveler {st['version']} (pid {st['pid']}), up {st['uptime_s'] / 60:.1f} min, "
        f"config {st['config_path']}",
        f"state       {st['state']}" + (f"  ({st['fault_reason']})" if st["fault_reason"] else ""),
        *([f"            LOOP STALLED: no cycle for {lp['last_cycle_age_s']:.1f} s (a device "
           "call that does not return?); values below are from the last cycle"]
          if lp.get("stalled") else []),
        _driver_errors(st.get("driver_errors")),
    ]
    if s:
        lines += [
            f"sensor      {s['sensor_m'] * 1e9:+.2f} nm   (tilt {st['tilt_rad'] * 1e9:+.2f} nrad)"
            if s.get("sensor_m") is not None else "sensor      no valid reading",
            ("piezo       last write failed (voltage held)"
             if s.get("applied_v") is None else f"piezo       {s['applied_v']:.3f} V applied")
            + f", {s['command_v']:.3f} V commanded"
            + ("  SATURATED" if s["saturated"] else ""),
        ]
    lines += [
        f"controller  kp {c['kp_v_per_m']:.4g} V/m  ki {c['ki_v_per_m_s']:.4g} V/(m s)  "
        f"kd {c['kd_v_s_per_m']:.4g} V s/m  setpoint {c['setpoint_m']:.4g} m  "
        f"limits {c['output_min_v']:g}..{c['output_max_v']:g} V  "
        f"slew {_limit(c['slew_v_per_s'])} V/s",
        f"loop        {lp['rate_hz']:g} Hz, {lp['cycles']} cycles, period p50/p99/max "
        f"{lp['period_p50_s'] * 1e3:.2f}/{lp['period_p99_s'] * 1e3:.2f}/"
        f"{lp['period_max_s'] * 1e3:.2f} ms, overruns {lp['overruns']}",
        _log_line(log),
    ]
    return "\n".join(lines)


def format_reload(reply: dict[str, Any]) -> str:
    """What a reload changed, one effective value a line; sections that wait for a restart."""
    changed = reply["changed"]
    lines = [f"reload applied: {len(changed)} value(s) changed"
             + (":" if changed else " (the file says what the daemon runs)")]
    lines += [f"  {key}: {old!r} -> {new!r}" for key, (old, new) in changed.items()]
    if reply["dropped"]:
        lines.append("back to their defaults (no longer in the file): "
                     + ", ".join(reply["dropped"]))
    if reply["needs_restart"]:
        lines.append("takes effect at the next restart: ["
                     + "], [".join(reply["needs_restart"]) + "]")
    return "\n".join(lines)


def run_watch(client: Client, rate_hz: float, count: int | None) -> None:
    """Print samples as they come: values and a trend of the last 40 sensor readings."""
    tty = sys.stdout.isatty()
    trend: list[float] = []
    for n, s in enumerate(client.watch(rate_hz), start=1):
        if s["sensor_m"] is not None:
            trend = [*trend[-39:], s["sensor_m"]]
        sensor = (f"{s['sensor_m'] * 1e9:+9.2f} nm" if s["sensor_m"] is not None
                  else "   (no reading)")
        line = (f"t={s['t_s']:10.2f} s  {s['state']:<7}  sensor={sensor}  "
                f"piezo={s['applied_v']:8.3f} V  {sparkline(trend)}")
        sys.stdout.write(f"\r{line}\033[K" if tty else f"{line}\n")
        sys.stdout.flush()
        if count is not None and n >= count:
            break
    if tty:
        sys.stdout.write("\n")
