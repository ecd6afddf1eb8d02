"""The simulated stand behind two pseudo-terminals: a piezo amplifier and a sensor controller.

The serial drivers talk to it exactly as to hardware (pyserial on a tty), so tests prove
the protocol and the error handling end to end; ptys ignore the baud rate, so they prove
nothing about timing. The plant runs in wall time: before answering, it is stepped to the
time elapsed since `start()`, as `SimulatedStand.read` steps it to loop time.

Each port is a symlink to the current pty slave, so an injected "drop" can really close the
pty (the client's next read or write fails with EIO) and open a new one at the same path,
which a reconnect then finds.
"""

from __future__ import annotations

import abc
import collections
import logging
import os
import re
import select
import shutil
import tempfile
import threading
import time
import tty
from dataclasses import dataclass
from typing import Literal

from leveler.sim.plant import Plant

log = logging.getLogger(__name__)

FaultKind = Literal["no_reply", "garbage", "partial_line", "drop", "error"]
FAULT_KINDS: tuple[FaultKind, ...] = ("no_reply", "garbage", "partial_line", "drop", "error")
GARBAGE = b"\xff\xfe#?%garbage"


@dataclass(frozen=True, slots=True)
class SensorFormat:
    """How the emulated sensor controller answers its query.

    The number is the displacement in units of unit_m with `decimals` decimals; with
    decimals = 0 it is an integer count, as some controllers send.
    """

    query: str = "MEAS?"
    unit_m: float = 1e-6
    decimals: int = 6
    line_ending: str = "\r\n"

    @property
    def resolution_m(self) -> float:
        return self.unit_m * 10.0**-self.decimals

    def render(self, value_m: float) -> str:
        x = value_m / self.unit_m
        return f"{x:.{self.decimals}f}" if self.decimals else str(round(x))


class Pty:
    """One raw pty pair behind a stable symlink; `reopen` is a pulled and replugged cable.

    The emulator holds the slave open too, so the master never sees EIO while no client
    has the port open, and a client's unread input survives until its next open flushes it.
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self.master = self.slave = -1
        self._buffer = b""
        self._open()

    def _open(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo or line editing before a client configures it
        os.set_blocking(self.master, False)
        tmp = self.path + ".new"
        os.symlink(os.ttyname(self.slave), tmp)
        os.replace(tmp, self.path)
        self._buffer = b""

    def reopen(self) -> None:
        """The new pty is at the path before the old one closes: a client that sees the
        old one fail and reconnects at once finds the new one."""
        old = self.master, self.slave
        self._open()
        for fd in old:
            os.close(fd)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass  # already closed
        self.master = self.slave = -1

    def read(self) -> bytes:
        """Whatever the client has written since the last read (b"" if nothing)."""
        try:
            return os.read(self.master, 4096)
        except BlockingIOError:
            return b""

    def lines(self) -> list[str]:
        """Complete command lines received so far; CR, LF or both end a line."""
        self._buffer += self.read()
        *done, self._buffer = re.split(rb"[\r\n]", self._buffer)
        return [s.decode("ascii", "replace").strip() for s in done if s.strip()]

    def send(self, data: bytes) -> None:
        try:
            os.write(self.master, data)
        except BlockingIOError:  # nobody reads and the buffer is full: an overrun
            log.warning("%s: reply dropped, pty buffer full", self.path)


class _Device(abc.ABC):
    """One emulated protocol; `handle` runs a command and returns its reply (None: none)."""

    reply_end: bytes = b"\n"

    def __init__(self, emulator: SerialEmulator) -> None:
        self.emulator = emulator

    def replies_to(self, line: str) -> bool:
        return True

    @abc.abstractmethod
    def handle(self, line: str) -> bytes | None: ...

    @abc.abstractmethod
    def refuse(self, line: str) -> bytes | None:
        """The reply to a command the device rejects (the "error" fault)."""


class _ThorlabsMDT(_Device):
    """MDT694B with echo on: echo, CR, answer, `>`; only the x axis drives the plant."""

    reply_end = b">"

    def _reply(self, line: str, body: str) -> bytes:
        return f"{line}\r{body}>".encode("ascii")

    def handle(self, line: str) -> bytes | None:
        emu = self.emulator
        if line == "id?":
            return self._reply(line, "Model MDT694B Piezo Control Module\r"
                                     "Firmware Version: emulated\r")
        if line == "vlimit?":
            return self._reply(line, f"[{emu.vlimit_v:4.0f}]\r")
        if line == "xvoltage?":
            return self._reply(line, f"[{emu.plant.v_applied:6.2f}]\r")
        if line.startswith("xvoltage="):
            try:
                emu.apply_v(float(line.removeprefix("xvoltage=")))
            except ValueError:
                return self.refuse(line)
            return self._reply(line, "")
        return self.refuse(line)

    def refuse(self, line: str) -> bytes | None:
        return self._reply(line, "CMD_NOT_DEFINED")


class _PIGCS2(_Device):
    """E-709 in GCS 2.0: queries answer one LF line, settings answer nothing, errors stick."""

    ERROR_SYNTAX, ERROR_UNKNOWN, ERROR_LIMITS = 1, 2, 7

    def __init__(self, emulator: SerialEmulator) -> None:
        super().__init__(emulator)
        self.error_code = 0

    def replies_to(self, line: str) -> bool:
        return line.split()[0].endswith("?")

    def handle(self, line: str) -> bytes | None:
        emu = self.emulator
        words = line.split()
        if line == "*IDN?":
            return b"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, E-709 (emulated), 0, 1.0\n"
        if line == "ERR?":
            code, self.error_code = self.error_code, 0
            return f"{code}\n".encode("ascii")
        if words[0] == "SVA?" and len(words) == 2:
            return f"{words[1]}={emu.plant.v_applied:.6f}\n".encode("ascii")
        if words[0] == "SVA" and len(words) == 3:
            try:
                emu.apply_v(float(words[2]))
            except ValueError:
                self.error_code = self.ERROR_SYNTAX
            return None
        self.error_code = self.ERROR_UNKNOWN
        return None

    def refuse(self, line: str) -> bytes | None:
        self.error_code = self.ERROR_LIMITS  # sticky: the next ERR? reports it
        return self.handle(line)


class _SensorController(_Device):
    """Answers the configured query with the plant's displacement; anything else: ERROR."""

    def __init__(self, emulator: SerialEmulator, fmt: SensorFormat) -> None:
        super().__init__(emulator)
        self.fmt = fmt
        self.reply_end = fmt.line_ending.encode("ascii")

    def handle(self, line: str) -> bytes | None:
        if line != self.fmt.query:
            return self.refuse(line)
        _, value_m, _ = self.emulator.plant.measure()
        return (self.fmt.render(value_m) + self.fmt.line_ending).encode("ascii")

    def refuse(self, line: str) -> bytes | None:
        return ("ERROR" + self.fmt.line_ending).encode("ascii")


class SerialEmulator:
    """A piezo amplifier (`piezo_port`) and a sensor controller (`sensor_port`) on ptys.

    Use as a context manager, or `start()` ... `close()`; `serve_forever()` for a CLI.
    `received_v` records every voltage the amplifier was sent, in order.
    """

    def __init__(self, plant: Plant, protocol: Literal["thorlabs_mdt", "pi_gcs2"] = "thorlabs_mdt",
                 sensor_format: SensorFormat | None = None, *, vlimit_v: float = 150.0) -> None:
        self.plant = plant
        self.vlimit_v = vlimit_v
        self.received_v: list[float] = []
        self._dir = tempfile.mkdtemp(prefix="leveler-emulate-")
        self._ptys = {"piezo": Pty(os.path.join(self._dir, "piezo")),
                      "sensor": Pty(os.path.join(self._dir, "sensor"))}
        piezo = _ThorlabsMDT(self) if protocol == "thorlabs_mdt" else _PIGCS2(self)
        self._devices: dict[str, _Device] = {
            "piezo": piezo, "sensor": _SensorController(self, sensor_format or SensorFormat())}
        self._faults: dict[str, collections.deque[FaultKind]] = {
            name: collections.deque() for name in self._ptys}
        self._lock = threading.Lock()  # faults are queued from other threads
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()

    @property
    def piezo_port(self) -> str:
        return self._ptys["piezo"].path

    @property
    def sensor_port(self) -> str:
        return self._ptys["sensor"].path

    def inject(self, kind: FaultKind, count: int = 1, *,
               port: Literal["piezo", "sensor"] = "piezo") -> None:
        """Spoil the next `count` replies on `port`.

        no_reply: the command is ignored and nothing comes back. garbage: it is executed,
        the reply is non-ASCII bytes. partial_line: executed, the first half of the reply
        only. drop: the pty is closed (the client sees an I/O error) and a new one appears
        at the same path. error: Thorlabs answers CMD_NOT_DEFINED without executing; PI
        executes and latches error 7 for the next ERR?; the sensor answers ERROR.
        For PI, only queries (`...?`) have replies, so only they consume faults.
        """
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault kind {kind!r}: expected one of {', '.join(FAULT_KINDS)}")
        with self._lock:
            self._faults[port].extend([kind] * count)

    def apply_v(self, v: float) -> None:
        """The amplifier received a voltage: record it and hand it to the plant."""
        self.received_v.append(v)
        self.plant.command(v)

    def start(self) -> None:
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="serial-emulator", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        for pty in self._ptys.values():
            pty.close()
        shutil.rmtree(self._dir, ignore_errors=True)

    def serve_forever(self) -> None:
        """Serve until Ctrl-C (for `leveler emulate serial`)."""
        self.start()
        log.info("piezo amplifier on %s, sensor controller on %s", self.piezo_port,
                 self.sensor_port)
        try:
            while not self._stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def __enter__(self) -> SerialEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            by_fd = {pty.master: name for name, pty in self._ptys.items()}
            ready, _, _ = select.select(list(by_fd), [], [], 0.05)
            for fd in ready:
                name = by_fd[fd]
                for line in self._ptys[name].lines():
                    if not self._serve(name, line):
                        break  # the pty was dropped: the rest of its input went with it

    def _advance_plant(self) -> None:
        plant = self.plant
        target = round((time.monotonic() - self._t0) / plant.dt_s)
        while plant.n < target:
            plant.step()

    def _serve(self, name: str, line: str) -> bool:
        """Run one command line; False if the pty was dropped."""
        pty, device = self._ptys[name], self._devices[name]
        self._advance_plant()
        fault = None
        if device.replies_to(line):
            with self._lock:
                queue = self._faults[name]
                fault = queue.popleft() if queue else None
        if fault == "no_reply":
            return True
        if fault == "drop":
            pty.reopen()
            return False
        reply = device.refuse(line) if fault == "error" else device.handle(line)
        if reply is None:
            return True
        if fault == "garbage":
            reply = GARBAGE + device.reply_end
        elif fault == "partial_line":
            reply = reply[: max(1, len(reply) // 2)]
        pty.send(reply)
        return True
