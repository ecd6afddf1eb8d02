"""The running loop as EPICS Channel Access PVs: the daemon's side.

The server (leveler.live.epics_ioc, caproto) runs as a child process, so its Python never
holds the interpreter lock the loop needs (on a thread of the daemon it cost the 1 kHz loop's
p99 lateness up to 2.6x). A thread of the daemon, below the loop, relays: a few times a second
it sends the child what the PVs show, read from `status()` (the loop itself is not touched),
and it answers each put through the daemon's own request path, so a put is checked exactly as
`leveler tune`/`start`/`stop`/`reset` are and its event names the client.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import select
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from leveler.live.config import EpicsConfig
from leveler.rt import background_thread
from leveler.typed_config import ConfigError

_log = logging.getLogger(__name__)


def _snapshot(st: dict[str, Any]) -> dict[str, Any]:
    """What the PVs show, from the daemon's status, as JSON the child reads."""
    s, loop = st["sample"], st["loop"]
    return {
        "sample": None if s is None else {
            "sensor_m": s.sensor_m, "tilt_rad": st["tilt_rad"], "applied_v": s.applied_v,
            "p_v": s.p_v, "i_v": s.i_v, "d_v": s.d_v, "saturated": bool(s.saturated),
            "limits_v": [st["controller"]["output_min_v"], st["controller"]["output_max_v"]]},
        "stalled": bool(loop["stalled"]), "period_p99_s": loop.get("period_p99_s", 0.0),
        "period_max_s": loop.get("period_max_s", 0.0), "overruns": int(loop["overruns"]),
        "state": st["state"], "fault_reason": st["fault_reason"],
        "controller": {k: st["controller"][k] for k in
                       ("setpoint_m", "kp_v_per_m", "ki_v_per_m_s", "kd_v_s_per_m")}}


class EpicsServer:
    """Serve `cfg.prefix`-named PVs from `status()`; `act(request, who)` applies a put (the
    daemon's `request`)."""

    def __init__(self, cfg: EpicsConfig, status: Callable[[], dict[str, Any]],
                 act: Callable[[dict[str, Any], str], dict[str, Any]],
                 piezo_range_v: tuple[float, float]) -> None:
        if importlib.util.find_spec("caproto") is None:  # the child's: said here, clearly
            raise ConfigError("[epics] serve = true but the caproto package is not "
                              "installed: install leveler's `epics` extra (docs/install.md), "
                              "or set serve = false")
        self.cfg, self._status, self._act = cfg, status, act
        self._args = json.dumps({"prefix": cfg.prefix, "interfaces": list(cfg.interfaces),
                                 "writable": cfg.writable, "piezo_range_v": list(piezo_range_v),
                                 "near_rail_fraction": cfg.piezo_near_rail_fraction,
                                 "stale_after_s": max(3.0 / cfg.update_hz, 2.0)})
        self._proc: subprocess.Popen[bytes] | None = None
        self._closing = threading.Event()
        self._failed = ""
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._relay, name="epics", daemon=True)
        self._thread.start()
        if not self._ready.wait(20) or self._failed:
            self.close()
            raise ConfigError(f"[epics] cannot serve on {', '.join(cfg.interfaces)}: "
                              f"{self._failed or 'no answer in 20 s'}")

    def _relay(self) -> None:
        background_thread()  # below the loop; the child is started from here, and lowers
        try:                 # itself to normal scheduling
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "leveler.live.epics_ioc", self._args],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE)
            lines = _Lines(self._proc.stdout.fileno())  # type: ignore[union-attr]
            first = lines.next(timeout_s=20) or {"failed": "no answer in 20 s"}
            self._failed = first.get("failed", "")
            self._ready.set()
            if not self._failed:
                self._serve(lines)
        except Exception as exc:  # reported to __init__ if it never became ready
            if self._ready.is_set() and not self._closing.is_set():
                _log.error("EPICS server stopped: %s: %s; the PVs are gone until leveler "
                           "restarts", type(exc).__name__, exc)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self._proc.wait(timeout=5)  # type: ignore[union-attr]  # reaped
            self._failed = self._failed or f"{type(exc).__name__}: {exc}"
            self._ready.set()
        finally:
            if self._proc is not None and self._proc.stdin is not None:
                with contextlib.suppress(OSError, ValueError):
                    self._send({"stop": True})
                    self._proc.stdin.close()

    def _send(self, msg: dict[str, Any]) -> None:
        assert self._proc is not None and self._proc.stdin is not None
        self._proc.stdin.write(json.dumps(msg).encode() + b"\n")
        self._proc.stdin.flush()

    def _serve(self, lines: _Lines) -> None:
        """Status to the child every 1/update_hz, puts answered as they come."""
        period = 1.0 / self.cfg.update_hz
        due = time.monotonic()
        while not self._closing.is_set():
            wait = due - time.monotonic()
            if wait > 0:
                msg = lines.next(timeout_s=min(wait, 0.25))
                if msg is not None:
                    self._answer(msg)
                continue
            try:
                snapshot = _snapshot(self._status())
            except Exception:  # one bad refresh must not end the PVs for good
                _log.exception("EPICS: reading the status for the PVs failed; trying again")
            else:
                self._send({"status": snapshot})
            due = max(due + period, time.monotonic())

    def _answer(self, msg: dict[str, Any]) -> None:
        """A put the child hands over: applied by the daemon, or refused with its reason."""
        try:
            self._act(msg["req"], msg["who"])
            error = None
        except Exception as exc:
            error = str(exc) or type(exc).__name__
        self._send({"reply": msg["put"], "error": error})

    @property
    def serving(self) -> bool:
        """The server process is up and its relay runs (`leveler status` shows it)."""
        return (self._thread.is_alive() and self._proc is not None
                and self._proc.poll() is None)

    def close(self) -> None:
        """Stop the relay (which tells the child to stop), then wait for the child."""
        self._closing.set()
        self._thread.join(timeout=5)
        if self._proc is not None:
            try:
                self._proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()


class _Lines:
    """JSON lines from a pipe, read without Python's buffering hiding a line from select."""

    def __init__(self, fd: int) -> None:
        self._fd, self._buf = fd, b""

    def next(self, timeout_s: float) -> dict[str, Any] | None:
        """The next message, None if none came within timeout_s; EOFError if it ended."""
        deadline = time.monotonic() + timeout_s
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._fd], [], [], left)[0]:
                return None
            chunk = os.read(self._fd, 65536)
            if not chunk:
                raise EOFError("the server process ended")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return dict(json.loads(line))
