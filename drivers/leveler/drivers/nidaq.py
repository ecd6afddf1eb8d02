"""NI-DAQmx analog I/O, the paper's NI PCIe/USB-6363: an AI reads the sensor, an AO drives
the piezo amplifier.

nidaqmx is an optional extra and needs NI's C runtime; both are looked for only in
connect(), so configs load and the rest of leveler runs on machines without them. Every
nidaqmx failure (package or runtime missing, a DaqError from the driver) becomes a
`DriverError` naming the channel. Tasks use on-demand timing, one sample per call when the
loop asks, as the Modbus and serial backends do. See docs/hardware.md for what of this was
tested without the hardware (the translation of a missing package or runtime) and what not.
"""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import ModuleType
from typing import Any

from leveler.drivers.base import DriverError, Reading, Status
from leveler.drivers.limits import limit_command
from leveler.drivers.nidaq_config import NidaqActuatorConfig, NidaqSensorConfig

log = logging.getLogger(__name__)

RUNTIME_HINT = ("install NI's NI-DAQmx runtime (`python -m nidaqmx installdriver`, or from "
                "ni.com; on Linux only the distributions NI supports)")
# Into the environment this daemon runs in, by its own interpreter: works for a checkout, a
# wheel and the /opt/leveler service alike (the `nidaq` extra is this one package).
INSTALL_HINT = (f"`{sys.executable} -m pip install 'nidaqmx>=1.0,<2'` (the nidaq extra; "
                f"docs/install.md), and {RUNTIME_HINT}")


def _import_nidaqmx(where: str) -> ModuleType:
    try:
        import nidaqmx
    except ImportError as exc:
        raise DriverError(f"{where}: the nidaqmx package is not installed ({exc}); "
                          f"{INSTALL_HINT}") from None
    return nidaqmx


@contextmanager
def _daq_errors(daq: ModuleType, where: str, action: str) -> Iterator[None]:
    """nidaqmx's exceptions (all derive from nidaqmx.errors.Error) as one-line DriverErrors."""
    try:
        yield
    except daq.errors.Error as exc:
        reason = " ".join(str(exc).split())  # DaqError messages span lines
        if isinstance(exc, daq.errors.DaqNotFoundError):
            reason = f"{reason.rstrip('.')}; {RUNTIME_HINT}"
        raise DriverError(f"{where}: {action}: {type(exc).__name__}: {reason}") from None


def _open_task(daq: ModuleType, where: str, add_channel: Callable[[Any], object]) -> Any:
    """A new task with one channel added by add_channel; closed again if that fails."""
    task = None
    try:
        with _daq_errors(daq, where, "create task"):
            task = daq.Task()
            add_channel(task)
    except DriverError:
        if task is not None:
            _close_task(daq, where, task)
        raise
    return task


def _close_task(daq: ModuleType, where: str, task: Any) -> None:
    try:
        with _daq_errors(daq, where, "close task"):
            task.close()
    except DriverError as exc:  # closing a task on a device that vanished: nothing to undo
        log.warning("%s", exc)


def ao_command(cfg: NidaqActuatorConfig, command_v: float, last_v: float,
               dt_s: float) -> tuple[float, float]:
    """(piezo volts, AO volts) that `NidaqActuator.write` applies for command_v, given the
    piezo's last voltage and the loop time since: NaN holds, range and slew clamp."""
    piezo_v = limit_command(command_v, last_v, dt_s, cfg.min_v, cfg.max_v, cfg.slew_v_per_s)
    return piezo_v, cfg.ao_v(piezo_v)


class NidaqSensor:
    """Displacement from one analog input (a differential AI of a 6363)."""

    def __init__(self, cfg: NidaqSensorConfig) -> None:
        self.cfg = cfg
        self.where = f"NI-DAQmx AI {cfg.channel}"
        self._daq: ModuleType | None = None
        self._task: Any = None

    def connect(self) -> None:
        self.close()
        cfg = self.cfg
        daq = self._daq = _import_nidaqmx(self.where)
        terminal = daq.constants.TerminalConfiguration[cfg.terminal_config.upper()]
        self._task = _open_task(daq, self.where, lambda task: task.ai_channels.add_ai_voltage_chan(
            cfg.channel, terminal_config=terminal, min_val=cfg.range_min_v,
            max_val=cfg.range_max_v))

    def read(self, t_s: float) -> Reading:
        cfg = self.cfg
        if self._task is None or self._daq is None:
            raise DriverError(f"{self.where}: read before connect()")
        with _daq_errors(self._daq, self.where, "read"):
            volts = float(self._task.read(timeout=cfg.timeout_s))
        value_m = cfg.volts_to_m(volts)
        if not math.isfinite(value_m):
            return Reading(t_s, 0, value_m, Status.INVALID)
        railed = not cfg.range_min_v < volts < cfg.range_max_v
        return Reading(t_s, 0, value_m, Status.RAILED if railed else Status.OK)

    def close(self) -> None:
        task, self._task = self._task, None
        if task is not None and self._daq is not None:
            _close_task(self._daq, self.where, task)


class NidaqActuator:
    """Piezo voltage through one analog output (AO0 of a 6363) and the amplifier.

    The AO's present voltage is measured through readback_channel on connect and after a
    failed write, so the slew limit starts from what the piezo really sees; the first write
    after that holds it (no loop time has passed yet).
    """

    def __init__(self, cfg: NidaqActuatorConfig) -> None:
        self.cfg = cfg
        self.where = f"NI-DAQmx AO {cfg.channel}"
        self._daq: ModuleType | None = None
        self._task: Any = None
        self._last_v: float | None = None
        self._last_t_s = math.nan

    @property
    def safe_v(self) -> float:
        return self.cfg.safe_v

    def connect(self) -> None:
        self.close()
        self._open()
        try:
            self._read_back()
        except DriverError:
            self.close()
            raise
        self._last_t_s = math.nan

    def write(self, command_v: float, t_s: float) -> float:
        if self._task is None:
            raise DriverError(f"{self.where}: write before connect()")
        if self._last_v is None:
            self._read_back()
        assert self._last_v is not None
        piezo_v, ao_v = ao_command(self.cfg, command_v, self._last_v, t_s - self._last_t_s)
        self._send(piezo_v, ao_v)
        if not (math.isnan(t_s) or t_s <= self._last_t_s):  # slew time never runs backwards
            self._last_t_s = t_s
        return piezo_v

    def make_safe(self) -> bool:
        """One attempt at safe_v at once (opening the AO task if there is none); logs
        instead of raising, since the loop calls it while already failing."""
        cfg = self.cfg
        try:
            if self._task is None:
                self._open()
            self._send(cfg.safe_v, cfg.ao_v(cfg.safe_v))
        except Exception as exc:  # the last line of defence must not raise
            log.error("%s: make_safe could not set %.3f V: %s", self.where, cfg.safe_v, exc)
            return False
        return True

    def close(self) -> None:
        task, self._task = self._task, None
        self._last_v = None
        if task is not None and self._daq is not None:
            _close_task(self._daq, self.where, task)

    def _open(self) -> None:
        cfg = self.cfg
        daq = self._daq = _import_nidaqmx(self.where)
        self._task = _open_task(daq, self.where, lambda task: task.ao_channels.add_ao_voltage_chan(
            cfg.channel, min_val=cfg.range_min_v, max_val=cfg.range_max_v))

    def _send(self, piezo_v: float, ao_v: float) -> None:
        assert self._task is not None and self._daq is not None
        try:
            with _daq_errors(self._daq, self.where, f"write {ao_v:.6f} V"):
                self._task.write(ao_v, auto_start=True, timeout=self.cfg.timeout_s)
        except DriverError:
            self._last_v = None  # it may or may not have arrived: measure it next time
            raise
        self._last_v = piezo_v

    def _read_back(self) -> None:
        """Measure the AO on a short-lived AI task, closed at once so that it does not hold
        the device's AI timing engine (the sensor's task uses it at every read)."""
        cfg, daq = self.cfg, self._daq
        assert daq is not None
        where = f"{self.where} readback {cfg.readback}"
        task = _open_task(daq, where, lambda task: task.ai_channels.add_ai_voltage_chan(
            cfg.readback, min_val=cfg.range_min_v, max_val=cfg.range_max_v))
        try:
            with _daq_errors(daq, where, "read"):
                ao_v = float(task.read(timeout=cfg.timeout_s))
        finally:
            _close_task(daq, where, task)
        if not math.isfinite(ao_v):
            raise DriverError(f"{where}: read {ao_v} V")
        # readback noise near an end of the range must not count as being outside it
        self._last_v = min(max(cfg.amplifier_gain * ao_v, cfg.min_v), cfg.max_v)
