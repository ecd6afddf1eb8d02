"""A third-party Modbus client (Debian's mbpoll) and leveler's own driver agree on what the
emulator serves: the register map is the real protocol, not a private convention."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from leveler.drivers.modbus import ModbusSensor
from leveler.drivers.modbus_config import ModbusActuatorConfig, ModbusSensorConfig
from leveler.emulate.modbus import ModbusEmulator
from leveler.sim.params import PlantParams
from leveler.sim.plant import Plant

MBPOLL = shutil.which("mbpoll")
pytestmark = pytest.mark.skipif(MBPOLL is None, reason="mbpoll not installed "
                                "(make test installs it as root: apt-get install mbpoll)")


def _mbpoll(port: int, *args: str) -> str:
    assert MBPOLL is not None
    out = subprocess.run([MBPOLL, "-m", "tcp", "-a", "1", "-0", "-1", "-p", str(port),
                          "-o", "1", *args], capture_output=True, text=True, timeout=10)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def test_mbpoll_reads_and_writes_what_the_driver_does() -> None:
    sensor_cfg = ModbusSensorConfig(port=1502, timeout_s=0.5)
    actuator_cfg = ModbusActuatorConfig(port=1502, timeout_s=0.5)
    plant = Plant(PlantParams(), 0.01, seed=1)
    with ModbusEmulator(plant, sensor_cfg, actuator_cfg, port=0) as emu:
        ours = ModbusSensor(ModbusSensorConfig(port=emu.port, timeout_s=0.5))
        ours.connect()
        try:
            before = ours.read(0.0).raw_counts
            text = _mbpoll(emu.port, "-t", "3", "-r", "0", "-c", "1", "127.0.0.1")
            after = ours.read(0.0).raw_counts
        finally:
            ours.close()
        (theirs,) = (int(v) for v in re.findall(r"^\[0\]:\s+(-?\d+)", text, re.M))
        # The plant moves (noise, drift) between the three reads: a few counts at most.
        assert min(before, after) - 5 <= theirs <= max(before, after) + 5, (before, theirs)
        _mbpoll(emu.port, "-t", "4", "-r", "10", "127.0.0.1", "2048")
        assert plant.v_target == pytest.approx(actuator_cfg.counts_to_piezo_v(2048))
        assert emu.received_v[-1] == pytest.approx(actuator_cfg.counts_to_piezo_v(2048))
