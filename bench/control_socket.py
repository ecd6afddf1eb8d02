"""Control-socket figures: `status` round trip while the loop runs at 1 kHz, and whether
the socket traffic costs the loop any overruns.

Baselines measured in the same run: a bare Unix-socket echo (the floor for any round
trip on this machine) and the same daemon's loop with no traffic.
"""

from __future__ import annotations

import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from leveler.client import Client

REPO = Path(__file__).resolve().parents[1]


def echo_rtt_s(n: int = 500) -> float:
    """Median round trip of one line through a bare Unix-socket echo thread."""
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "echo.sock")
        srv = socket.socket(socket.AF_UNIX)
        srv.bind(path)
        srv.listen()

        def serve() -> None:
            while True:
                try:
                    conn, _ = srv.accept()
                except OSError:
                    return
                with conn:
                    conn.sendall(conn.makefile("rb").readline())

        threading.Thread(target=serve, daemon=True).start()
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            with socket.socket(socket.AF_UNIX) as c:
                c.connect(path)
                c.sendall(b'{"v":1,"verb":"status"}\n')
                c.makefile("rb").readline()
            times.append(time.perf_counter() - t0)
        srv.close()
    return statistics.median(times)


def _overruns(sock: Path) -> tuple[int, int]:
    with Client(sock) as c:
        loop = c.request("status")["status"]["loop"]
    return loop["overruns"], loop["cycles"]


def daemon_figures(rate_hz: float = 1000.0, phase_s: float = 5.0) -> dict[str, float]:
    """Start the daemon at rate_hz: a quiet phase, back-to-back status requests (a storm),
    then status at 50 requests/s (a busy lab)."""
    with tempfile.TemporaryDirectory() as tmp:
        tmpdir = Path(tmp)
        sock = tmpdir / "c.sock"
        cfg = (REPO / "config" / "sim.toml").read_text()
        cfg = cfg.replace("rate_hz = 10.0", f"rate_hz = {rate_hz}")
        cfg = cfg.replace('dir = "logs"', f'dir = "{tmpdir / "logs"}"')
        cfg += f'\n[control]\nsocket_path = "{sock}"\n'
        (tmpdir / "d.toml").write_text(cfg)
        proc = subprocess.Popen([sys.executable, "-m", "leveler.cli", "run", "--config",
                                 str(tmpdir / "d.toml")], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 30
            while not sock.exists():
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("daemon did not start")
                time.sleep(0.05)
            time.sleep(1.0)  # let start-up settle
            o0, c0 = _overruns(sock)
            time.sleep(phase_s)
            o1, c1 = _overruns(sock)
            rtts = []
            end = time.monotonic() + phase_s
            while time.monotonic() < end:
                t0 = time.perf_counter()
                with Client(sock) as c:
                    c.request("status")
                rtts.append(time.perf_counter() - t0)
            o2, c2 = _overruns(sock)
            paced = []
            end = time.monotonic() + phase_s
            while time.monotonic() < end:  # a lab's use: a few clients, tens of requests/s
                t0 = time.perf_counter()
                with Client(sock) as c:
                    c.request("status")
                paced.append(time.perf_counter() - t0)
                time.sleep(max(0.0, 0.02 - (time.perf_counter() - t0)))
            o3, c3 = _overruns(sock)
            cli = []
            for _ in range(5):
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "leveler.cli", "status", "--socket",
                                str(sock)], capture_output=True, check=True)
                cli.append(time.perf_counter() - t0)
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    return {
        "rate_hz": rate_hz,
        "status_rtt_median_s": statistics.median(rtts),
        "status_rtt_p99_s": sorted(rtts)[int(0.99 * (len(rtts) - 1))],
        "status_requests": len(rtts),
        "cli_status_median_s": statistics.median(cli),
        "overruns_per_1e5_quiet": 1e5 * (o1 - o0) / max(c1 - c0, 1),
        "overruns_per_1e5_storm": 1e5 * (o2 - o1) / max(c2 - c1, 1),
        "paced_requests": len(paced),
        "paced_rtt_median_s": statistics.median(paced),
        "overruns_per_1e5_paced": 1e5 * (o3 - o2) / max(c3 - c2, 1),
    }


def main() -> dict[str, float]:
    echo = echo_rtt_s()
    d = daemon_figures()
    print(f"\ncontrol socket, daemon at {d['rate_hz']:g} Hz on the simulated plant")
    print(f"{'what':<44} {'value':>12} {'x baseline':>11}")
    print(f"{'bare Unix-socket echo round trip (baseline)':<44} {echo * 1e3:9.3f} ms {1:10.1f}x")
    print(f"{'status round trip, median':<44} {d['status_rtt_median_s'] * 1e3:9.3f} ms "
          f"{d['status_rtt_median_s'] / echo:10.1f}x")
    print(f"{'status round trip, p99':<44} {d['status_rtt_p99_s'] * 1e3:9.3f} ms "
          f"{d['status_rtt_p99_s'] / echo:10.1f}x")
    print(f"{'`leveler status` command, median':<44} {d['cli_status_median_s'] * 1e3:9.1f} ms")
    print(f"{'loop overruns per 1e5 cycles, no traffic':<44} {d['overruns_per_1e5_quiet']:12.1f}")
    print(f"{'loop overruns per 1e5 cycles, status at 50/s':<44} "
          f"{d['overruns_per_1e5_paced']:12.1f}")
    print(f"{'  (status round trip at 50/s, median)':<44} {d['paced_rtt_median_s'] * 1e3:9.3f} ms")
    storm = f"loop overruns per 1e5, {d['status_requests'] / 5:.0f} requests/s"
    print(f"{storm:<44} {d['overruns_per_1e5_storm']:12.1f}")
    return {"echo_rtt_median_s": echo, **d}
