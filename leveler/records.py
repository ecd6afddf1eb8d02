"""The records one loop cycle produces, as flat slotted classes.

They are built once per cycle on the loop thread and handed to the logger as they are,
so they stay small, typed and cheap; field names are the log's JSON keys
(see docs/log-format.md), units in the names.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(slots=True)
class Sample:
    """Everything the loop knew and did in one cycle."""

    seq: int
    t_s: float
    raw_counts: int
    sensor_m: float
    status: int
    setpoint_m: float
    error_m: float
    p_v: float
    i_v: float
    d_v: float
    command_v: float
    applied_v: float
    saturated: bool
    state: str


@dataclass(slots=True)
class Truth:
    """What only a simulation knows: the true state behind the sensor reading."""

    seq: int
    t_s: float
    tilt_rad: float
    thermal_tilt_rad: float
    cooler_tilt_rad: float
    piezo_tilt_rad: float
    pendulum_rad: float
    temperature_k: float
    sensor_drift_m: float


@dataclass(slots=True)
class Event:
    """A discrete happening: start/stop, a gain change, a fault, a state transition."""

    t_s: float
    kind: str
    reason: str
    detail: dict[str, object]


@dataclass(slots=True)
class Environment:
    """A measured condition of the stand's surroundings, e.g. the table's temperature.

    Replay and diagnose use it as a model input (thermal tilt). The daemon writes one at
    each thermometer reading (its seq is that cycle's; it holds until the next), imported
    logs one per row. `feedforward_v` is what the temperature feedforward adds to the
    command from then on while the loop is engaged (0 without one; older logs lack it).
    """

    seq: int
    t_s: float
    temperature_k: float
    feedforward_v: float = 0.0


@dataclass(slots=True)
class ThrustStand:
    """One sample of a torsion-pendulum thrust stand recorded beside (or without) the leveler.

    `leveler analyze stiffness LOG` fits the stand's stiffness and its tilt coupling from these;
    only imported logs carry them so far (`import-csv` roles thrust, displacement, tilt).
    """

    seq: int
    t_s: float
    thrust_n: float
    displacement_m: float
    tilt_rad: float  # NaN when the recording has no tilt column
