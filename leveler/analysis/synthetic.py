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
from leveler.settings import Config
from leveler.sim.effects import Effect, EffectsParams
from leveler.virtual import VirtualStand


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

    def dither(actuator: Actuator) -> Actuator:
        if dither_v <= 0:
            return actuator
        return DitheredActuator(actuator, dither_v, dither_period_s, dither_shape)

    meta = {"config": nominal_text, "version": __version__, "seed": str(seed),
            "mode": "hidden-effect test data", "duration_s": repr(duration_s)}
    with (LogWriter(out, truth=True, metadata=meta) as writer,
          VirtualStand(truth, seed, sinks=[writer], wrap_actuator=dither, start_wall_ns=0) as vs):
        vs.loop.emit("start", "hidden-effect test data", vs.t_s, seed=seed)
        vs.cycle()
        vs.loop.engage(vs.t_s, "start")
        vs.run(round(duration_s / vs.dt_s) - 1, writer=writer)
        vs.loop.emit("stop", "end", vs.t_s)
