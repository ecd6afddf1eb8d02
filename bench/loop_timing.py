"""The real-time loop at 1 kHz with logging on, next to `cyclictest` (issue 7; issue 8's soak).

What is measured is what `leveler run` gives a user: the daemon (`leveler.daemon.service.Daemon`
with its `RealtimeClock`, the simulated backend and the MCAP log through `RotatingLog`) with
config/sim.toml at `rate_hz = 1000`, in a child process that first takes what
systemd/leveler.service gives the service: SCHED_FIFO at the unit's CPUSchedulingPriority (its
helper threads then lower themselves, as under systemd), and mlockall(). Each is checked and the
table says what was obtained (without root: normal scheduling, no lock). The daemon's code runs
unchanged; two thin wrappers record, per cycle, the lateness of the wake-up (the time the clock read
on waking minus the deadline it slept to), whether the thread had to wait again after waking (a
voluntary context switch inside the tick beyond the sleep itself: the interpreter lock held by
another thread), and the thread CPU time of `Loop.cycle` (read -> update -> write -> log).

Baselines, measured in the same benchmark, one after another (never concurrently):
- `cyclictest` (Debian rt-tests) with the same policy, priority, interval (1000 us) and
  mlockall, and `--default-system`: it does not tune the machine (cpu_dma_latency) beyond
  what the daemon gets. Skipped, with the reason, if it is not installed.
- the same daemon with its log switched off (the loop's sinks emptied): what logging costs.
- a bare loop on the same `RealtimeClock`, same process set-up and instrumentation, doing
  no work: the floor for a Python loop on this clock.
- the same logged daemon with its live view on ([live] foxglove on loopback, issue 20) and a
  real WebSocket client (another process) subscribed to every topic, and its EPICS PVs
  served ([epics] serve): what watching costs.
In the full run each is measured in three rounds (cyclictest, daemon, daemon without log,
daemon with the live view, bare loop; again), so a change in the load of a shared machine
falls on all of them alike.

Lateness is counted in 1 us bins, as cyclictest counts it; "late cycles" are wake-ups more
than one period (1000 us) late. The daemon's first tick (after start-up, not after a sleep)
is not counted.

    python bench/loop_timing.py [--quick] [--duration SECONDS] [--json FILE]

`--duration` runs the logged daemon once for that long (cyclictest for as long, at most
600 s; the shorter baselines as in the full run) and reports the daemon's RSS growth over
it: `make bench-soak` is the one-hour run issue 8 asks for.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from common import REPO, row  # beside this script

SECTION = "loop timing"
RATE_HZ = 1000.0
PERIOD_US = 1000
HIST_US = 20_000  # lateness histogram range (1 us bins); the last bin holds everything later
CYCLICTEST_MAX_S = 600.0  # baseline length cap for long (soak) runs
RSS_RATE_MIN_S = 600.0  # shorter runs give the growth, not a rate per hour
CHILD_GRACE_S = 120.0  # start-up and shutdown allowance before a child is killed
_MCL_CURRENT, _MCL_FUTURE = 1, 2
# One BLAS thread in the measured process. numpy's OpenBLAS starts worker threads at import,
# which inherit SCHED_FIFO; scipy's expm (the simulated plant's set-up) then spins waiting
# for them, and with every core held by a real-time spinner they never run: two such
# processes on two cores livelocked (observed). The loop itself makes no threaded BLAS call.
_CHILD_ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}


def unit_priority() -> int:
    """CPUSchedulingPriority= of systemd/leveler.service: the priority the service runs at."""
    text = (REPO / "systemd" / "leveler.service").read_text()
    m = re.search(r"^CPUSchedulingPriority=(\d+)", text, re.M)
    return int(m.group(1)) if m else 50


def plan(quick: bool, duration_s: float | None) -> dict[str, float]:
    """Seconds of each run, and the number of rounds."""
    if duration_s is not None:
        return {"rounds": 1, "cyclictest": min(duration_s, CYCLICTEST_MAX_S),
                "logged": duration_s, "unlogged": min(duration_s, 36.0),
                "live": min(duration_s, 36.0), "bare": min(duration_s, 24.0)}
    if quick:
        return {"rounds": 1, "cyclictest": 6.0, "logged": 6.0, "unlogged": 4.0, "live": 6.0,
                "bare": 3.0}
    return {"rounds": 3, "cyclictest": 25.0, "logged": 25.0, "unlogged": 12.0, "live": 25.0,
            "bare": 8.0}


# ---- the child: one measured run --------------------------------------------------------

def _realtime_setup(priority: int) -> dict[str, Any]:
    """SCHED_FIFO and mlockall for this (still single-threaded) process, as systemd gives
    the service; returns what was obtained."""
    out: dict[str, Any] = {"sched_error": ""}
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        out["sched_error"] = str(exc)
    names = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_FIFO: "SCHED_FIFO",
             os.SCHED_RR: "SCHED_RR"}
    pol = os.sched_getscheduler(0)
    out["policy"] = names.get(pol, str(pol))
    out["priority"] = os.sched_getparam(0).sched_priority
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
        out["mlockall"] = "locked"
    else:
        out["mlockall"] = f"not locked ({os.strerror(ctypes.get_errno())})"
    return out


class _Recorder:
    """Per-cycle figures in fixed-size histograms: constant memory, so a soak's RSS growth
    is the daemon's own."""

    def __init__(self) -> None:
        self.started = False
        self.late = [0] * (HIST_US + 1)  # lateness, 1 us bins
        self.late_max_ns = 0
        self.gil_late = [0] * (HIST_US + 1)  # lateness of the cycles that waited for the GIL
        self.work_cpu = [0] * 2001  # CPU of Loop.cycle, 1 us bins up to 2 ms
        self.work_cpu_sum = 0
        self.work_cpu_max = 0
        self.n = 0
        self.cpu0 = self.cpu_last = 0  # thread CPU at the first and the last cycle

    def lateness(self, late_ns: int, switches: int) -> None:
        if not self.started:  # the first tick comes after start-up, not after a sleep
            self.started = True
            return
        late_ns = max(late_ns, 0)
        b = min(late_ns // 1000, HIST_US)
        self.late[b] += 1
        if late_ns > self.late_max_ns:
            self.late_max_ns = late_ns
        if switches > 1:  # woke, then blocked again: another thread held the interpreter
            self.gil_late[b] += 1

    def work(self, c0: int, c1: int) -> None:
        w = c1 - c0
        self.work_cpu[min(w // 1000, 2000)] += 1
        self.work_cpu_sum += w
        if w > self.work_cpu_max:
            self.work_cpu_max = w
        if self.n == 0:
            self.cpu0 = c0
        self.cpu_last = c0
        self.n += 1

    def result(self) -> dict[str, Any]:
        return {"late_hist": self.late, "late_max_ns": self.late_max_ns,
                "gil_late_hist": self.gil_late, "work_cpu_hist": self.work_cpu,
                "work_cpu_mean_ns": self.work_cpu_sum / max(self.n, 1),
                "work_cpu_max_ns": self.work_cpu_max,
                "period_cpu_mean_ns": (self.cpu_last - self.cpu0) / max(self.n - 1, 1)}


def _thread_usage() -> dict[str, int]:
    ru = resource.getrusage(resource.RUSAGE_THREAD)
    return {"minflt": ru.ru_minflt, "majflt": ru.ru_majflt, "nvcsw": ru.ru_nvcsw,
            "nivcsw": ru.ru_nivcsw}


def child_daemon(config: Path, duration_s: float, logged: bool) -> dict[str, Any]:
    """`leveler run --config config --duration duration_s`, instrumented."""
    import logging

    from leveler.daemon.service import Daemon

    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)  # as run_daemon
    d = Daemon(config, duration_s)
    if not logged:
        d.loop.sinks = []  # the log stays open (and idle); the loop hands it nothing
    rec = _Recorder()
    clock, loop = d.clock, d.loop
    tick, cycle = clock.tick, loop.cycle
    now_cpu = time.thread_time_ns
    getrusage, thread = resource.getrusage, resource.RUSAGE_THREAD

    def timed_tick() -> float:
        deadline = clock._next_ns  # the deadline this tick sleeps to (before any skip)
        sw = getrusage(thread).ru_nvcsw
        t = tick()
        rec.lateness(clock._last_ns - deadline, getrusage(thread).ru_nvcsw - sw)
        return t

    u0: dict[str, int] = {}

    def timed_cycle(t: float, wall_ns: int) -> Any:
        if rec.n == 1:  # start-up is over (threads started, first sample out)
            u0.update(_thread_usage())
        c0 = now_cpu()
        s = cycle(t, wall_ns)
        rec.work(c0, now_cpu())
        return s

    clock.tick = timed_tick  # type: ignore[method-assign]
    loop.cycle = timed_cycle  # type: ignore[method-assign]
    d.run()
    u1 = _thread_usage()
    return {**rec.result(), "usage": {k: u1[k] - u0.get(k, 0) for k in u1},
            "overruns": clock.overruns, "samples_written": d.log.samples_written,
            "dropped": d.log.dropped, "log_error": d.log.last_error or ""}


def child_bare(duration_s: float) -> dict[str, Any]:
    """The same clock, process set-up and instrumentation, no work."""
    from leveler.loop.clock import RealtimeClock

    rec = _Recorder()
    clock = RealtimeClock(1.0 / RATE_HZ)
    now_cpu = time.thread_time_ns
    getrusage, thread = resource.getrusage, resource.RUSAGE_THREAD
    u0 = _thread_usage()
    t = 0.0
    while t < duration_s:
        deadline = clock._next_ns
        sw = getrusage(thread).ru_nvcsw
        t = clock.tick()
        rec.lateness(clock._last_ns - deadline, getrusage(thread).ru_nvcsw - sw)
        c0 = now_cpu()
        rec.work(c0, now_cpu())
    u1 = _thread_usage()
    return {**rec.result(), "usage": {k: u1[k] - u0[k] for k in u0},
            "overruns": clock.overruns}


def child_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="loop_timing.py --child")
    p.add_argument("mode", choices=["logged", "unlogged", "live", "bare"])
    p.add_argument("--config", type=Path)
    p.add_argument("--duration", type=float, required=True)
    p.add_argument("--priority", type=int, required=True)
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args(argv)
    rt = _realtime_setup(a.priority)  # first, before any thread exists
    if a.mode == "bare":
        out = child_bare(a.duration)
    else:
        out = child_daemon(a.config, a.duration, logged=a.mode != "unlogged")
    a.out.write_text(json.dumps({**out, "rt": rt}))
    return 0


# ---- the parent: the runs and the table ---------------------------------------------------

def _config(tmp: Path, live_port: int | None = None) -> Path:
    """config/sim.toml at 1 kHz, logging into tmp, its control socket in tmp; with
    `live_port`, the live view on loopback at the default 50 Hz."""
    text = (REPO / "config" / "sim.toml").read_text()
    text, n = re.subn(r"^rate_hz = [\d.]+", f"rate_hz = {RATE_HZ}", text, flags=re.M)
    if n != 1:
        raise RuntimeError("config/sim.toml: no `rate_hz = ...` line to set to 1000")
    text = text.replace('dir = "logs"', f'dir = "{tmp / "logs"}"')
    text += f'\n[control]\nsocket_path = "{tmp / "control.sock"}"\n'
    if live_port is not None:  # both servers of issue 20 on, as a lab would run them
        text += (f'\n[live]\nfoxglove = "127.0.0.1:{live_port}"\n'
                 '\n[epics]\nserve = true\n')
    path = tmp / ("sim-1khz.toml" if live_port is None else "sim-1khz-live.toml")
    path.write_text(text)
    return path


def _rss_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def client_main(argv: list[str]) -> int:
    """A Foxglove client for the live run: subscribes to every topic and reads until the
    server goes; prints the messages it got per topic as JSON."""
    import asyncio
    import struct

    import websockets

    async def read(url: str, timeout_s: float) -> dict[str, int]:
        deadline = time.monotonic() + timeout_s
        while True:  # the daemon opens the port after its start-up
            try:
                ws = await websockets.connect(url, subprotocols=["foxglove.sdk.v1"])
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.1)
        got: dict[str, int] = {}
        async with ws:
            chans: dict[int, str] = {}
            while not chans:
                m = json.loads(await ws.recv())
                if m["op"] == "advertise":
                    chans = {c["id"]: c["topic"] for c in m["channels"]}
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": cid, "channelId": cid} for cid in chans]}))
            with contextlib.suppress(websockets.ConnectionClosed):
                async for frame in ws:
                    if isinstance(frame, bytes):
                        topic = chans[struct.unpack_from("<I", frame, 1)[0]]
                        got[topic] = got.get(topic, 0) + 1
        return got

    print(json.dumps(asyncio.run(read(argv[0], float(argv[1])))))
    return 0


def _run_child(mode: str, duration_s: float, priority: int, tmp: Path,
               config: Path | None = None, live_port: int | None = None) -> dict[str, Any]:
    """One child run; the parent (normal priority, asleep) reads its RSS meanwhile. With
    `live_port`, a client process watches the live view all along."""
    out = tmp / f"{mode}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", mode,
           "--duration", repr(duration_s), "--priority", str(priority), "--out", str(out)]
    if config is not None:
        cmd += ["--config", str(config)]
    every = 10.0 if duration_s > 600 else 1.0
    rss: list[tuple[float, int]] = []
    with open(tmp / f"{mode}.stdout", "w") as stdout, open(tmp / f"{mode}.stderr", "w+") as err:
        proc = subprocess.Popen(cmd, stdout=stdout, stderr=err, cwd=tmp, env=_CHILD_ENV)
        client = None if live_port is None else subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--client",
             f"ws://127.0.0.1:{live_port}", "30"], stdout=subprocess.PIPE, text=True)
        t0 = time.monotonic()
        while proc.poll() is None:
            kib = _rss_kib(proc.pid)
            if kib is not None:
                rss.append((time.monotonic() - t0, kib))
            if time.monotonic() - t0 > duration_s + CHILD_GRACE_S:
                proc.kill()  # a real-time process that does not end must not stay
                proc.wait()
                raise RuntimeError(f"{mode} run did not end {CHILD_GRACE_S:g} s after its "
                                   f"{duration_s:g} s; killed")
            try:
                proc.wait(timeout=every)
            except subprocess.TimeoutExpired:
                pass
        err.seek(0)
        stderr = err.read()
    watched: dict[str, int] = {}
    if client is not None:
        got, _ = client.communicate(timeout=CHILD_GRACE_S)
        watched = json.loads(got) if client.returncode == 0 else {}
    if proc.returncode != 0:
        raise RuntimeError(f"{mode} run failed ({proc.returncode}): {stderr[-2000:]}")
    return {**json.loads(out.read_text()), "rss": rss, "watched": watched}


def run_cyclictest(duration_s: float, priority: int, tmp: Path,
                interval_us: int = PERIOD_US) -> dict[str, Any]:
    """cyclictest, one thread, same policy/priority/interval, mlockall; its histogram."""
    path = tmp / "cyclictest.json"
    cmd = ["cyclictest", "--mlockall", "--policy=fifo", f"--priority={priority}",
           f"--interval={interval_us}", "--threads=1",
           f"--loops={round(duration_s * 1e6 / interval_us)}", "--quiet",
           f"--histogram={HIST_US}",
           "--default-system", f"--json={path}"]
    if os.geteuid() != 0:  # as the daemon's child would run: normal scheduling, no lock
        cmd = [c for c in cmd if c not in ("--mlockall", "--policy=fifo")
               and not c.startswith("--priority")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=duration_s * 2 + 60)
    if p.returncode != 0:
        raise RuntimeError(f"cyclictest failed ({p.returncode}): {p.stderr[-2000:]}")
    th = json.loads(path.read_text())["thread"]["0"]
    hist = [0] * (HIST_US + 1)
    for k, v in th["histogram"].items():
        hist[min(int(k), HIST_US)] += v
    hist[HIST_US] += th["cycles"] - sum(hist)  # the histogram's overflows
    return {"late_hist": hist, "late_max_ns": th["max"] * 1000, "cmd": " ".join(cmd)}


def _merge(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Several rounds of one kind of run, as one."""
    m: dict[str, Any] = dict(runs[0])
    for key in ("late_hist", "gil_late_hist", "work_cpu_hist"):
        if key in m:
            m[key] = [sum(col) for col in zip(*(r[key] for r in runs), strict=True)]
    for key in ("overruns", "samples_written", "dropped"):
        if key in m:
            m[key] = sum(r[key] for r in runs)
    if "watched" in m:
        m["watched"] = {t: sum(r["watched"].get(t, 0) for r in runs)
                        for t in set().union(*(r["watched"] for r in runs))}
    m["late_max_ns"] = max(r["late_max_ns"] for r in runs)
    if "work_cpu_mean_ns" in m:
        n = [sum(r["late_hist"]) for r in runs]
        for key in ("work_cpu_mean_ns", "period_cpu_mean_ns"):
            m[key] = sum(r[key] * k for r, k in zip(runs, n, strict=True)) / max(sum(n), 1)
        m["work_cpu_max_ns"] = max(r["work_cpu_max_ns"] for r in runs)
        m["usage"] = {k: sum(r["usage"][k] for r in runs) for k in runs[0]["usage"]}
        m["rss_runs"] = [r["rss"] for r in runs]
    m["cycles"] = sum(m["late_hist"])
    return m


def measure(quick: bool, duration_s: float | None = None) -> dict[str, Any]:
    """Every run of the plan, merged per kind."""
    pl = plan(quick, duration_s)
    prio = unit_priority()
    have_ct = shutil.which("cyclictest") is not None
    runs: dict[str, list[dict[str, Any]]] = {"cyclictest": [], "logged": [], "unlogged": [],
                                             "live": [], "bare": []}
    with tempfile.TemporaryDirectory(prefix="leveler-loop-timing-") as tmp_name:
        tmp = Path(tmp_name)
        config = _config(tmp)
        for _ in range(int(pl["rounds"])):
            if have_ct:
                runs["cyclictest"].append(run_cyclictest(pl["cyclictest"], prio, tmp))
            runs["logged"].append(_run_child("logged", pl["logged"], prio, tmp, config))
            runs["unlogged"].append(_run_child("unlogged", pl["unlogged"], prio, tmp, config))
            port = _free_port()  # a fresh one each round: no wait for the last to be freed
            runs["live"].append(_run_child("live", pl["live"], prio, tmp, _config(tmp, port),
                                           port))
            runs["bare"].append(_run_child("bare", pl["bare"], prio, tmp))
    merged: dict[str, Any] = {k: _merge(v) for k, v in runs.items() if v}
    merged.update(plan=pl, priority=prio, quick=quick)
    return merged


# ---- figures --------------------------------------------------------------------------------

def pct_us(hist: list[int], q: float) -> float:
    """The q-quantile of a 1 us histogram, read as cyclictest reads its own (bin floor)."""
    need, acc = q * sum(hist), 0
    for i, c in enumerate(hist):
        acc += c
        if acc >= need:
            return float(i)
    return float(len(hist) - 1)


def late_cycles(hist: list[int]) -> int:
    """Wake-ups more than one period late (from the 1001 us bin on, as for cyclictest)."""
    return sum(hist[PERIOD_US + 1:])


def per_1e5(count: int, cycles: int) -> float:
    return count / max(cycles, 1) * 1e5


class RssGrowth(NamedTuple):
    """VmRSS after the warm-up. RSS swings by a few hundred KiB as the allocator takes and
    returns pages, so the growth is the least-squares slope across all readings times the
    span, not the last reading minus the first (one swing would pass for a leak)."""

    fitted_kib: float  # slope x span
    span_s: float
    first_kib: int
    last_kib: int
    spread_kib: int  # max - min


def rss_growth(rss: list[tuple[float, int]]) -> RssGrowth | None:
    """The growth from the end of the warm-up (20% of the run, at least 5 s) to the last
    reading."""
    if not rss:
        return None
    end = rss[-1][0]
    warm = [s for s in rss if s[0] >= max(5.0, 0.2 * end)]
    if len(warm) < 2:
        return None
    t = np.array([s[0] for s in warm])
    kib = np.array([s[1] for s in warm])
    span = float(t[-1] - t[0])
    slope = float(np.polyfit(t, kib, 1)[0]) if span > 0 else 0.0
    return RssGrowth(slope * span, span, int(kib[0]), int(kib[-1]), int(kib.max() - kib.min()))


def rows(m: dict[str, Any]) -> list[dict[str, Any]]:
    pl, prio, judge = m["plan"], m["priority"], not m["quick"]
    lg, ul, bare, ct = m["logged"], m["unlogged"], m["bare"], m.get("cyclictest")
    lv = m["live"]
    rt = lg["rt"]
    out: list[dict[str, Any]] = []

    def add(what: str, value: float, unit: str, baseline: str = "", ratio: float | None = None,
            goal: str = "", met: bool | None = None, note: str = "") -> None:
        out.append(row(SECTION, what, value, unit, baseline=baseline, ratio=ratio, goal=goal,
                       met=met if judge else None, note=note))

    want = f"SCHED_FIFO {prio}"
    got = f"{rt['policy']} {rt['priority']}"
    add(f"real-time policy: {got}", float(rt["priority"]), "priority",
        f"unit: FIFO {prio}", None, "as the service", got == want and rt["mlockall"] == "locked",
        f"wanted {want} (CPUSchedulingPriority= of systemd/leveler.service) and mlockall; got "
        f"{got}" + (f" (sched_setscheduler: {rt['sched_error']})" if rt["sched_error"] else "")
        + f", mlockall {rt['mlockall']}; the log writer's threads at the lowest FIFO "
        f"priority, the control thread at SCHED_OTHER; one BLAS thread (OPENBLAS_NUM_THREADS=1)."
        f" {int(pl['rounds'])} round(s), one run "
        f"after another: cyclictest {pl['cyclictest']:g} s, daemon with log {pl['logged']:g} s,"
        f" without {pl['unlogged']:g} s, bare loop {pl['bare']:g} s"
        + ("" if ct else "; cyclictest not installed (apt-get install rt-tests): the rows "
           "against it are skipped"))

    n = lg["cycles"]
    lp50, lp99 = pct_us(lg["late_hist"], 0.5), pct_us(lg["late_hist"], 0.99)
    lmax = lg["late_max_ns"] / 1000
    llate = late_cycles(lg["late_hist"])
    if ct is not None:
        cp50, cp99 = pct_us(ct["late_hist"], 0.5), pct_us(ct["late_hist"], 0.99)
        cmax, cn = ct["late_max_ns"] / 1000, ct["cycles"]
        clate = late_cycles(ct["late_hist"])
        note = (f"{n} cycles of the daemon, {cn} of cyclictest ({ct['cmd']}); lateness = wake-up "
                "minus deadline")
        add("lateness p50, 1 kHz daemon, logging on", lp50, "us", f"cyclictest {cp50:g}",
            lp50 / cp50 if cp50 else None, note=note)
        r99 = lp99 / cp99 if cp99 else None
        add("lateness p99, 1 kHz daemon, logging on", lp99, "us", f"cyclictest {cp99:g}", r99,
            "<= 2.0x", r99 is not None and r99 <= 2.0)
        add("lateness max, 1 kHz daemon, logging on", lmax, "us", f"cyclictest {cmax:g}",
            lmax / cmax if cmax else None,
            note="one event each: on a shared virtual machine, mostly the host's")
        dl, cl = per_1e5(llate, n), per_1e5(clate, cn)
        rl = dl / cl if cl else None
        add("late cycles (>1 period) per 1e5, log on", dl, "per 1e5", f"cyclictest "
            f"{cl:.3g}", rl, "<= 1.0x", llate == 0 if cl == 0 else rl is not None and rl <= 1.0,
            f"{llate} of {n} cycles vs cyclictest {clate} of {cn}; the daemon's clock counted "
            f"{lg['overruns']} overruns")
    else:
        for what, v in (("lateness p50, 1 kHz daemon, logging on", lp50),
                        ("lateness p99, 1 kHz daemon, logging on", lp99),
                        ("lateness max, 1 kHz daemon, logging on", lmax)):
            add(what, v, "us", "cyclictest", note="cyclictest not installed: no baseline")
        add("late cycles (>1 period) per 1e5, log on", per_1e5(llate, n), "per 1e5",
            "cyclictest", goal="<= 1.0x", note="cyclictest not installed: no baseline")

    # What the log costs: the same daemon without it.
    up99, un = pct_us(ul["late_hist"], 0.99), ul["cycles"]
    ulate = late_cycles(ul["late_hist"])
    add("lateness p99, logging on vs off", lp99, "us", f"log off {up99:g}",
        lp99 / up99 if up99 else None,
        note=f"log off: {un} cycles, {per_1e5(ulate, un):.3g} late cycles per 1e5 ({ulate}), "
        f"max {ul['late_max_ns'] / 1000:.0f} us")
    gw, ugw = sum(lg["gil_late_hist"]), sum(ul["gil_late_hist"])
    add("woke into a held GIL, per 1e5 cycles", per_1e5(gw, n), "per 1e5",
        f"log off {per_1e5(ugw, un):.3g}", None,
        note=f"cycles that, once awake, waited for another thread's interpreter lock: {gw} of "
        f"{n} with logging on (p50 {pct_us(lg['gil_late_hist'], 0.5):g} us late; "
        f"{sum(lg['gil_late_hist'][250:])} over 250 us, {late_cycles(lg['gil_late_hist'])} "
        f"over a period), {ugw} of {un} with it off")
    # What watching costs: the same logged daemon serving a live client.
    vp99, vn = pct_us(lv["late_hist"], 0.99), lv["cycles"]
    vlate = late_cycles(lv["late_hist"])
    r = vp99 / lp99 if lp99 else None
    watched = ", ".join(f"{t} {n}" for t, n in sorted(lv["watched"].items())) or "nothing"
    add("lateness p99, live view on vs off", vp99, "us", f"live off {lp99:g}", r, "<= 1.5x",
        r is not None and r <= 1.5,
        note=f"[live] foxglove on loopback at 50 Hz, a client in another process subscribed to "
        f"every topic (messages it got: {watched}), and [epics] serving its PVs at 2 Hz; "
        f"{vn} cycles, {per_1e5(vlate, vn):.3g} late "
        f"per 1e5 ({vlate}), max {lv['late_max_ns'] / 1000:.0f} us")
    vw = lv["work_cpu_mean_ns"] / 1000
    w0 = lg["work_cpu_mean_ns"] / 1000
    rw = vw / w0 if w0 else None
    add("CPU per cycle, live view on vs off", vw, "us", f"live off {w0:.2f}", rw, "<= 1.2x",
        rw is not None and rw <= 1.2,
        note="thread CPU time around Loop.cycle, mean: the loop's own cost of a sink that "
        "appends to a deque; the publishing runs on its own thread")
    bp99, bn = pct_us(bare["late_hist"], 0.99), bare["cycles"]
    if ct is not None:
        add("lateness p99, bare Python loop", bp99, "us", f"cyclictest {cp99:g}",
            bp99 / cp99 if cp99 else None,
            note=f"RealtimeClock alone, no work: {bn} cycles, "
            f"{per_1e5(late_cycles(bare['late_hist']), bn):.3g} late per 1e5, max "
            f"{bare['late_max_ns'] / 1000:.0f} us. The floor for any Python loop on this clock")

    # CPU per cycle.
    w, bw = lg["work_cpu_mean_ns"] / 1000, bare["work_cpu_mean_ns"] / 1000
    add("CPU per cycle: read, update, write, log", w, "us", f"bare {bw:.2f}",
        w / bw if bw else None,
        note=f"thread CPU time around Loop.cycle, mean; p99 {pct_us(lg['work_cpu_hist'], 0.99):g}"
        f" us, max {lg['work_cpu_max_ns'] / 1000:.0f} us; without the log "
        f"{ul['work_cpu_mean_ns'] / 1000:.1f} us. The bare loop's figure is the "
        "instrumentation alone")
    p, bp = lg["period_cpu_mean_ns"] / 1000, bare["period_cpu_mean_ns"] / 1000
    add("loop thread CPU per period, logging on", p, "us", f"bare {bp:.1f}", p / bp if bp else None,
        note=f"everything the loop thread does in a period (clock, control socket calls, cycle, "
        f"watchdog, status): {p / PERIOD_US:.1%} of a core; the bare loop's is the clock and the "
        f"instrumentation. Loop thread page faults after start-up {lg['usage']['minflt']} "
        f"minor, {lg['usage']['majflt']} major (all runs); involuntary switches "
        f"{lg['usage']['nivcsw']}")

    # The log kept up; memory.
    add("samples logged, logging on", float(lg["samples_written"]), "samples",
        f"cycles {lg['cycles'] + int(pl['rounds'])}", None, "no drops",
        lg["dropped"] == 0, f"dropped {lg['dropped']}" + (f"; log error: {lg['log_error']}"
                                                         if lg["log_error"] else ""))
    g = max((g for g in map(rss_growth, lg["rss_runs"]) if g is not None),
            key=lambda g: g.span_s, default=None)
    if g is not None:
        rate = (f"{g.fitted_kib / 1024 / g.span_s * 3600:+.2f} MiB/h" if g.span_s >= RSS_RATE_MIN_S
                else f"a run under {RSS_RATE_MIN_S:g} s gives no hourly rate (make bench-soak)")
        add("daemon RSS growth, logging on", g.fitted_kib / 1024, "MiB",
            f"start {g.first_kib / 1024:.0f} MiB", None,
            note=f"VmRSS over {g.span_s:.0f} s of the logged run after its warm-up, least-squares "
            f"slope x span: {rate}; readings spread over {g.spread_kib / 1024:.2f} MiB, last "
            f"minus first {(g.last_kib - g.first_kib) / 1024:+.2f} MiB. With mlockall every "
            "mapping is resident, thread stacks included")
    return out


def run(quick: bool, duration_s: float | None = None) -> list[dict[str, Any]]:
    """The table's rows: quick about 25 s, full about 4 minutes, or a soak of duration_s."""
    return rows(measure(quick, duration_s))


def main(argv: list[str]) -> int:
    if argv[:1] == ["--child"]:
        return child_main(argv[1:])
    if argv[:1] == ["--client"]:
        return client_main(argv[1:])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="about 25 s instead of about 4 min")
    p.add_argument("--duration", type=float, default=None, metavar="SECONDS",
                   help="one logged run this long, with its RSS growth (soak: 3600)")
    p.add_argument("--json", type=Path, default=None, help="also write the rows to this file")
    a = p.parse_args(argv)
    if a.duration is not None and a.duration <= 0:
        p.error("--duration must be positive")
    started = time.monotonic()
    table = run(a.quick, a.duration)
    for r in table:
        ratio = f"{r['ratio']:.3g}x" if r["ratio"] is not None else "-"
        met = {True: "yes", False: "NO", None: "-"}[r["met"]]
        print(f"{r['what']:<46} {r['value']:>10.4g} {r['unit']:<9} {ratio:>7}  "
              f"{r['baseline']:<18} {r['goal']:<14} {met}")
        if r["note"]:
            print(f"      {r['note']}")
    print(f"({time.monotonic() - started:.0f} s)")
    if a.json is not None:
        a.json.write_text(json.dumps(table, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
