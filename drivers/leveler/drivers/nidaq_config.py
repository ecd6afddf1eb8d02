"""Configuration of NI-DAQmx analog channels (`[sensor.nidaq]`, `[actuator.nidaq]`), in SI units.

Frozen dataclasses like every other config section: `leveler.typed_config.build` checks types and
the metadata bounds, `__post_init__` the cross-field rules, so a config that would let the
driver put the piezo outside its range cannot be constructed. Nothing here needs nidaqmx,
so a config is checked on any machine, with or without the NI driver.

DAQmx scales to volts itself (with the board's calibration), so unlike Modbus there are no
counts to configure: only the channel's voltage range, which also picks the ADC gain.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from leveler.drivers.limits import check_piezo_range
from leveler.typed_config import positive

# One physical channel, "device/line": no lists ("a,b") or ranges ("ai0:3"), which would
# make DAQmx read or write several channels at once.
_CHANNEL = re.compile(r"[^/\s,:]+/[^/\s,:]+")
_AO_LINE = re.compile(r"ao[0-9]+")

TerminalConfig = Literal["diff", "rse", "nrse", "pseudo_diff"]


@dataclass(frozen=True, slots=True)
class NidaqChannelConfig:
    """One DAQmx voltage channel: where it is, its range, and how long a call may block."""

    channel: str = "Dev1/ai0"
    range_min_v: float = -10.0
    range_max_v: float = 10.0
    timeout_s: float = positive(0.05)

    def __post_init__(self) -> None:
        _check_channel("channel", self.channel)
        if not self.range_min_v < self.range_max_v:
            raise ValueError(f"range_min_v ({self.range_min_v} V) must be below "
                             f"range_max_v ({self.range_max_v} V)")

    @property
    def device(self) -> str:
        return self.channel.split("/", 1)[0]


@dataclass(frozen=True, slots=True)
class NidaqSensorConfig(NidaqChannelConfig):
    """An analog input reading the displacement sensor controller's voltage.

    Readings at or beyond range_min_v/range_max_v are RAILED: the ADC range DAQmx picks
    covers at least that span, so outside it the voltage no longer means a position.
    """

    terminal_config: TerminalConfig = "diff"
    m_per_v: float = positive(5.0e-6)
    offset_m: float = 0.0

    def __post_init__(self) -> None:
        NidaqChannelConfig.__post_init__(self)

    def volts_to_m(self, volts: float) -> float:
        return self.offset_m + self.m_per_v * volts


@dataclass(frozen=True, slots=True)
class NidaqActuatorConfig(NidaqChannelConfig):
    """An analog output driving the piezo amplifier's input; limits are in piezo volts.

    readback_channel is the AI that measures the AO, so the slew limit starts from what the
    piezo really sees; "" means the X Series internal channel `<device>/_aoN_vs_aognd`.
    """

    channel: str = "Dev1/ao0"
    range_min_v: float = 0.0
    range_max_v: float = 10.0
    readback_channel: str = ""
    amplifier_gain: float = positive(15.0)
    min_v: float = 0.0
    max_v: float = 150.0
    slew_v_per_s: float = positive(100.0)
    safe_v: float = 75.0

    def __post_init__(self) -> None:
        NidaqChannelConfig.__post_init__(self)
        if self.readback_channel:
            _check_channel("readback_channel", self.readback_channel)
        elif not _AO_LINE.fullmatch(self.channel.split("/", 1)[1]):
            raise ValueError(f"readback_channel: cannot derive an internal channel from "
                             f"channel {self.channel!r}; name the AI that measures the AO")
        check_piezo_range(self.min_v, self.max_v, self.safe_v, self.amplifier_gain,
                          self.range_min_v, self.range_max_v, "range_min_v..range_max_v is")

    @property
    def readback(self) -> str:
        """The AI channel read at connect to learn the AO's present voltage."""
        return self.readback_channel or f"{self.device}/_{self.channel.split('/', 1)[1]}_vs_aognd"

    def ao_v(self, piezo_v: float) -> float:
        """AO volts for a piezo voltage in [min_v, max_v], kept inside the AO range (DAQmx
        refuses a write outside it) against the rounding of the division."""
        return min(max(piezo_v / self.amplifier_gain, self.range_min_v), self.range_max_v)


def _check_channel(key: str, channel: str) -> None:
    if not _CHANNEL.fullmatch(channel):
        raise ValueError(f"{key} {channel!r}: expected one physical channel 'device/line', "
                         "e.g. 'Dev1/ai0'")
