"""A displacement sensor controller that answers a text query with one number per line.

The query, reply pattern, unit and line ending are configuration (`SerialSensorConfig`), so
one class serves any controller with an ASCII "measure once" command. A timeout or a reply
that does not parse raises DriverError (the loop faults); a value outside [min_m, max_m] is
a RAILED reading, which the loop logs but does not feed to the controller.
"""

from __future__ import annotations

import math
import re

from leveler.drivers.base import DriverError, Reading, Status
from leveler.drivers.piezo_serial import SerialLink
from leveler.drivers.serial_config import SerialSensorConfig

_INTEGER = re.compile(r"[-+]?[0-9]+")


class SerialSensor:
    """A `Sensor` on a serial port: query, one line back, regex, scale to metres."""

    def __init__(self, cfg: SerialSensorConfig) -> None:
        self.cfg = cfg
        self._pattern = re.compile(cfg.reply_pattern)
        self._ending = cfg.line_ending.encode("ascii")
        self._link = SerialLink(cfg, "sensor controller")

    def connect(self) -> None:
        self._link.open()

    def read(self, t_s: float) -> Reading:
        cfg = self.cfg
        line = self._link.exchange(cfg.query, self._ending, self._ending)[: -len(self._ending)]
        match = self._pattern.search(line)
        try:
            text = match.group(1) if match else ""
            value = float(text)
        except ValueError:
            raise DriverError(f"{self._link.where(cfg.query)}: unparsable reply {line!r} "
                              f"(reply_pattern {cfg.reply_pattern!r})") from None
        raw_counts = int(text) if _INTEGER.fullmatch(text) else 0
        value_m = value * cfg.scale_m_per_unit + cfg.offset_m
        if not math.isfinite(value_m):
            return Reading(t_s, raw_counts, value_m, Status.INVALID)
        railed = not cfg.min_m <= value_m <= cfg.max_m
        return Reading(t_s, raw_counts, value_m, Status.RAILED if railed else Status.OK)

    def close(self) -> None:
        self._link.close()
