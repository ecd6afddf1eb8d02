"""The daemon driven only through its CLI and control socket, as a lab would."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import as_user

from leveler.log.reader import read_log
from leveler.settings import load_config


def raw(sock_path: Path, payload: bytes, timeout: float = 5.0) -> dict:  # type: ignore[type-arg]
    """Send raw bytes on a fresh connection; return the first reply line. A connection the
    daemon refuses is answered and closed at once: the send may fail (EPIPE), the answer is
    there to read all the same."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(str(sock_path))
        try:
            s.sendall(payload)
        except BrokenPipeError:
            pass
        return json.loads(s.makefile("rb").readline())


def status(d) -> dict:  # type: ignore[no-untyped-def,type-arg]
    proc = d.cli("status", "--json")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_status_start_stop_through_the_cli(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(engage=False)
    st = status(d)
    assert st["state"] == "idle" and st["pid"] == d.proc.pid
    human = d.cli("status")
    assert "state       idle" in human.stdout and "period p50/p99/max" in human.stdout
    assert d.cli("start").stdout.strip() == "state: engaged"
    assert status(d)["state"] == "engaged"
    assert d.cli("stop").stdout.strip() == "state: idle"
    time.sleep(0.3)
    held = status(d)["sample"]["applied_v"]
    time.sleep(0.3)
    assert status(d)["sample"]["applied_v"] == held  # idle holds the actuator
    assert d.stop() is not None and d.proc.returncode == 0
    (log,) = d.logs.glob("*.mcap")
    events = [(e["kind"], e["reason"]) for e in read_log(log).events]
    import pwd

    me = f"uid {os.getuid()} ({pwd.getpwuid(os.getuid()).pw_name})"  # the peer, named
    assert ("state", f"start by {me}") in events, events
    assert ("state", f"stop by {me}") in events, events


def dotted_controller(text: str) -> str:
    """The same config with [controller] written as dotted keys at the top of the file."""
    head, _, rest = text.partition("[controller]")
    body, _, tail = rest.partition("\n[")
    keys = [f"controller.{line}" for line in body.splitlines()[1:]
            if line and not line.startswith("#")]
    return "\n".join(keys) + "\n" + head + "[" + tail


def test_tune_persist_keeps_a_dotted_key_config_valid_and_dotted(start_daemon) -> None:  # type: ignore[no-untyped-def]
    """Issue 19: a valid config with `controller.ki_v_per_m_s = ...` once came out of
    `tune --persist` with a second [controller] table, failed validation, and nothing was
    saved. Through the real daemon: the value is saved, the form kept, and it reloads."""
    d = start_daemon(edit=dotted_controller)
    assert "[controller]" not in d.config.read_text()
    d.wait_status_lines(1)
    persisted = d.cli("tune", "--ki", "2.0e7", "--persist")
    assert persisted.returncode == 0 and "written to the config file" in persisted.stdout
    text = d.config.read_text()
    assert "[controller]" not in text
    assert text.count("controller.ki_v_per_m_s") == 1
    assert "controller.kd_v_s_per_m = 1.9e6" in text  # the untouched keys as they were
    cfg, _ = load_config(d.config)
    assert cfg.controller.ki_v_per_m_s == 2.0e7
    reload = d.cli("reload")
    assert reload.returncode == 0, reload.stderr
    assert status(d)["controller"]["ki_v_per_m_s"] == 2.0e7
    d.stop()


def test_tune_is_bumpless_validated_and_persisted(start_daemon) -> None:  # type: ignore[no-untyped-def]
    # The slow integral-only loop: the default's unfiltered D moves the command by ~0.6 V
    # rms per cycle at 50 Hz on sensor noise alone, which would drown the step looked for.
    d = start_daemon(replace={"ki_v_per_m_s = 2.2e7": "ki_v_per_m_s = 7.0e5",
                              "kd_v_s_per_m = 1.9e6": "kd_v_s_per_m = 0.0"})
    d.wait_status_lines(1)
    assert d.cli("tune", "--slew", "1000").returncode == 0
    # a setpoint step leaves a large error for the P term to act on
    assert d.cli("tune", "--setpoint", "5e-8").returncode == 0
    time.sleep(0.5)
    proc = d.cli("tune", "--kp", "5e5")
    assert proc.returncode == 0, proc.stderr
    assert "kp_v_per_m = 500000" in proc.stdout
    bad = d.cli("tune", "--min-v", "200")
    assert bad.returncode == 2 and "output_min_v" in bad.stderr
    beyond = d.cli("tune", "--max-v", "1e6")  # the piezo's range is 0..150 V
    assert beyond.returncode == 2 and "150" in beyond.stderr, beyond.stderr
    neg = d.cli("tune", "--ki", "-5")
    assert neg.returncode == 2 and "ki_v_per_m_s must be >= 0" in neg.stderr
    assert status(d)["controller"]["kp_v_per_m"] == 5e5
    persisted = d.cli("tune", "--ki", "6e5", "--persist")
    assert persisted.returncode == 0 and "written to the config file" in persisted.stdout
    cfg, text = load_config(d.config)
    assert cfg.controller.ki_v_per_m_s == 6e5
    assert "[controller]                # error = setpoint_m" in text  # comments survive
    time.sleep(0.3)
    d.stop()
    (log,) = d.logs.glob("*.mcap")
    data = read_log(log)
    tune = next(e for e in data.events if e["kind"] == "tune" and "kp_v_per_m" in e["detail"])
    i = int(np.searchsorted(data.samples["t_s"], tune["t_s"]))
    cmd = data.samples["command_v"]
    jump = abs(cmd[i + 1] - cmd[i - 1])
    naive = abs(5e5 * data.samples["error_m"][i])  # what a non-bumpless PID would add
    assert naive > 5e-3, "precondition: the gain change had an error to act on"
    assert jump < 0.1 * naive


def test_watch_streams_samples(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon()
    proc = d.cli("watch", "--count", "4", "--rate", "20")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 4
    ts = [float(ln.split("t=")[1].split(" s")[0]) for ln in lines]
    assert ts == sorted(ts) and len(set(ts)) == 4
    assert all("piezo=" in ln and "engaged" in ln for ln in lines)


def test_rotate_starts_a_new_complete_file(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon()
    d.wait_status_lines(1)
    proc = d.cli("rotate")
    assert proc.returncode == 0, proc.stderr
    new = Path(proc.stdout.split("logging to ")[1].strip())
    d.wait_status_lines(1)
    d.stop()
    files = sorted(d.logs.glob("*.mcap"))
    assert len(files) == 2 and files[1] == new
    first, second = read_log(files[0]), read_log(files[1])
    assert first.complete and second.complete
    assert second.samples["seq"][0] == first.samples["seq"][-1] + 1


def test_fault_needs_reset_before_start(start_daemon) -> None:  # type: ignore[no-untyped-def]
    no_auto = "engage_on_start = true\nreconnect_min_s = 1000.0"
    d = start_daemon(sim="fail_at_s = 1.0", replace={"engage_on_start = true": no_auto})
    deadline = time.monotonic() + 20
    while status(d)["state"] != "fault":
        assert time.monotonic() < deadline, "no fault"
        time.sleep(0.1)
    st = status(d)
    assert "injected sensor fault" in st["fault_reason"]
    assert st["sample"]["applied_v"] == pytest.approx(75.0, abs=1e-9)  # safe voltage
    refused = d.cli("start")
    assert refused.returncode == 2 and "leveler reset" in refused.stderr
    assert d.cli("reset").stdout.strip() == "state: idle"
    assert d.cli("start").stdout.strip() == "state: engaged"
    d.stop()
    (log,) = d.logs.glob("*.mcap")
    states = [e["detail"].get("new") for e in read_log(log).events if e["kind"] == "state"]
    assert states == ["engaged", "fault", "idle", "engaged", "idle"]


def test_fault_recovers_by_itself_when_the_device_answers_again(start_daemon) -> None:  # type: ignore[no-untyped-def]
    fast = "engage_on_start = true\nreconnect_min_s = 0.5"
    d = start_daemon(sim="fail_at_s = 1.0", replace={"engage_on_start = true": fast})
    deadline = time.monotonic() + 20
    # The fault lasts about reconnect_min_s: a poll can miss it on a loaded machine, the
    # fault count (kept since start) cannot; the log below gives the whole sequence.
    while not ((st := status(d))["faults"] == 1 and st["state"] == "engaged"):
        assert time.monotonic() < deadline, "no fault and recovery"
        time.sleep(0.05)
    assert "injected sensor fault" in st["last_fault"] and st["fault_reason"] == ""
    shown = d.cli("status").stdout
    assert "1 fault(s) since start; last: sensor read failed: injected" in shown, shown
    d.stop()
    (log,) = d.logs.glob("*.mcap")
    events = read_log(log).events
    states = [e["detail"].get("new") for e in events if e["kind"] == "state"]
    assert states == ["engaged", "fault", "idle", "engaged", "idle"]
    assert [e["reason"] for e in events if e["kind"] == "reconnect"] == ["devices answer again"]


def test_bad_requests_get_errors_and_the_daemon_carries_on(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon()
    cases = {
        b'{"v":1,"verb":"fly"}\n': "unknown verb",
        b"{broken\n": "not valid JSON",
        b'{"v":1,"verb":"tune","kp_v_per_m":"abc"}\n': "must be a number",
        b'{"v":1,"verb":"tune","kp_v_per_m":NaN}\n': "not valid JSON",
        b'{"v":9,"verb":"status"}\n': "version 9 not supported",
        b"x" * 70000 + b"\n": "longer than",
    }
    for payload, needle in cases.items():
        reply = raw(d.socket, payload)
        assert reply["ok"] is False and needle in reply["error"], (payload[:40], reply)
    assert status(d)["state"] == "engaged"
    assert d.proc.poll() is None


def test_sighup_with_a_broken_config_keeps_the_old_one(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon()
    good = d.config.read_text()
    ki = load_config(d.config)[0].controller.ki_v_per_m_s
    line = re.search(r"(?m)^ki_v_per_m_s = .*$", good)
    assert line is not None
    d.config.write_text(good.replace(line[0], "ki_v_per_m_s = 'lots'"))
    d.proc.send_signal(signal.SIGHUP)
    time.sleep(0.5)
    assert d.proc.poll() is None
    assert status(d)["controller"]["ki_v_per_m_s"] == ki
    d.config.write_text("")  # an editor that crashed, a stray `>`: not the defaults
    d.proc.send_signal(signal.SIGHUP)
    time.sleep(0.5)
    assert status(d)["controller"]["ki_v_per_m_s"] == ki
    d.config.write_text(good.replace(line[0], "ki_v_per_m_s = 5.0e5"))
    d.proc.send_signal(signal.SIGHUP)
    deadline = time.monotonic() + 10
    while status(d)["controller"]["ki_v_per_m_s"] != 5e5:
        assert time.monotonic() < deadline, "valid reload not applied"
        time.sleep(0.1)
    err = d.stop()
    assert "reload rejected" in err and "ki_v_per_m_s" in err
    assert f"reload rejected, keeping the running config: {d.config}: is empty" in err
    (log,) = d.logs.glob("*.mcap")
    reloads = [e["reason"] for e in read_log(log).events if e["kind"] == "reload"]
    assert reloads[0].startswith("rejected:") and reloads[1].startswith("rejected:")
    assert "is empty" in reloads[1] and reloads[2] == "applied"


def test_notify_ready_then_watchdog_which_stops_when_the_loop_stalls(
        start_daemon, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    addr = f"leveler-notify-{os.getpid()}"
    sock.bind("\0" + addr)
    sock.settimeout(10)
    try:
        d = start_daemon(sim="hang_at_s = 4.0\nhang_for_s = 3.0",
                         env={"NOTIFY_SOCKET": "@" + addr, "WATCHDOG_USEC": "400000"})
        msgs: list[tuple[float, bytes]] = []
        deadline = time.monotonic() + 12
        while time.monotonic() < deadline:
            try:
                msgs.append((time.monotonic(), sock.recv(4096)))
            except TimeoutError:
                break
        d.stop()
    finally:
        sock.close()
    kinds = [m.split(b"\n")[0] for _, m in msgs]
    assert kinds[0] == b"READY=1" or b"READY=1" in kinds[:3]
    assert b"STATUS=" in msgs[kinds.index(b"READY=1")][1]
    wd = [t for t, m in msgs if m == b"WATCHDOG=1"]
    gaps = np.diff(wd)
    assert len(wd) > 10
    assert np.median(gaps) == pytest.approx(0.2, abs=0.06)  # WATCHDOG_USEC / 2
    assert gaps.max() > 2.5  # silent while the loop hung for 3 s
    assert any(m.startswith(b"STATUS=t=") for _, m in msgs)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to act as another user (nobody)")
def test_a_client_without_access_is_refused(start_daemon) -> None:  # type: ignore[no-untyped-def]
    from leveler.daemon.client import Client

    d = start_daemon()
    nobody = 65534

    def connect_with_cli_client() -> str:
        Client(d.socket)
        return "connected"

    def talk_raw() -> str:
        return str(raw(d.socket, b'{"verb": "status"}\n'))

    # file mode 0660: nobody cannot even connect, and the client says why
    assert (d.socket.stat().st_mode & 0o777) == 0o660
    assert "access denied" in as_user(nobody, connect_with_cli_client)
    # loosen the mode by accident: the peer-credential check still refuses
    os.chmod(d.socket.parent, 0o755)
    os.chmod(d.socket, 0o666)
    reply = as_user(nobody, talk_raw)
    assert "access denied: uid 65534" in reply
    d.stop()
    (log,) = d.logs.glob("*.mcap")
    refused = [e for e in read_log(log).events if e["kind"] == "access"]
    assert refused and refused[0]["detail"]["uid"] == nobody


def test_no_daemon_is_a_clear_message(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "status", "--socket",
                           str(tmp_path / "none.sock")], capture_output=True, text=True,
                          timeout=30)
    assert proc.returncode == 2
    assert "no leveler daemon is running" in proc.stderr and "Traceback" not in proc.stderr


def test_suggested_gains_can_be_applied(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon()
    proc = d.cli("tune", "--suggest", "--apply")
    assert proc.returncode == 0, proc.stderr
    assert f"plant model from {d.config}" in proc.stdout  # asked the daemon for its config
    assert "gain margin" in proc.stdout and "applied: kp_v_per_m = 0" in proc.stdout
    ki = float(proc.stdout.split("applied:")[1].split("ki_v_per_m_s = ")[1].split(",")[0])
    assert ki > 7e5  # more low-frequency gain than the integral-only tuning it replaces
    assert status(d)["controller"]["ki_v_per_m_s"] == ki


def test_a_second_daemon_on_the_same_socket_is_refused(start_daemon) -> None:  # type: ignore[no-untyped-def]
    first = start_daemon()
    logs_before = sorted(first.logs.glob("*.mcap*"))
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "run", "--config",
                           str(first.config), "--duration", "5s"], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2
    assert "another leveler daemon is listening" in proc.stderr
    assert "Traceback" not in proc.stderr
    # Refused before it opened anything: no log of its own (and no device touched: the
    # fresh-eyes run saw a refused daemon write safe_v to the first one's amplifier).
    assert sorted(first.logs.glob("*.mcap*")) == logs_before
    assert status(first)["state"] == "engaged"  # the first one carries on


def test_status_text_counts_driver_errors(start_daemon) -> None:  # type: ignore[no-untyped-def]
    """reliability.md and hardware.md say driver errors are counted "in `status`": in the
    text a person reads, not only in --json."""
    d = start_daemon(sim='[[sim.faults]]\nkind = "timeout"\nat_s = 0.5\n'
                         '[[sim.faults]]\nkind = "write_fail"\nat_s = 1.0\n')
    deadline = time.monotonic() + 20
    while sum(status(d)["driver_errors"].values()) < 2:
        assert time.monotonic() < deadline, "the injected errors never counted"
        time.sleep(0.1)
    text = d.cli("status")
    assert text.returncode == 0, text.stderr
    assert "errors      2 driver errors since start (sensor 1, actuator 1)" in text.stdout
    assert "state       engaged" in text.stdout  # one error each: held, not a fault


def test_tune_refuses_nan_and_a_setpoint_in_metres_and_takes_an_infinite_slew(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon()
    d.wait_status_lines(1)
    nan = d.cli("tune", "--kp", "nan")
    assert nan.returncode == 2 and nan.stderr == (
        "leveler tune: error: --kp: nan is not a finite number\n"), nan.stderr
    metre = d.cli("tune", "--setpoint", "1")  # 1 m where 1e-6 (1 um) was meant
    assert metre.returncode == 2
    assert "setpoint_m 1 m is not a plausible sensor reading" in metre.stderr, metre.stderr
    assert status(d)["controller"]["setpoint_m"] == 0.0
    assert d.cli("tune", "--slew=-inf").returncode == 2
    # docs/configuration.md: slew_v_per_s = inf is allowed (no limit); so it is live
    unlimited = d.cli("tune", "--slew", "inf", "--persist")
    assert unlimited.returncode == 0, unlimited.stderr
    assert unlimited.stdout == "applied: slew_v_per_s = inf; written to the config file\n"
    assert status(d)["controller"]["slew_v_per_s"] is None  # JSON's null for infinity
    assert "slew none V/s" in d.cli("status").stdout
    cfg, _ = load_config(d.config)
    assert cfg.controller.slew_v_per_s == float("inf")
    assert d.cli("tune", "--slew", "10").returncode == 0
    assert status(d)["controller"]["slew_v_per_s"] == 10.0
    d.stop()
    (log,) = d.logs.glob("*.mcap")
    tunes = [e["detail"] for e in read_log(log).events if e["kind"] == "tune"]
    assert [list(t) for t in tunes] == [["slew_v_per_s"], ["slew_v_per_s"]]


def test_every_line_gets_one_answer_and_a_repeated_verb_does_not_act(
        start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon()
    for blank in (b"\n", b"\r\n"):
        reply = raw(d.socket, blank, timeout=3.0)
        assert reply["ok"] is False and "empty request" in reply["error"], reply
    # pipelined: every line in order gets its answer, blank ones included
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(5.0)
        s.connect(str(d.socket))
        s.sendall(b'{"v":1,"verb":"status"}\n\n{"v":1,"verb":"status"}\n')
        reader = s.makefile("rb")
        replies = [json.loads(reader.readline()) for _ in range(3)]
    assert [r["ok"] for r in replies] == [True, False, True]
    reply = raw(d.socket, b'{"v":1,"verb":"start","verb":"stop"}\n')
    assert reply == {"v": 1, "ok": False,
                     "error": "key 'verb' given twice; which one was meant is not guessed"}
    assert status(d)["state"] == "engaged"  # the last verb did not act


def test_cli_output_into_a_closed_pipe_ends_quietly(start_daemon) -> None:  # type: ignore[no-untyped-def]
    """`leveler status | head -3`: the reader may be gone before we write; exit like a tool
    killed by SIGPIPE (141), without a traceback."""
    d = start_daemon()
    for args in (["status"], ["status", "--json"], ["watch", "--count", "100", "--rate", "50"],
                 ["--help"]):
        r, w = os.pipe()
        os.close(r)
        cmd = [sys.executable, "-m", "leveler.cli", *args]
        if args != ["--help"]:
            cmd += ["--socket", str(d.socket)]
        try:
            proc = subprocess.run(cmd, stdout=w, stderr=subprocess.PIPE, text=True, timeout=60)
        finally:
            os.close(w)
        # argparse swallows the error of printing help itself (and exits 0)
        assert proc.returncode in ((0, 141) if args == ["--help"] else (141,)), (
            args, proc.returncode, proc.stderr)
        assert proc.stderr == "", (args, proc.stderr)


def test_a_full_daemon_tells_the_cli_to_try_later(tmp_path: Path) -> None:
    """Over max_clients the daemon answers "too many clients; try later" and closes; the
    CLI must show that, not the EPIPE of its own send."""
    from conftest import daemon_config

    short = Path(tempfile.mkdtemp(prefix="lvmc", dir="/tmp"))  # AF_UNIX paths are short
    sock = short / "c.sock"
    config = daemon_config(tmp_path, sock)
    with config.open("a") as fh:  # [control] is the config's last table
        fh.write("max_clients = 1\n")
    proc = subprocess.Popen([sys.executable, "-m", "leveler.cli", "run", "--config",
                             str(config)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 30
        while not sock.exists():
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "daemon socket never appeared"
            time.sleep(0.05)
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as held:
            held.connect(str(sock))  # takes the one slot (idle_timeout_s is 60 s)
            time.sleep(0.5)
            for _ in range(3):
                cli = subprocess.run([sys.executable, "-m", "leveler.cli", "status", "--socket",
                                      str(sock)], capture_output=True, text=True, timeout=30)
                assert cli.returncode == 2
                assert cli.stderr == "leveler status: error: too many clients; try later\n", \
                    cli.stderr
        deadline = time.monotonic() + 10  # the slot is free again once the client left
        while (cli := subprocess.run([sys.executable, "-m", "leveler.cli", "status", "--socket",
                                      str(sock)], capture_output=True, text=True,
                                     timeout=30)).returncode:
            assert time.monotonic() < deadline, cli.stderr
        assert "state       engaged" in cli.stdout
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
        shutil.rmtree(short, ignore_errors=True)


def test_status_text_says_what_a_null_means() -> None:
    """JSON carries NaN and infinity as null: a failed write, an unlimited slew, no log file
    (the disk is full) must read as such, not as `None` or a TypeError."""
    from leveler.cli.status import format_status

    st = {"version": "0", "pid": 1, "uptime_s": 60.0, "config_path": "c.toml",
          "state": "engaged", "fault_reason": "", "driver_errors": {"sensor": 0, "actuator": 1},
          "sample": {"sensor_m": None, "applied_v": None, "command_v": 74.5,
                     "saturated": False},
          "tilt_rad": None,
          "controller": {"kp_v_per_m": 0.0, "ki_v_per_m_s": 7e5, "kd_v_s_per_m": 0.0,
                         "setpoint_m": 0.0, "output_min_v": 0.0, "output_max_v": 150.0,
                         "slew_v_per_s": None},
          "loop": {"rate_hz": 10.0, "cycles": 600, "period_p50_s": 0.1, "period_p99_s": 0.1,
                   "period_max_s": 0.1, "overruns": 0},
          "log": {"path": None, "samples_written": 10, "dropped": 5, "healthy": False,
                  "error": "[Errno 28] No space left on device"}}
    text = format_status(st)
    assert "None" not in text
    assert "errors      1 driver errors since start (sensor 0, actuator 1)" in text
    assert "piezo       last write failed (voltage held), 74.500 V commanded" in text
    assert "slew none V/s" in text
    assert ("log         no file open (logging is down; retrying), 10 samples, FAULT: "
            "[Errno 28] No space left on device, 5 dropped") in text


def test_status_tells_a_stalled_loop_from_a_healthy_one(start_daemon) -> None:  # type: ignore[no-untyped-def]
    """Outside systemd no watchdog notices a loop hung in a device call; `status` must."""
    d = start_daemon(rate_hz=10.0, sim="hang_at_s = 3.0\nhang_for_s = 4.0")
    first = json.loads(d.cli("status", "--json").stdout)["loop"]
    assert not first["stalled"] and first["last_cycle_age_s"] < 1.0
    deadline = time.monotonic() + 10.0
    while not (st := json.loads(d.cli("status", "--json").stdout))["loop"]["stalled"]:
        assert time.monotonic() < deadline, "never reported stalled"
        time.sleep(0.2)
    assert st["loop"]["last_cycle_age_s"] > 1.0
    assert "LOOP STALLED: no cycle for" in d.cli("status").stdout
    deadline = time.monotonic() + 10.0  # the device answers again: healthy again
    while json.loads(d.cli("status", "--json").stdout)["loop"]["stalled"]:
        assert time.monotonic() < deadline, "still stalled after the hang ended"
        time.sleep(0.2)
    assert "STALLED" not in d.cli("status").stdout
    d.stop()
