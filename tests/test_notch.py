"""The notch on the reading (leveler.loop.notch) and its design against a named mode
(leveler.analysis.notch): the filter is the transfer function it claims, the PID switches it
bumplessly, the daemon's numpy stability check holds its states as python-control does, and
a designed notch keeps the margins over every tolerance corner where the current loop did
not, and takes a mode's line out of the true tilt when the stand is simulated."""

from __future__ import annotations

import dataclasses
import math

import control
import numpy as np
import pytest

from leveler.analysis import notch as design_notch
from leveler.analysis import periodic
from leveler.analysis.spectral import asd_at
from leveler.analysis.stability import closed_loop_matrix, predicted_instability
from leveler.analysis.suggest import controller_tf, plant_tf
from leveler.loop.notch import Notch, NotchFilter
from leveler.loop.pid import PID, ControllerConfig
from leveler.settings import Config, load_config
from leveler.sim.effects import ExtraResonance
from leveler.typed_config import ConfigError
from leveler.virtual import VirtualStand, _Kernel, run_virtual

from conftest import REPO  # isort: skip

CFG = load_config(REPO / "config" / "sim.toml")[0]
RATE = CFG.loop.rate_hz


def _with_mode(cfg: Config, **mode: float) -> Config:
    plant = dataclasses.replace(cfg.plant, effects=cfg.plant.effects.with_effect(
        ExtraResonance(**mode)))
    return dataclasses.replace(cfg, plant=plant)


def _response(n: Notch, f_hz: float, rate_hz: float) -> complex:
    (b0, b1, b2), (a1, a2) = n.coefficients(1.0 / rate_hz)
    z = np.exp(2j * np.pi * f_hz / rate_hz)
    return complex((b0 * z * z + b1 * z + b2) / (z * z + a1 * z + a2))


@pytest.mark.parametrize(("f", "q", "depth", "rate"), [
    (1.5, 5.0, 0.0, 10.0), (1.5, 2.0, 0.3, 10.0), (4.0, 1.0, 0.1, 10.0), (60.0, 10.0, 0.0, 1e3)])
def test_the_filter_is_the_notch_it_claims(f: float, q: float, depth: float,
                                           rate: float) -> None:
    n = Notch(f, q, depth)
    assert abs(_response(n, f, rate)) == pytest.approx(depth, abs=1e-9)
    assert abs(_response(n, 1e-6, rate)) == pytest.approx(1.0, abs=1e-9)  # 0 Hz passes
    assert abs(_response(n, rate / 2 * (1 - 1e-9), rate)) == pytest.approx(1.0, abs=1e-6)
    assert abs(_response(n, f / 20, rate)) > 0.99  # far below: untouched
    # the sample-by-sample filter is that transfer function: a sine at f comes out at depth
    filt, dt = NotchFilter(n, 1.0 / rate), 1.0 / rate
    t = np.arange(int(40 * q * rate / f) + 400) * dt
    out = np.array([filt.step(x, dt) for x in np.sin(2 * np.pi * f * t)])
    tail = out[-int(10 * rate / f):]
    assert np.max(np.abs(tail)) == pytest.approx(depth, abs=0.01)


def test_a_seeded_filter_passes_a_constant_and_the_nyquist_limit_is_refused() -> None:
    filt = NotchFilter(Notch(1.5, 3.0, 0.2), 0.1)
    filt.seed(4.2e-7)
    assert all(filt.step(4.2e-7, 0.1) == pytest.approx(4.2e-7, rel=1e-12) for _ in range(50))
    with pytest.raises(ValueError, match="Nyquist"):
        Notch(5.0).coefficients(0.1)
    for bad in ({"q": 0.0}, {"depth": 1.0}, {"depth": -0.1}):
        with pytest.raises(ValueError):
            Notch(1.0, **bad)


def test_a_notch_above_nyquist_in_the_config_names_the_key_and_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "lab.toml"
    path.write_text((REPO / "config" / "sim.toml").read_text().replace(
        "slew_v_per_s = 10.0\n", "slew_v_per_s = 10.0\nnotch_frequency_hz = 6.0\n", 1))
    with pytest.raises(ConfigError, match=r"lab\.toml: controller\.notch_frequency_hz 6 Hz "
                                          r"is at or above the loop's Nyquist"):
        load_config(path)


def _settled_pid(c: ControllerConfig, y: float = 3e-8) -> PID:
    """Held at a reading of y = the setpoint, with a little noise on it."""
    pid = PID(dataclasses.replace(c, setpoint_m=y).pid_config(), initial_output_v=75.0)
    for k in range(400):
        pid.update(y + 1e-10 * math.sin(0.9 * k), 0.1)
    return pid


@pytest.mark.parametrize("on", [True, False])
def test_switching_the_notch_is_bumpless(on: bool) -> None:
    c = CFG.controller
    notched = dataclasses.replace(c, notch_frequency_hz=1.5, notch_q=3.0, notch_depth=0.1)
    pid = _settled_pid(c if on else notched)
    last = pid.output_v
    pid.set_notch(notched.notch() if on else None)
    assert pid.config.notch == (notched.notch() if on else None)
    y = 3e-8 + 1e-10 * math.sin(0.9 * 400)
    ref = _settled_pid(c if on else notched)
    ref_next = ref.update(y, 0.1).command_v  # what the old controller would do next
    nxt = pid.update(y, 0.1).command_v
    assert abs(nxt - last) <= 2 * abs(ref_next - last) + 1e-9, (nxt, ref_next, last)


def test_a_constant_reading_gives_the_same_commands_with_and_without_a_notch() -> None:
    c = CFG.controller
    a = PID(c.pid_config(), initial_output_v=70.0)
    b = PID(dataclasses.replace(c, notch_frequency_hz=2.0).pid_config(), initial_output_v=70.0)
    for _ in range(200):
        assert b.update(1e-8, 0.1).command_v == pytest.approx(a.update(1e-8, 0.1).command_v,
                                                               rel=1e-9, abs=1e-9)
    b.engage(2e-8, 71.0)  # an engage restarts the filter from that reading: no bump
    assert b.update(2e-8, 0.1).command_v == pytest.approx(71.0, abs=1e-9)


@pytest.mark.parametrize("n", [Notch(1.5, 5.0, 0.3), Notch(0.3, 0.7, 0.0), Notch(3.0, 2.0, 0.1)])
def test_the_daemons_check_holds_the_notch_as_python_control_does(n: Notch) -> None:
    c = CFG.controller
    m = closed_loop_matrix(CFG.plant, RATE, c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m,
                           c.d_filter_tau_s, None, n)
    (b0, b1, b2), (a1, a2) = n.coefficients(1.0 / RATE)
    filt = control.tf([b0, b1, b2], [1.0, a1, a2], 1.0 / RATE)
    loop = filt * controller_tf(c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m,
                                c.d_filter_tau_s, RATE) * plant_tf(CFG.plant, RATE)
    ref = np.sort_complex(np.asarray(control.feedback(loop, 1).poles()))
    ours = np.sort_complex(np.linalg.eigvals(m))
    ours = ours[np.abs(ours) > 1e-9]  # the matrix's zero poles (python-control drops them)
    ref = ref[np.abs(ref) > 1e-9]
    np.testing.assert_allclose(np.abs(ours), np.abs(ref), atol=1e-6)
    # a loop the notch makes unstable is refused: ki x 30 with the shipped D
    assert predicted_instability(CFG.plant, RATE, 0.0, c.ki_v_per_m_s * 30, c.kd_v_s_per_m,
                                 c.d_filter_tau_s, None, n) is not None


@pytest.mark.parametrize("mode", [
    {"frequency_hz": 1.5, "q": 20.0, "gain": -0.2},  # eats the gain margin
    {"frequency_hz": 2.5, "q": 30.0, "gain": -0.5},  # unstable on a tolerance corner
    {"frequency_hz": 1.5, "q": 12.0, "noise_rms_m": 2e-9},  # rung by the floor
])
def test_a_designed_notch_keeps_the_margins_over_every_corner(mode: dict[str, float]) -> None:
    cfg = _with_mode(CFG, **mode)
    d = design_notch.design(cfg.plant, RATE, cfg.controller)
    assert d.ours.stable and d.ours.gain_margin_db >= 6.0 and d.ours.phase_margin_deg >= 40.0
    assert d.ours.corners == (65 if mode.get("gain") else 17)
    assert not d.theirs.ok  # the current loop missed the goals on some model
    assert periodic.refusal(d.ours, d.theirs) == ""
    assert design_notch.not_needed(d) == ""
    n = d.controller.notch()
    assert n is not None and n.frequency_hz == mode["frequency_hz"]
    # each corner again, through the daemon's own numpy check (another code path; the
    # pendulum only, so it holds the notch and the scaled gains, not the mode)
    c = d.controller
    assert predicted_instability(cfg.plant, RATE, c.kp_v_per_m, c.ki_v_per_m_s,
                                 c.kd_v_s_per_m, c.d_filter_tau_s, None, n) is None


def test_a_slow_loop_needs_no_notch() -> None:
    lab = load_config(REPO / "config" / "lab.toml")[0]  # integral only, ~10 mHz crossover
    cfg = _with_mode(lab, frequency_hz=1.5, q=20.0, gain=-0.2)
    d = design_notch.design(cfg.plant, lab.loop.rate_hz, lab.controller)
    why = design_notch.not_needed(d)
    assert "No notch suggested" in why and "|L| = " in why, why
    with pytest.raises(ValueError, match="Nyquist"):
        design_notch.design(_with_mode(CFG, frequency_hz=7.0, q=20.0, gain=-0.2).plant, RATE,
                            CFG.controller)


def test_the_notch_takes_the_mode_out_of_the_true_tilt() -> None:
    """Simulated, with the loop's own objects: the mode rung by the floor, which the loop
    copied onto the table, is under the sensor floor's level there with the notch."""
    cfg = _with_mode(CFG, frequency_hz=1.5, q=12.0, noise_rms_m=2e-9)
    d = design_notch.design(cfg.plant, RATE, cfg.controller)
    runs = [run_virtual(dataclasses.replace(cfg, controller=c), 1800.0, 11, engaged=True)
            for c in (cfg.controller, d.controller)]
    floor = asd_at(periodic.floor_tilt(cfg, len(runs[0].tilt_rad), 11), RATE, [1.5])[0]
    was, now = (asd_at(r.tilt_rad[600:], RATE, [1.5])[0] for r in runs)
    assert was > 5 * floor, (was, floor)
    assert now < was / 4 and now < 3 * floor, (was, now, floor)


def test_the_kernel_leaves_a_notched_loop_to_the_objects() -> None:
    cfg = dataclasses.replace(CFG, controller=dataclasses.replace(
        CFG.controller, notch_frequency_hz=1.5))
    with VirtualStand(cfg, 1, kernel="python") as vs:
        assert _Kernel.unsupported(vs) == "a notch on the reading"
        vs.run(60_000)
        assert vs._kernel is None


def test_a_refused_sample_leaves_the_notch_as_it_was() -> None:
    """An overflowing reading raises and changes nothing, the notch's state included."""
    c = dataclasses.replace(CFG.controller, notch_frequency_hz=1.5, kp_v_per_m=1e6)
    a, b = (PID(c.pid_config(), initial_output_v=70.0) for _ in range(2))
    for k in range(50):
        for pid in (a, b):
            pid.update(1e-8 * math.sin(0.3 * k), 0.1)
    with pytest.raises(OverflowError):
        a.update(1e308, 0.1)
    for k in range(50, 60):
        assert a.update(1e-8 * math.sin(0.3 * k), 0.1).command_v == \
            b.update(1e-8 * math.sin(0.3 * k), 0.1).command_v
