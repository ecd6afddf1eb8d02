"""The bench's baselines are what they claim to be (short runs; the timings are `make bench`'s)."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture
def bench_path(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.syspath_prepend(str(BENCH))
    yield
    for name in ("common", "sim_speed", "logging_speed", "pid_speed", "daemon_startup"):
        sys.modules.pop(name, None)


def _import(name: str) -> ModuleType:
    return __import__(name)


def test_python_control_twin_is_the_same_loop(bench_path: None) -> None:
    """python-control's closed loop reproduces leveler's Plant + PID exactly, so steps/s
    compare the simulators and nothing else."""
    sim = _import("sim_speed")
    cfg = sim.nonlinear(sim.load_config(sim.CONFIG)[0])
    n = 300
    _, pc_y, pc_cmd = sim.python_control_steps(cfg, n)
    _, lev_y, lev_cmd = sim.leveler_steps(cfg, n)
    assert (pc_y == lev_y).all() and (pc_cmd == lev_cmd).all()
    assert lev_cmd.std() > 0  # the controller did something


def test_raw_and_leveler_logs_hold_the_same_samples(bench_path: None, tmp_path: Path) -> None:
    import json

    from mcap.reader import make_reader

    from leveler.log.reader import read_log

    lg = _import("logging_speed")
    pool = lg.sample_pool(500)
    n = 1200  # cycles through the pool
    lg.raw_write(tmp_path / "raw.mcap", pool, n)
    lg.leveler_write(tmp_path / "lev.mcap", pool, n)
    with open(tmp_path / "raw.mcap", "rb") as f:
        raw = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages()]
    assert len(raw) == n and raw[700] == json.loads(json.dumps(
        {k: getattr(pool[200], k) for k in pool[200].__slots__}))
    log = read_log(tmp_path / "lev.mcap")
    assert log.complete and len(log.samples["seq"]) == n
    assert log.samples["sensor_m"][700] == pool[200].sensor_m == raw[700]["sensor_m"]


def test_pid_baseline_gets_the_same_job(bench_path: None) -> None:
    simple_pid = pytest.importorskip("simple_pid")
    ps = _import("pid_speed")
    ms = ps.measurements(20_000)  # one period of the swing
    lev = ps.leveler_pid()
    ref = simple_pid.PID(ps.KP, ps.KI, ps.KD, setpoint=2.0e-6, sample_time=None,
                         output_limits=(ps.LO, ps.HI), starting_output=75.0)
    outs = [lev.update(m, ps.DT).command_v for m in ms]
    refs = [ref(m, dt=ps.DT) for m in ms]
    # Both rail both ways on this input: the features (slew, anti-windup) are exercised.
    assert min(outs) == ps.LO and max(outs) == ps.HI
    assert min(refs) == ps.LO and max(refs) == ps.HI


def test_the_startup_bench_times_a_real_daemon_to_ready(bench_path: None, tmp_path: Path) -> None:
    """daemon_startup's figures come from a real daemon's READY=1 and its /proc status, on
    a config that reports READY after one good sample and logs into the scratch directory."""
    ds = _import("daemon_startup")
    config = ds._config(tmp_path, "sim.toml", {})
    text = config.read_text()
    assert "ready_samples = 1" in text and f'dir = "{tmp_path / "logs"}"' in text
    ready_s, rss_mib = ds.start(config, tmp_path)
    assert 0.05 < ready_s < 30 and 30 < rss_mib < 1000
    assert list((tmp_path / "logs").glob("*.mcap"))  # it ran and logged where it was told
    base_s, base_mib = ds.baseline()
    assert 0 < base_s < ready_s and 5 < base_mib < rss_mib  # numpy alone: less of both
