"""Driver protocols: what the loop needs from a sensor and an actuator, in SI units.

Every backend (simulated plant, serial, Modbus) implements these, so switching
hardware changes configuration, not code. Drivers translate device errors into
`DriverError` at their edge; the loop turns those into a safe state.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


class DriverError(RuntimeError):
    """A device failed to connect, read or write; the message says which and why."""


class Status(enum.IntEnum):
    """Quality of one reading; anything but OK must not be fed to the controller."""

    OK = 0
    TIMEOUT = 1
    INVALID = 2
    RAILED = 3
    FAULT = 4


@dataclass(frozen=True, slots=True)
class Reading:
    """One sensor sample: loop time, raw ADC counts and the displacement they mean."""

    t_s: float
    raw_counts: int
    value_m: float
    status: Status = Status.OK


@dataclass(frozen=True, slots=True)
class Block:
    """Several conversions from one cycle (oldest first), for the loop to average down.

    With noise of about one count or more acting as dither, the mean of n conversions
    resolves steps sqrt(n) times finer than one ADC count, which a single conversion cannot.
    """

    t_s: float
    raw_counts: np.ndarray
    values_m: np.ndarray
    status: Status = Status.OK

    def mean(self) -> Reading:
        """The block as one reading: the mean displacement, the nearest whole count."""
        return Reading(self.t_s, round(float(np.mean(self.raw_counts))),
                       float(np.mean(self.values_m)), self.status)


@runtime_checkable
class Sensor(Protocol):
    """A displacement sensor read once per loop cycle (one conversion or a block of them)."""

    def connect(self) -> None: ...

    def read(self, t_s: float) -> Reading | Block: ...

    def close(self) -> None: ...


@runtime_checkable
class Actuator(Protocol):
    """A voltage-driven actuator; `make_safe` must work even after a failed write."""

    @property
    def safe_v(self) -> float: ...

    def connect(self) -> None: ...

    def write(self, command_v: float, t_s: float) -> float:
        """Command a voltage; returns the voltage actually applied (clamped, slewed)."""
        ...

    def make_safe(self) -> bool:
        """Set safe_v at once; True if the device took it. Never raises: it runs when
        something has already gone wrong, and its caller must say so if it failed."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True, slots=True)
class TemperatureReading:
    """One thermometer sample: loop time and the temperature [K]; anything but an OK status
    is no reading (the feedforward then holds)."""

    t_s: float
    temperature_k: float
    status: Status = Status.OK


@runtime_checkable
class Thermometer(Protocol):
    """The table's thermometer, read every `[thermometer] interval_s` for the temperature
    feedforward. `read_temperature`, not `read`: the simulated stand is a sensor too."""

    def connect(self) -> None: ...

    def read_temperature(self, t_s: float) -> TemperatureReading: ...

    def close(self) -> None: ...
