"""The control socket server: transport and access control, nothing about leveling.

A Unix stream socket, mode 0660 and owned by the configured group, in a directory only the daemon's
user (or root) can write, as ssh-agent and tmux insist; every connection's peer credentials
(SO_PEERCRED) are checked as well, because a file mode is easy to loosen by accident. A refused peer
is answered and closed by the accepting thread at once: it never holds a slot, and its `access`
event is rate-limited. One thread per accepted connection (bounded by max_clients, of which
RESERVED_SLOTS are kept for root and the daemon's user, and by max_clients_per_uid for any other
uid) reads line-delimited JSON requests and hands them to a `Handler`; a malformed request gets an
error line back and the daemon carries on. A client holds its slot only while it keeps up: each
request must be complete within idle_timeout_s of the last (a byte a second does not keep a slot), a
reply must be read within idle_timeout_s, and a watcher must read its stream; a watcher that hangs
up is noticed while the server waits, not at its next send.
"""

from __future__ import annotations

import contextlib
import errno
import grp
import io
import logging
import os
import select
import socket
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from leveler.daemon.protocol import (
    MAX_LINE_BYTES,
    ProtocolError,
    encode,
    parse_request,
    untrusted_socket_dir,
)
from leveler.errors import ControlError
from leveler.rt import demote_thread

_log = logging.getLogger(__name__)
_UCRED = struct.Struct("3i")
RESERVED_SLOTS = 2  # of max_clients, that only root and the daemon's user may take
REFUSAL_REPORT_S = 10.0  # at most one `access` event per uid in this time; the rest counted


@dataclass(frozen=True)
class Peer:
    pid: int
    uid: int
    gid: int


#: waits up to the given seconds; False if the client has gone (or the server is closing)
Wait = Callable[[float], bool]


class Handler(Protocol):
    def handle(self, req: dict[str, Any], peer: Peer) -> dict[str, Any]: ...

    def watch(self, req: dict[str, Any], wait: Wait) -> Iterator[dict[str, Any]]: ...

    def refused(self, peer: Peer, why: str, repeats: int) -> None: ...


def peer_of(conn: socket.socket) -> Peer:
    pid, uid, gid = _UCRED.unpack(
        conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _UCRED.size))
    return Peer(pid, uid, gid)


SO_PEERGROUPS = getattr(socket, "SO_PEERGROUPS", 59)  # Linux >= 4.13; not named in 3.11


def peer_groups(conn: socket.socket) -> set[int]:
    """The peer's supplementary groups as the kernel saw them at connect().

    From the socket, not /proc/PID/status: the service runs with ProtectProc=invisible,
    which hides other users' processes.
    """
    size = 4 * 64
    while True:
        try:
            raw = conn.getsockopt(socket.SOL_SOCKET, SO_PEERGROUPS, size)
        except OSError as exc:
            if exc.errno == errno.ERANGE and size < 4 * 65536:
                size *= 4
                continue
            return set()
        return set(struct.unpack(f"{len(raw) // 4}I", raw))


def resolve_group(name: str) -> int:
    """gid of `name`, or the daemon's own group for ''; KeyError names an unknown group."""
    if not name:
        return os.getegid()
    try:
        return grp.getgrnam(name).gr_gid
    except KeyError:
        raise KeyError(f"control.group: no group named {name!r} on this machine") from None


class _Deadline(io.RawIOBase):
    """The connection as a raw stream whose reads all end by one deadline, so a line that
    trickles in times out as a whole rather than per byte."""

    def __init__(self, conn: socket.socket) -> None:
        self._conn = conn
        self.deadline = 0.0  # time.monotonic()

    def readable(self) -> bool:
        return True

    def readinto(self, buf: Any) -> int:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError
        self._conn.settimeout(left)
        return self._conn.recv_into(buf)


def _answer_and_close(conn: socket.socket, message: str) -> None:
    """Refuse a connection at once, without ever blocking the accepting thread: the answer
    goes into an empty socket buffer, and a client that sent its request first still reads
    it after our close (the CLI also reads it if its send fails)."""
    with conn, contextlib.suppress(OSError):
        conn.setblocking(False)
        conn.send(encode({"ok": False, "error": message}))


def claim_socket_dir(path: Path) -> None:
    """Make the socket's directory if need be; ControlError unless it is the daemon user's
    (or root's) and writable by no one else: whoever can write it can swap the socket."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
        why = untrusted_socket_dir(path.parent, {os.geteuid(), 0})
    except OSError as exc:
        raise ControlError(f"control socket {path}: {exc.strerror or exc} (set [control] "
                           "socket_path to a writable place)") from None
    if why is not None:
        raise ControlError(f"control socket {path}: refusing its directory: {why}; remove it, "
                           "or set [control] socket_path to a directory of this user's own")


def refuse_if_served(path: Path) -> bool:
    """Raise ControlError if a daemon answers on `path`; True if a dead one's file is there.

    The daemon asks this before it opens any device: a second `leveler run` on the same
    config must not touch the actuator the first one is driving, not even to make it safe.
    """
    if not (path.exists() or path.is_symlink()):
        return False
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(str(path))
    except OSError:
        return True
    else:
        raise ControlError(f"another leveler daemon is listening on {path}")
    finally:
        probe.close()


class ControlServer:
    """Listens on `path`; serves until close()."""

    def __init__(self, path: Path, handler: Handler, *, gid: int, max_clients: int = 16,
                 max_clients_per_uid: int = 8, idle_timeout_s: float = 60.0) -> None:
        self.path = path
        self._handler = handler
        self._gid = gid
        self._uid = os.geteuid()
        self._max = max_clients
        self._max_per_uid = max_clients_per_uid
        # kept for root and the daemon's user: group members together cannot lock them out
        self._reserved = min(RESERVED_SLOTS, max_clients - 1)
        self._idle = idle_timeout_s
        self._lock = threading.Lock()
        self._served: Counter[int] = Counter()  # uid -> connections being served
        self._refusals: dict[int, tuple[float, int]] = {}  # uid -> (last report, since then)
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()
        self._bound = (-1, -1)  # (st_dev, st_ino) of the socket file we made

    def allowed(self, peer: Peer, conn: socket.socket) -> bool:
        if peer.uid in (0, self._uid) or peer.gid == self._gid:
            return True
        return self._gid in peer_groups(conn)

    def start(self) -> None:
        """Bind (replacing a stale socket, refusing a live one) and start accepting."""
        try:
            self._bind()
        except OSError as exc:
            raise ControlError(f"control socket {self.path}: {exc.strerror or exc} "
                               "(set [control] socket_path to a writable place)") from None

    def _bind(self) -> None:
        claim_socket_dir(self.path)
        if refuse_if_served(self.path):
            self.path.unlink()  # left behind by a daemon that died
        # Bound and listening under a side name first, then linked into place: a client
        # that sees the socket file is never refused (bound at its own name, the file
        # appeared before listen(), and a test on a loaded CI runner connected in
        # between), and a link, unlike a rename, never replaces another daemon's socket.
        side = self.path.with_name(self.path.name + "~")
        side.unlink(missing_ok=True)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o117)  # the socket is born 0660: no window with wider access
        try:
            sock.bind(str(side))
        finally:
            os.umask(old)
        try:
            st = os.lstat(side)
            self._bound = (st.st_dev, st.st_ino)
            os.chmod(side, 0o660)
            if self._gid != os.getegid():
                os.chown(side, -1, self._gid)
            sock.listen(16)
            os.link(side, self.path)
        except OSError:
            sock.close()
            raise
        finally:
            side.unlink(missing_ok=True)
        self._sock = sock
        self._thread = threading.Thread(target=self._accept, name="control", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop serving; remove the socket file only if it is ours (never another daemon's)."""
        self._closing.set()
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)
            self._sock.close()
            self._sock = None
            self._remove_socket_file()
        if self._thread is not None:
            self._thread.join(timeout=2)

    def _remove_socket_file(self) -> None:
        """Unlink the socket we bound, not whatever stands at its path now (a directory
        swapped under us holds someone else's file); a failure is logged, never raised:
        the daemon still has its log to finish."""
        try:
            st = os.lstat(self.path)
            if (st.st_dev, st.st_ino) == self._bound:
                self.path.unlink()
            else:
                _log.warning("control socket %s was replaced while we served; left alone",
                             self.path)
        except FileNotFoundError:
            pass
        except OSError as exc:
            _log.warning("could not remove the control socket %s: %s", self.path, exc)

    def _accept(self) -> None:
        assert self._sock is not None
        demote_thread()  # client threads are started from here and inherit this
        while not self._closing.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            try:
                peer = peer_of(conn)
            except OSError:  # gone already
                conn.close()
                continue
            refusal = self._admit(peer, conn)
            if refusal is not None:
                _answer_and_close(conn, refusal)
                continue
            threading.Thread(target=self._serve, args=(conn, peer), name="control-client",
                             daemon=True).start()

    def _admit(self, peer: Peer, conn: socket.socket) -> str | None:
        """Why `peer` is turned away, or None after taking a slot for it."""
        if not self.allowed(peer, conn):
            why = (f"access denied: uid {peer.uid} is not root, the daemon's user or a member "
                   f"of group {self._gid}")
            self._report_refusal(peer, why)
            return why
        privileged = peer.uid in (0, self._uid)
        with self._lock:
            served = sum(self._served.values())
            if served >= self._max:
                return "too many clients; try later"
            if not privileged:
                others = served - sum(self._served[u] for u in {0, self._uid})
                if others >= self._max - self._reserved:
                    return "too many clients; try later"
                if self._served[peer.uid] >= self._max_per_uid:
                    return (f"too many connections from uid {peer.uid} (at most "
                            f"{self._max_per_uid} at once); try later")
            self._served[peer.uid] += 1
        return None

    def _report_refusal(self, peer: Peer, why: str) -> None:
        """At most one report per uid every REFUSAL_REPORT_S, with the count it stood for:
        a refused peer that reconnects in a loop must not flood the journal and the log."""
        now = time.monotonic()
        with self._lock:
            last, since = self._refusals.get(peer.uid, (-float("inf"), 0))
            if now - last < REFUSAL_REPORT_S:
                self._refusals[peer.uid] = (last, since + 1)
                return
            self._refusals[peer.uid] = (now, 0)
        self._handler.refused(peer, why, since)

    def _serve(self, conn: socket.socket, peer: Peer) -> None:
        try:
            with conn:
                raw = _Deadline(conn)
                reader = io.BufferedReader(raw)
                while not self._closing.is_set():
                    raw.deadline = time.monotonic() + self._idle
                    try:
                        line = reader.readline(MAX_LINE_BYTES + 1)
                    except TimeoutError:
                        conn.settimeout(1.0)  # a client that reads nothing cannot stall us
                        conn.sendall(encode({"ok": False, "error": (
                            f"idle: no complete request within {self._idle:g} s; closing "
                            "the connection")}))
                        return
                    conn.settimeout(self._idle)  # for the reply: a client must read it
                    if not line:
                        return
                    if len(line) > MAX_LINE_BYTES:
                        conn.sendall(encode({"ok": False,
                                             "error": f"request longer than {MAX_LINE_BYTES} "
                                                      "bytes; closing the connection"}))
                        return
                    # every line is answered, a blank one too (with an error)
                    if not self._answer(conn, line, peer):
                        return
        except (OSError, TimeoutError):
            return  # client went away or stalled past the idle timeout
        finally:
            with self._lock:
                self._served[peer.uid] -= 1
                if not self._served[peer.uid]:
                    del self._served[peer.uid]

    def _wait(self, conn: socket.socket, seconds: float) -> bool:
        """Wait up to `seconds` (at most idle_timeout_s) between a watch's lines; False as
        soon as the client hangs up or the server closes. What a watcher sends meanwhile is
        read and dropped (the protocol gives a watch no further requests)."""
        deadline = time.monotonic() + min(seconds, self._idle)
        poller = select.poll()
        poller.register(conn, select.POLLIN | select.POLLHUP | select.POLLERR)
        while not self._closing.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                return True
            if poller.poll(min(left, 0.5) * 1000):
                try:
                    if not conn.recv(4096, socket.MSG_DONTWAIT):
                        return False  # EOF: the client has gone
                except BlockingIOError:
                    pass
                except OSError:
                    return False
        return False

    def _answer(self, conn: socket.socket, line: bytes, peer: Peer) -> bool:
        """Serve one request; False ends the connection (after a watch)."""
        try:
            req = parse_request(line)
            if req["verb"] == "watch":
                conn.sendall(encode({"ok": True, "watching": True}))
                try:  # a watcher that stops reading for idle_timeout_s is dropped
                    for item in self._handler.watch(req, lambda s: self._wait(conn, s)):
                        conn.sendall(encode(item))
                except OSError:
                    pass  # the watcher left (or stalled): not an error of the daemon's
                return False
            reply = self._handler.handle(req, peer)
        except ProtocolError as exc:
            reply = {"ok": False, "error": str(exc)}
        except Exception as exc:  # a bug in a verb must not kill the daemon: report it
            _log.exception("control request failed")
            reply = {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}
        conn.sendall(encode(reply))
        return True

