"""The virtual loop's kernel (leveler.loop.kernel) against the objects it stands in for:
the daemon's Loop, PID and drivers on the simulated Plant. Bit for bit, compiled by numba
and interpreted, on runs that also send cycles back to the objects (railed and spiking
readings, a stuck sensor, retuning, a setpoint ramp, engaging mid-run), and the logs the
two write byte for byte."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import orjson
import pytest
from mcap.reader import make_reader

from leveler.log.writer import Columns, LogWriter, encode
from leveler.loop.pid import PIDGains
from leveler.records import Sample, Truth
from leveler.settings import Config, load_config
from leveler.sim.effects import ActuatorDelay
from leveler.virtual import VirtualStand, _Kernel

REPO = Path(__file__).resolve().parents[1]
MODES = ["python", pytest.param("numba", marks=pytest.mark.skipif(
    not __import__("importlib").util.find_spec("numba"), reason="numba not installed"))]


def _cfg(**plant: dict[str, object]) -> Config:
    cfg, _ = load_config(REPO / "config" / "sim.toml")
    p = cfg.plant
    for part, changes in plant.items():
        p = dataclasses.replace(p, **{part: dataclasses.replace(getattr(p, part), **changes)})
    return dataclasses.replace(cfg, plant=p)


def _noisy_screened() -> Config:
    """The loop held 3 nm below the ADC's top, so its noise rails it now and then; a coarse
    11-bit converter that repeats values; screens for spikes and a stuck sensor."""
    setpoint = 4.4e-7  # about the idle reading: engaging makes no large transient
    cfg = _cfg(sensor={"adc_min_v": -0.01, "adc_max_v": (setpoint + 3e-9) * 2e5,
                       "adc_bits": 11})
    loop = dataclasses.replace(cfg.loop, max_step_m=6e-9, stuck_after_samples=3)
    return dataclasses.replace(cfg, loop=loop, controller=dataclasses.replace(
        cfg.controller, setpoint_m=setpoint))


def _script(vs: VirtualStand, n: int, idle: bool) -> None:
    """Idle (if `idle`), engage, retune, move the setpoint, open and close the loop (if
    `idle`): each change made by the objects between runs that the kernel takes over."""
    vs.loop.emit("start", "test", vs.t_s)
    vs.cycle()
    if idle:
        vs.run(n // 5)
    vs.loop.engage(vs.t_s, "test")
    vs.run(n // 5)
    vs.loop.pid.set_gains(PIDGains(1e5, 2.0e7, 1.8e6))
    vs.loop.pid.set_setpoint(vs.loop.pid.config.setpoint_m - 2e-9)
    vs.run(n // 5)
    if idle:
        vs.loop.disengage(vs.t_s, "test")
        vs.run(n // 5)
        vs.loop.engage(vs.t_s, "test")
    vs.run(n // 5)


def _resonant() -> Config:
    """Resonant terms at the cooler's first three harmonics (as `tune --suggest --model`
    designs them for the default stand)."""
    cfg = _cfg()
    return dataclasses.replace(cfg, controller=dataclasses.replace(
        cfg.controller, periodic_period_s=300.0,
        periodic_gains_v_per_m_s=(1.32e7, 6.6e6, 4.4e6),
        periodic_phases_rad=(-1.55915, -1.54751, -1.53587)))


CASES = {
    "default closed loop": (lambda: _cfg(), 30_000),
    "non-linear pendulum": (lambda: _cfg(pendulum={"model": "nonlinear"}), 12_000),
    "railing, spiking, stuck": (_noisy_screened, 30_000),
    "resonant terms": (_resonant, 30_000),
    "slow setpoint ramp, slew-limited": (lambda: dataclasses.replace(
        _cfg(), controller=dataclasses.replace(_cfg().controller, setpoint_ramp_m_per_s=1e-11,
                                               slew_v_per_s=0.05)), 20_000),
}


def _run(cfg: Config, n: int, kernel: str) -> tuple[VirtualStand, int]:
    with VirtualStand(cfg, 7, start_wall_ns=1_700_000_000_000_000_000, kernel=kernel) as vs:
        _script(vs, n, idle=cfg.loop.max_step_m == 0)
        return vs, 0 if vs._kernel is None else vs._kernel.cycles


def _events(vs: VirtualStand) -> list[tuple[object, ...]]:
    return [(e.t_s, e.kind, e.reason, sorted(e.detail.items())) for e in vs.recorder.events]


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("case", list(CASES))
def test_kernel_matches_the_objects_bit_for_bit(case: str, mode: str) -> None:
    make, n = CASES[case]
    ref, _ = _run(make(), n, "off")
    got, kernel_cycles = _run(make(), n, mode)
    a, b = ref.recorded(), got.recorded()
    for name in ("t_s", "sensor_m", "applied_v", "tilt_rad"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert _events(got) == _events(ref)
    assert got.loop.last == ref.loop.last
    assert got.loop.state == ref.loop.state
    assert got.loop.pid._i == ref.loop.pid._i and got.loop.pid._df == ref.loop.pid._df
    if ref.loop.pid._res is not None:
        assert got.loop.pid._res._re == ref.loop.pid._res._re
        assert any(ref.loop.pid._res._re), "the resonant terms never ran"
    assert got.stand.sensor.plant.pendulum.theta == ref.stand.sensor.plant.pendulum.theta
    cycles = len(a.t_s) - 1
    assert kernel_cycles > 0.5 * cycles, "the kernel ran too little of the run to be tested"
    if case == "railing, spiking, stuck":  # the objects took the cycles the kernel must not
        assert kernel_cycles < 0.99 * cycles
        assert {"railed", "spike", "stuck"} <= {e[2].split()[2] for e in _events(ref)
                                                 if e[2].startswith("sensor reading")}


@pytest.mark.parametrize("mode", MODES)
def test_a_delayed_piezo_is_left_to_the_objects(mode: str) -> None:
    """The kernel steps no delay (`leveler.sim.pendulum.delayed_slew` is the plant's):
    given a stand with one, it had run the day without it."""
    cfg = _cfg()
    cfg = dataclasses.replace(cfg, plant=dataclasses.replace(
        cfg.plant, effects=cfg.plant.effects.with_effect(ActuatorDelay(delay_s=0.03))))
    ref, _ = _run(cfg, 12_000, "off")
    got, kernel_cycles = _run(cfg, 12_000, mode)
    assert np.array_equal(ref.recorded().sensor_m, got.recorded().sensor_m)
    assert kernel_cycles == 0
    assert "actuator" in _Kernel.unsupported(got)


def _messages(path: Path) -> list[tuple[str, int, int, bytes]]:
    with open(path, "rb") as f:
        return [(ch.topic, m.log_time, m.sequence, m.data)
                for _, ch, m in make_reader(f).iter_messages(log_time_order=False)]


@pytest.mark.parametrize("mode", MODES[-1:])
def test_kernel_log_is_the_objects_log_byte_for_byte(mode: str, tmp_path: Path) -> None:
    cfg = _noisy_screened()
    logs = {}
    for kernel in ("off", mode):
        out = tmp_path / f"{kernel}.mcap"
        with (LogWriter(out, truth=True) as writer,
              VirtualStand(cfg, 3, sinks=[writer], start_wall_ns=0, kernel=kernel) as vs):
            _script(vs, 20_000, idle=False)
        logs[kernel] = _messages(out)
    assert len(logs["off"]) > 2 * 12_000  # samples and truth of three fifths of 20,000 cycles
    assert logs[mode] == logs["off"]


def test_columns_encode_as_records_do() -> None:
    """Awkward values through the bulk path: NaN (null), -0.0, infinities, subnormals."""
    values = [math.nan, -0.0, math.inf, -math.inf, 5e-324, 1e300, 0.1, 75.0]
    n = len(values)
    samples = [Sample(i, 0.1 * i, 2**40 + i, v, 3, v, -v, v, v, v, v, v, i % 2 == 0, "fault")
               for i, v in enumerate(values)]
    truths = [Truth(i, 0.1 * i, v, v, v, v, v, v, v) for i, v in enumerate(values)]
    cols = Columns({"seq": np.arange(n), "t_s": [s.t_s for s in samples],
                    "raw_counts": np.array([s.raw_counts for s in samples]),
                    "sensor_m": np.array(values), "status": 3, "setpoint_m": values,
                    "error_m": -np.array(values), "p_v": values, "i_v": values, "d_v": values,
                    "command_v": values, "applied_v": values,
                    "saturated": np.arange(n) % 2 == 0, "state": "fault"},
                   {"seq": np.arange(n), "t_s": [t.t_s for t in truths],
                    **{k: values for k in ("tilt_rad", "thermal_tilt_rad", "cooler_tilt_rad",
                                           "piezo_tilt_rad", "pendulum_rad", "temperature_k",
                                           "sensor_drift_m")}},
                   list(range(n)))
    from leveler.log.writer import _SAMPLE_TEMPLATE, _TRUTH_TEMPLATE

    assert [_SAMPLE_TEMPLATE % r for r in cols.rows("sample")] == [encode(s) for s in samples]
    assert [_TRUTH_TEMPLATE % r for r in cols.rows("truth")] == [encode(t) for t in truths]
    assert orjson.loads(encode(samples[0]))["sensor_m"] is None


def test_columns_refuse_what_they_cannot_encode() -> None:
    good = {"seq": [0, 1], "t_s": [0.0, 0.1], "raw_counts": [1, 2], "sensor_m": [0.0, 0.0],
            "status": 0, "setpoint_m": 0.0, "error_m": [0.0, 0.0], "p_v": 0.0, "i_v": 0.0,
            "d_v": 0.0, "command_v": [1.0, 1.0], "applied_v": [1.0, 1.0], "saturated": False,
            "state": "engaged"}
    Columns(good, None, [0, 1])
    with pytest.raises(ValueError, match="sensor_m has 1 values, not 2"):
        Columns({**good, "sensor_m": [0.0]}, None, [0, 1])
    with pytest.raises(ValueError, match="state: only numbers and bools"):
        Columns({**good, "state": ["engaged", "idle"]}, None, [0, 1])
    with pytest.raises(ValueError, match="sample columns must be"):
        Columns({k: v for k, v in good.items() if k != "p_v"}, None, [0, 1])


def test_an_unknown_kernel_is_refused() -> None:
    with pytest.raises(ValueError, match="kernel must be one of auto, numba, python, off"):
        VirtualStand(_cfg(), 1, kernel="fast")
