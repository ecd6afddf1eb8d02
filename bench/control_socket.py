"""Control-socket figures: `status` round trip while the loop runs at 1 kHz, and whether
the socket traffic (well-formed or malformed) costs the loop any overruns.

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
from typing import Any

from common import REPO, row  # beside this script

from leveler.daemon.client import Client

SECTION = "control socket"


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


# Malformed lines of the kinds tests/test_fuzz_socket.py sends, each refused with one error
# on a connection that stays open: there the test judges the answers, here the loop's cost.
MALFORMED = (
    b'{"v":1,"verb":"tune","kp_v_per_m":1.5',
    b'{"v":1,"verb":"sta\xfftus"}',
    b'{"v":1,"verb":"fly"}',
    b'{"v":2,"verb":"stop"}',
    b'{"v":1,"verb":"tune","kp_v_per_m":NaN}',
    b'{"v":1,"verb":"tune","kp_v_per_m":' + b"9" * 400 + b"}",
    b"[" * 5000 + b"]" * 5000,
)


def malformed_storm(sock: Path, duration_s: float, batch: int = 50) -> int:
    """Pipeline malformed lines on one connection for duration_s; return how many."""
    lines = b"\n".join(MALFORMED[i % len(MALFORMED)] for i in range(batch)) + b"\n"
    sent = 0
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(10.0)
        s.connect(str(sock))
        replies = s.makefile("rb")
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            s.sendall(lines)
            for _ in range(batch):
                if b'"ok":false' not in replies.readline():
                    raise RuntimeError("a malformed line was not refused")
            sent += batch
    return sent


def _overruns(sock: Path) -> tuple[int, int]:
    with Client(sock) as c:
        loop = c.request("status")["status"]["loop"]
    return loop["overruns"], loop["cycles"]


def daemon_figures(rate_hz: float = 1000.0, phase_s: float = 5.0) -> dict[str, float]:
    """Start the daemon at rate_hz: a quiet phase, back-to-back status requests (a storm),
    status at 50 requests/s (a busy lab), then malformed lines back to back."""
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
            junk = malformed_storm(sock, phase_s)
            o4, c4 = _overruns(sock)
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
        "malformed_lines": junk,
        "overruns_per_1e5_malformed": 1e5 * (o4 - o3) / max(c4 - c3, 1),
    }


def run(quick: bool) -> list[dict[str, Any]]:
    phase_s = 2.0 if quick else 5.0
    echo = echo_rtt_s(200 if quick else 500)
    d = daemon_figures(phase_s=phase_s)
    rate = f"daemon at {d['rate_hz']:g} Hz on the simulated plant"
    storm_rate = d["status_requests"] / phase_s
    return [
        row(SECTION, "bare Unix-socket echo round trip (baseline)", echo * 1e3, "ms",
            note="connect, one line each way, close: the floor for any round trip here"),
        row(SECTION, "status round trip, median", d["status_rtt_median_s"] * 1e3, "ms",
            baseline="echo", ratio=d["status_rtt_median_s"] / echo,
            note=f"{rate}; back-to-back requests for {phase_s:g} s"),
        row(SECTION, "status round trip, p99", d["status_rtt_p99_s"] * 1e3, "ms",
            baseline="echo", ratio=d["status_rtt_p99_s"] / echo),
        row(SECTION, "`leveler status` command, median", d["cli_status_median_s"] * 1e3, "ms",
            note="a new Python process each time: start-up dominates"),
        row(SECTION, "overruns per 1e5 cycles, no traffic", d["overruns_per_1e5_quiet"],
            "per 1e5", note=f"{phase_s:g} s at {d['rate_hz']:g} Hz"),
        row(SECTION, "overruns per 1e5 cycles, status at 50/s",
            d["overruns_per_1e5_paced"], "per 1e5",
            note=f"round trip meanwhile {d['paced_rtt_median_s'] * 1e3:.3f} ms median"),
        row(SECTION, f"overruns per 1e5 cycles, status at {storm_rate:.0f}/s",
            d["overruns_per_1e5_storm"], "per 1e5", note="the back-to-back storm above"),
        row(SECTION, f"overruns per 1e5 cycles, malformed lines at "
            f"{d['malformed_lines'] / phase_s:.0f}/s", d["overruns_per_1e5_malformed"],
            "per 1e5", note="pipelined on one connection, each refused with one error"),
    ]
