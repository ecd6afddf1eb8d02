"""Modbus analog I/O: an AI module reads the sensor, an AO module drives the piezo amplifier.

pymodbus's synchronous clients do the framing; this module adds what the loop needs on top:
every failure becomes a `DriverError` naming link, device, register and cause, a lost link
is retried with exponential backoff without ever blocking the loop in a reconnect loop, and
the actuator enforces the piezo's range and slew limit itself (defence in depth: no command
outside them reaches the wire, whatever the controller computed).
"""

from __future__ import annotations

import logging
import math
import time
import weakref
from collections.abc import Callable
from typing import Literal

from pymodbus import FramerType, ModbusException
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from leveler.drivers.base import DriverError, Reading, Status, TemperatureReading
from leveler.drivers.limits import slew_window
from leveler.drivers.modbus_config import (
    ModbusActuatorConfig,
    ModbusChannelConfig,
    ModbusSensorConfig,
    ModbusThermometerConfig,
)

log = logging.getLogger(__name__)

EXCEPTION_MEANINGS = {
    1: "ILLEGAL_FUNCTION: the device does not support this function code",
    2: "ILLEGAL_DATA_ADDRESS: the device has no such register (check register and words)",
    3: "ILLEGAL_DATA_VALUE: the device rejected the value or count",
    4: "SLAVE_DEVICE_FAILURE: the device failed while serving the request",
    5: "ACKNOWLEDGE: the device accepted a long request and is still working on it",
    6: "SLAVE_DEVICE_BUSY: the device is busy, retry later",
    8: "MEMORY_PARITY_ERROR: the device found a parity error in its memory",
    10: "GATEWAY_PATH_UNAVAILABLE: the gateway has no path to the device",
    11: "GATEWAY_TARGET_FAILED_TO_RESPOND: the device behind the gateway did not answer",
}


class ModbusLink:
    """One Modbus client with reconnect backoff.

    After a failure the link closes. The first failure after good replies is taken for a
    glitch (a garbled frame, a lost packet): the next call reconnects at once, so the loop
    rides through it. Further failures wait reconnect_min_s, doubling up to reconnect_max_s;
    a call during the wait fails at once instead of blocking. A call
    blocks at most about timeout_s x (retries + 1), plus timeout_s for a reconnect attempt.
    """

    def __init__(self, cfg: ModbusChannelConfig,
                 clock_s: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self._client = _make_client(cfg)
        if cfg.transport == "rtu":
            _rtu_links.add(self)
        self._clock_s = clock_s
        self._backoff_s = 0.0
        self._answered = False  # the device has answered since the last failure
        self._retry_at_s = -math.inf
        self._last_error = "not connected yet"

    def connect(self) -> None:
        self._ensure(force=True)

    def close(self) -> None:
        self._client.close()

    def read(self, kind: Literal["input", "holding"], address: int, count: int,
             *, force: bool = False) -> list[int]:
        """Read `count` registers; `force` skips a pending backoff wait (one attempt)."""
        fn = (self._client.read_input_registers if kind == "input"
              else self._client.read_holding_registers)
        what = f"read {kind} register {address} ({count} word{'s' * (count > 1)})"
        response = self._call(what, force, lambda: fn(address, count=count,
                                                      device_id=self.cfg.device_id))
        registers = list(response.registers)
        if len(registers) != count:
            raise DriverError(f"{self.cfg.where}: {what}: malformed reply with "
                              f"{len(registers)} registers")
        return registers

    def write(self, address: int, values: list[int], *, force: bool = False) -> None:
        what = f"write holding register {address} = {values}"
        self._call(what, force, lambda: self._client.write_registers(
            address, values, device_id=self.cfg.device_id))

    def _call(self, what: str, force: bool, request: Callable[[], ModbusPDU]) -> ModbusPDU:
        self._ensure(force)
        try:
            response = request()
        except (ModbusException, OSError) as exc:
            self._fail(self._describe(exc))
            raise DriverError(f"{self.cfg.where}: {what}: {self._last_error}; "
                              f"reconnecting {self._when()}") from None
        self._backoff_s = 0.0  # the device answered: the link is good
        self._answered = True
        if response.isError():
            code = response.exception_code
            meaning = EXCEPTION_MEANINGS.get(code, "unknown exception code")
            raise DriverError(f"{self.cfg.where}: {what}: Modbus exception {code} ({meaning})")
        return response

    def _ensure(self, force: bool) -> None:
        if self._client.connected:
            return
        wait_s = self._retry_at_s - self._clock_s()
        if wait_s > 0 and not force:
            raise DriverError(f"{self.cfg.where}: disconnected ({self._last_error}); "
                              f"next reconnect attempt in {wait_s:.2f} s")
        if not self._client.connect():
            self._fail("cannot connect (refused, unreachable or no such port)")
            raise DriverError(f"{self.cfg.where}: {self._last_error}; "
                              f"retrying {self._when()}")

    def _fail(self, reason: str) -> None:
        self._client.close()  # a late reply must not be taken for the next request's
        cfg = self.cfg
        if self._answered:  # the first failure after good replies: a glitch, retry at once
            self._answered = False
            self._backoff_s = 0.0
        else:
            self._backoff_s = min(max(2.0 * self._backoff_s, cfg.reconnect_min_s),
                                  cfg.reconnect_max_s)
        self._retry_at_s = self._clock_s() + self._backoff_s
        self._last_error = reason

    def _when(self) -> str:
        return f"in {self._backoff_s:.2f} s" if self._backoff_s else "at the next request"

    def _describe(self, exc: Exception) -> str:
        if isinstance(exc, ModbusIOException):
            tries = self.cfg.retries + 1
            return (f"no valid reply within {self.cfg.timeout_s} s "
                    f"({tries} tr{'ies' if tries > 1 else 'y'}): {exc}")
        if isinstance(exc, ConnectionException):
            return f"connection lost: {exc}"
        return f"{type(exc).__name__}: {exc}"


# The live RTU links: channels on one serial port share its client (an AI and an AO module on
# one RS-485 line, or one module serving both). pyserial opens a port for exclusive use, so a
# second client could not connect, and two readers would steal each other's replies. A failure
# on one channel closes the line for both; the other reopens it on its next call (its own
# backoff). Links, not clients, are tracked: a client sits in a reference cycle and outlives
# its last link until the garbage collector runs.
_rtu_links: weakref.WeakSet[ModbusLink] = weakref.WeakSet()
_LINE_SETTINGS = ("baudrate", "timeout_s", "retries")  # the client's, so shared


def _make_client(cfg: ModbusChannelConfig) -> ModbusTcpClient | ModbusSerialClient:
    if cfg.transport == "tcp":
        return ModbusTcpClient(cfg.host, port=cfg.port, timeout=cfg.timeout_s,
                               retries=cfg.retries)
    for other in _rtu_links:
        if other.cfg.serial_port != cfg.serial_port:
            continue
        theirs = [getattr(other.cfg, key) for key in _LINE_SETTINGS]
        ours = [getattr(cfg, key) for key in _LINE_SETTINGS]
        if theirs != ours:
            raise ValueError(f"{cfg.where}: another channel on this serial port has "
                             f"{', '.join(_LINE_SETTINGS)} = {theirs}, this one {ours}; "
                             "channels sharing a line must agree")
        return other._client
    return ModbusSerialClient(cfg.serial_port, framer=FramerType.RTU, baudrate=cfg.baudrate,
                              timeout=cfg.timeout_s, retries=cfg.retries)


class _AnalogInput:
    """One analog input channel on its own link: what the sensor and the thermometer share."""

    def __init__(self, cfg: ModbusSensorConfig | ModbusThermometerConfig) -> None:
        self._link = ModbusLink(cfg)

    def connect(self) -> None:
        self._link.connect()

    def close(self) -> None:
        self._link.close()

    def _counts(self, cfg: ModbusSensorConfig | ModbusThermometerConfig) -> tuple[int, Status]:
        """The channel's counts, railed at either end of its range."""
        counts = cfg.decode(self._link.read(cfg.register_kind, cfg.register, cfg.words))
        railed = counts <= cfg.counts_min or counts >= cfg.counts_max
        return counts, Status.RAILED if railed else Status.OK


class ModbusSensor(_AnalogInput):
    """Displacement from an analog input module (ADAM-6017 style)."""

    def __init__(self, cfg: ModbusSensorConfig) -> None:
        super().__init__(cfg)
        self.cfg = cfg

    def read(self, t_s: float) -> Reading:
        counts, status = self._counts(self.cfg)
        return Reading(t_s, counts, self.cfg.counts_to_m(counts), status)


class ModbusThermometer(_AnalogInput):
    """The table's temperature from an analog input (a PT100 transmitter's output)."""

    def __init__(self, cfg: ModbusThermometerConfig) -> None:
        super().__init__(cfg)
        self.cfg = cfg

    def read_temperature(self, t_s: float) -> TemperatureReading:
        counts, status = self._counts(self.cfg)
        return TemperatureReading(t_s, self.cfg.counts_to_k(counts), status)


class ModbusActuator:
    """Piezo voltage through an analog output module (ADAM-6024 style) and an amplifier.

    The AO's present value is read back on connect and after a failed write, so the slew
    limit starts from what the piezo really sees. The first write after that holds it
    (no time has passed yet); later ones move at most slew_v_per_s x elapsed loop time.
    """

    def __init__(self, cfg: ModbusActuatorConfig) -> None:
        self.cfg = cfg
        self._link = ModbusLink(cfg)
        self._last_counts: int | None = None
        self._last_t_s = math.nan

    @property
    def safe_v(self) -> float:
        return self.cfg.safe_v

    def connect(self) -> None:
        self._link.connect()
        self._read_back(force=True)
        self._last_t_s = math.nan

    def write(self, command_v: float, t_s: float) -> float:
        cfg = self.cfg
        if self._last_counts is None:
            self._read_back(force=False)
        assert self._last_counts is not None
        last_v = cfg.counts_to_piezo_v(self._last_counts)
        lo, hi = slew_window(last_v, t_s - self._last_t_s, cfg.min_v, cfg.max_v,
                             cfg.slew_v_per_s)
        counts = self._quantize(last_v if math.isnan(command_v) else command_v, lo, hi)
        self._send(counts, force=False)
        if not (math.isnan(t_s) or t_s <= self._last_t_s):  # slew time never runs backwards
            self._last_t_s = t_s
        return cfg.counts_to_piezo_v(counts)

    def make_safe(self) -> bool:
        """One attempt at safe_v, even during a reconnect wait; logs instead of raising."""
        cfg = self.cfg
        try:
            self._send(self._quantize(cfg.safe_v, cfg.min_v, cfg.max_v), force=True)
        except Exception as exc:  # the loop calls this while already failing: never raise
            log.error("%s: make_safe could not set %.3f V: %s", cfg.where, cfg.safe_v, exc)
            return False
        return True

    def close(self) -> None:
        self._link.close()

    def _quantize(self, target_v: float, lo: float, hi: float) -> int:
        """Counts nearest target_v whose voltage lies in [lo, hi]; else hold the last counts."""
        cfg = self.cfg
        x = cfg.piezo_v_to_counts(min(max(target_v, lo), hi))
        for counts in (round(x), math.floor(x), math.ceil(x)):
            if (cfg.counts_min <= counts <= cfg.counts_max
                    and lo <= cfg.counts_to_piezo_v(counts) <= hi):
                return counts
        assert self._last_counts is not None  # [min_v, max_v] spans a count: only slew ends here
        return self._last_counts

    def _send(self, counts: int, force: bool) -> None:
        cfg = self.cfg
        try:
            self._link.write(cfg.register, cfg.encode(counts), force=force)
        except DriverError:
            self._last_counts = None  # it may or may not have arrived: read back next time
            raise
        self._last_counts = counts

    def _read_back(self, force: bool) -> None:
        cfg = self.cfg
        self._last_counts = cfg.decode(self._link.read("holding", cfg.register, cfg.words,
                                                       force=force))
