"""[[sim.faults]]: the simulated stand's fault schedule, apart from the stand itself so that
reading a config never imports the simulation (a hardware daemon then stays without scipy)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

FaultKind = Literal["timeout", "nan", "stuck", "railed", "spike", "write_fail", "disconnect",
                    "clock_step", "thermometer"]


@dataclass(frozen=True, slots=True)
class FaultSpec:
    """One fault of the simulated stand (`[[sim.faults]]`), from at_s for duration_s of loop
    time (0: one cycle). size: a spike's height [m], a wall-clock step [s] (the daemon
    applies those); unused by the other kinds."""

    kind: FaultKind
    at_s: float = field(default=0.0, metadata={"ge": 0.0})
    duration_s: float = field(default=0.0, metadata={"ge": 0.0})
    size: float = 0.0

    def active(self, t_s: float, dt_s: float) -> bool:
        return self.at_s <= t_s < self.at_s + max(self.duration_s, dt_s)
