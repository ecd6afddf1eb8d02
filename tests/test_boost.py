"""The PID's double integral (ki2) and the boost chosen from the model's tolerances
(leveler.analysis.boost, `tune --suggest --boost`): the running controller is the transfer
function the analysis uses, its closed loop has python-control's poles, switching it is
bumpless and it does not wind up on a rail; the boost keeps the margins on every corner,
and simulated it takes the cooler's lines down to the sensor floor without resonant terms."""

from __future__ import annotations

import dataclasses
import json
import math

import control
import numpy as np
import pytest

from leveler.analysis import boost, periodic
from leveler.analysis.spectral import asd_at
from leveler.analysis.stability import closed_loop_matrix
from leveler.analysis.suggest import controller_tf, plant_tf
from leveler.log.reader import read_log
from leveler.loop.notch import Notch
from leveler.loop.pid import PID, PIDGains
from leveler.settings import load_config
from leveler.virtual import VirtualStand, _Kernel, run_virtual

from conftest import REPO  # isort: skip

CFG = load_config(REPO / "config" / "sim.toml")[0]
RATE = CFG.loop.rate_hz
KI2 = 2e7


def test_the_running_double_integral_is_the_analysed_transfer_function() -> None:
    c = dataclasses.replace(CFG.controller, kp_v_per_m=1e5, ki2_v_per_m_s2=KI2,
                            slew_v_per_s=math.inf, output_min_v=-1e9, output_max_v=1e9)
    pid = PID(c.pid_config(), initial_output_v=0.0)
    pid.update(0.0, 0.1)
    e = np.random.default_rng(3).normal(size=80) * 1e-9
    out = np.array([pid.update(-x, 0.1).command_v for x in e])  # error = setpoint - reading
    tf = controller_tf(1e5, c.ki_v_per_m_s, c.kd_v_s_per_m, c.d_filter_tau_s, RATE, KI2)
    _, ref = control.forced_response(tf, T=np.arange(80) * 0.1, U=e)
    np.testing.assert_allclose(out, ref, atol=1e-12 * np.max(np.abs(ref)) + 1e-15)


@pytest.mark.parametrize("notch", [None, Notch(1.5, 3.0, 0.2)])
def test_the_daemons_check_has_python_controls_poles(notch: Notch | None) -> None:
    c = CFG.controller
    m = closed_loop_matrix(CFG.plant, RATE, 1e5, c.ki_v_per_m_s, c.kd_v_s_per_m,
                           c.d_filter_tau_s, None, notch, KI2)
    ctrl = control.ss(controller_tf(1e5, c.ki_v_per_m_s, c.kd_v_s_per_m, c.d_filter_tau_s,
                                    RATE, KI2))
    if notch is not None:
        (b0, b1, b2), (a1, a2) = notch.coefficients(1.0 / RATE)
        ctrl = control.series(control.ss(control.tf([b0, b1, b2], [1, a1, a2], 1 / RATE)), ctrl)
    closed = control.feedback(control.series(ctrl, control.ss(plant_tf(CFG.plant, RATE))), 1)
    ref = np.sort(np.abs(np.linalg.eigvals(closed.A)))[::-1]
    ours = np.sort(np.abs(np.linalg.eigvals(m)))[::-1]
    np.testing.assert_allclose(ours[:len(ref)], ref, atol=1e-7)
    assert np.all(ours[len(ref):] < 1e-9)


def _held(c: PIDGains, y: float = 3e-8) -> PID:
    cfg = dataclasses.replace(CFG.controller, setpoint_m=y, ki2_v_per_m_s2=c.ki2)
    pid = PID(cfg.pid_config(), initial_output_v=75.0)
    for k in range(300):
        pid.update(y + 1e-10 * math.sin(0.7 * k), 0.1)
    return pid


@pytest.mark.parametrize("ki2", [0.0, KI2])
def test_switching_the_double_integral_is_bumpless(ki2: float) -> None:
    c = CFG.controller
    pid = _held(PIDGains(c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m, ki2))
    last = pid.output_v
    pid.set_gains(PIDGains(c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m, KI2 - ki2))
    y = 3e-8 + 1e-10 * math.sin(0.7 * 300)
    ref = _held(PIDGains(c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m, ki2))
    step = abs(ref.update(y, 0.1).command_v - last)
    assert abs(pid.update(y, 0.1).command_v - last) <= 2 * step + 1e-9


def test_the_double_integral_does_not_wind_up_on_a_rail() -> None:
    c = dataclasses.replace(CFG.controller, ki2_v_per_m_s2=KI2)
    pid = PID(c.pid_config(), initial_output_v=75.0)
    for _ in range(50):
        pid.update(-1e-6, 0.1)  # far below the setpoint: the command runs to its rail
    held = pid._s1
    for _ in range(200):
        out = pid.update(-1e-6, 0.1)
    assert out.command_v == c.output_max_v and pid._s1 == held  # frozen while railed
    for _ in range(30):  # the error reverses: the command leaves the rail within seconds
        out = pid.update(1e-6, 0.1)
    assert out.command_v < c.output_max_v - 1.0


def test_the_boost_keeps_the_margins_and_takes_the_cooler_to_the_floor() -> None:
    b = boost.design(CFG.plant, RATE, CFG.controller)
    assert b is not None and b.ours.ok and b.ours.stable
    assert b.suppression >= 200 and b.suppression >= 2 * b.current_suppression
    c = b.controller
    assert c.ki2_v_per_m_s2 > 0 and c.periodic_terms() is None
    with pytest.raises(ValueError, match="double integral"):
        periodic.design(CFG.plant, RATE, c, 300.0)
    hours = 6
    lines = [h / 300.0 for h in (1, 2, 3)]
    runs = [run_virtual(dataclasses.replace(CFG, controller=x), hours * 3600.0, 5,
                        engaged=True) for x in (CFG.controller, c)]
    floor = asd_at(periodic.floor_tilt(CFG, len(runs[0].tilt_rad), 5), RATE, lines)
    was, now = (asd_at(r.tilt_rad, RATE, lines) / floor for r in runs)
    assert np.all(was > 1.5), was
    assert np.all(now < 1.35), now


def test_the_kernel_leaves_a_double_integral_to_the_objects() -> None:
    cfg = dataclasses.replace(CFG, controller=dataclasses.replace(CFG.controller,
                                                                  ki2_v_per_m_s2=KI2))
    with VirtualStand(cfg, 1, kernel="python") as vs:
        assert _Kernel.unsupported(vs) == "a double integral"


def test_suggest_boost_applies_on_a_daemon(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(rate_hz=10.0)
    out = d.cli("tune", "--suggest", "--boost", "--predict-hours", "0", "--apply", timeout=120)
    assert out.returncode == 0, out.stderr
    assert "with a double integral" in out.stdout and "applied: " in out.stdout
    status = json.loads(d.cli("status", "--json").stdout)
    shown = d.cli("status").stdout
    d.stop()
    ki2 = status["controller"]["ki2_v_per_m_s2"]
    assert ki2 > 0 and f"ki2 {ki2:.4g} V/(m s^2)" in shown
    tune = [e for e in read_log(next(d.logs.glob("*.mcap"))).events if e["kind"] == "tune"]
    assert tune and "ki2_v_per_m_s2" in tune[-1]["detail"]
