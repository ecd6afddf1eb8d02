"""Test data with a hidden effect: a "measured" log from a truth plant the model lacks.

The truth plant is the nominal one plus one effect (or nothing, for the null case); the
log is written by the real loop and log writer, and carries the *nominal* config as its
model, as a lab's log carries the model the lab believes. An optional square or triangle
wave on the actuator (as the paper's tilt modulation) excites actuator-side effects that
a quiet closed loop would never show.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from leveler import __version__
from leveler.drivers.base import Actuator
from leveler.log.writer import LogWriter
from leveler.loop.clock import VirtualClock
from leveler.loop.cycle import Loop
from leveler.loop.pid import PID
from leveler.settings import Config
from leveler.sim.effects import Effect, EffectsParams
from leveler.stand import open_stand


class DitheredActuator:
    """Adds a square wave to every command: excitation the log records as applied_v."""

    def __init__(self, inner: Actuator, amplitude_v: float, period_s: float,
                 shape: str = "square") -> None:
        self.inner, self.amplitude_v, self.period_s = inner, amplitude_v, period_s
        self.shape = shape

    @property
    def safe_v(self) -> float:
        return self.inner.safe_v

    def connect(self) -> None:
        self.inner.connect()

    def close(self) -> None:
        self.inner.close()

    def make_safe(self) -> bool:
        return self.inner.make_safe()

    def write(self, command_v: float, t_s: float) -> float:
        frac = math.fmod(t_s, self.period_s) / self.period_s
        if self.shape == "triangle":  # slow reversals: what shows a hysteresis loop's width
            level = 1.0 - 4.0 * abs(frac - 0.5)
        else:
            level = 1.0 if frac < 0.5 else -1.0
        return self.inner.write(command_v + self.amplitude_v * level, t_s)


def make_measured(out: str | Path, nominal: Config, nominal_text: str, effect: Effect | None,
                  *, duration_s: float, seed: int, dither_v: float = 0.0,
                  dither_period_s: float = 60.0, dither_shape: str = "square") -> None:
    """Write a closed-loop log of the truth plant (nominal + `effect`) to `out`."""
    effects = EffectsParams() if effect is None else EffectsParams().with_effect(effect)
    truth = dataclasses.replace(nominal, plant=dataclasses.replace(nominal.plant,
                                                                   effects=effects))
    dt = 1.0 / truth.loop.rate_hz
    stand = open_stand(truth, seed)
    stand.connect()
    actuator: Actuator = stand.actuator
    if dither_v > 0:
        actuator = DitheredActuator(actuator, dither_v, dither_period_s, dither_shape)
    meta = {"config": nominal_text, "version": __version__, "seed": str(seed),
            "mode": "hidden-effect test data", "duration_s": repr(duration_s)}
    with LogWriter(out, truth=True, metadata=meta) as writer:
        loop = Loop(stand.sensor, actuator, PID(truth.controller.pid_config()), dt, [writer],
                    stand.truth)
        clock = VirtualClock(dt, 0)
        n = round(duration_s / dt)
        t = clock.tick()
        loop.emit("start", "hidden-effect test data", t, seed=seed)
        loop.cycle(t, clock.wall_ns(t))
        loop.engage(t, "start")
        for k in range(1, n):
            t = clock.tick()
            loop.cycle(t, clock.wall_ns(t))
            if k % 20000 == 0:
                writer.wait_drained(max_backlog=20000)
        loop.emit("stop", "end", t)
    stand.close()
