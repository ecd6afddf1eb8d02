"""How fast the daemon is up and how much memory it holds, on the simulated stand and on
hardware (config/lab-modbus.toml against the Modbus emulator on loopback, so the device
answers in microseconds and connecting costs next to nothing).

Time to READY: from exec to the READY=1 datagram on a NOTIFY_SOCKET of the bench's own, with
ready_samples = 1 (the config's usual 10 good samples are a deliberate wait, not start-up).
RSS: VmRSS two seconds after READY. Baseline in the same run: a bare interpreter that imports
numpy (the floor for any process of this stack), its wall time and peak RSS. Each figure is
the best of a few starts: on a shared machine the others measure the load. Under the
service the daemon also locks its memory (mlockall), which makes every mapping resident;
these runs are at normal scheduling, as `make run`.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from common import REPO, at_most, row  # beside this script

from leveler.emulate.modbus import ModbusEmulator
from leveler.settings import load_config
from leveler.sim.plant import Plant

SECTION = "daemon start-up"
READY_GOAL_S, RSS_GOAL_MIB = 0.5, 60.0
_ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


def _vm_kib(pid: int, key: str) -> int:
    text = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(rf"^{key}:\s+(\d+) kB", text, re.M).group(1))  # type: ignore[union-attr]


def baseline() -> tuple[float, float]:
    """Wall time [s] of `python -c 'import numpy'`, and its VmRSS [MiB] as it ends (not the
    child's peak: that counts the bench's own pages, shared from the fork before exec)."""
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", "import numpy; "
                          "print(open('/proc/self/status').read())"], env=_ENV,
                         capture_output=True, text=True, check=True).stdout
    wall = time.perf_counter() - t0
    return wall, int(re.search(r"^VmRSS:\s+(\d+) kB", out, re.M).group(1)) / 1024  # type: ignore[union-attr]


def _config(tmp: Path, base: str, replace: dict[str, str]) -> Path:
    text = (REPO / "config" / base).read_text()
    for old, new in replace.items():
        if old not in text:
            raise RuntimeError(f"config/{base}: no {old!r} to replace")
        text = text.replace(old, new)
    text = re.sub(r"^\[loop\]$", "[loop]\nready_samples = 1", text, count=1, flags=re.M)
    text = re.sub(r'^dir = "[^"]*"', f'dir = "{tmp / "logs"}"', text, count=1, flags=re.M)
    text += f'\n[control]\nsocket_path = "{tmp / "c.sock"}"\n'
    path = tmp / f"bench-{base}"
    path.write_text(text)
    return path


def start(config: Path, tmp: Path) -> tuple[float, float]:
    """Time to READY [s] and VmRSS two seconds later [MiB] of one daemon."""
    addr = tmp / "notify.sock"
    addr.unlink(missing_ok=True)
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify:
        notify.bind(str(addr))
        notify.settimeout(30)
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "leveler.cli", "run", "--config",
                                 str(config)], env={**_ENV, "NOTIFY_SOCKET": str(addr)},
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=tmp)
        try:
            while b"READY=1" not in notify.recv(4096):
                pass
            ready = time.perf_counter() - t0
            time.sleep(2.0)
            rss = _vm_kib(proc.pid, "VmRSS") / 1024
        except TimeoutError:
            proc.kill()
            raise RuntimeError(f"no READY in 30 s: {proc.communicate()[1][-2000:]!r}") from None
        finally:
            if proc.poll() is None:
                proc.terminate()
                proc.communicate(timeout=30)
    return ready, rss


def best(config: Path, tmp: Path, repeats: int) -> tuple[float, float]:
    runs = [start(config, tmp) for _ in range(repeats)]
    return min(r[0] for r in runs), min(r[1] for r in runs)


def run(quick: bool) -> list[dict[str, Any]]:
    repeats = 2 if quick else 5
    base_s, base_mib = min(baseline() for _ in range(repeats))
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        sim_s, sim_mib = best(_config(tmp, "sim.toml", {}), tmp, repeats)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        hw_config = _config(tmp, "lab-modbus.toml", {"port = 5020": f"port = {port}"})
        cfg, _ = load_config(hw_config)
        sensor, actuator = cfg.sensor.modbus, cfg.actuator.modbus
        assert sensor is not None and actuator is not None
        with ModbusEmulator(Plant(cfg.plant, 1.0 / cfg.loop.rate_hz, cfg.sim.seed), sensor,
                            actuator, port=port):
            hw_s, hw_mib = best(hw_config, tmp, repeats)
    floor = f"python -c 'import numpy' {base_s:.3f} s"
    mem_floor = f"import numpy {base_mib:.1f} MiB"
    return [
        row(SECTION, "bare interpreter + numpy, to exit (baseline)", base_s, "s",
            note=f"its VmRSS at the end {base_mib:.1f} MiB; best of {repeats}"),
        row(SECTION, "time to READY, hardware (Modbus, emulated)", hw_s, "s", baseline=floor,
            ratio=hw_s / base_s, goal=f"<= {READY_GOAL_S:g} s",
            met=at_most(hw_s, READY_GOAL_S),
            note="config/lab-modbus.toml, ready_samples = 1; the emulator on loopback, so "
            "connecting costs microseconds"),
        row(SECTION, "daemon RSS, hardware (Modbus, emulated)", hw_mib, "MiB",
            baseline=mem_floor, ratio=hw_mib / base_mib, goal=f"<= {RSS_GOAL_MIB:g} MiB",
            met=at_most(hw_mib, RSS_GOAL_MIB),
            note="VmRSS 2 s after READY, normal scheduling (the service's mlockall makes "
            "every mapping resident)"),
        row(SECTION, "time to READY, simulated stand", sim_s, "s", baseline=floor,
            ratio=sim_s / base_s, note="config/sim.toml: the simulated plant is numpy alone"),
        row(SECTION, "daemon RSS, simulated stand", sim_mib, "MiB", baseline=mem_floor,
            ratio=sim_mib / base_mib),
    ]
