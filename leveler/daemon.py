"""`leveler run`: the foreground daemon on a real-time clock (what systemd starts).

SIGINT and SIGTERM end the loop between cycles; whatever ends it, the actuator is made
safe and the log is finished, so the last file is always complete and readable.
"""

from __future__ import annotations

import signal
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType

from leveler import __version__
from leveler.clock import RealtimeClock
from leveler.logwriter import LogWriter
from leveler.loop import Loop
from leveler.pid import PID
from leveler.settings import Config, load_config
from leveler.stand import open_stand


def log_path(cfg: Config, now: datetime | None = None) -> Path:
    """A new file per start, named by UTC start time so files sort in time order."""
    now = now or datetime.now(UTC)
    return Path(cfg.log.dir) / f"leveler-{now:%Y%m%dT%H%M%S}Z.mcap"


class _Stop:
    """Set by SIGINT/SIGTERM; checked once per cycle."""

    def __init__(self) -> None:
        self.reason = ""

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.reason = signal.Signals(signum).name


def status_line(loop: Loop, clock: RealtimeClock, cfg: Config, writer: LogWriter) -> str:
    s = loop.last
    if s is None:
        return "no sample yet"
    pend = cfg.plant.pendulum
    tilt_rad = s.sensor_m / (pend.amplification * pend.sensor_arm_m)
    st = clock.stats()
    return (
        f"t={s.t_s:9.1f} s  {s.state:<7}  sensor={s.sensor_m * 1e9:+9.2f} nm  "
        f"tilt={tilt_rad * 1e9:+8.2f} nrad  piezo={s.applied_v:7.3f} V"
        f"{' SAT' if s.saturated else ''}  period p50/p99/max="
        f"{st['period_p50_s'] * 1e3:.2f}/{st['period_p99_s'] * 1e3:.2f}/"
        f"{st['period_max_s'] * 1e3:.2f} ms  overruns={clock.overruns}  "
        f"logged={writer.samples_written}"
    )


def run_daemon(config_path: str | Path, duration_s: float | None = None) -> int:
    """Run until signalled (or for duration_s); returns the process exit code."""
    cfg, text = load_config(config_path)
    stop = _Stop()
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    stand = open_stand(cfg)
    stand.connect()
    path = log_path(cfg)
    path.parent.mkdir(parents=True, exist_ok=True)
    metadata = {"config": text, "config_path": str(Path(config_path).resolve()),
                "version": __version__, "started_utc": datetime.now(UTC).isoformat()}
    writer = LogWriter(path, metadata=metadata, chunk_interval_s=cfg.log.chunk_interval_s,
                       compression=cfg.log.compression, truth=stand.truth is not None)
    dt = 1.0 / cfg.loop.rate_hz
    pid = PID(cfg.controller.pid_config(), initial_output_v=stand.actuator.safe_v)
    loop = Loop(stand.sensor, stand.actuator, pid, dt, [writer], stand.truth)
    clock = RealtimeClock(dt)
    print(f"leveler {__version__}: {cfg.sensor.backend} backend at {cfg.loop.rate_hz:g} Hz, "
          f"logging to {path}", flush=True)
    next_status = time.monotonic() + cfg.loop.status_interval_s
    t = 0.0
    try:
        t = clock.tick()
        loop.emit("start", "daemon started", t, config=str(config_path))
        loop.cycle(t, clock.wall_ns(t))
        if cfg.loop.engage_on_start:
            loop.engage(t, "engage_on_start")
        while not stop.reason and (duration_s is None or t < duration_s):
            t = clock.tick()
            loop.cycle(t, clock.wall_ns(t))
            if time.monotonic() >= next_status:
                next_status += cfg.loop.status_interval_s
                print(status_line(loop, clock, cfg, writer), flush=True)
    finally:
        stand.actuator.make_safe()
        loop.emit("stop", stop.reason or "finished", t, overruns=clock.overruns)
        writer.close()
        stand.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(f"stopped ({stop.reason or 'finished'}): {writer.samples_written} samples in {path}",
          file=sys.stderr, flush=True)
    return 0
