"""The NI-DAQmx backend without the hardware: what can be checked honestly, and nothing faked.

No NI device and no NI-DAQmx runtime exist here, and nidaqmx is not mocked. So these tests
cover the config (validation, the shipped example), the wiring into the stand, the errors a
user without the package or runtime gets, and the command path (NaN, range and slew) that
every AO write goes through. The test marked for an installed nidaqmx runs where the package
is (with or without NI's runtime); see docs/hardware.md for what remains untested.
"""

from __future__ import annotations

import importlib.util
import logging
import math
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leveler.drivers.base import DriverError
from leveler.drivers.limits import slew_window
from leveler.drivers.nidaq import NidaqActuator, NidaqSensor, ao_command
from leveler.drivers.nidaq_config import NidaqActuatorConfig, NidaqSensorConfig
from leveler.settings import load_config
from leveler.stand import open_stand
from leveler.typed_config import ConfigError

REPO = Path(__file__).resolve().parents[1]
HAVE_NIDAQMX = importlib.util.find_spec("nidaqmx") is not None

BOTH = '[sensor]\nbackend = "nidaq"\n[actuator]\nbackend = "nidaq"\n'
AO = "[sensor.nidaq]\n[actuator.nidaq]\n"  # a good sensor table, then the actuator's keys


def _load(tmp_path: Path, text: str) -> ConfigError:
    path = tmp_path / "lab.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(path) in str(err.value)
    return err.value


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[actuator.nidaq]\n", 'sensor: backend = "nidaq" needs a [sensor.nidaq] table'),
        ("[sensor.nidaq]\n", 'actuator: backend = "nidaq" needs an [actuator.nidaq] table'),
        ('[sensor.nidaq]\nchannel = "Dev1/ai0:3"\n',
         "sensor.nidaq: channel 'Dev1/ai0:3': expected one physical channel"),
        ('[sensor.nidaq]\nchannel = "ai0"\n', "sensor.nidaq: channel 'ai0'"),
        ('[sensor.nidaq]\nterminal_config = "differential"\n',
         "sensor.nidaq.terminal_config: expected 'diff' or 'rse'"),
        ("[sensor.nidaq]\nrange_min_v = 5.0\nrange_max_v = -5.0\n",
         "sensor.nidaq: range_min_v (5.0 V) must be below range_max_v"),
        ("[sensor.nidaq]\nm_per_v = 0.0\n", "sensor.nidaq.m_per_v: must be > 0"),
        ("[sensor.nidaq]\ntimeout_s = -0.1\n", "sensor.nidaq.timeout_s: must be > 0"),
        ("[sensor.nidaq]\nsamples = 4\n", "sensor.nidaq.samples: unknown key"),
        (AO + "max_v = 200.0\n",
         "actuator.nidaq: piezo range [0.0, 200.0] V needs the AO to span [0, 13.33] V"),
        (AO + "safe_v = 160.0\n", "actuator.nidaq: safe_v (160.0 V) must lie in"),
        (AO + "min_v = 100.0\nmax_v = 50.0\nsafe_v = 75.0\n",
         "actuator.nidaq: min_v (100.0 V) must be below max_v (50.0 V)"),
        (AO + 'channel = "Dev1/ai1"\n',
         "actuator.nidaq: readback_channel: cannot derive an internal channel"),
        (AO + 'readback_channel = "Dev1 ai0"\n', "actuator.nidaq: readback_channel 'Dev1 ai0'"),
        (AO + "amplifier_gain = -15.0\n", "actuator.nidaq.amplifier_gain: must be > 0"),
    ],
)
def test_bad_nidaq_config_names_file_and_key(tmp_path: Path, text: str, needle: str) -> None:
    assert needle in str(_load(tmp_path, BOTH + text))


def test_shipped_nidaq_config_loads() -> None:
    cfg, _ = load_config(REPO / "config" / "lab-nidaq.toml")
    assert (cfg.sensor.backend, cfg.actuator.backend) == ("nidaq", "nidaq")
    assert cfg.sensor.nidaq == NidaqSensorConfig()
    assert cfg.actuator.nidaq is not None
    assert cfg.actuator.nidaq.readback == "Dev1/_ao0_vs_aognd"


def test_readback_channel_is_derived_or_given() -> None:
    assert NidaqActuatorConfig(channel="PXI1Slot2/ao1").readback == "PXI1Slot2/_ao1_vs_aognd"
    cfg = NidaqActuatorConfig(channel="Dev2/ao0", readback_channel="Dev2/ai7")
    assert cfg.readback == "Dev2/ai7"


def test_the_stand_is_built_without_nidaqmx() -> None:
    cfg, _ = load_config(REPO / "config" / "lab-nidaq.toml")
    stand = open_stand(cfg)
    assert isinstance(stand.sensor, NidaqSensor)
    assert isinstance(stand.actuator, NidaqActuator)
    assert stand.truth is None
    assert stand.actuator.safe_v == 75.0
    with pytest.raises(DriverError, match=r"NI-DAQmx AO Dev1/ao0: write before connect\(\)"):
        stand.actuator.write(75.0, 0.0)
    with pytest.raises(DriverError, match=r"NI-DAQmx AI Dev1/ai0: read before connect\(\)"):
        stand.sensor.read(0.0)


@pytest.mark.skipif(HAVE_NIDAQMX, reason="nidaqmx is installed here")
def test_without_nidaqmx_connect_says_what_to_install(caplog: pytest.LogCaptureFixture) -> None:
    cfg, _ = load_config(REPO / "config" / "lab-nidaq.toml")
    stand = open_stand(cfg)
    with pytest.raises(DriverError) as err:
        stand.connect()
    message = str(err.value)
    assert message.startswith("NI-DAQmx AI Dev1/ai0: the nidaqmx package is not installed")
    assert f"{sys.executable} -m pip install 'nidaqmx>=1.0,<2'" in message
    assert "NI-DAQmx runtime" in message
    with pytest.raises(DriverError, match=r"^NI-DAQmx AO Dev1/ao0: .*the nidaq extra"):
        stand.actuator.connect()
    with caplog.at_level(logging.ERROR):
        stand.actuator.make_safe()  # what the loop calls on a fault: logs, never raises
    assert "make_safe could not set 75.000 V" in caplog.text
    stand.close()


@pytest.mark.skipif(not HAVE_NIDAQMX, reason="nidaqmx is not installed (the optional extra)")
def test_with_nidaqmx_a_missing_device_or_runtime_is_a_driver_error() -> None:
    """With the package but no such device: DaqNotFoundError without NI's runtime, a
    DaqError (no such device) with it. Either way a DriverError naming the channel."""
    sensor = NidaqSensor(NidaqSensorConfig(channel="LevelerNoSuchDev/ai0"))
    with pytest.raises(DriverError, match=r"^NI-DAQmx AI LevelerNoSuchDev/ai0: create task: "
                                          r"Daq\w*Error: "):
        sensor.connect()
    actuator = NidaqActuator(NidaqActuatorConfig(channel="LevelerNoSuchDev/ao0"))
    with pytest.raises(DriverError, match=r"^NI-DAQmx AO LevelerNoSuchDev/ao0: create task: "):
        actuator.connect()
    actuator.make_safe()  # never raises


CFG = NidaqActuatorConfig()
_commands = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from(
    [math.nan, math.inf, -math.inf, -1e300, 1e300, -5.0, 0.0, 75.0, 150.0, 151.0])
_dt_s = st.floats(-1.0, 10.0) | st.sampled_from([math.nan, 0.0, math.inf])


@settings(max_examples=500, deadline=None)
@given(command_v=_commands, last_v=st.floats(CFG.min_v, CFG.max_v), dt_s=_dt_s)
def test_every_ao_command_respects_range_and_slew(command_v: float, last_v: float,
                                                  dt_s: float) -> None:
    piezo_v, ao_v = ao_command(CFG, command_v, last_v, dt_s)
    assert CFG.min_v <= piezo_v <= CFG.max_v
    assert CFG.range_min_v <= ao_v <= CFG.range_max_v
    assert ao_v == pytest.approx(piezo_v / CFG.amplifier_gain, abs=1e-12)
    if math.isnan(command_v) or not dt_s > 0:
        assert piezo_v == last_v  # NaN, first write or time not advancing: hold
    else:
        assert abs(piezo_v - last_v) <= CFG.slew_v_per_s * dt_s * (1 + 1e-12) + 1e-12
        lo, hi = slew_window(last_v, dt_s, CFG.min_v, CFG.max_v, CFG.slew_v_per_s)
        assert piezo_v == command_v if lo <= command_v <= hi else piezo_v in (lo, hi)


@given(last_v=st.sampled_from([-20.0, 151.0, 1e9]), command_v=_commands, dt_s=_dt_s)
def test_an_ao_left_outside_the_range_is_brought_into_it(last_v: float, command_v: float,
                                                         dt_s: float) -> None:
    piezo_v, _ = ao_command(CFG, command_v, last_v, dt_s)
    assert CFG.min_v <= piezo_v <= CFG.max_v


def test_a_step_command_ramps_at_the_slew_limit() -> None:
    """From 0 V at 10 Hz, a 150 V command climbs 10 V per cycle (100 V/s) and stops there."""
    last_v, applied = 0.0, []
    for _ in range(17):
        last_v, ao_v = ao_command(CFG, 150.0, last_v, 0.1)
        applied.append(last_v)
    assert applied[:3] == pytest.approx([10.0, 20.0, 30.0])
    assert applied[14:] == [150.0, 150.0, 150.0]
    assert ao_v == 10.0
