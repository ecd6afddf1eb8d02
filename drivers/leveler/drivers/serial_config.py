"""Configuration of the serial drivers: the `[actuator.serial]` and `[sensor.serial]` tables.

Frozen dataclasses like every other config section (`leveler.typed_config.build` walks their
fields and checks the metadata bounds); the cross-field checks live in `__post_init__`, so
a config that would make a driver unsafe cannot even be constructed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Literal

from leveler.typed_config import positive

PiezoProtocol = Literal["thorlabs_mdt", "pi_gcs2"]


@dataclass(frozen=True, slots=True)
class SerialPortConfig:
    """One serial port, 8N1 without flow control (what both device families use)."""

    port: str = ""
    baudrate: int = field(default=115200, metadata={"gt": 0})
    timeout_s: float = positive(0.2)


@dataclass(frozen=True, slots=True)
class SerialPiezoConfig(SerialPortConfig):
    """A piezo amplifier on a serial port.

    min_v/max_v/slew_v_per_s are the driver's own limits, enforced before anything reaches
    the wire, independent of the controller's limits and the amplifier's (defence in depth).
    axis: "x", "y" or "z" for Thorlabs; the GCS axis id (e.g. "1") for PI.
    """

    protocol: PiezoProtocol = "thorlabs_mdt"
    axis: str = "x"
    min_v: float = 0.0
    max_v: float = 150.0
    slew_v_per_s: float = positive(10.0)
    safe_v: float = 75.0

    def __post_init__(self) -> None:
        if not self.min_v < self.max_v:
            raise ValueError(f"min_v ({self.min_v} V) must be below max_v ({self.max_v} V)")
        if not self.min_v <= self.safe_v <= self.max_v:
            raise ValueError(
                f"safe_v ({self.safe_v} V) must lie in [min_v, max_v] = "
                f"[{self.min_v}, {self.max_v}] V")
        if self.protocol == "thorlabs_mdt" and self.axis not in ("x", "y", "z"):
            raise ValueError(f"axis {self.axis!r}: a Thorlabs MDT axis is 'x', 'y' or 'z'")
        if not self.axis or any(c.isspace() for c in self.axis):
            raise ValueError(f"axis {self.axis!r}: must be a non-empty word")


@dataclass(frozen=True, slots=True)
class SerialSensorConfig(SerialPortConfig):
    """A sensor controller that answers a text query with one number per line.

    metres = number * scale_m_per_unit + offset_m; a value outside [min_m, max_m] is
    reported RAILED (the default range is the simulated stand's +-10 V ADC at 2e5 V/m).
    """

    query: str = "MEAS?"
    reply_pattern: str = r"^\s*([-+0-9.eE]+)\s*$"
    line_ending: str = "\r\n"
    scale_m_per_unit: float = positive(1e-6)
    offset_m: float = 0.0
    min_m: float = -5e-5
    max_m: float = 5e-5

    def __post_init__(self) -> None:
        if not self.query.strip():
            raise ValueError("query must not be empty")
        if not self.line_ending:
            raise ValueError("line_ending must not be empty")
        try:
            groups = re.compile(self.reply_pattern).groups
        except re.error as exc:
            raise ValueError(f"reply_pattern {self.reply_pattern!r}: {exc}") from None
        if groups < 1:
            raise ValueError(
                f"reply_pattern {self.reply_pattern!r} needs a group (...) around the number")
        if not self.min_m < self.max_m:
            raise ValueError(f"min_m ({self.min_m} m) must be below max_m ({self.max_m} m)")
