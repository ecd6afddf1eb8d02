"""The six attacks of issue 15, replayed against a real daemon: each is refused or survived
with a clear message, and nothing is lost.

1. a config cut at a line boundary (valid TOML, keys missing) sent with SIGHUP;
2. `watch` at a rate of 1e-6 Hz, which used to keep its slot after the client left;
3. refused peers trickling bytes to hold every slot, each refusal logged unlimited;
4. a socket directory made by someone else first (the default /tmp/leveler-<uid>);
5. the log directory deleted under a running daemon;
6. the small ones: a full connection queue, `rotate` into an unusable directory, logs
   world-readable when the daemon is started by hand.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import as_user

from leveler.log.reader import read_log

ROOT_ONLY = pytest.mark.skipif(os.geteuid() != 0, reason="needs root to act as another user")
NOBODY = 65534


def status(d) -> dict:  # type: ignore[no-untyped-def,type-arg]
    proc = d.cli("status", "--json")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def wait_for(cond: Callable[[], object], what: str, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.1)


def events(d, kind: str) -> list[dict]:  # type: ignore[no-untyped-def,type-arg]
    out = []
    for f in sorted(d.logs.glob("*.mcap")):
        out += [e for e in read_log(f).events if e["kind"] == kind]
    return out


# ---- 1. a config cut short ---------------------------------------------------------------
def test_a_config_cut_at_a_line_boundary_is_refused_and_applied_only_whole(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    """The attack: the file cut just before `kd_v_s_per_m` is valid TOML; SIGHUP used to apply
    it, kd fell from its default to 0 and d_filter_tau_s rose to 0.5, and the loop oscillated."""
    d = start_daemon(rate_hz=10.0)
    good = d.config.read_text()
    cut = good[:good.index("kd_v_s_per_m")]
    d.config.write_text(cut)
    d.proc.send_signal(signal.SIGHUP)
    time.sleep(1.0)  # the reload is checked (and refused) on a thread of its own
    st = status(d)
    assert st["controller"]["kd_v_s_per_m"] == 1.9e6 and st["controller"]["d_filter_tau_s"] == 0.03
    by_hand = d.cli("reload")
    assert by_hand.returncode == 2 and "Traceback" not in by_hand.stderr
    assert "no longer sets" in by_hand.stderr and "controller.kd_v_s_per_m" in by_hand.stderr
    assert "control.socket_path" in by_hand.stderr  # the rest of the file is gone too
    assert "--accept-dropped" in by_hand.stderr
    # Accepting the dropped keys still meets the stability guard: kd 0 with ki 2.2e7 rings.
    accepted = d.cli("reload", "--accept-dropped")
    assert accepted.returncode == 2 and "predicts an unstable loop" in accepted.stderr
    assert status(d)["controller"]["kd_v_s_per_m"] == 1.9e6

    # A file that drops one key on purpose (its default is what it said) goes in when asked.
    line = re.search(r"(?m)^slew_v_per_s = 10.0\n", good)
    assert line is not None
    d.config.write_text(good.replace(line[0], ""))
    assert d.cli("reload").returncode == 2
    ok = d.cli("reload", "--accept-dropped")
    assert ok.returncode == 0, ok.stderr
    assert "0 value(s) changed" in ok.stdout
    assert "back to their defaults (no longer in the file): controller.slew_v_per_s" in ok.stdout

    # A whole, stable change through SIGHUP: applied, its diff in the journal and the log.
    d.config.write_text(good.replace("ki_v_per_m_s = 2.2e7", "ki_v_per_m_s = 2.0e7"))
    d.proc.send_signal(signal.SIGHUP)
    wait_for(lambda: status(d)["controller"]["ki_v_per_m_s"] == 2.0e7, "reload not applied")
    err = d.stop()
    assert ("reload (SIGHUP) applied: controller.ki_v_per_m_s 22000000.0 -> 20000000.0"
            in err), err
    assert err.count("reload rejected, keeping the running config") == 4, err
    reloads = events(d, "reload")
    assert [e["reason"].split(":")[0] for e in reloads] == [
        "rejected", "rejected", "rejected", "rejected", "applied", "applied"]
    assert "controller.kd_v_s_per_m" in reloads[0]["reason"]
    assert reloads[4]["detail"]["dropped"] == ["controller.slew_v_per_s"]
    assert reloads[-1]["detail"]["changed"] == {"controller.ki_v_per_m_s": [2.2e7, 2.0e7]}
    assert reloads[-1]["detail"]["by"] == "SIGHUP"


def test_gains_the_model_predicts_unstable_are_not_engaged_on_start(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    """Gains tuned for another rate or another pendulum (here: the D that damps the
    resonance dropped) must not close the loop at start, where the stand would ring at once;
    the actuator stays at its safe voltage, the reason goes to the journal and the log, and
    `leveler start` still engages by hand."""
    d = start_daemon(rate_hz=10.0, replace={"kd_v_s_per_m = 1.9e6": "kd_v_s_per_m = 0.0"})
    d.wait_status_lines(1)
    st = status(d)
    assert st["state"] == "idle"
    assert d.cli("start").returncode == 0
    wait_for(lambda: status(d)["state"] == "engaged", "start by hand did not engage")
    err = d.stop()
    assert ("not engaged on start: the plant model predicts an unstable loop at 10 Hz: a "
            "closed-loop pole at |z| = 1.09") in err, err
    assert "leveler tune --suggest" in err
    (ev,) = events(d, "stability")
    assert ev["reason"].startswith("not engaged on start: the plant model predicts an unstable")


def test_tune_refuses_gains_the_model_predicts_unstable_unless_forced(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(rate_hz=10.0)
    refused = d.cli("tune", "--kd", "0")
    assert refused.returncode == 2
    assert refused.stderr.startswith("leveler tune: error: tune: the plant model predicts an "
                                     "unstable loop at 10 Hz: a closed-loop pole at |z| = 1.09")
    assert "--force" in refused.stderr
    assert status(d)["controller"]["kd_v_s_per_m"] == 1.9e6
    assert d.cli("tune", "--setpoint", "1e-8").returncode == 0  # not a gain: not judged
    assert d.cli("tune", "--kd", "2.4e6").returncode == 0  # stable: applied
    forced = d.cli("tune", "--kd", "0", "--force")
    assert forced.returncode == 0, forced.stderr
    assert status(d)["controller"]["kd_v_s_per_m"] == 0.0
    d.stop()
    tunes = [e["reason"] for e in events(d, "tune")]
    assert tunes[-1].endswith("(--force: no stability check)"), tunes
    assert not any("--force" in r for r in tunes[:-1]), tunes


def test_a_file_cut_mid_line_at_its_end_is_refused(start_daemon) -> None:  # type: ignore[no-untyped-def]
    """Found by a second attack: a file whose last line is cut inside a number is still
    valid TOML and sets every key (`idle_timeout_s = 60.0` -> `= 6`); a reload applied it.
    A whole file ends with a newline."""
    d = start_daemon(rate_hz=10.0, control="idle_timeout_s = 60.0\n")
    good = d.config.read_text()
    assert good.endswith("idle_timeout_s = 60.0\n")
    d.config.write_text(good[:-len("0.0\n")])
    refused = d.cli("reload")
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert "ends mid-line (no newline after 'idle_timeout_s = 6')" in refused.stderr
    d.proc.send_signal(signal.SIGHUP)
    time.sleep(1.5)  # the reload is checked (and refused) on a thread of its own
    err = d.stop()
    assert err.count("reload rejected, keeping the running config") == 2, err
    assert [e["reason"].split(":")[0] for e in events(d, "reload")] == ["rejected"] * 2


# ---- 2. a watcher at 1e-6 Hz -------------------------------------------------------------
def _watch(sock: Path, rate_hz: float) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(10.0)
    s.connect(str(sock))
    s.sendall(json.dumps({"v": 1, "verb": "watch", "rate_hz": rate_hz}).encode() + b"\n")
    return s


def _raw_status_ok(sock: Path) -> bool:
    """False while the daemon refuses: it answers "too many clients" at once and closes,
    and the close may break the pipe before the request is sent (CI failed twice there)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(5.0)
        s.connect(str(sock))
        try:
            s.sendall(b'{"v": 1, "verb": "status"}\n')
            line = s.makefile("rb").readline()
        except (BrokenPipeError, ConnectionResetError):
            return False
        return bool(line) and bool(json.loads(line)["ok"])


def test_watchers_at_a_tiny_rate_give_their_slots_back_when_they_leave(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    """Sixteen watchers at 1e-6 Hz that hang up: the server threads used to sleep 1e6 s and
    keep every slot ("too many clients" until a restart)."""
    d = start_daemon(rate_hz=10.0, control="idle_timeout_s = 2.0\n")
    watchers = [_watch(d.socket, 1e-6) for _ in range(16)]
    for w in watchers:
        reader = w.makefile("rb")
        assert json.loads(reader.readline())["watching"] is True
        assert "sample" in json.loads(reader.readline())
    t0 = time.monotonic()
    for w in watchers:
        w.close()
    wait_for(lambda: _raw_status_ok(d.socket), "slots never came back", 5.0)
    assert time.monotonic() - t0 < 3.0  # before: never (each thread slept 1e6 s)
    # A watcher that stays gets a line at least every idle_timeout_s (2 s), however slow
    # its rate: a departed one is noticed by the send at the latest.
    with _watch(d.socket, 1e-6) as w:
        reader = w.makefile("rb")
        t0 = time.monotonic()
        lines = [reader.readline() for _ in range(4)]  # ack, then samples
        assert all(lines) and time.monotonic() - t0 < 8.0
    d.stop()


# ---- 3. refused peers holding slots ------------------------------------------------------
def _trickle(sock: Path, seconds: float) -> str:
    """Connect and send a byte every 0.5 s; what the daemon answered, and when it closed."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(1.0)
    s.connect(str(sock))
    got = b""
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        try:
            s.sendall(b"{")
        except OSError:
            pass  # closed by the daemon: what it said is still there to read
        try:
            data = s.recv(4096)
        except TimeoutError:
            continue
        except OSError:
            break
        if not data:
            break
        got += data
        time.sleep(0.5)
    s.close()
    return f"{time.monotonic() - t0:.2f} {got.decode(errors='replace')}"


@ROOT_ONLY
def test_refused_peers_cannot_hold_slots_and_their_events_are_rate_limited(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(rate_hz=10.0)
    os.chmod(d.socket.parent, 0o755)  # the accident the credential check exists for
    os.chmod(d.socket, 0o666)
    results: list[str] = []

    def attacker() -> None:
        results.append(as_user(NOBODY, lambda: _trickle(d.socket, 4.0)))

    threads = [threading.Thread(target=attacker) for _ in range(20)]
    for t in threads:
        t.start()
    time.sleep(1.0)
    assert d.cli("status").returncode == 0  # the slots are free while they trickle
    for t in threads:
        t.join()
    assert len(results) == 20
    for r in results:
        seconds, reply = r.split(" ", 1)
        assert "access denied: uid 65534" in reply, r
        assert float(seconds) < 3.0, r  # closed at once (before: held while trickling)
    err = d.stop()
    refusals = [line for line in err.splitlines() if "control: refused" in line]
    assert len(refusals) == 1, refusals  # 20 refusals, one report (one per uid per 10 s)
    (access,) = events(d, "access")
    assert access["detail"]["uid"] == NOBODY


@ROOT_ONLY
def test_one_user_cannot_take_every_slot(start_daemon) -> None:  # type: ignore[no-untyped-def]
    """A member of the daemon's group (here: gid 0) holds at most max_clients_per_uid (8) of
    the 16 slots; root and the daemon's own user are not limited."""
    d = start_daemon(rate_hz=10.0)
    os.chmod(d.socket.parent, 0o755)
    root_done = d.socket.parent / "root-status-done"  # where nobody can look

    def hold_eight_then_ask_a_ninth() -> str:
        held = []
        for _ in range(8):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(d.socket))
            held.append(s)
        time.sleep(0.3)
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(5.0)
        s.connect(str(d.socket))
        ninth = s.makefile("rb").readline().decode()
        deadline = time.monotonic() + 20
        while not root_done.exists():  # hold the eight while root asks for its status
            assert time.monotonic() < deadline
            time.sleep(0.1)
        return ninth

    result: list[str] = []
    child = threading.Thread(target=lambda: result.append(
        as_user(NOBODY, hold_eight_then_ask_a_ninth, gid=0)))
    child.start()
    time.sleep(1.5)
    assert d.cli("status").returncode == 0
    root_done.touch()
    child.join()
    assert "too many connections from uid 65534 (at most 8 at once); try later" in result[0]
    d.stop()


@ROOT_ONLY
def test_group_members_together_cannot_lock_root_out(start_daemon) -> None:  # type: ignore[no-untyped-def]
    """Found by a second attack: two members of the daemon's group, eight connections each,
    took all 16 slots and root's `status` got "too many clients" for as long as they stayed.
    Two slots are kept for root and the daemon's user."""
    d = start_daemon(rate_hz=10.0)
    os.chmod(d.socket.parent, 0o755)
    root_done = d.socket.parent / "root-status-done"

    def hold_eight() -> str:
        held = []
        for _ in range(8):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(d.socket))
            held.append(s)
        deadline = time.monotonic() + 20
        while not root_done.exists():  # hold them while root asks for its status
            assert time.monotonic() < deadline
            time.sleep(0.1)
        return "held"

    children = [threading.Thread(target=as_user, args=(uid, hold_eight), kwargs={"gid": 0})
                for uid in (NOBODY, NOBODY - 1)]
    for c in children:
        c.start()
    time.sleep(1.5)
    assert d.cli("status").returncode == 0  # a reserved slot
    root_done.touch()
    for c in children:
        c.join()
    d.stop()


# ---- 4. a socket directory someone else made ----------------------------------------------
@ROOT_ONLY
def test_the_daemon_refuses_a_socket_directory_it_does_not_own(tmp_path: Path) -> None:
    from conftest import REPO, daemon_config

    short = Path(tempfile.mkdtemp(prefix="lvh", dir="/tmp"))
    try:
        for mode, owner, needle in ((0o755, NOBODY, "belongs to uid 65534"),
                                    (0o777, 0, "is writable by anyone"),
                                    (0o770, 0, "is writable by its group")):
            planted = short / f"planted-{mode:o}-{owner}"
            planted.mkdir()
            os.chown(planted, owner, owner)
            planted.chmod(mode)
            config = daemon_config(tmp_path, planted / "control.sock")
            proc = subprocess.run([sys.executable, "-m", "leveler.cli", "run", "--config",
                                   str(config)], capture_output=True, text=True, timeout=60,
                                  cwd=REPO)
            assert proc.returncode == 2, proc.stderr
            assert "refusing its directory" in proc.stderr and needle in proc.stderr
            assert "Traceback" not in proc.stderr
            assert not (planted / "control.sock").exists()
            assert not (tmp_path / "logs").exists()  # refused before any device or log
        # A symlink someone else owns, to a directory of ours: they can re-point it at will.
        ours = short / "ours"
        ours.mkdir(mode=0o700)
        link = short / "link"
        link.symlink_to(ours)
        os.lchown(link, NOBODY, NOBODY)
        config = daemon_config(tmp_path, link / "control.sock")
        proc = subprocess.run([sys.executable, "-m", "leveler.cli", "run", "--config",
                               str(config)], capture_output=True, text=True, timeout=60, cwd=REPO)
        assert proc.returncode == 2, proc.stderr
        assert f"{link} is a symlink of uid 65534, who could point it elsewhere" in proc.stderr
        assert not (ours / "control.sock").exists()
    finally:
        shutil.rmtree(short)


def _fake_daemon(path: Path, reply: bytes, received: list[bytes]) -> threading.Thread:
    """A socket at `path` that records what it is sent and answers `reply`."""
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(path))
    srv.listen(4)
    srv.settimeout(10.0)

    def serve() -> None:
        with srv:
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                return
            with conn:
                conn.settimeout(5.0)
                received.append(conn.recv(65536))
                conn.sendall(reply)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    return t


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "leveler.cli", *args], capture_output=True,
                          text=True, timeout=60)


@ROOT_ONLY
def test_the_cli_sends_nothing_to_a_socket_someone_else_planted() -> None:
    """The attack: another user made /tmp/leveler-<uid> first and put their own socket in it;
    a `tune` was captured and the CLI crashed with KeyError: 'controller'."""
    short = Path(tempfile.mkdtemp(prefix="lvp", dir="/tmp"))
    try:
        short.chmod(0o1777)  # like /tmp: anyone may make the directory first
        planted = short / "leveler-0"
        planted.mkdir()
        os.chown(planted, NOBODY, NOBODY)
        received: list[bytes] = []
        sock = planted / "control.sock"
        _fake_daemon(sock, b'{"v": 1, "ok": true}\n', received)
        os.chown(sock, NOBODY, NOBODY)
        proc = _cli("tune", "--kp", "1", "--socket", str(sock))
        assert proc.returncode == 2
        assert proc.stderr.startswith(f"leveler tune: error: refusing to talk to {sock}: "
                                      f"{planted} belongs to uid 65534"), proc.stderr
        assert "nothing was sent" in proc.stderr and "Traceback" not in proc.stderr
        time.sleep(0.3)
        assert received == []
    finally:
        shutil.rmtree(short)


@pytest.mark.parametrize(("reply", "verb"), [
    (b'{"v": 1, "ok": true}\n', ["tune", "--kp", "1"]),
    (b'{"v": 1, "ok": true, "status": {"state": "engaged"}}\n', ["status"]),
    (b'{"v": 1, "ok": true, "state": 3}\n', ["rotate"]),
    (b"HTTP/1.1 400 Bad Request\r\n\r\n", ["start"]),
    (b"[1, 2]\n", ["stop"]),
])
def test_a_reply_the_cli_cannot_read_is_one_line_not_a_traceback(
        tmp_path: Path, reply: bytes, verb: list[str]) -> None:
    short = Path(tempfile.mkdtemp(prefix="lvr", dir="/tmp"))
    try:
        sock = short / "c.sock"
        received: list[bytes] = []
        t = _fake_daemon(sock, reply, received)
        proc = _cli(*verb, "--socket", str(sock))
        t.join(timeout=10)
        assert proc.returncode == 2, proc
        assert "Traceback" not in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert ("another version, or not a leveler daemon?" in proc.stderr
                or "not a leveler daemon?" in proc.stderr), proc.stderr
    finally:
        shutil.rmtree(short)


def test_a_socket_file_replaced_under_the_daemon_is_left_alone_and_the_log_finished(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    """Found by a second attack: with the socket's directory swapped under a running daemon,
    removing the socket at exit raised PermissionError, which skipped finishing the log and
    closing the stand (exit 1). It unlinks only the file it made; every close runs."""
    d = start_daemon(rate_hz=10.0)
    d.socket.unlink()
    d.socket.write_text("someone else's")
    err = d.stop()
    assert d.proc.returncode == 0, err
    assert "was replaced while we served; left alone" in err and "Traceback" not in err
    assert d.socket.read_text() == "someone else's"
    log = read_log(next(d.logs.glob("*.mcap")))
    assert log.complete and log.events[-1]["kind"] == "stop"


# ---- 5. a deleted log directory -----------------------------------------------------------
def test_a_deleted_log_directory_is_a_fault_the_log_survives_with_nothing_lost(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    """The attack: `rm -rf logs` under a running daemon; it kept writing to the unlinked file,
    `status` said healthy, and everything until the next rotation was lost."""
    d = start_daemon(rate_hz=50.0)
    wait_for(lambda: status(d)["log"]["samples_written"] > 50, "no samples logged")
    (first,) = d.logs.glob("*.mcap")
    shutil.rmtree(d.logs)
    wait_for(lambda: status(d)["log"]["faults"] == 1, "the deleted file was not noticed", 10)
    wait_for(lambda: first.exists() and len(list(d.logs.glob("*.mcap"))) == 2,
             "no restored file and new file in a re-created directory", 10)
    st = status(d)
    assert st["log"]["healthy"] and st["log"]["dropped"] == 0
    assert "was deleted while being written; restored" in st["log"]["last_fault"]
    assert "1 log fault(s) since start; last:" in d.cli("status").stdout
    d.stop()
    seqs, kinds = [], []
    for f in sorted(d.logs.glob("*.mcap")):
        data = read_log(f)
        assert data.complete
        seqs.append(np.asarray(data.samples["seq"]))
        kinds += [e["reason"] for e in data.events if e["kind"] == "log"]
    seq = np.concatenate(seqs)
    assert seq[0] == 0 and np.all(np.diff(seq) == 1), "a sample lost or repeated"
    assert any("was deleted while being written; restored from its open descriptor" in k
               for k in kinds), kinds


def test_a_moved_log_directory_and_a_failed_rotation_are_log_faults_not_internal_errors(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(rate_hz=50.0)
    wait_for(lambda: status(d)["log"]["samples_written"] > 20, "no samples logged")
    moved = d.logs.with_name("logs.moved")
    d.logs.rename(moved)
    d.logs.write_text("not a directory")  # where the log wants its directory: unusable
    wait_for(lambda: not status(d)["log"]["healthy"], "the moved file was not noticed", 10)
    rot = d.cli("rotate")
    assert rot.returncode == 2 and "Traceback" not in rot.stderr
    assert "internal error" not in rot.stderr
    assert rot.stderr.startswith("leveler rotate: error: rotate failed: cannot start a new log "
                                 "file:"), rot.stderr
    assert "a log fault in `leveler status`" in rot.stderr
    st = status(d)
    assert "is no longer at its path" in st["log"]["error"]
    assert "cannot start a new log file" in st["log"]["error"]
    assert "FAULT:" in d.cli("status").stdout
    d.logs.unlink()  # the directory can be made again: the retry opens a new file there
    wait_for(lambda: status(d)["log"]["healthy"], "logging did not resume", 15)
    d.stop()
    seq = np.concatenate([np.asarray(read_log(f).samples["seq"])
                          for f in sorted([*moved.glob("*.mcap"), *d.logs.glob("*.mcap")],
                                         key=lambda f: f.name)])
    assert seq[0] == 0 and np.all(np.diff(seq) == 1)


# ---- 6. the small ones --------------------------------------------------------------------
def test_logs_are_not_world_readable_whoever_starts_the_daemon(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(rate_hz=10.0, umask=0o000)
    wait_for(lambda: list(d.logs.glob("*.mcap")), "no log file")
    d.stop()
    assert stat.S_IMODE(d.logs.stat().st_mode) == 0o750
    for f in d.logs.glob("*.mcap"):
        assert stat.S_IMODE(f.stat().st_mode) == 0o640, f


def test_a_full_connection_queue_is_busy_not_a_traceback(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    """With the daemon stopped (SIGSTOP) nothing is accepted: connections pile up in the
    listen queue until connect() says EAGAIN."""
    d = start_daemon(rate_hz=10.0)
    d.proc.send_signal(signal.SIGSTOP)
    tasks = Path(f"/proc/{d.proc.pid}/task")  # every thread, not only the main one

    def stopped() -> bool:
        return all((t / "stat").read_text().rsplit(")", 1)[1].split()[0] == "T"
                   for t in tasks.iterdir())

    wait_for(stopped, "the daemon's threads did not all stop")
    pending: list[socket.socket] = []
    try:
        while True:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.setblocking(False)
            try:
                s.connect(str(d.socket))
            except BlockingIOError:
                s.close()
                break
            pending.append(s)
            assert len(pending) < 1000
        proc = d.cli("status")
        assert proc.returncode == 2
        assert proc.stderr == (f"leveler status: error: the daemon on {d.socket} is busy (its "
                               "queue of pending connections stayed full); try later\n")
        # reload waits up to a minute for its reply, but not for a queue that stays full
        began = time.monotonic()
        proc = d.cli("reload", timeout=30)
        assert proc.returncode == 2 and "is busy" in proc.stderr
        assert time.monotonic() - began < 20
    finally:
        d.proc.send_signal(signal.SIGCONT)
        for s in pending:
            s.close()
    wait_for(lambda: d.cli("status").returncode == 0, "daemon did not answer again")
    d.stop()
