"""`leveler sim`: the daemon's loop in virtual time, closed loop vs open loop.

Both runs see the same disturbance realization (same seed); the open-loop run holds the
piezo at its safe voltage. Spectra are read at the paper's frequencies from the in-loop
sensor and from the true platform tilt (out of loop, known only in simulation).
"""

from __future__ import annotations

import sys
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from leveler.analysis.spectral import asd_at
from leveler.log.writer import LogWriter
from leveler.loop.clock import VirtualClock
from leveler.loop.cycle import Loop, Sink
from leveler.loop.pid import PID
from leveler.records import Event, Sample, Truth
from leveler.settings import Config
from leveler.stand import open_stand

REPORT_FREQS_HZ = (1e-4, 1e-3, 1e-2)
_MAX_SIM_BACKLOG = 20_000  # records queued for the log writer before the sim waits


class Recorder:
    """In-memory sink keeping the two series the spectra need."""

    def __init__(self) -> None:
        self.sensor_m = array("d")
        self.tilt_rad = array("d")
        self.events: list[Event] = []

    def sample(self, s: Sample, log_time_ns: int) -> None:
        self.sensor_m.append(s.sensor_m)

    def truth(self, t: Truth, log_time_ns: int) -> None:
        self.tilt_rad.append(t.tilt_rad)

    def event(self, e: Event, log_time_ns: int) -> None:
        self.events.append(e)


@dataclass
class Run:
    sensor_m: np.ndarray
    tilt_rad: np.ndarray
    events: list[Event] = field(default_factory=list)


def run_virtual(cfg: Config, duration_s: float, seed: int, *, engaged: bool,
                writer: LogWriter | None = None,
                progress: Callable[[float], None] | None = None,
                start_wall_ns: int | None = None) -> Run:
    """Run the loop for duration_s of virtual time; returns the recorded series.

    Virtual time outruns any log writer, so the loop waits for the writer to catch up
    every few thousand cycles instead of letting its backlog grow (or drop records).
    """
    dt = 1.0 / cfg.loop.rate_hz
    stand = open_stand(cfg, seed)
    stand.connect()
    rec = Recorder()
    sinks: list[Sink] = [rec] if writer is None else [rec, writer]
    loop = Loop(stand.sensor, stand.actuator, PID(cfg.controller.pid_config()), dt, sinks,
                stand.truth, policy=cfg.loop)
    clock = VirtualClock(dt, start_wall_ns)
    n = round(duration_s / dt)
    report_every = max(n // 200, 1)
    try:
        t = clock.tick()
        loop.emit("start", "sim", t, engaged=engaged, seed=seed)
        loop.cycle(t, clock.wall_ns(t))
        if engaged:
            loop.engage(t, "sim start")
        for k in range(1, n):
            t = clock.tick()
            loop.cycle(t, clock.wall_ns(t))
            if k % report_every == 0:
                if writer is not None:
                    writer.wait_drained(max_backlog=_MAX_SIM_BACKLOG)
                if progress is not None:
                    progress(k / n)
        loop.emit("stop", "sim end", t)
    finally:
        stand.actuator.make_safe()
        stand.close()
    return Run(np.frombuffer(rec.sensor_m), np.frombuffer(rec.tilt_rad), rec.events)


def _asd_or_none(x: np.ndarray, fs_hz: float) -> list[float | None]:
    """ASD at each report frequency; None where the run is too short to reach it."""
    out: list[float | None] = []
    for f in REPORT_FREQS_HZ:
        try:
            out.append(float(asd_at(x, fs_hz, [f])[0]))
        except ValueError:
            out.append(None)
    return out


def spectra(run: Run, fs_hz: float) -> dict[str, list[float | None]]:
    """In-loop sensor and true-tilt ASD at REPORT_FREQS_HZ."""
    return {"sensor_m_rthz": _asd_or_none(run.sensor_m, fs_hz),
            "tilt_rad_rthz": _asd_or_none(run.tilt_rad, fs_hz)}


class ProgressBar:
    """A plain progress bar on stderr, redrawn at most a few times a second."""

    def __init__(self, label: str, total_s: float) -> None:
        self.label, self.total_s = label, total_s
        self._last = 0.0
        self._tty = sys.stderr.isatty()

    def __call__(self, frac: float) -> None:
        now = time.monotonic()
        if now - self._last < (0.25 if self._tty else 5.0) and frac < 1.0:
            return
        self._last = now
        bar = "#" * int(frac * 30)
        end = "\r" if self._tty else "\n"
        sys.stderr.write(f"{self.label} [{bar:<30}] {frac * 100:5.1f}% "
                         f"{frac * self.total_s / 3600:6.2f}/{self.total_s / 3600:.2f} h{end}")
        sys.stderr.flush()

    def done(self) -> None:
        self(1.0)
        if self._tty:
            sys.stderr.write("\n")
