"""The loop in virtual time against the simulated stand: the one harness that `leveler sim`,
`leveler modulate --sim`, the synthetic logs of the analysis tests and the benchmarks run.

It is the daemon's own loop, drivers and PID, with a `VirtualClock` instead of the real-time
one, so every simulated figure is a figure of the code that runs the stand. Virtual time
outruns any log writer: a run given a writer waits for it every few thousand cycles rather
than letting its backlog grow (or drop records).
"""

from __future__ import annotations

from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from leveler.drivers.base import Actuator
from leveler.log.writer import LogWriter
from leveler.loop.clock import VirtualClock
from leveler.loop.cycle import Loop, Sink
from leveler.loop.pid import PID
from leveler.records import Event, Sample, Truth
from leveler.settings import Config
from leveler.stand import open_stand

_PACE_EVERY = 20_000  # cycles between waits for a log writer, and its allowed backlog


class Recorder:
    """In-memory sink: sample times, reading, applied voltage, true tilt, events."""

    def __init__(self) -> None:
        self.t_s = array("d")
        self.sensor_m = array("d")
        self.applied_v = array("d")
        self.tilt_rad = array("d")
        self.events: list[Event] = []

    def sample(self, s: Sample, log_time_ns: int) -> None:
        self.t_s.append(s.t_s)
        self.sensor_m.append(s.sensor_m)
        self.applied_v.append(s.applied_v)

    def truth(self, t: Truth, log_time_ns: int) -> None:
        self.tilt_rad.append(t.tilt_rad)

    def event(self, e: Event, log_time_ns: int) -> None:
        self.events.append(e)


@dataclass
class Run:
    """What a run recorded, as numpy views of the recorder's arrays."""

    t_s: np.ndarray
    sensor_m: np.ndarray
    applied_v: np.ndarray
    tilt_rad: np.ndarray
    events: list[Event] = field(default_factory=list)


class VirtualStand:
    """The stand a config describes (backend "sim"), its loop and a virtual clock.

    `wrap_actuator` lets a caller put something between the loop and the piezo (the
    synthetic logs' dither); `sinks` receive every record besides the recorder. Use as a
    context manager: leaving it puts the actuator in its safe state and closes the stand.
    """

    def __init__(self, cfg: Config, seed: int, *, sinks: Sequence[Sink] = (),
                 wrap_actuator: Callable[[Actuator], Actuator] | None = None,
                 start_wall_ns: int | None = None) -> None:
        self.dt_s = 1.0 / cfg.loop.rate_hz
        self.stand = open_stand(cfg, seed)
        self.stand.connect()
        actuator = self.stand.actuator if wrap_actuator is None else wrap_actuator(
            self.stand.actuator)
        self.recorder = Recorder()
        self.loop = Loop(self.stand.sensor, actuator, PID(cfg.controller.pid_config()),
                         self.dt_s, [self.recorder, *sinks], self.stand.truth, policy=cfg.loop)
        self.clock = VirtualClock(self.dt_s, start_wall_ns)
        self.t_s = self.clock.tick()

    def __enter__(self) -> VirtualStand:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stand.actuator.make_safe()
        self.stand.close()

    def cycle(self) -> Sample:
        """One cycle at the present time; `step` advances the clock first."""
        return self.loop.cycle(self.t_s, self.clock.wall_ns(self.t_s))

    def tick(self) -> float:
        """Advance the clock one period (a procedure may act between tick and cycle)."""
        self.t_s = self.clock.tick()
        return self.t_s

    def step(self) -> Sample:
        self.tick()
        return self.cycle()

    def run(self, cycles: int, *, writer: LogWriter | None = None,
            progress: Callable[[float], None] | None = None) -> None:
        """`cycles` steps, pacing to `writer` and reporting the fraction done to `progress`."""
        every = max(min(cycles // 200, _PACE_EVERY), 1)
        for k in range(1, cycles + 1):
            self.step()
            if k % every == 0:
                if writer is not None:
                    writer.wait_drained(max_backlog=_PACE_EVERY)
                if progress is not None:
                    progress(k / cycles)
        if progress is not None:
            progress(1.0)

    def recorded(self, first: int = 0) -> Run:
        """The recorded series from sample `first` on."""
        r = self.recorder
        return Run(*(np.frombuffer(a)[first:] for a in (r.t_s, r.sensor_m, r.applied_v,
                                                         r.tilt_rad)), r.events)


def run_virtual(cfg: Config, duration_s: float, seed: int, *, engaged: bool,
                writer: LogWriter | None = None,
                progress: Callable[[float], None] | None = None,
                start_wall_ns: int | None = None) -> Run:
    """`leveler sim`'s run: duration_s of virtual time, closed loop or open (the piezo at
    its safe voltage), with every record to `writer` if given."""
    sinks = [] if writer is None else [writer]
    with VirtualStand(cfg, seed, sinks=sinks, start_wall_ns=start_wall_ns) as vs:
        vs.loop.emit("start", "sim", vs.t_s, engaged=engaged, seed=seed)
        vs.cycle()
        if engaged:
            vs.loop.engage(vs.t_s, "sim start")
        vs.run(round(duration_s / vs.dt_s) - 1, writer=writer, progress=progress)
        vs.loop.emit("stop", "sim end", vs.t_s)
        return vs.recorded()

