"""The simulated plant behind a real Modbus TCP server, for testing the Modbus drivers.

A pymodbus 3.16 `ModbusTcpServer` runs on its own event loop in a background thread. Its
datastore is a `SimDevice` whose `action` hook runs before every register access: it steps
the plant to the wall time elapsed since `start()`, writes the sensor reading into the input
registers (encoded as the sensor config says) and turns a write of the actuator's holding
registers into `plant.command(piezo volts)`. The same hook injects faults; a `trace_packet`
hook garbles replies. One block serves functions 3 and 4 alike, so the sensor can be read as
input or holding registers.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import deque
from typing import Literal

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from leveler.drivers.modbus_config import ModbusActuatorConfig, ModbusSensorConfig
from leveler.sim.plant import Plant

FaultKind = Literal["no_reply", "exception", "drop", "garbage"]


class ModbusEmulator:
    """A Modbus AI/AO module wired to a `Plant`, with fault injection.

    `received_v` lists every piezo voltage written to the actuator registers, in order.
    Faults apply to the next requests, one request each: "no_reply" answers only after
    no_reply_s (longer than a client's timeout), "exception" answers with Modbus exception
    `code`, "drop" closes every client connection (the server keeps listening) and
    "garbage" replaces the reply's bytes with junk of the same length.
    """

    def __init__(self, plant: Plant, sensor_cfg: ModbusSensorConfig,
                 actuator_cfg: ModbusActuatorConfig, host: str = "127.0.0.1", port: int = 0,
                 *, no_reply_s: float = 1.0) -> None:
        s, a = sensor_cfg, actuator_cfg
        if s.register < a.register + a.words and a.register < s.register + s.words:
            raise ValueError(f"sensor registers {s.register}+{s.words} overlap actuator "
                             f"registers {a.register}+{a.words}")
        self.plant = plant
        self.sensor_cfg = s
        self.actuator_cfg = a
        self.host = host
        self.port = port
        self.no_reply_s = no_reply_s
        self.received_v: list[float] = []
        self._faults: deque[tuple[FaultKind, int]] = deque()
        self._faults_lock = threading.Lock()
        self._garble_next = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: ModbusTcpServer | None = None
        self._t0_s = 0.0
        self._n0 = plant.n

    def __enter__(self) -> ModbusEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Listen; `port` is the bound port afterwards. Plant time starts now."""
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
        ], action=self._action)
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
        if kind == "no_reply":
            await asyncio.sleep(self.no_reply_s)
        elif kind == "exception":
            return ExcCodes(code)
        elif kind == "drop":
            assert self._server is not None
            for conn in list(self._server.active_connections.values()):
                conn.close()
            return None
        elif kind == "garbage":
            self._garble_next = True
        self._advance_plant()
        s, a = self.sensor_cfg, self.actuator_cfg
        if values is None:
            if address < s.register + s.words and s.register < address + count:
                _, value_m, _ = self.plant.measure()
                counts = min(max(round(s.m_to_counts(value_m)), s.counts_min), s.counts_max)
                registers[s.register - start:s.register - start + s.words] = s.encode(counts)
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
        if sending and self._garble_next:
            self._garble_next = False
            return bytes((0xA5 + 7 * i) & 0xFF for i in range(len(data)))
        return data
