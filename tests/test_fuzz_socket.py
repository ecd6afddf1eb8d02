"""Control-socket fuzzing against a real daemon at 100 Hz (issue 8, "bad input").

Seeded, so a failure replays. More than 10,000 malformed requests (random bytes, invalid
UTF-8, broken JSON, JSON that is not an object, unknown verbs, bad versions, arguments of
the wrong type or out of range, unknown arguments, NaN and Infinity literals, huge numbers,
nesting beyond the parser's depth) go in pipelined on a few connections and one per
connection on many short-lived ones; besides them, lines longer than MAX_LINE_BYTES, lines
cut off by a close, connections closed at once or before the answer, clients that connect
and stall (more than max_clients of them), one that sends a byte a second and a watcher
that stops reading.

Afterwards the daemon must still answer `status`, still be engaged with the controller it
started with (no malformed request may act), its RSS must have grown by less than
RSS_GROWTH_MB, every line that can be answered must have had exactly one error reply, its
stderr must hold no traceback and its log must be complete and engaged throughout.

The loop's overruns and period p99 before and after are printed, not bounded: on a shared
2-core machine make test's other workers move them more than the fuzz does (7 overruns in
895 cycles on a CI run even under SCHED_FIFO 50). What socket traffic costs the loop is a
benchmark's figure against a no-traffic baseline of the same run (bench/control_socket.py,
malformed lines back to back among its phases).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import orjson
import pytest
from conftest import daemon_config
from hypothesis import event, given, settings
from hypothesis import strategies as st

from leveler.daemon.protocol import (
    MAX_LINE_BYTES,
    NO_ARGS,
    TUNE_KEYS,
    VERBS,
    ProtocolError,
    modulate_args,
    parse_request,
    reload_args,
    tune_args,
)
from leveler.log.reader import read_log

SEED = 20261122
RATE_HZ = 100.0
MAX_CLIENTS = 16
IDLE_S = 3.0
RSS_GROWTH_MB = 20.0


# ---- the daemon -------------------------------------------------------------------------
@dataclass
class Daemon:
    proc: subprocess.Popen[str]
    socket: Path
    logs: Path
    stdout: list[str] = field(default_factory=list)
    stderr: list[str] = field(default_factory=list)

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise AssertionError("no VmRSS")

    def status(self) -> dict[str, Any]:
        reply = ask(self.socket, b'{"v":1,"verb":"status"}\n')
        assert reply["ok"], reply
        return reply["status"]


def _drain(stream: Iterator[str], into: list[str]) -> None:
    """Keep reading a pipe so the daemon never blocks printing its status line."""
    for line in stream:
        into.append(line)


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[Daemon]:
    short = Path(tempfile.mkdtemp(prefix="lvfz", dir="/tmp"))  # AF_UNIX paths are short
    sock = short / "c.sock"
    config = daemon_config(tmp_path, sock, rate_hz=RATE_HZ)
    with config.open("a") as fh:  # [control] is the config's last table
        fh.write(f"max_clients = {MAX_CLIENTS}\nidle_timeout_s = {IDLE_S}\n")
    proc = subprocess.Popen([sys.executable, "-m", "leveler.cli", "run",
                             "--config", str(config)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    d = Daemon(proc, sock, tmp_path / "logs")
    for stream, into in ((proc.stdout, d.stdout), (proc.stderr, d.stderr)):
        threading.Thread(target=_drain, args=(stream, into), daemon=True).start()
    deadline = time.monotonic() + 30
    while not sock.exists():
        assert proc.poll() is None, f"daemon died: {''.join(d.stderr)}"
        assert time.monotonic() < deadline, "daemon socket never appeared"
        time.sleep(0.05)
    try:
        yield d
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        shutil.rmtree(short, ignore_errors=True)


def connect(path: Path, timeout: float = 10.0) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    s.connect(str(path))
    return s


def ask(path: Path, payload: bytes = b"") -> dict[str, Any]:
    """The first reply on a fresh connection (to `payload`, or to connecting at all)."""
    with connect(path) as s:
        if payload:
            s.sendall(payload)
        return json.loads(s.makefile("rb").readline())


# ---- malformed requests -----------------------------------------------------------------
def _dumps(obj: object) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode()


def _bad_value(rng: random.Random) -> object:
    return rng.choice(["abc", "", "1.0", True, False, None, [], [1.0], {}, {"a": 1}])


def _random_bytes(rng: random.Random) -> bytes:
    return bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200)))


def _invalid_utf8(rng: random.Random) -> bytes:
    bad = rng.choice([b"\xff", b"\xc3\x28", b"\xed\xa0\x80", b"\xf8\x88\x80\x80\x80", b"\x80"])
    return b'{"v":1,"verb":"sta' + bad + b'tus"}'


def _broken_json(rng: random.Random) -> bytes:
    good = _dumps({"v": 1, "verb": "tune", "kp_v_per_m": 1.5, "persist": False})
    how = rng.randrange(4)
    if how == 0:  # cut short: no proper prefix of an object is JSON
        return good[: rng.randrange(1, len(good))]
    if how == 1:
        return good.replace(b'"', b"'")
    if how == 2:
        return good[:-1] + b",}"
    return b'{"v":1,"verb":"status"} // comment'


def _not_an_object(rng: random.Random) -> bytes:
    return _dumps(rng.choice([1, -2.5, "status", ["status"], [], None, True, [{"verb": "stop"}]]))


def _unknown_verb(rng: random.Random) -> bytes:
    verb = rng.choice(["fly", "", "STATUS", "status ", "Stop", "shutdown", "exec", 7, None,
                       ["stop"], {"verb": "stop"}, "".join(rng.choices("abcxyz_", k=6))])
    req = {"v": 1} if rng.random() < 0.1 else {"v": 1, "verb": verb}
    return _dumps(req)


def _bad_version(rng: random.Random) -> bytes:
    return _dumps({"v": rng.choice([0, 2, -1, 99, "1", None, [1], 1.5, True]),
                   "verb": rng.choice(["status", "stop", "start"])})


def _bad_arguments(rng: random.Random) -> bytes:
    """A real verb with at least one argument it refuses, so nothing may act."""
    verb = rng.choice(["tune", "tune", "modulate", "watch", "status", "start", "stop", "reset",
                       "rotate"])
    req: dict[str, object] = {"v": 1, "verb": verb}
    if verb == "tune":
        key = rng.choice(sorted(TUNE_KEYS))
        how = rng.randrange(4)
        if how == 0:
            req[key] = _bad_value(rng)
        elif how == 1:
            req["k" + key] = 1.0  # unknown key
        elif how == 2:
            req["persist"] = rng.choice([True, False])  # nothing to change
        else:
            req |= {"ki_v_per_m_s": 1.0, "persist": rng.choice(["yes", 1, None])}
    elif verb == "modulate":
        req |= {"amplitude_v": 1.0, "period_s": 2.0, "cycles": 1}
        key = rng.choice(["amplitude_v", "period_s", "cycles", "force", "extra"])
        req[key] = rng.choice([0, -1.0, 10**20, 2.5, "1", None, [], True]) if key != "force" \
            else rng.choice(["yes", 1, None])
        if key == "cycles" and req[key] == 1:
            req[key] = 0
    elif verb == "watch":
        req["rate_hz"] = rng.choice([0, -1, 1e9, 5000, "10", None, True, []])
    else:  # the verbs without arguments take none
        req[rng.choice(["force", "now", "reason", "rate_hz"])] = _bad_value(rng)
    return _dumps(req)


def _non_finite(rng: random.Random) -> bytes:
    lit = rng.choice([b"NaN", b"Infinity", b"-Infinity", b"nan", b"inf", b"1e400", b"-1e999"])
    key = rng.choice(sorted(TUNE_KEYS)).encode()
    return b'{"v":1,"verb":"tune","' + key + b'":' + lit + b"}"


def _huge(rng: random.Random) -> bytes:
    key = rng.choice(["kp_v_per_m", "ki_v_per_m_s", "kd_v_s_per_m", "slew_v_per_s"])
    value = rng.choice(["-1e300", "-" + "9" * 400, "1" + "0" * 400, "-1.7976931348623157e308"])
    return f'{{"v":1,"verb":"tune","{key}":{value}}}'.encode()


def _deep(rng: random.Random) -> bytes:
    """Past the parser's depth limit (1024), and within it but inside an unknown argument."""
    depth = rng.choice([50, 1100, 5000, 30000])
    if rng.random() < 0.5:
        return b"[" * depth + b"]" * depth
    depth = min(depth, 9000)  # 7 bytes a level: keep within MAX_LINE_BYTES
    return b'{"v":1,"verb":"status","x":' + b'{"a":' * depth + b"1" + b"}" * (depth + 1)


KINDS: dict[str, Callable[[random.Random], bytes]] = {
    "random bytes": _random_bytes, "invalid UTF-8": _invalid_utf8, "broken JSON": _broken_json,
    "not an object": _not_an_object, "unknown verb": _unknown_verb,
    "bad version": _bad_version, "bad arguments": _bad_arguments,
    "NaN/Infinity": _non_finite, "huge numbers": _huge, "deep nesting": _deep,
}


def junk(rng: random.Random) -> tuple[str, bytes]:
    """One malformed request line (no newline in it, not blank: each gets an answer)."""
    kind = rng.choice(list(KINDS))
    line = KINDS[kind](rng).replace(b"\n", b"?")
    assert len(line) <= MAX_LINE_BYTES
    return kind, line if line.strip() else line + b"?"


# ---- clients ----------------------------------------------------------------------------
@dataclass
class Tally:
    lines: int = 0  # malformed lines sent
    answered: int = 0  # ... of them answered with an error
    kinds: dict[str, int] = field(default_factory=dict)  # how often each case came up
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, kind: str, sent: int = 1, answered: int = 0) -> None:
        with self.lock:
            self.lines += sent
            self.answered += answered
            self.kinds[kind] = self.kinds.get(kind, 0) + 1


TRY_LATER = "too many clients; try later"


class TryLater(Exception):
    """The daemon turned the connection away, as it may while full."""


def check_refusal(line: bytes) -> None:
    """An error reply to the request itself (not a refusal to serve at all)."""
    reply = json.loads(line)
    assert reply.get("v") == 1 and reply.get("ok") is False, reply
    assert isinstance(reply.get("error"), str) and reply["error"], reply
    if reply["error"] == TRY_LATER:
        raise TryLater


def as_asked(client: Callable[..., None], *args: Any, tally: Tally) -> None:
    """Run a client; on "try later" try again, as the daemon asks. A client that has hung
    up keeps its slot until its server thread has run, which on a loaded machine can trail
    the fuzz's next connects (seen once in eight runs beside a diagnosis board)."""
    for _ in range(100):
        try:
            return client(*args, tally)
        except TryLater:
            tally.add("try later, tried again", sent=0)
            time.sleep(0.01)
    raise AssertionError("the daemon answered try later 100 times running")


def pipelined(path: Path, seed: int, n: int, tally: Tally) -> None:
    """n malformed lines in one write, then a status: n refusals in order, then the answer."""
    rng = random.Random(seed)
    lines = [junk(rng) for _ in range(n)]
    payload = b"".join(line + b"\n" for _, line in lines) + b'{"v":1,"verb":"status"}\n'
    with connect(path, timeout=30) as s:
        def send() -> None:
            with contextlib.suppress(OSError):  # turned away: the refusal is read below
                s.sendall(payload)

        writer = threading.Thread(target=send)
        writer.start()  # replies are read while we send: neither side's buffer may fill
        reader = s.makefile("rb")
        try:
            for _ in lines:
                check_refusal(reader.readline())
            assert json.loads(reader.readline())["ok"] is True
        finally:
            writer.join()
    for kind, _ in lines:
        tally.add(kind, answered=1)


def one_shot(path: Path, seed: int, tally: Tally) -> None:
    """A short-lived connection: one line, and one of the ways a client can leave."""
    rng = random.Random(seed)
    kind, line = junk(rng)
    how = rng.choice(["answer", "answer", "no newline", "close at once", "close unread",
                      "oversized", "oversized, no newline"])
    with connect(path) as s:
        if how == "close at once":
            tally.add("connect and close", sent=0)
            return
        if how.startswith("oversized"):
            big = bytes(rng.randrange(32, 127) for _ in range(64)) * (MAX_LINE_BYTES // 64 + 2)
            s.sendall(big + (b"" if "no newline" in how else b"\n"))
            reply = s.makefile("rb").readline()
            check_refusal(reply)
            assert b"longer than" in reply
            assert s.recv(1) == b"", "an oversized line must close the connection"
            tally.add(how, answered=1)
            return
        if how == "no newline":
            s.sendall(line)
            s.shutdown(socket.SHUT_WR)  # the cut-off line is still a request to answer
        else:
            s.sendall(line + b"\n")
        if how == "close unread":
            tally.add(f"{kind}, closed unread")
            return
        check_refusal(s.makefile("rb").readline())
        tally.add(kind if how == "answer" else f"{kind}, no newline", answered=1)


def stalled(path: Path, hold_s: float) -> bytes:
    """Connect, send nothing; return what the daemon sent before closing (or b'' )."""
    with connect(path, timeout=hold_s) as s:
        try:
            return s.makefile("rb").read()
        except TimeoutError:
            return b"still open"


def stalled_watcher(path: Path, stall_s: float) -> bytes:
    """Start a 100 Hz watch and stop reading it; after stall_s, read what is left: the
    stream must have been cut (EOF), not be flowing still."""
    with connect(path, timeout=stall_s) as s:
        s.sendall(b'{"v":1,"verb":"watch","rate_hz":1000}\n')
        time.sleep(stall_s)
        deadline = time.monotonic() + 3.0
        got = b""
        while time.monotonic() < deadline:
            chunk = s.recv(65536)
            if not chunk:
                return got
            got += chunk
    return b"still open"


def slow_loris(path: Path, give_up_s: float) -> tuple[float, bytes]:
    """A request sent a byte a second; returns when and what the daemon answered."""
    payload = b'{"v":1,"verb":"status","padding":"' + b"x" * 100
    start = time.monotonic()
    with connect(path, timeout=1.0) as s:
        for byte in payload:
            if time.monotonic() - start > give_up_s:
                break
            try:
                s.sendall(bytes([byte]))
            except OSError:  # closed by the daemon: its refusal may be waiting unread
                when = time.monotonic() - start
                try:
                    return when, s.recv(4096)
                except OSError:
                    return when, b""
            try:
                got = s.recv(4096)
            except TimeoutError:
                continue
            return time.monotonic() - start, got
    return time.monotonic() - start, b"still open"


# ---- the test ---------------------------------------------------------------------------
def fuzz(d: Daemon, *, pipes: int, per_pipe: int, one_shots: int) -> Tally:
    tally = Tally()
    with ThreadPoolExecutor(max_workers=4) as pool:
        jobs = [pool.submit(as_asked, pipelined, d.socket, SEED + i, per_pipe, tally=tally)
                for i in range(pipes)]
        jobs += [pool.submit(as_asked, one_shot, d.socket, SEED + 10_000 + i, tally=tally)
                 for i in range(one_shots)]
        for job in jobs:
            job.result()
    return tally


@dataclass
class Outcome:
    tally: Tally
    before: dict[str, Any]  # status before the fuzz
    after: dict[str, Any]  # ... right after it (loop statistics)
    last: dict[str, Any]  # ... after the clients beyond max_clients
    rss_mb: tuple[float, float]  # before the fuzz, at the end
    messages_s: float
    fuzz_s: float
    stalls: list[bytes]
    loris: tuple[float, bytes]
    watched: bytes
    extra: list[dict[str, Any]]
    closed: list[bytes]


def run_fuzz(d: Daemon, *, pipes: int, per_pipe: int, one_shots: int) -> Outcome:
    d.status()
    fuzz(d, pipes=1, per_pipe=200, one_shots=50)  # warm-up: threads, buffers, allocator
    time.sleep(3.0)  # a quiet stretch for the period statistics before
    before, rss_before = d.status(), d.rss_mb()
    t0 = time.monotonic()
    with ThreadPoolExecutor(max_workers=4) as side:
        # alongside the fuzz: two clients that stall, one that sends a byte a second and
        # a watcher that stops reading
        stalls = [side.submit(stalled, d.socket, IDLE_S + 5) for _ in range(2)]
        loris = side.submit(slow_loris, d.socket, IDLE_S + 5)
        watcher = side.submit(stalled_watcher, d.socket, IDLE_S + 5)
        tally = fuzz(d, pipes=pipes, per_pipe=per_pipe, one_shots=one_shots)
        messages_s = time.monotonic() - t0
    fuzz_s = time.monotonic() - t0
    time.sleep(1.1)  # the loop statistics are recomputed at most once a second
    after = d.status()

    # more stalled clients than max_clients: the extra ones are told so; once the idle
    # timeout has closed the stalled ones, the daemon serves again
    hold = [connect(d.socket) for _ in range(MAX_CLIENTS)]
    time.sleep(0.3)
    extra = [ask(d.socket) for _ in range(3)]
    time.sleep(IDLE_S + 1.0)
    closed = []
    for s in hold:
        with s:
            closed.append(s.makefile("rb").read())
    return Outcome(tally, before, after, d.status(), (rss_before, d.rss_mb()), messages_s,
                   fuzz_s, [s.result() for s in stalls], loris.result(), watcher.result(),
                   extra, closed)


def check(d: Daemon, r: Outcome, min_lines: int) -> None:
    lb, la = r.before["loop"], r.after["loop"]
    print(f"\nsocket fuzz: {r.tally.lines} malformed lines ({r.tally.answered} answered, each "
          f"with one error) in {r.messages_s:.1f} s, stalled clients until {r.fuzz_s:.1f} s; "
          f"kinds {dict(sorted(r.tally.kinds.items()))}\n"
          f"RSS {r.rss_mb[0]:.1f} -> {r.rss_mb[1]:.1f} MB; overruns {lb['overruns']} -> "
          f"{la['overruns']} in {la['cycles'] - lb['cycles']} cycles; period p99 "
          f"{lb['period_p99_s'] * 1e3:.2f} -> {la['period_p99_s'] * 1e3:.2f} ms, max "
          f"{lb['period_max_s'] * 1e3:.2f} -> {la['period_max_s'] * 1e3:.2f} ms; "
          f"slow loris cut after {r.loris[0]:.1f} s")
    assert r.tally.lines >= min_lines
    assert d.proc.poll() is None
    for status in (r.after, r.last):
        assert status["state"] == "engaged"
        assert status["controller"] == r.before["controller"]
    assert r.rss_mb[1] - r.rss_mb[0] < RSS_GROWTH_MB
    assert la["cycles"] > lb["cycles"], "the loop must keep cycling through the fuzz"
    for got in r.stalls:
        check_refusal(got.splitlines()[0])
        assert b"idle" in got
    check_refusal(r.loris[1].splitlines()[0])
    assert r.loris[0] < IDLE_S + 2.0, "a request trickling in must not hold a slot for ever"
    assert r.watched != b"still open", "a watcher that stops reading must be dropped"
    for reply in r.extra:
        assert reply == {"v": 1, "ok": False, "error": "too many clients; try later"}
    for got in r.closed:
        check_refusal(got.splitlines()[0])
        assert b"idle" in got


def finish(d: Daemon) -> None:
    """A clean stop; no traceback in stderr; the log says engaged throughout."""
    d.proc.send_signal(signal.SIGTERM)
    assert d.proc.wait(timeout=20) == 0
    time.sleep(0.2)  # the drain threads reach EOF
    err = "".join(d.stderr)
    assert "Traceback" not in err and "internal error" not in err, err[-3000:]
    (log,) = d.logs.glob("*.mcap")
    data = read_log(log)
    assert data.complete
    assert set(data.samples["state"][5:]) == {"engaged"}
    kinds = {e["kind"] for e in data.events}
    assert not kinds & {"tune", "modulate", "persist"}, kinds


def test_socket_fuzz_leaves_the_daemon_running_unchanged(daemon: Daemon) -> None:
    r = run_fuzz(daemon, pipes=40, per_pipe=1100, one_shots=3000)
    check(daemon, r, min_lines=10_000)
    finish(daemon)


# ---- the same checks in-process, over a wider space ---------------------------------------
def _containers(inner: st.SearchStrategy[object]) -> st.SearchStrategy[object]:
    return st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                         max_size=4)


JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(),
    _containers, max_leaves=6)
NUMBER = st.floats() | st.integers(-(2**63), 2**64 - 1) | JSON
ARGS = {"tune": {**{k: NUMBER for k in TUNE_KEYS}, "persist": st.booleans() | JSON,
                 "force": st.booleans() | JSON},
        "reload": {"accept_dropped": st.booleans() | JSON, "force": st.booleans() | JSON},
        "modulate": {"amplitude_v": NUMBER, "period_s": NUMBER, "cycles": NUMBER,
                     "shape": st.sampled_from(["square", "triangle", "sine"]) | JSON,
                     "force": st.booleans() | JSON},
        "watch": {"rate_hz": NUMBER}}
REQUESTS = st.sampled_from(VERBS).flatmap(lambda verb: st.fixed_dictionaries(
    {"v": st.one_of(st.just(1), st.just(1), st.just(1), JSON), "verb": st.just(verb)},
    optional={**ARGS.get(verb, {}), "extra": JSON}))


@settings(max_examples=400, deadline=None)
@given(req=REQUESTS | st.dictionaries(st.text(max_size=8), JSON, max_size=5))
def test_requests_are_refused_or_exactly_valid(req: dict[str, object]) -> None:
    """What parse_request and the argument checks let through is a well-formed request;
    everything else is a ProtocolError (never another exception)."""
    line = orjson.dumps(req, option=orjson.OPT_SERIALIZE_NUMPY)  # NaN becomes null
    try:
        ok = parse_request(line)
        if ok["verb"] == "tune":
            values, persist = tune_args(ok)
            assert values and isinstance(persist, bool)
            assert all(isinstance(v, float) and (math.isfinite(v) or (
                k == "slew_v_per_s" and v == math.inf)) for k, v in values.items())
            assert abs(values.get("setpoint_m", 0.0)) <= 1e-3
        elif ok["verb"] == "modulate":
            amplitude, period, cycles, shape, force = modulate_args(ok)
            assert amplitude > 0 and period > 0 and 1 <= cycles <= 10_000
            assert shape in ("square", "triangle")
            assert isinstance(force, bool)
        elif ok["verb"] == "reload":
            accept_dropped, force = reload_args(ok)
            assert isinstance(accept_dropped, bool) and isinstance(force, bool)
            assert set(ok) <= {"v", "verb", "accept_dropped", "force"}
    except ProtocolError as exc:
        event(f"refused: {str(exc).split(':')[0].split(' ')[0]}")
        return
    event(f"accepted: {ok['verb']}")
    assert type(ok["v"]) is int and ok["v"] == 1
    if ok["verb"] in NO_ARGS:
        assert set(ok) == {"v", "verb"}
    if ok["verb"] == "watch":
        rate = ok.get("rate_hz", 10.0)
        assert set(ok) <= {"v", "verb", "rate_hz"} and not isinstance(rate, bool)
        assert 0 < rate <= 1000  # type: ignore[operator]


@settings(max_examples=400, deadline=None)
@given(line=st.binary(max_size=300))
def test_any_bytes_are_a_request_or_a_protocol_error(line: bytes) -> None:
    try:
        parse_request(line)
    except ProtocolError:
        pass


@pytest.mark.parametrize(
    ("line", "needle"),
    [
        (b'{"v":1,"verb":"stop","force":true}', "stop takes no arguments"),
        (b'{"v":1,"verb":"status","x":{"a":1}}', "status takes no arguments"),
        (b'{"v":true,"verb":"stop"}', "protocol version True not supported"),
        (b'{"v":1.0,"verb":"stop"}', "protocol version 1.0 not supported"),
        (b'{"v":1,"verb":"watch","rate_hz":0}', "rate_hz must be a number in (0, 1000]"),
        (b'{"v":1,"verb":"watch","rate":5}', "watch: unknown key 'rate'"),
        (b"\r\n", "empty request"),
        (b'{"v":1,"verb":"stop","verb":"start"}', "key 'verb' given twice"),
    ],
)
def test_requests_with_what_the_verb_does_not_take_are_refused(line: bytes,
                                                               needle: str) -> None:
    """Before these were refused, `stop` with any extra key stopped the loop, a watch at a
    bad rate was first promised (ok, watching) and then refused, a blank line got no answer
    at all and a repeated verb acted on the last one."""
    with pytest.raises(ProtocolError) as err:
        parse_request(line)
    assert needle in str(err.value)
