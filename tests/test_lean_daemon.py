"""A daemon on hardware imports no simulation, analysis or plotting stack (issue 21): scipy,
matplotlib and python-control stay out of the real-time process. Judged on the real daemon
on config/lab-modbus.toml against the Modbus emulator on loopback: a sitecustomize hook
writes every module the process has imported (sys.modules) as it exits."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from conftest import daemon_config
from test_backend_parity import free_port

from leveler.emulate.modbus import ModbusEmulator
from leveler.settings import load_config
from leveler.sim.plant import Plant

HEAVY = ("scipy", "matplotlib", "control")


HOOK = """
import atexit, os, sys
def _write_modules():
    with open(os.environ["LEVELER_TEST_MODULES"], "w") as f:
        f.write("\\n".join(sorted(sys.modules)))
atexit.register(_write_modules)
"""


def run_and_log_imports(start_daemon: Callable[..., object], tmp_path: Path, base: str,
                        replace: dict[str, str] | None = None) -> set[str]:
    """The top-level packages a daemon on `base` had imported when it stopped."""
    hook, modules = tmp_path / "hook", tmp_path / "modules.txt"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(HOOK)
    d = start_daemon(rate_hz=10.0, base=base, replace=replace,
                     env={"PYTHONPATH": str(hook), "LEVELER_TEST_MODULES": str(modules)})
    d.wait_status_lines(2)  # type: ignore[attr-defined]
    d.cli("status")  # type: ignore[attr-defined]  # the control path's imports too
    d.stop()  # type: ignore[attr-defined]
    return {m.split(".")[0] for m in modules.read_text().split()}


def test_a_daemon_on_hardware_imports_no_scipy_matplotlib_or_control(
        start_daemon: Callable[..., object], tmp_path: Path) -> None:
    replace = {"port = 5020": f"port = {free_port()}"}
    (tmp_path / "emu").mkdir()
    cfg, _ = load_config(daemon_config(tmp_path / "emu", tmp_path / "unused.sock",
                                       rate_hz=10.0, base="lab-modbus.toml", replace=replace))
    s, a = cfg.sensor.modbus, cfg.actuator.modbus
    assert s is not None and a is not None
    with ModbusEmulator(Plant(cfg.plant, 0.1, cfg.sim.seed), s, a, port=s.port):
        hardware = run_and_log_imports(start_daemon, tmp_path, "lab-modbus.toml", replace)
    assert {"numpy", "mcap", "pymodbus"} <= hardware  # the log is read: these are there
    assert not hardware & set(HEAVY), sorted(hardware & set(HEAVY))


def test_the_simulated_stand_imports_no_scipy_either(
        start_daemon: Callable[..., object], tmp_path: Path) -> None:
    """The simulated plant's filters are numpy alone (its thermal lag in closed form, a
    mode's noise scale by Parseval): scipy.signal, imported for lfilter, took a second of
    every `leveler run` on the sim backend (make run, and each daemon test)."""
    simulated = run_and_log_imports(start_daemon, tmp_path, "sim.toml")
    assert "numpy" in simulated and not simulated & set(HEAVY), sorted(simulated & set(HEAVY))
