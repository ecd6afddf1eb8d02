"""The real unit under the machine's own systemd, booted in a container (`make test-systemd`).

`systemd-nspawn -D / --volatile=yes` boots this machine's systemd on a throw-away root (the
host's /usr, a fresh /etc in tmpfs). The installer then runs inside it for real (group, user,
config, unit, daemon-reload), and the tests check what only a running systemd can show:
READY and STATUS from the daemon, the sandbox as the process sees it, the control socket
open to group leveler only, reload, a clean stop, and a stalled loop killed by the watchdog
and restarted. Every wait is bounded; the container is powered off (or killed) at the end.

The service's venv is /opt/leveler in the container, made from the container's own
/usr/bin/python3 and chained (.pth) to this checkout's venv: the unit stays exactly the
canonical one, ProtectHome=yes included, even where this venv's interpreter lives in /root.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import sysconfig
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

pytestmark = pytest.mark.systemd

REPO = Path(__file__).resolve().parents[2]
SITE_PACKAGES = Path(sysconfig.get_path("purelib"))
# The checkout may live where the unit's sandbox hides it (PrivateTmp=, ProtectHome=): a
# clone under /tmp, say. The test's drop-ins bind it back in, read-only, for the service only.
CHECKOUT_BINDS = f"BindReadOnlyPaths={REPO} {SITE_PACKAGES}\n"
BOOT_TIMEOUT_S = 90.0
HANG_AT_S = 20.0  # loop time at which the simulated sensor stops answering...
HANG_FOR_S = 60.0  # ...for this long: far past the test's WatchdogSec=3s
CAP_IPC_LOCK, CAP_SYS_NICE = 14, 23
SCHED_FIFO = 1

# What the service sees of its sandbox, as one JSON line in the journal. Errors are errno names.
PROBE = r'''
import ctypes, ctypes.util, errno, json, os, socket, threading
out = {}
def check(name, fn):
    try:
        out[name] = fn() or "ok"
    except OSError as exc:
        out[name] = errno.errorcode.get(exc.errno, str(exc))
    except Exception as exc:
        out[name] = f"{type(exc).__name__}: {exc}"
def imports():
    import numpy, scipy.linalg, serial, pymodbus, mcap, zstandard, orjson, lz4.frame
    import leveler.daemon.service
    scipy.linalg.expm(numpy.eye(3))
def callback():  # libffi closures: what MemoryDenyWriteExecute= could break
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    cmp = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int))
    a = (ctypes.c_int * 3)(3, 1, 2)
    libc.qsort(a, 3, ctypes.sizeof(ctypes.c_int), cmp(lambda x, y: x[0] - y[0]))
    return None if list(a) == [1, 2, 3] else "unsorted"
def mlockall():
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if libc.mlockall(3) != 0:  # MCL_CURRENT | MCL_FUTURE
        raise OSError(ctypes.get_errno(), "mlockall")
def thread_sched():
    seen = []
    def run():
        seen.append(os.sched_getscheduler(0))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        seen.append(os.sched_getscheduler(0))
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
        seen.append(os.sched_getparam(0).sched_priority)
    t = threading.Thread(target=run)
    t.start()
    t.join()
    return seen
def write(path):
    with open(path, "w") as fh:
        fh.write("x")
    os.unlink(path)
check("imports", imports)
check("ctypes callback", callback)
check("mlockall", mlockall)
check("thread sched", thread_sched)
for path in ("/etc/probe", "/usr/probe", "/home/probe", "/etc/leveler/probe",
             "/var/lib/leveler/logs/probe", "/run/leveler/probe", "/tmp/probe"):
    check("write " + path, lambda path=path: write(path))
check("list /root", lambda: os.listdir("/root") and None)
for path in ("/home", "/root"):  # ProtectHome=yes: inaccessible, not merely not ours
    check("mode " + path, lambda path=path: f"{os.stat(path).st_mode & 0o777:03o}")
check("inet socket", lambda: socket.socket(socket.AF_INET, socket.SOCK_DGRAM).close())
check("unix socket", lambda: socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM).close())
check("chown", lambda: os.chown("/var/lib/leveler/logs", -1, os.getegid()))
check("see pid 1", lambda: os.stat("/proc/1") and None)
check("read /proc/cpuinfo", lambda: open("/proc/cpuinfo").close())
print("PROBE " + json.dumps(out), flush=True)
'''

PROBE_EXPECTED: dict[str, object] = {
    "imports": "ok", "ctypes callback": "ok", "mlockall": "ok",
    "thread sched": [SCHED_FIFO, os.SCHED_OTHER, 60],  # inherits FIFO; may drop or raise it
    "write /etc/probe": "EROFS", "write /usr/probe": "EROFS", "write /home/probe": "EACCES",
    "write /etc/leveler/probe": "ok", "write /var/lib/leveler/logs/probe": "ok",
    "write /run/leveler/probe": "ok", "write /tmp/probe": "ok",
    "list /root": "EACCES", "mode /home": "000", "mode /root": "000",
    "inet socket": "EAFNOSUPPORT", "unix socket": "ok",
    "chown": "EPERM", "see pid 1": "ENOENT", "read /proc/cpuinfo": "ENOENT",
}


def why_not() -> str:
    """Why the container cannot run here, or '' if it can."""
    if os.geteuid() != 0:
        return "needs root to boot a container: sudo make test-systemd"
    if shutil.which("systemd-nspawn") is None or shutil.which("nsenter") is None:
        return "systemd-nspawn missing: apt-get install systemd-container (make systemd-deps)"
    if not Path("/lib/systemd/systemd").exists():
        return "no systemd on this machine to boot"
    probe = "import sys; print(f'{sys.version_info[0]}.{sys.version_info[1]}')"
    ours = f"{sys.version_info[0]}.{sys.version_info[1]}"
    usr = subprocess.run(["/usr/bin/python3", "-c", probe], capture_output=True, text=True,
                         check=False) if Path("/usr/bin/python3").exists() else None
    if usr is None or usr.stdout.strip() != ours:
        return f"/usr/bin/python3 is not Python {ours}: it cannot load this venv's packages"
    return ""


def host_caps() -> int:
    """This process's capability bounding set: the most the container can hand on."""
    return int(Path("/proc/self/status").read_text().split("CapBnd:")[1].split()[0], 16)


def wait_for(what: str, cond: Callable[[], object], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out after {timeout_s:g} s waiting for {what}"
        time.sleep(0.2)


class Container:
    """A booted container, driven with nsenter (--register=no: no machinectl)."""

    def __init__(self, leader: int) -> None:
        self.leader = leader

    def run(self, *cmd: str, input: str | None = None, timeout: float = 30.0,
            check: bool = True) -> str:
        res = subprocess.run(["nsenter", "-t", str(self.leader), "-a", "--", *cmd],
                             input=input, capture_output=True, text=True, timeout=timeout)
        assert not check or res.returncode == 0, f"{cmd}: {res.stdout}{res.stderr}"
        return res.stdout

    def write(self, path: str, text: str, mode: int = 0o644) -> None:
        self.run("sh", "-c", f'mkdir -p "$(dirname "$1")" && cat > "$1" && chmod {mode:o} "$1"',
                 "sh", path, input=text)

    def show(self, unit: str = "leveler") -> dict[str, str]:
        out = self.run("systemctl", "show", unit)
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def journal(self, unit: str = "leveler") -> str:
        return self.run("journalctl", "-u", unit, "-o", "cat", "--no-pager")

    def proc_status(self, pid: str) -> dict[str, str]:
        text = self.run("cat", f"/proc/{pid}/status")
        return {k: v.strip() for k, v in (ln.split(":", 1) for ln in text.splitlines())}

    def sched(self, pid: str) -> tuple[int, int]:
        """(policy, rt_priority) from /proc/PID/stat, fields 41 and 40."""
        fields = self.run("cat", f"/proc/{pid}/stat").rsplit(")", 1)[1].split()
        return int(fields[38]), int(fields[37])


def leader_of(nspawn: subprocess.Popen[bytes]) -> int | None:
    """The container's init: nspawn's child once it is systemd in a new pid namespace."""
    ours = os.readlink("/proc/self/ns/pid")
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                if (ppid == nspawn.pid and os.readlink(entry / "ns" / "pid") != ours
                        and (entry / "comm").read_text().strip() == "systemd"):
                    return int(entry.name)
            except OSError:
                continue
    return None


@pytest.fixture(scope="module")
def container(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Container]:
    reason = why_not()
    if reason:
        pytest.skip(reason)
    console = tmp_path_factory.mktemp("nspawn") / "console.log"
    binds = [f"--bind-ro={REPO}"]
    if not SITE_PACKAGES.is_relative_to(REPO):
        binds.append(f"--bind-ro={SITE_PACKAGES}")
    cmd = ["systemd-nspawn", "-D", "/", "--volatile=yes", "--register=no", "--keep-unit",
           "--console=passive", f"--machine=leveler-test-{os.getpid()}", *binds,
           "--capability=CAP_IPC_LOCK",  # nspawn drops it by default; a host has it
           "-b", "systemd.firstboot=no"]
    with console.open("wb") as log:
        nspawn = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                  stdin=subprocess.DEVNULL)
    leader: int | None = None
    try:
        deadline = time.monotonic() + 30
        while leader is None and nspawn.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
            leader = leader_of(nspawn)
        if leader is None:
            pytest.skip(f"systemd-nspawn cannot boot here: {console.read_text()[-2000:]}")
        ct = Container(leader)
        booted = ("running", "degraded")
        state, deadline = "", time.monotonic() + BOOT_TIMEOUT_S
        while state not in booted and nspawn.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)  # until systemd listens, systemctl cannot connect and says nothing
            state = ct.run("systemctl", "is-system-running", "--wait", check=False,
                           timeout=BOOT_TIMEOUT_S).strip()
        if state not in booted:
            pytest.skip(f"container systemd is {state!r}: {console.read_text()[-2000:]}")
        yield ct
    finally:
        nspawn.send_signal(signal.SIGTERM)  # nspawn powers the container off
        try:
            nspawn.wait(timeout=30)
        except subprocess.TimeoutExpired:
            nspawn.kill()
            nspawn.wait(timeout=10)
        if leader is not None and Path(f"/proc/{leader}").exists():
            os.kill(leader, signal.SIGKILL)  # the container's init: ends its pid namespace


def hanging_config(lab: str) -> str:
    """config/lab.toml with a quick status and the simulated sensor hanging once."""
    for old, new in (("status_interval_s = 5.0", "status_interval_s = 1.0"),
                     ("[sim]\nseed = 1\n",
                      f"[sim]\nseed = 1\nhang_at_s = {HANG_AT_S}\nhang_for_s = {HANG_FOR_S}\n")):
        assert lab.count(old) == 1, old
        lab = lab.replace(old, new)
    return lab


@pytest.fixture(scope="module")
def service(container: Container) -> Container:
    """Installed by leveler.daemon.install inside the container and started (start returns
    at READY)."""
    ct = container
    ct.run("/usr/bin/python3", "-m", "venv", "--without-pip", "/opt/leveler")
    purelib = ct.run("/opt/leveler/bin/python", "-c",
                     "import sysconfig; print(sysconfig.get_path('purelib'))").strip()
    ct.write(f"{purelib}/leveler-checkout.pth",
             f"import site; site.addsitedir({str(SITE_PACKAGES)!r})\n")
    ct.write("/opt/leveler/bin/leveler", "#!/opt/leveler/bin/python\nimport sys\n"
             "from leveler.cli.main import main\nsys.exit(main())\n", mode=0o755)
    config = hanging_config((REPO / "config" / "lab.toml").read_text())
    ct.write("/etc/leveler/leveler.toml", config)  # a lab's config, already there
    out = ct.run("/opt/leveler/bin/python", "-c",
                 "from leveler.daemon.install import install_service; "
                 "print('\\n'.join(install_service(build_venv=False)))", timeout=60)
    for line in ("created group leveler", "created user leveler", "daemon-reload: done",
                 "config /etc/leveler/leveler.toml: kept as it is (never overwritten)"):
        assert line in out, out
    assert ct.run("cat", "/etc/leveler/leveler.toml") == config
    ct.write("/etc/systemd/system/leveler.service.d/test.conf",
             "[Service]\nWatchdogSec=3s\nRestartSec=1s\n" + CHECKOUT_BINDS)
    ct.run("systemctl", "daemon-reload")
    ct.run("systemctl", "start", "leveler", timeout=60)
    return ct


def test_ready_and_status_come_from_the_daemon(service: Container) -> None:
    s = service.show()
    assert (s["ActiveState"], s["SubState"]) == ("active", "running"), s
    assert s["StatusText"], "the daemon sent no STATUS="
    assert s["WatchdogUSec"] == "3s" and s["NRestarts"] == "0"


def test_process_runs_unprivileged_at_sched_fifo(service: Container) -> None:
    pid = service.show()["MainPID"]
    st = service.proc_status(pid)
    uid = service.run("id", "-u", "leveler").strip()
    dialout = service.run("getent", "group", "dialout").split(":")[2]
    assert st["Uid"].split() == [uid] * 4 and dialout in st["Groups"].split()
    assert st["NoNewPrivs"] == "1" and st["Seccomp"] == "2"
    assert int(st["CapEff"], 16) == ((1 << CAP_IPC_LOCK) | (1 << CAP_SYS_NICE)) & host_caps()
    assert service.sched(pid) == (SCHED_FIFO, 50)


def test_socket_and_logs_are_where_the_group_can_reach_them(service: Container) -> None:
    stat = service.run("stat", "-c", "%a %U %G", "/run/leveler", "/run/leveler/control.sock",
                       "/var/lib/leveler/logs").splitlines()
    assert stat == ["750 leveler leveler", "660 leveler leveler", "750 leveler leveler"]
    logs = service.run("ls", "/var/lib/leveler/logs").split()
    assert any(name.endswith(".mcap") for name in logs), logs


def test_group_members_and_only_they_reach_the_socket(service: Container) -> None:
    """`usermod -aG leveler NAME` is what the README tells a lab to do; it must suffice."""
    for name, groups in (("lvmember", ["-G", "leveler"]), ("lvstranger", [])):
        service.run("useradd", "--no-create-home", "-N", *groups, name)

    def status_as(name: str) -> subprocess.CompletedProcess[str]:
        gid = service.run("id", "-g", name).strip()
        return subprocess.run(
            ["nsenter", "-t", str(service.leader), "-a", "--", "setpriv", f"--reuid={name}",
             f"--regid={gid}", "--init-groups", "/opt/leveler/bin/leveler", "status"],
            capture_output=True, text=True, timeout=30)

    member, stranger = status_as("lvmember"), status_as("lvstranger")
    assert member.returncode == 0 and "state" in member.stdout, member.stdout + member.stderr
    assert stranger.returncode != 0 and "state" not in stranger.stdout


def test_sandbox_holds_for_python_in_the_unit(service: Container) -> None:
    """The unit's own sandbox, run as a oneshot probe instead of the daemon."""
    service.write("/opt/leveler/probe.py", PROBE)
    service.run("cp", "/etc/systemd/system/leveler.service",
                "/etc/systemd/system/leveler-probe.service")
    service.write("/etc/systemd/system/leveler-probe.service.d/probe.conf",
                  "[Service]\nType=oneshot\nWatchdogSec=0\nRestart=no\nExecStart=\n"
                  "ExecStart=/opt/leveler/bin/python /opt/leveler/probe.py\n" + CHECKOUT_BINDS)
    service.run("systemctl", "daemon-reload")
    service.run("systemctl", "start", "leveler-probe", timeout=60)
    line = next(ln for ln in service.journal("leveler-probe").splitlines()
                if ln.startswith("PROBE "))
    got, expected = json.loads(line.removeprefix("PROBE ")), dict(PROBE_EXPECTED)
    if not host_caps() & (1 << CAP_IPC_LOCK):  # nothing can grant it here
        del got["mlockall"], expected["mlockall"]
    assert got == expected


def test_reload_keeps_the_process(service: Container) -> None:
    pid = service.show()["MainPID"]
    service.run("systemctl", "reload", "leveler")
    s = service.show()
    assert (s["MainPID"], s["ActiveState"], s["NRestarts"]) == (pid, "active", "0")


def test_stop_is_clean_and_removes_the_socket(service: Container) -> None:
    service.run("systemctl", "restart", "leveler", timeout=60)  # well before the hang
    service.run("systemctl", "stop", "leveler", timeout=30)
    s = service.show()
    assert (s["ActiveState"], s["Result"]) == ("inactive", "success"), s
    assert "stopped (SIGTERM)" in service.journal()
    assert "leveler" not in service.run("ls", "/run").split()


def test_watchdog_kills_a_stalled_loop_and_restarts_it(service: Container) -> None:
    service.run("systemctl", "start", "leveler", timeout=60)
    first = service.show()["MainPID"]
    wait_for("a watchdog restart", lambda: int(service.show()["NRestarts"]) >= 1,
             HANG_AT_S + 30)
    assert "Watchdog timeout" in service.journal()
    wait_for("the restarted daemon to be READY",
             lambda: service.show()["SubState"] == "running", 30)
    assert service.show()["MainPID"] not in ("0", first)
