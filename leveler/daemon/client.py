"""The client side of the control socket: requests to a running daemon, and its replies."""

from __future__ import annotations

import contextlib
import socket
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

CONNECT_WAIT_S = 5.0  # retrying a full queue of pending connections


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
        (a Unix socket then says EAGAIN at once rather than waiting), for at most
        CONNECT_WAIT_S: a reply may take long (a reload), but a queue that stays full says
        what it has to say in seconds."""
        deadline = time.monotonic() + min(timeout_s, CONNECT_WAIT_S)
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
