"""The temperature feedforward on a running daemon (issue 21, part 1): set by hand, shown by
status, suggested from a model and applied and persisted, logged with each thermometer
reading; refused where no thermometer is read; and the thermometer over Modbus against a
real pymodbus server."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from leveler.drivers.base import Status
from leveler.drivers.modbus import ModbusThermometer
from leveler.drivers.modbus_config import (
    ModbusActuatorConfig,
    ModbusSensorConfig,
    ModbusThermometerConfig,
)
from leveler.emulate.modbus import ModbusEmulator
from leveler.log.reader import read_log
from leveler.settings import load_config
from leveler.sim.params import PlantParams
from leveler.sim.plant import Plant

from conftest import REPO  # isort: skip

THERMOMETER = '\n[thermometer]\nbackend = "sim"\ninterval_s = 0.5\n'
# config/lab.toml's integral-only loop, weak where a temperature tilts the table
INTEGRAL_ONLY = {"ki_v_per_m_s = 2.2e7": "ki_v_per_m_s = 7.0e5",
                 "kd_v_s_per_m = 1.9e6": "kd_v_s_per_m = 0.0"}
COUPLING = ("\n[plant.effects.temperature_coupling]\ntilt_per_kelvin_rad_per_k = 5.0e-6\n"
            "lag_s = 600.0\n")


def test_feedforward_on_a_running_daemon(tmp_path: Path, start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(rate_hz=10.0, edit=lambda t: t + THERMOMETER, replace=INTEGRAL_ONLY)
    out = d.cli("tune", "--ff-gain", "-50", "--ff-lag", "1800")
    assert out.returncode == 0 and "temperature feedforward over 1 path(s)" in out.stdout, out
    shown = d.cli("status").stdout
    assert "thermometer sim, every 0.5 s:" in shown and " K, " in shown, shown
    assert "temperature feedforward " in shown, shown

    model = tmp_path / "model.toml"
    model.write_text((REPO / "config" / "sim.toml").read_text() + COUPLING)
    out = d.cli("tune", "--suggest", "--model", str(model), "--apply", "--persist",
                "--predict-hours", "0", timeout=120)
    assert out.returncode == 0, out.stderr
    assert "Suggested feedforward (-50 V/K through 1800 s; -25 V/K through 600 s)" in out.stdout
    assert "feedforward_gains_v_per_k = [-50, -25]" in out.stdout
    assert "applied: temperature feedforward over 2 path(s); written to the config file" \
        in out.stdout, out.stdout
    assert d.cli("tune", "--ff-gain", "1", "--ff-lag", "-3").returncode != 0
    d.stop()

    ff = load_config(d.config)[0].controller.feedforward()  # persisted, and loads again
    assert ff is not None and [(p.gain_v_per_k, p.lag_s) for p in ff.paths] == [
        (pytest.approx(-50), 1800.0), (pytest.approx(-25), 600.0)]
    log = read_log(next(d.logs.glob("*.mcap")))
    env, seq = log.environment, log.samples["seq"]
    assert len(env["seq"]) == pytest.approx(len(seq) / 5, abs=2)  # every 0.5 s at 10 Hz
    assert np.all(np.abs(env["temperature_k"] - 295.15) < 1.0)
    held = log.per_sample("temperature_k")
    assert held is not None and len(held) == len(seq) and np.isfinite(held).all()
    tunes = [e for e in log.events if e["kind"] == "tune"]
    assert [len(e["detail"]["feedforward_gains_v_per_k"][1]) for e in tunes] == [1, 2]


def test_a_daemon_without_a_thermometer_refuses_a_feedforward(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(rate_hz=10.0)
    out = d.cli("tune", "--ff-gain", "-50", "--ff-lag", "1800")
    assert out.returncode != 0
    assert "needs a thermometer, and this daemon reads none: add [thermometer]" in out.stderr
    assert "thermometer" not in d.cli("status").stdout
    d.stop()


def _cfgs(**th: object) -> tuple[ModbusSensorConfig, ModbusActuatorConfig,
                                  ModbusThermometerConfig]:
    fast = {"timeout_s": 1.0, "reconnect_min_s": 0.2, "reconnect_max_s": 0.8}
    return (ModbusSensorConfig(**fast), ModbusActuatorConfig(**fast),
            ModbusThermometerConfig(**fast, **th))  # type: ignore[arg-type]


def test_modbus_thermometer_reads_the_plate_through_the_registers() -> None:
    params = PlantParams()
    params = dataclasses.replace(params, thermal=dataclasses.replace(
        params.thermal, thermometer_noise_k=0.0))
    plant = Plant(params, dt_s=0.01, seed=1)
    s, a, th = _cfgs(register=4, words=2, signed=True, counts_min=-(1 << 20),
                     counts_max=1 << 20, value_at_min=-10.0, value_at_max=10.0)
    with ModbusEmulator(plant, s, a, thermometer_cfg=th) as emu:
        th = dataclasses.replace(th, port=emu.port)
        t = ModbusThermometer(th)
        t.connect()
        for _ in range(3):
            r = t.read_temperature(0.0)
            assert r.status is Status.OK
            assert r.temperature_k == pytest.approx(plant.thermometer_k(),
                                                    abs=th.k_per_v * th.volts_per_count)
        t.close()
    # a transmitter whose range the temperature has left reads railed, not a temperature
    s, a, th = _cfgs(offset_k=300.0)
    with ModbusEmulator(Plant(PlantParams(), 0.01, 1), s, a, thermometer_cfg=th) as emu:
        t = ModbusThermometer(dataclasses.replace(th, port=emu.port))
        t.connect()
        assert t.read_temperature(0.0).status is Status.RAILED
        t.close()
    with pytest.raises(ValueError, match="thermometer registers 0"):
        ModbusEmulator(plant, s, a, thermometer_cfg=dataclasses.replace(th, register=0))
