"""EPICS Channel Access PVs of the running daemon (a real subprocess), read and written by a
real CA client: pyepics, whose libca is EPICS base's own C client, in a process of its own
(on loopback with EPICS_CA_AUTO_ADDR_LIST=NO and a port of the test's). Units, precision,
alarm severities (near a rail, stale, fault), writes only when [epics] writable, each put
checked as `leveler tune` checks it and logged with the client's user@host."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from typing import Any

import pytest
from ca_server import ca_env, epics_daemon

from leveler.log.reader import read_log

pytest.importorskip("epics", reason="pyepics (the test extra) is not installed")

CLIENT = """
import json, sys, time
import epics
out = {}
for op in json.loads(sys.argv[1]):
    name = "LEV:" + op["pv"]
    if "put" in op:
        try:
            out[op["pv"] + "=put"] = epics.caput(name, op["put"], wait=True, timeout=5)
        except epics.ca.CASeverityException as exc:
            out[op["pv"] + "=put"] = str(exc)
        time.sleep(0.5)  # the readback follows at the server's update rate
        continue
    pv = epics.PV(name)
    wait = op.get("timeout", 5)  # 1 s for a PV that should not exist: absence is a timeout
    value = pv.get(timeout=wait, as_string=op.get("string", False))
    if not pv.connected:  # its units, severity... would each wait for it again
        out[op["pv"]] = {"connected": False}
        continue
    ctrl = pv.get_ctrlvars(timeout=wait)
    out[op["pv"]] = {"value": value, "units": pv.units, "precision": pv.precision,
                     "severity": pv.severity, "status": pv.status,
                     "write": pv.write_access,
                     "connected": pv.connected,
                     "limits": [ctrl.get(k) for k in ("lower_alarm_limit",
                                "lower_warning_limit", "upper_warning_limit",
                                "upper_alarm_limit")],
                     "display": [ctrl.get(k) for k in ("lower_disp_limit",
                                 "upper_disp_limit")]}
print(json.dumps(out))
"""


#: puts of the wrong type, straight onto the wire: caproto's own client does not convert
WRONG_TYPES = """
import json
from caproto import ChannelType
from caproto.sync.client import write
out = []
for name, data, dtype in (("LEV:KP", ["abc"], ChannelType.STRING),
                          ("LEV:SETPOINT", [1e-9, 2e-9, 3e-9], ChannelType.DOUBLE),
                          ("LEV:ENGAGE", ["yes"], ChannelType.STRING),
                          ("LEV:KI", [b"\\xff" * 40], ChannelType.STRING)):
    try:
        write(name, data, data_type=dtype, notify=True, timeout=5, repeater=False)
        out.append("ok")
    except Exception as exc:
        out.append(type(exc).__name__ + ": " + str(exc)[:200])
print(json.dumps(out))
"""


def ca(port: int, *ops: dict[str, Any]) -> dict[str, Any]:
    proc = subprocess.run([sys.executable, "-c", CLIENT, json.dumps(ops)],
                          env={**os.environ, **ca_env(port)}, capture_output=True, text=True,
                          timeout=90)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_read_only_pvs_carry_units_precision_and_no_alarm(start_daemon: Any) -> None:
    d, port = epics_daemon(start_daemon)
    got = ca(port, *({"pv": n} for n in ("READING", "TILT", "PIEZO", "P", "I", "D",
                                          "PERIOD_P99", "OVERRUNS")),
             {"pv": "STATE", "string": True}, {"pv": "KI", "timeout": 1},
             {"pv": "READING", "put": 1e-6}, {"pv": "STATE", "string": True})
    status = json.loads(d.cli("status", "--json").stdout)
    assert status["live"]["epics"] == {"serving": True, "prefix": "LEV:", "writable": False,
                                       "interfaces": ["127.0.0.1"]}
    for name, units in (("READING", "m"), ("TILT", "rad"), ("PIEZO", "V"), ("I", "V"),
                        ("PERIOD_P99", "s")):
        assert got[name]["units"] == units and got[name]["severity"] == 0, (name, got[name])
        assert got[name]["write"] is False
    assert got["READING"]["precision"] == 12
    assert abs(got["READING"]["value"]) < 1e-6  # levelled: nanometres
    assert 0 < got["PIEZO"]["value"] < 150
    assert 0.04 < got["PERIOD_P99"]["value"] < 0.1  # 20 Hz
    assert got["STATE"]["value"] == "engaged"
    assert got["KI"]["connected"] is False  # no writable PVs unless [epics] writable
    assert "Write access denied" in got["READING=put"]
    d.stop()
    events = read_log(next(d.logs.glob("*.mcap"))).events
    assert not [e for e in events if e["kind"] == "tune"]  # the put on READING did nothing


def test_writes_are_checked_as_tune_and_logged_with_the_client(start_daemon: Any) -> None:
    d, port = epics_daemon(start_daemon, writable=True)
    got = ca(port, {"pv": "KI"}, {"pv": "KI", "put": 2.1e7}, {"pv": "KI"},
             {"pv": "KI", "put": -5.0}, {"pv": "KI"}, {"pv": "ENGAGE", "put": 0},
             {"pv": "STATE", "string": True}, {"pv": "ENGAGE", "put": 1},
             {"pv": "STATE", "string": True}, {"pv": "SETPOINT"})
    assert got["KI"]["write"] is True and got["KI"]["units"] == "V/(m s)"
    status = json.loads(d.cli("status", "--json").stdout)
    assert status["controller"]["ki_v_per_m_s"] == 2.1e7  # the good put; the bad one refused
    assert status["state"] == "engaged"
    assert got["SETPOINT"]["units"] == "m"
    err = d.stop()
    assert "ki_v_per_m_s must be >= 0" in err  # the refusal, in the journal
    assert "Traceback" not in err
    events = read_log(next(d.logs.glob("*.mcap"))).events
    tunes = [e for e in events if e["kind"] == "tune"]
    assert len(tunes) == 1 and tunes[0]["reason"].startswith("tune by EPICS ")
    assert "@" in tunes[0]["reason"]  # user@host of the client
    moves = [e["reason"] for e in events if e["kind"] == "state"]
    assert any(r.startswith("stop by EPICS ") for r in moves)
    assert any(r.startswith("start by EPICS ") for r in moves)


def test_a_piezo_near_its_rail_is_minor(start_daemon: Any) -> None:
    d, port = epics_daemon(start_daemon, replace={
        "engage_on_start = true": "engage_on_start = false",
        "safe_v = 75.0": "safe_v = 148.0"})
    got = ca(port, {"pv": "PIEZO"}, {"pv": "STATE", "string": True})
    assert got["STATE"]["value"] == "idle"
    assert got["PIEZO"]["value"] == pytest.approx(148.0)
    assert got["PIEZO"]["severity"] == 1  # MINOR: within 5 % of 150 V
    assert got["PIEZO"]["limits"] == [0.0, 7.5, 142.5, 150.0]  # LOLO, LOW, HIGH, HIHI [V]
    assert got["PIEZO"]["display"] == [0.0, 150.0]  # what a Phoebus bar spans
    d.stop()


@pytest.mark.parametrize(("applied_v", "saturated", "limits_v", "severity", "status"), [
    (59.9, True, (0.0, 60.0), "MAJOR_ALARM", "HIHI"),  # capped at 60 V: the top, though low
    (90.0, True, (90.0, 150.0), "MAJOR_ALARM", "LOLO"),  # held up at 90 V: the bottom
    (150.0, False, (0.0, 150.0), "MAJOR_ALARM", "HIHI"),  # at the actuator's rail
    (0.0, False, (0.0, 150.0), "MAJOR_ALARM", "LOLO"),
    (145.0, False, (0.0, 150.0), "MINOR_ALARM", "HIGH"),  # within 5 % of 150 V
    (5.0, False, (0.0, 150.0), "MINOR_ALARM", "LOW"),
    (75.0, False, (0.0, 150.0), "NO_ALARM", "NO_ALARM"),
])
def test_the_piezo_alarm_names_the_side_it_is_pressed_against(
        applied_v: float, saturated: bool, limits_v: tuple[float, float], severity: str,
        status: str) -> None:
    """A saturated command is HIHI at the top of the controller's limits and LOLO at the
    bottom, whichever half of the actuator's range that is in."""
    from caproto import AlarmSeverity, AlarmStatus

    from leveler.live.epics_ioc import Ioc

    ioc = Ioc("LEV:", ["127.0.0.1"], False, (0.0, 150.0), 0.05, 2.0)
    got = ioc._piezo_alarm({"applied_v": applied_v, "saturated": saturated,
                            "limits_v": list(limits_v)})
    assert got == {"severity": AlarmSeverity[severity], "status": AlarmStatus[status]}


def test_stale_data_is_invalid_and_a_fault_is_major(start_daemon: Any) -> None:
    d, port = epics_daemon(start_daemon, sim="hang_at_s = 2.0\nhang_for_s = 6.0")
    time.sleep(1.5)  # the sensor hangs from t = 2 s: the loop stalls
    got = ca(port, {"pv": "READING"}, {"pv": "STATE", "string": True})
    assert got["READING"]["severity"] == 3, got  # INVALID
    d.stop()
    d, port = epics_daemon(start_daemon, sim="fail_at_s = 1.0", replace={
        "engage_on_start = true": "engage_on_start = true\nreconnect_min_s = 1000.0"})
    deadline = time.monotonic() + 20
    while json.loads(d.cli("status", "--json").stdout)["state"] != "fault":
        assert time.monotonic() < deadline, "no fault"
        time.sleep(0.1)
    got = ca(port, {"pv": "STATE", "string": True}, {"pv": "FAULT", "string": True})
    assert got["STATE"]["value"] == "fault" and got["STATE"]["severity"] == 2  # MAJOR
    reason = json.loads(d.cli("status", "--json").stdout)["fault_reason"]
    assert len(reason) > 40 and got["FAULT"]["value"] == reason  # whole, not a DBR_STRING's 40
    d.stop()


def test_hostile_puts_are_refused_and_reach_nothing(start_daemon: Any) -> None:
    """Out-of-range, unstable and non-finite values, a switch put 7: each refused with its
    reason, the loop's gains and state as they were, no tune event in the log. Wrong types
    on the wire too (pyepics refuses a string to a numeric PV before sending it, so
    caproto's client sends them raw): text to a gain, an array to the setpoint, a string
    to ENGAGE."""
    d, port = epics_daemon(start_daemon, writable=True)
    before = json.loads(d.cli("status", "--json").stdout)
    got = ca(port, {"pv": "KP", "put": 1e30},
             {"pv": "KD", "put": -1.0}, {"pv": "SETPOINT", "put": 1.0},
             {"pv": "ENGAGE", "put": 7}, {"pv": "RESET", "put": -3},
             {"pv": "KI", "put": float("nan")}, {"pv": "STATE", "string": True})
    raw = subprocess.run([sys.executable, "-c", WRONG_TYPES], capture_output=True,
                         text=True, timeout=60, env={**os.environ, **ca_env(port)})
    assert raw.returncode == 0, raw.stderr
    answers = json.loads(raw.stdout.strip().splitlines()[-1])
    assert len(answers) == 4 and all("ECA_PUTFAIL" in a for a in answers), answers
    after = json.loads(d.cli("status", "--json").stdout)
    assert after["controller"] == before["controller"]
    assert after["state"] == "engaged" == got["STATE"]["value"]
    err = d.stop()
    for reason in ("kd_v_s_per_m must be >= 0", "ENGAGE takes 0 or 1", "RESET takes 0 or 1"):
        assert reason in err, reason
    assert "Traceback" not in err
    events = read_log(next(d.logs.glob("*.mcap"))).events
    assert not [e for e in events if e["kind"] in ("tune", "reload", "procedure")]
    assert [e["detail"]["new"] for e in events if e["kind"] == "state"] == ["engaged", "idle"]


def server_process(daemon_pid: int) -> int:
    """The pid of the daemon's EPICS server process (a child of its relay thread)."""
    from pathlib import Path

    for task in Path(f"/proc/{daemon_pid}/task").iterdir():
        for pid in (task / "children").read_text().split():
            if b"leveler.live.epics_ioc" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return int(pid)
    raise AssertionError("no EPICS server process under the daemon")


def gone(pid: int, within_s: float) -> bool:
    import os

    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


def test_the_server_process_dying_leaves_the_loop_and_an_error_line(start_daemon: Any) -> None:
    """The PVs run in a process of their own: killed, the loop levels on, the journal says
    so once; the daemon killed, the server ends too rather than holding the port."""
    import os
    import signal

    d, _ = epics_daemon(start_daemon)
    os.kill(server_process(d.proc.pid), signal.SIGKILL)
    time.sleep(1.0)
    status = json.loads(d.cli("status", "--json").stdout)
    assert status["state"] == "engaged" and not status["loop"]["stalled"]
    err = d.stop()
    assert err.count("EPICS server stopped") == 1, err
    d, _ = epics_daemon(start_daemon)
    server = server_process(d.proc.pid)
    d.proc.kill()
    d.proc.communicate(timeout=10)
    assert gone(server, within_s=10), "the EPICS server outlived the daemon"


def test_an_interface_it_cannot_bind_is_a_clear_config_error(start_daemon: Any) -> None:
    """An address not on this machine: the daemon says which and exits 2, the log finished."""
    d = start_daemon(wait_socket=False, edit=lambda text: text + (
        '\n[epics]\nserve = true\ninterfaces = ["10.255.255.1"]\n'))
    _, err = d.proc.communicate(timeout=60)
    assert d.proc.returncode == 2, err
    assert "[epics] cannot serve on 10.255.255.1" in err and "Traceback" not in err
    (log,) = d.logs.glob("*.mcap")
    assert read_log(log).complete


def test_a_frozen_daemon_makes_its_readings_invalid(start_daemon: Any) -> None:
    """SIGSTOP: the daemon cannot say it stalled, so the server notices that no status came
    (2 s here) and marks the readings INVALID; SIGCONT, and they are good again."""
    import signal

    d, port = epics_daemon(start_daemon)
    d.proc.send_signal(signal.SIGSTOP)
    try:
        time.sleep(3.0)
        frozen = ca(port, {"pv": "READING"}, {"pv": "PIEZO"}, {"pv": "STATE", "string": True})
    finally:
        d.proc.send_signal(signal.SIGCONT)
    time.sleep(1.5)
    thawed = ca(port, {"pv": "READING"}, {"pv": "STATE", "string": True})
    err = d.stop()
    assert all(frozen[k]["severity"] == 3 for k in ("READING", "PIEZO", "STATE")), frozen
    assert frozen["STATE"]["value"] == "engaged"  # the last value, marked as stale
    assert thawed["READING"]["severity"] == 0 and thawed["STATE"]["severity"] == 0, thawed
    assert err.count("no status from the daemon") == 1
