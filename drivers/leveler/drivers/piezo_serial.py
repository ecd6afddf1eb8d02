"""Piezo amplifiers over a serial port: Thorlabs MDT693B/694B and PI E-709/E-727 (GCS 2.0).

What the protocols here rest on (shared/reference/DEVICES.md and public open-source drivers;
none of it was tried against real hardware):

- Thorlabs MDT69xB: 115200 8N1, ASCII commands ended by CR; `xvoltage=V` sets, `xvoltage?`
  and `vlimit?` answer bracketed numbers (`[ 12.50]`, `[ 150]`); every reply ends with the
  prompt `>`, and with echo on (the 694B's default) the command comes back first, so an
  echo is accepted but not required. An unknown command answers `CMD_NOT_DEFINED`. One
  public trace shows `*` where the manual says `>`: if a real unit does that, `prompt` is
  the one line to change.
- PI GCS 2.0: ASCII ended by LF; `SVA <axis> <v>` sets the open-loop value and answers
  nothing; `SVA? <axis>` answers `<axis>=<v>`; `ERR?` answers the sticky error code (0 =
  fine) and clears it. There is no voltage-limit query in the core set we rely on, so
  `connect` cannot check the amplifier's range against max_v for PI.

Checking every write: Thorlabs answers every command anyway (echo and prompt). For PI we send
`SVA ...` and `ERR?` in one write and read the one-line answer, so every write is verified
for the price of a few bytes, not a second round trip: at 10 Hz a refused command is known
within the same cycle rather than N cycles later.

Voltages go on the wire with 1 mV resolution, rounded towards the previous voltage so that
rounding can never push a command past the range or the slew limit.
"""

from __future__ import annotations

import abc
import logging
import math
import re
import termios
from typing import ClassVar

import serial

from leveler.drivers.base import DriverError
from leveler.drivers.serial_config import SerialPiezoConfig, SerialPortConfig

log = logging.getLogger(__name__)

_STEPS_PER_V = 1000  # 1 mV on the wire
_NUMBER = r"([-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)"


class SerialLink:
    """One serial port and a command/reply exchange with a deadline.

    Every failure (cannot open, OSError, timeout, a reply cut short, non-ASCII bytes) becomes
    a DriverError naming the device, port, command and what came back, so the loop can log
    it as it is.
    """

    def __init__(self, cfg: SerialPortConfig, device: str) -> None:
        self.cfg = cfg
        self.device = device
        self._port: serial.Serial | None = None

    def where(self, command: str) -> str:
        return f"{self.device} on {self.cfg.port or '(no port)'}, command {command!r}"

    def open(self) -> None:
        self.close()
        if not self.cfg.port:
            raise DriverError(f"{self.device}: no serial port configured (port = \"\")")
        try:
            self._port = serial.Serial(self.cfg.port, self.cfg.baudrate,
                                       timeout=self.cfg.timeout_s,
                                       write_timeout=self.cfg.timeout_s)
        except (OSError, ValueError) as exc:
            raise DriverError(f"{self.device} on {self.cfg.port}: cannot open: {exc}") from None

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (OSError, termios.error) as exc:  # closing a port whose device vanished
                log.warning("%s on %s: close failed: %s", self.device, self.cfg.port, exc)

    def exchange(self, command: str, ending: bytes, reply_end: bytes) -> str:
        """Send command + ending; return the reply up to and including reply_end."""
        if self._port is None:
            raise DriverError(f"{self.where(command)}: port not open (connect() first)")
        try:
            self._port.reset_input_buffer()  # whatever a timed-out reply left behind
            self._port.write(command.encode("ascii") + ending)
            data = self._port.read_until(reply_end)
        except (OSError, termios.error) as exc:  # a vanished pty fails in tcflush (termios)
            raise DriverError(f"{self.where(command)}: {exc}") from None
        if not data.endswith(reply_end):
            got = f"incomplete reply {data!r}" if data else "no reply"
            raise DriverError(f"{self.where(command)}: {got} within {self.cfg.timeout_s} s")
        try:
            return data.decode("ascii")
        except UnicodeDecodeError:
            raise DriverError(f"{self.where(command)}: garbled reply {data!r}") from None


class CommandSet(abc.ABC):
    """One amplifier protocol: how to identify, limit-check, set and read back a voltage."""

    @abc.abstractmethod
    def identify(self, link: SerialLink) -> str: ...

    def limit_v(self, link: SerialLink, axis: str) -> float | None:
        """The amplifier's own output limit, or None if the protocol cannot tell."""
        return None

    @abc.abstractmethod
    def set_v(self, link: SerialLink, axis: str, volts: str) -> None:
        """Set the voltage (already formatted); raise DriverError unless the device agrees."""

    @abc.abstractmethod
    def read_v(self, link: SerialLink, axis: str) -> float: ...


class ThorlabsMDT(CommandSet):
    """Thorlabs MDT693B/MDT694B: CR-ended commands, replies ending in a `>` prompt."""

    ending: ClassVar[bytes] = b"\r"
    prompt: ClassVar[bytes] = b">"
    _bracketed = re.compile(rf"\[\s*{_NUMBER}\s*\]")

    def _ask(self, link: SerialLink, command: str) -> list[str]:
        """The reply's non-empty lines, echo and prompt removed."""
        reply = link.exchange(command, self.ending, self.prompt)[: -len(self.prompt)]
        lines = [s.strip() for s in re.split(r"[\r\n]+", reply) if s.strip()]
        if lines and lines[0] == command:
            lines = lines[1:]
        if any("CMD_NOT_DEFINED" in s for s in lines):
            raise DriverError(f"{link.where(command)}: device refused it: {reply!r}")
        return lines

    def _number(self, link: SerialLink, command: str) -> float:
        lines = self._ask(link, command)
        match = self._bracketed.fullmatch(lines[0]) if len(lines) == 1 else None
        if match is None:
            raise DriverError(f"{link.where(command)}: expected '[ <number>]', got {lines!r}")
        return float(match.group(1))

    def identify(self, link: SerialLink) -> str:
        return " / ".join(self._ask(link, "id?"))

    def limit_v(self, link: SerialLink, axis: str) -> float | None:
        return self._number(link, "vlimit?")

    def set_v(self, link: SerialLink, axis: str, volts: str) -> None:
        command = f"{axis}voltage={volts}"
        lines = self._ask(link, command)
        if lines:
            raise DriverError(f"{link.where(command)}: unexpected reply {lines!r}")

    def read_v(self, link: SerialLink, axis: str) -> float:
        return self._number(link, f"{axis}voltage?")


class PIGCS2(CommandSet):
    """PI E-709/E-727 in GCS 2.0: LF-ended lines; `SVA` checked by `ERR?` in the same write."""

    ending: ClassVar[bytes] = b"\n"

    def _line(self, link: SerialLink, command: str) -> str:
        return link.exchange(command, self.ending, self.ending).strip()

    def identify(self, link: SerialLink) -> str:
        return self._line(link, "*IDN?")

    def set_v(self, link: SerialLink, axis: str, volts: str) -> None:
        command = f"SVA {axis} {volts}\nERR?"
        code = self._line(link, command)
        if code != "0":
            what = f"device error {code}" if code.isdigit() else f"unexpected reply {code!r}"
            raise DriverError(f"{link.where(command)}: {what}")

    def read_v(self, link: SerialLink, axis: str) -> float:
        command = f"SVA? {axis}"
        line = self._line(link, command)
        match = re.fullmatch(rf"{re.escape(axis)}={_NUMBER}", line)
        if match is None:
            raise DriverError(f"{link.where(command)}: expected '{axis}=<number>', got {line!r}")
        return float(match.group(1))


COMMAND_SETS: dict[str, type[CommandSet]] = {"thorlabs_mdt": ThorlabsMDT, "pi_gcs2": PIGCS2}


def _towards(v: float, ref: float) -> float:
    """v on the wire's 1 mV grid, rounded towards ref (never past v). A v already on the
    grid stays there: 64.88 * 1000 is 64879.99999999999 in binary."""
    steps = v * _STEPS_PER_V
    nearest = round(steps)
    if abs(steps - nearest) < 1e-9:
        return nearest / _STEPS_PER_V
    return (math.floor(steps) if v >= ref else math.ceil(steps)) / _STEPS_PER_V


class SerialPiezo:
    """An `Actuator` on a serial piezo amplifier, with its own range and slew limits."""

    def __init__(self, cfg: SerialPiezoConfig, commands: CommandSet | None = None) -> None:
        self.cfg = cfg
        self.commands = commands or COMMAND_SETS[cfg.protocol]()
        self._link = SerialLink(cfg, f"piezo amplifier ({cfg.protocol})")
        self._last_v: float | None = None
        self._last_t_s: float | None = None

    @property
    def safe_v(self) -> float:
        return self.cfg.safe_v

    @property
    def last_v(self) -> float | None:
        """The last voltage sent (or read back by connect): the slew limit's reference."""
        return self._last_v

    def connect(self) -> None:
        """Open, identify, check the amplifier's limit, and start slewing from its output."""
        cfg, link = self.cfg, self._link
        link.open()
        ident = self.commands.identify(link)
        limit_v = self.commands.limit_v(link, cfg.axis)
        if limit_v is not None and limit_v < cfg.max_v:
            link.close()
            raise DriverError(
                f"{link.device} on {cfg.port} ({ident}): its voltage limit {limit_v} V is below "
                f"max_v = {cfg.max_v} V; set the front-panel limit or lower max_v")
        now_v = self.commands.read_v(link, cfg.axis)
        self._last_v = round(now_v * _STEPS_PER_V) / _STEPS_PER_V
        self._last_t_s = None  # no elapsed time yet: the first write holds this voltage
        log.info("%s on %s: %s, limit %s V, output %.3f V", link.device, cfg.port, ident,
                 limit_v, now_v)

    def read_v(self) -> float:
        """The amplifier's output as it reports it (it slews; the loop need not wait)."""
        return self.commands.read_v(self._link, self.cfg.axis)

    def write(self, command_v: float, t_s: float) -> float:
        """Clamp to [min_v, max_v], limit the change to slew_v_per_s since the last write,
        send, verify; returns the voltage sent. NaN is a DriverError (an upstream bug must
        not be hidden by a hold); +-inf clamps like any other out-of-range command."""
        cfg = self.cfg
        if math.isnan(command_v) or not math.isfinite(t_s):
            raise DriverError(
                f"{self._link.device} on {cfg.port}: refusing command {command_v} V at "
                f"t = {t_s} s (a NaN command or a non-finite time)")
        if self._last_v is None:
            raise DriverError(f"{self._link.device} on {cfg.port}: write before connect()")
        last_v, last_t_s = self._last_v, self._last_t_s
        max_dv = 0.0 if last_t_s is None else cfg.slew_v_per_s * max(0.0, t_s - last_t_s)
        target = min(max(command_v, cfg.min_v), cfg.max_v)
        v = min(max(target, last_v - max_dv), last_v + max_dv)
        v = min(max(_towards(v, last_v), cfg.min_v), cfg.max_v)  # range wins over slew
        volts = f"{v:.3f}"
        # the reference is what went on the wire, even if the reply then fails
        self._last_v = float(volts)
        self._last_t_s = t_s if last_t_s is None else max(last_t_s, t_s)
        self.commands.set_v(self._link, cfg.axis, volts)
        return self._last_v

    def make_safe(self) -> bool:
        """Set safe_v at once (the amplifier's output still slews); reopen the port once if
        that fails. Never raises: it runs when something has already gone wrong."""
        volts = f"{self.cfg.safe_v:.3f}"
        for attempt in (1, 2):
            try:
                if attempt == 2:
                    self._link.open()
                self.commands.set_v(self._link, self.cfg.axis, volts)
            except Exception as exc:  # the last line of defence must not raise
                log.error("make_safe attempt %d: %s", attempt, exc)
                continue
            self._last_v, self._last_t_s = float(volts), None
            return True
        log.critical("%s on %s: could not set safe voltage %s V", self._link.device,
                     self.cfg.port, volts)
        return False

    def close(self) -> None:
        self._link.close()
        self._last_v = self._last_t_s = None
