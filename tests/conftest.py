"""Shared test harness: the daemon as a real subprocess with its own temporary directories."""

from __future__ import annotations

import atexit
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from hypothesis import settings

if TYPE_CHECKING:
    from leveler.analysis.predict import Measured

REPO = Path(__file__).resolve().parents[1]

# `make test` draws the same Hypothesis examples every run, so CI passes or fails on the code
# alone; `make test-explore` draws new ones (HYPOTHESIS_PROFILE=explore) to hunt for bugs.
settings.register_profile("repeatable", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))

# A null calibration `leveler diagnose` cached on this machine must not decide a test: the
# tests (and the CLIs they start) read and write a cache of their own, gone at the end.
os.environ["LEVELER_CACHE_DIR"] = tempfile.mkdtemp(prefix="leveler-test-cache-")
atexit.register(shutil.rmtree, os.environ["LEVELER_CACHE_DIR"], ignore_errors=True)


@dataclass
class DaemonProc:
    proc: subprocess.Popen[str]
    config: Path
    socket: Path
    logs: Path
    lines: list[str] = field(default_factory=list)

    def cli(self, *args: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
        """Run `leveler ARGS --socket <this daemon>` as a separate process."""
        return subprocess.run([sys.executable, "-m", "leveler.cli", *args, "--socket",
                               str(self.socket)], capture_output=True, text=True,
                              timeout=timeout)

    def wait_status_lines(self, n: int, timeout_s: float = 30.0) -> list[str]:
        """Read stdout until n more status lines have appeared."""
        assert self.proc.stdout is not None
        deadline = time.monotonic() + timeout_s
        seen = 0
        while seen < n:
            assert time.monotonic() < deadline, f"no status lines in time; got {self.lines}"
            line = self.proc.stdout.readline()
            if not line:
                err = self.proc.stderr.read() if self.proc.stderr else ""
                raise AssertionError(f"daemon exited early: {err}")
            self.lines.append(line)
            seen += "period p50/p99/max" in line
        return self.lines

    def stop(self, sig: signal.Signals = signal.SIGTERM, timeout_s: float = 20.0) -> str:
        """Signal the daemon and return its stderr after it exits."""
        self.proc.send_signal(sig)
        _, err = self.proc.communicate(timeout=timeout_s)
        return err


def run_cli(*args: str, cwd: Path) -> str:
    """`leveler ARGS` as a separate process in `cwd`; its stdout, asserting it succeeded."""
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", *args], capture_output=True,
                          text=True, timeout=300, cwd=cwd)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def daemon_config(tmp_path: Path, sock: Path, *, rate_hz: float = 50.0, sim: str = "",
                  engage: bool = True, base: str = "sim.toml",
                  replace: dict[str, str] | None = None, control: str = "",
                  edit: Callable[[str], str] | None = None) -> Path:
    cfg = (REPO / "config" / base).read_text()
    for old, new in (replace or {}).items():
        assert old in cfg, old
        cfg = cfg.replace(old, new)
    cfg = cfg.replace("rate_hz = 10.0", f"rate_hz = {rate_hz}")
    cfg = cfg.replace("status_interval_s = 5.0", "status_interval_s = 0.5")
    cfg = cfg.replace('dir = "logs"', f'dir = "{tmp_path / "logs"}"')
    if not engage:
        cfg = cfg.replace("engage_on_start = true", "engage_on_start = false")
    cfg = cfg.replace("[sim]\nseed = 1\n", f"[sim]\nseed = 1\n{sim}\n")
    cfg += f'\n[control]\nsocket_path = "{sock}"\n{control}'
    if edit is not None:  # another form of the same config (dotted keys, inline tables)
        cfg = edit(cfg)
    path = tmp_path / "daemon.toml"
    path.write_text(cfg)
    return path


@pytest.fixture
def start_daemon(tmp_path: Path) -> Iterator:  # type: ignore[type-arg]
    """Factory: start_daemon(rate_hz=..., sim='hang_at_s = 3.0', env={...}, base='x.toml',
    replace={'old text': 'new text'}, control='idle_timeout_s = 2.0\n', edit=fn) ->
    DaemonProc."""
    started: list[DaemonProc] = []
    short = Path(tempfile.mkdtemp(prefix="lv", dir="/tmp"))  # AF_UNIX paths are short

    def start(*, rate_hz: float = 50.0, sim: str = "", engage: bool = True,
              env: dict[str, str] | None = None, wait_socket: bool = True,
              base: str = "sim.toml", replace: dict[str, str] | None = None,
              control: str = "", umask: int | None = None,
              edit: Callable[[str], str] | None = None) -> DaemonProc:
        sock = short / f"c{len(started)}.sock"
        config = daemon_config(tmp_path, sock, rate_hz=rate_hz, sim=sim, engage=engage,
                               base=base, replace=replace, control=control, edit=edit)
        proc = subprocess.Popen(
            [sys.executable, "-m", "leveler.cli", "run", "--config", str(config)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            umask=-1 if umask is None else umask)
        d = DaemonProc(proc, config, sock, tmp_path / "logs")
        started.append(d)
        deadline = time.monotonic() + 30
        while wait_socket and not sock.exists():
            assert proc.poll() is None, f"daemon died: {proc.communicate()[1]}"
            assert time.monotonic() < deadline, "daemon socket never appeared"
            time.sleep(0.05)
        return d

    yield start
    for d in started:
        if d.proc.poll() is None:
            d.proc.kill()
            d.proc.communicate(timeout=10)
    shutil.rmtree(short, ignore_errors=True)


def as_user(uid: int, fn: Callable[[], object], gid: int | None = None) -> str:
    """fn() in a forked child that dropped to uid (and gid, default uid; no exec: the venv
    may be unreadable to that user); returns what fn returned, or the exception's text."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child
        os.close(r)
        try:
            os.setgroups([])
            os.setgid(uid if gid is None else gid)
            os.setuid(uid)
            out = str(fn())
        except BaseException as exc:  # report everything to the parent
            out = f"{type(exc).__name__}: {exc}"
        os.write(w, out.encode())
        os._exit(0)
    os.close(w)
    with os.fdopen(r) as fh:
        out = fh.read()
    os.waitpid(pid, 0)
    return out


@pytest.fixture(scope="session")
def quiet(tmp_path_factory: pytest.TempPathFactory) -> Measured:
    """Two hours of the simulated stand with nothing missing (seed 12), loaded for replay:
    shared read-only; a test changes it through `dataclasses.replace`."""
    from leveler.analysis.predict import load_measured
    from leveler.analysis.synthetic import make_measured
    from leveler.settings import load_config

    cfg, text = load_config(REPO / "config" / "sim.toml")
    log = tmp_path_factory.mktemp("quiet") / "quiet.mcap"
    make_measured(log, cfg, text, None, duration_s=2 * 3600, seed=12)
    return load_measured(log)

