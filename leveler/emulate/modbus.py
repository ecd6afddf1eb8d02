"""The simulated plant behind a real Modbus server, TCP or RTU, for testing the Modbus drivers.

A pymodbus 3.16 `ModbusTcpServer`, or a `ModbusSerialServer` (RTU framing) on a pty, runs on
its own event loop in a background thread. Its datastore is a `SimDevice` whose `action` hook
runs before every register access: it steps the plant to the wall time elapsed since
`start()`, writes the sensor reading into the input registers (encoded as the sensor config
says) and turns a write of the actuator's holding registers into `plant.command(piezo
volts)`. The same hook injects faults; a `trace_packet` hook garbles or withholds replies.
One block serves functions 3 and 4 alike, so the sensor can be read as input or holding
registers.

RTU needs a tty at each end: pymodbus's serial server opens a port by path, as the client
does, and a pty pair has only one path (its slave). So two pty pairs are joined master to
master by a copying thread, as socat would join them: the server opens one slave, the client
the other (`serial_port`, a symlink that follows a "drop" to a new pty).
"""

from __future__ import annotations

import asyncio
import os
import select
import shutil
import tempfile
import threading
import time
from collections import deque
from typing import Literal

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from leveler.drivers.modbus_config import (
    ModbusActuatorConfig,
    ModbusSensorConfig,
    ModbusThermometerConfig,
)
from leveler.emulate.serial import Pty
from leveler.sim.plant import Plant

FaultKind = Literal["no_reply", "exception", "drop", "garbage"]


class _NullModem:
    """Two raw pty pairs joined master to master: a serial cable with a tty at each end.

    `drop` is a pulled cable on the client's side: its pty closes (the client's port fails)
    and a new one appears at `client.path`, which a reconnect then finds.
    """

    def __init__(self) -> None:
        self._dir = tempfile.mkdtemp(prefix="leveler-modbus-rtu-")
        self.server = Pty(os.path.join(self._dir, "server"))
        self.client = Pty(os.path.join(self._dir, "client"))
        self._drop = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="modbus-rtu-line", daemon=True)
        self._thread.start()

    def drop(self) -> None:
        """Reopen the client's pty; thread-safe: the copying thread owns the descriptors."""
        self._drop.set()

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.server.close()
        self.client.close()
        shutil.rmtree(self._dir, ignore_errors=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._drop.is_set():
                self._drop.clear()
                self.client.reopen()
            ends = {self.server.master: (self.server, self.client),
                    self.client.master: (self.client, self.server)}
            ready, _, _ = select.select(list(ends), [], [], 0.02)
            for fd in ready:
                src, dst = ends[fd]
                if data := src.read():
                    dst.send(data)


class ModbusEmulator:
    """A Modbus AI/AO module wired to a `Plant`, with fault injection.

    transport "tcp" listens at host:port; "rtu" serves RTU frames on a pty whose client end
    is `serial_port` (set by `start()`; host and port are unused).
    `received_v` lists every piezo voltage written to the actuator registers, in order.
    With `thermometer_cfg`, its registers serve the plant's plate thermometer too.
    Faults apply to the next requests, one request each: "no_reply" answers only after
    no_reply_s (longer than a client's timeout) on TCP and never on RTU (a late answer on a
    serial line would be taken for the next request's: RTU frames carry no transaction id),
    "exception" answers with Modbus exception `code`, "drop" closes every client connection
    (TCP: the server keeps listening; RTU: the client's pty is replaced, the request goes
    unanswered) and "garbage" replaces the reply's bytes with junk of the same length.
    """

    def __init__(self, plant: Plant, sensor_cfg: ModbusSensorConfig,
                 actuator_cfg: ModbusActuatorConfig, host: str = "127.0.0.1", port: int = 0,
                 *, transport: Literal["tcp", "rtu"] = "tcp", no_reply_s: float = 1.0,
                 thermometer_cfg: ModbusThermometerConfig | None = None) -> None:
        if transport not in ("tcp", "rtu"):
            raise ValueError(f"transport {transport!r}: expected 'tcp' or 'rtu'")
        s, a, th = sensor_cfg, actuator_cfg, thermometer_cfg
        channels = [("sensor", s), ("actuator", a)] + ([("thermometer", th)] if th else [])
        for i, (name, c) in enumerate(channels):
            for other, o in channels[i + 1:]:
                if c.register < o.register + o.words and o.register < c.register + c.words:
                    raise ValueError(f"{name} registers {c.register}+{c.words} overlap "
                                     f"{other} registers {o.register}+{o.words}")
        self.thermometer_cfg = th
        self.plant = plant
        self.sensor_cfg = s
        self.actuator_cfg = a
        self.host = host
        self.port = port
        self.transport = transport
        self.serial_port = ""
        self.no_reply_s = no_reply_s
        self.received_v: list[float] = []
        self._faults: deque[tuple[FaultKind, int]] = deque()
        self._faults_lock = threading.Lock()
        self._spoil_next: Literal["garble", "mute"] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        self._line: _NullModem | None = None
        self._t0_s = 0.0
        self._n0 = plant.n

    def __enter__(self) -> ModbusEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Listen; `port` (TCP) or `serial_port` (RTU) is set afterwards. Plant time starts now."""
        if self.transport == "rtu":
            self._line = _NullModem()
            self.serial_port = self._line.client.path
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True,
                                        name="modbus-emulator")
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self._listen(), self._loop).result(timeout=5.0)
        self._t0_s = time.monotonic()
        self._n0 = self.plant.n

    def close(self) -> None:
        """Stop serving and end the thread; safe to call twice."""
        loop, self._loop = self._loop, None
        if loop is None:
            return
        asyncio.run_coroutine_threadsafe(self._shutdown(), loop).result(timeout=5.0)
        loop.call_soon_threadsafe(loop.stop)
        assert self._thread is not None
        self._thread.join(timeout=5.0)
        loop.close()
        if self._line is not None:
            self._line.close()

    def inject(self, kind: FaultKind, count: int = 1,
               code: int = ExcCodes.DEVICE_FAILURE) -> None:
        """Make the next `count` requests fail as `kind` (`code` for "exception")."""
        if kind not in ("no_reply", "exception", "drop", "garbage"):
            raise ValueError(f"unknown fault kind {kind!r}")
        with self._faults_lock:
            self._faults.extend([(kind, code)] * count)

    async def _listen(self) -> None:
        s, a = self.sensor_cfg, self.actuator_cfg
        counts_v = a.piezo_v_to_counts(self.plant.v_applied)
        initial_ao = a.encode(min(max(round(counts_v), a.counts_min), a.counts_max))
        device = SimDevice(0, simdata=[
            SimData(s.register, values=[0] * s.words, datatype=DataType.REGISTERS,
                    readonly=True),
            SimData(a.register, values=initial_ao, datatype=DataType.REGISTERS),
            *([SimData(self.thermometer_cfg.register, values=[0] * self.thermometer_cfg.words,
                       datatype=DataType.REGISTERS, readonly=True)]
              if self.thermometer_cfg is not None else []),
        ], action=self._action)
        if self._line is not None:
            self._server = ModbusSerialServer(device, framer=FramerType.RTU,
                                              port=self._line.server.path, baudrate=s.baudrate,
                                              trace_packet=self._trace_packet)
            await self._server.serve_forever(background=True)
            return
        self._server = ModbusTcpServer(device, address=(self.host, self.port),
                                       trace_packet=self._trace_packet)
        await self._server.serve_forever(background=True)
        self.port = self._server.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]

    async def _shutdown(self) -> None:
        assert self._server is not None
        await self._server.shutdown()
        pending = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in pending:
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)

    async def _action(self, func_code: int, start: int, address: int, count: int,
                      registers: list[int], values: list[int] | list[bool] | None
                      ) -> ExcCodes | None:
        """The SimDevice hook: faults, plant time, sensor out, actuator in."""
        with self._faults_lock:
            kind, code = self._faults.popleft() if self._faults else (None, 0)
        if kind == "no_reply" and self._line is not None:
            self._spoil_next = "mute"
        elif kind == "no_reply":
            await asyncio.sleep(self.no_reply_s)
        elif kind == "exception":
            return ExcCodes(code)
        elif kind == "drop" and self._line is not None:
            self._line.drop()
            self._spoil_next = "mute"
            return None
        elif kind == "drop":
            assert self._server is not None
            for conn in list(self._server.active_connections.values()):
                conn.close()
            return None
        elif kind == "garbage":
            self._spoil_next = "garble"
        self._advance_plant()
        s, a = self.sensor_cfg, self.actuator_cfg
        if values is None:
            if address < s.register + s.words and s.register < address + count:
                _, value_m, _ = self.plant.measure()
                counts = min(max(round(s.m_to_counts(value_m)), s.counts_min), s.counts_max)
                registers[s.register - start:s.register - start + s.words] = s.encode(counts)
            th = self.thermometer_cfg
            if th is not None and address < th.register + th.words and th.register < (
                    address + count):
                counts = min(max(round(th.k_to_counts(self.plant.thermometer_k())),
                                 th.counts_min), th.counts_max)
                registers[th.register - start:th.register - start + th.words] = th.encode(
                    counts)
            return None
        if address < a.register + a.words and a.register < address + count:
            if (address, count) != (a.register, a.words):
                return ExcCodes.ILLEGAL_ADDRESS  # a partial write of a multi-word value
            piezo_v = a.counts_to_piezo_v(a.decode([int(v) for v in values]))
            self.received_v.append(piezo_v)
            self.plant.command(piezo_v)
        return None

    def _advance_plant(self) -> None:
        plant = self.plant
        target = self._n0 + round((time.monotonic() - self._t0_s) / plant.dt_s)
        while plant.n < target:
            plant.step()

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending or self._spoil_next is None:
            return data
        spoil, self._spoil_next = self._spoil_next, None
        return b"" if spoil == "mute" else bytes((0xA5 + 7 * i) & 0xFF for i in range(len(data)))
