"""The daemon levels the simulated plant as well through `leveler emulate` (Modbus TCP on
127.0.0.1, serial on ptys) as on the direct simulated backend, over the same time.

Three real daemons run side by side for the same 92 s, on config/sim.toml,
config/lab-modbus.toml and config/lab-serial.toml with the same plant and gains. To make a
minute and a half tell, the test plant is a faster pendulum (inertia 5e-5 kg m^2: resonance
2.2 Hz) under gains near the crossover `leveler tune --suggest` proposes for it (190 mHz), and
the water cooler's tilt sawtooth is 40 s, 0.4 urad peak to peak. Suppression is the amplitude
of the cooler's fundamental at the sensor in open loop (the same plant in virtual time, loop
open) over that in each daemon's log (a lock-in over two whole periods after 8 s of pull-in).
"""

from __future__ import annotations

import re
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import daemon_config

from leveler.log.reader import read_log
from leveler.settings import load_config
from leveler.virtual import run_virtual

REPO_CONFIG = Path(__file__).resolve().parents[1] / "config"
PERIOD_S = 40.0
SETTLE_S = 8.0
RUN_S = SETTLE_S + 2 * PERIOD_S + 4.0
FAST_PLANT = {
    "inertia_kgm2 = 5.0e-4": "inertia_kgm2 = 5.0e-5",
    "period_s = 300.0": f"period_s = {PERIOD_S}",
    "peak_to_peak_rad = 2.8e-8": "peak_to_peak_rad = 4.0e-7",
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def lock_in_amplitude(t_s: np.ndarray, y: np.ndarray, freq_hz: float) -> float:
    """Amplitude of the sinusoid at freq_hz in y, fitted with an offset and a linear trend."""
    w = 2 * np.pi * freq_hz
    a = np.column_stack([np.cos(w * t_s), np.sin(w * t_s), np.ones_like(t_s), t_s - t_s[0]])
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    return float(np.hypot(coef[0], coef[1]))


def _closed_loop_amplitude(log_dir: Path) -> tuple[float, int]:
    """The cooler's amplitude at the sensor over two periods after the pull-in, and how
    many samples of that window were not good and engaged."""
    log = read_log(next(log_dir.glob("*.mcap")))
    assert log.complete
    s = log.samples
    t = s["t_s"]
    window = (t >= SETTLE_S) & (t < SETTLE_S + 2 * PERIOD_S)
    good = window & (s["status"] == 0) & (s["state"] == "engaged")
    return lock_in_amplitude(t[good], s["sensor_m"][good], 1 / PERIOD_S), int(
        window.sum() - good.sum())


@pytest.mark.slow  # 95 s of real time; make test-slow (make test keeps the per-backend e2e tests)
def test_emulated_hardware_levels_as_well_as_the_direct_simulated_backend(
        tmp_path: Path) -> None:
    port = free_port()
    replace = {**FAST_PLANT, "port = 5020": f"port = {port}",
               'port = "/tmp/leveler-sensor"': f'port = "{tmp_path / "sensor"}"',
               'port = "/tmp/leveler-piezo"': f'port = "{tmp_path / "piezo"}"'}
    configs = {}
    for base in ("sim.toml", "lab-modbus.toml", "lab-serial.toml"):
        d = tmp_path / base.removesuffix(".toml")
        d.mkdir()
        configs[base] = daemon_config(d, d / "c.sock", rate_hz=10.0, base=base,
                                      replace={k: v for k, v in replace.items()
                                               if k in (REPO_CONFIG / base).read_text()})
        # One controller for all three, whatever each config ships with: integral-only,
        # as fast as the fast plant allows.
        text, n = re.subn(r"(?m)^(ki_v_per_m_s|kd_v_s_per_m) = .*$",
                          lambda m: f"{m[1]} = {1.3e7 if m[1].startswith('ki') else 0.0}",
                          configs[base].read_text())
        assert n == 2, base
        configs[base].write_text(text)
    emulators = [subprocess.Popen([sys.executable, "-m", "leveler.cli", "emulate", kind,
                                   "--config", str(configs[base])],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for kind, base in (("modbus", "lab-modbus.toml"), ("serial", "lab-serial.toml"))]
    try:
        for emu in emulators:
            assert emu.stdout is not None
            assert "leveler emulate" in emu.stdout.readline(), emu.communicate(timeout=10)
        daemons = [subprocess.Popen([sys.executable, "-m", "leveler.cli", "run", "--config",
                                     str(c), "--duration", f"{RUN_S}s"], cwd=c.parent,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                   for c in configs.values()]
        for proc in daemons:
            _, err = proc.communicate(timeout=RUN_S + 60)
            assert proc.returncode == 0, err
    finally:
        for emu in emulators:
            emu.terminate()
            emu.communicate(timeout=10)

    cfg, _ = load_config(configs["sim.toml"])
    open_loop = run_virtual(cfg, RUN_S, cfg.sim.seed, engaged=False)
    t = np.arange(len(open_loop.sensor_m)) / cfg.loop.rate_hz
    window = (t >= SETTLE_S) & (t < SETTLE_S + 2 * PERIOD_S)
    a_open = lock_in_amplitude(t[window], open_loop.sensor_m[window], 1 / PERIOD_S)
    suppression = {}
    for base, config in configs.items():
        a_closed, not_good = _closed_loop_amplitude(config.parent / "logs")
        # A lone driver error on a loaded machine holds one sample; more means trouble.
        assert not_good <= 8, f"{base}: {not_good} samples in the window not good and engaged"
        suppression[base] = a_open / a_closed
    print(f"\ncooler fundamental {a_open * 1e9:.1f} nm open loop; suppression "
          + ", ".join(f"{b}: {s:.2f}x" for b, s in suppression.items()))
    assert suppression["sim.toml"] > 4.0  # the loop does real work at 25 mHz
    for base in ("lab-modbus.toml", "lab-serial.toml"):
        assert abs(suppression[base] / suppression["sim.toml"] - 1) <= 0.2, suppression
