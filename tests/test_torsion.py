"""The torsion-pendulum model: statics, eigenfrequency, gravity coupling, mass model, ZOH sim."""

from __future__ import annotations

import math

import numpy as np
import pytest

from leveler.sim.params import G_STANDARD
from leveler.sim.torsion import TorsionParams, com_offset_m, simulate, zoh_filter


def test_static_deflection_is_thrust_torque_over_pivot_stiffness() -> None:
    p = TorsionParams(com_y_m=0.0)
    fs = 5.0
    thrust = np.r_[np.zeros(5), np.full(round(600 * fs), 1e-6)]  # 60 decay times
    theta = simulate(p, 1 / fs, thrust)
    assert theta[0] == 0.0
    assert theta[-1] == pytest.approx(1e-6 * p.arm_m / p.stiffness_nm_per_rad, rel=1e-9)
    assert float(p.static_deflection_rad(1e-6)) == pytest.approx(1.25e-6, rel=1e-12)


def test_step_response_matches_the_analytic_underdamped_solution() -> None:
    p = TorsionParams()
    dt, n, step_at = 0.1, 4000, 7
    thrust = np.where(np.arange(n) >= step_at, 1e-6, 0.0)
    theta = simulate(p, dt, thrust, pitch_rad=0.0)
    k, j, lam = p.stiffness_nm_per_rad, p.inertia_kgm2, p.damping_nms_per_rad
    wn = math.sqrt(k / j)
    zeta = lam / (2 * math.sqrt(k * j))
    wd = wn * math.sqrt(1 - zeta**2)
    t = (np.arange(n) - step_at) * dt
    tp = np.clip(t, 0, None)
    exact = 1e-6 * p.arm_m / k * (1 - np.exp(-zeta * wn * tp) * (
        np.cos(wd * tp) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * tp)))
    exact[t <= 0] = 0.0
    assert np.max(np.abs(theta - exact)) < 1e-9 * np.max(exact)


def test_free_oscillation_is_at_sqrt_k0_over_j() -> None:
    for k0 in (0.2, 0.02):
        p = TorsionParams(stiffness_nm_per_rad=k0, damping_nms_per_rad=0.0, com_y_m=0.0)
        fs, duration = 20.0, 400.0
        thrust = np.r_[1e-6, np.zeros(round(duration * fs) - 1)]  # released from deflection
        theta = simulate(p, 1 / fs, thrust)
        ups = np.flatnonzero((theta[:-1] < 0) & (theta[1:] >= 0))
        # linear interpolation of the upward zero crossings
        times = (ups + theta[ups] / (theta[ups] - theta[ups + 1])) / fs
        f_measured = (len(times) - 1) / (times[-1] - times[0])
        assert f_measured == pytest.approx(p.natural_frequency_hz, rel=1e-4)
        assert p.natural_frequency_hz == pytest.approx(math.sqrt(k0 / 0.05) / (2 * math.pi))


def test_gravity_torque_sign_and_size() -> None:
    p = TorsionParams(mass_kg=2.0, com_x_m=1e-3, com_y_m=2e-4)
    mg = 2.0 * G_STANDARD
    # pitch couples l_cm,y, roll couples l_cm,x; positive tilt and offset add to positive thrust
    assert float(p.gravity_torque_nm(10e-6)) == pytest.approx(mg * math.sin(10e-6) * 2e-4)
    assert float(p.gravity_torque_nm(0.0, 10e-6)) == pytest.approx(mg * math.sin(10e-6) * 1e-3)
    assert float(p.gravity_torque_nm(-10e-6)) < 0
    assert float(p.static_deflection_rad(1e-6, 10e-6)) > float(p.static_deflection_rad(1e-6))
    # at rest the pendulum sits where K0 theta = F L + M g sin(pitch) l_cm,y
    theta = simulate(p, 0.2, np.full(10, 1e-6), pitch_rad=np.full(10, -5e-6))
    want = (1e-6 * p.arm_m + mg * math.sin(-5e-6) * 2e-4) / p.stiffness_nm_per_rad
    assert theta == pytest.approx(np.full(10, want), rel=1e-12)
    assert p.coupling_ratio(1e-6, 10e-6) == pytest.approx(mg * math.sin(10e-6) * 2e-4 / 0.25e-6)


def test_centre_of_mass_model() -> None:
    assert com_offset_m(2.0, 0.2, 3e-3) == pytest.approx(0.2 / 2.2 * 3e-3)
    p = TorsionParams.with_counterweight(2.0, 0.2, offset_y_m=3e-3, offset_x_m=-1e-3)
    assert p.mass_kg == pytest.approx(2.2)
    # the frame's gravity torque is the counterweight's alone (paper eqs. 8, 9)
    assert float(p.gravity_torque_nm(1e-5)) == pytest.approx(0.2 * G_STANDARD
                                                            * math.sin(1e-5) * 3e-3)
    assert float(p.gravity_torque_nm(0.0, 1e-5)) == pytest.approx(-0.2 * G_STANDARD
                                                                 * math.sin(1e-5) * 1e-3)
    assert TorsionParams().com_y_m == pytest.approx(com_offset_m(2.0, 0.2, 3e-3))
    with pytest.raises(ValueError):
        com_offset_m(-1.0, 0.2, 1e-3)


def test_defaults_match_the_documented_stand() -> None:
    p = TorsionParams()
    assert p.natural_frequency_hz == pytest.approx(0.318, abs=1e-3)
    assert p.quality_factor == pytest.approx(10.0)
    # the paper: tilt sensitivity "0.01 uN m per urad or lower"
    assert 0.001 < p.tilt_sensitivity_nm_per_rad < 0.01


@pytest.mark.parametrize("field", ["stiffness_nm_per_rad", "inertia_kgm2", "arm_m", "mass_kg"])
def test_invalid_parameters_are_rejected(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        TorsionParams(**{field: 0.0})
    with pytest.raises(ValueError, match="damping"):
        TorsionParams(damping_nms_per_rad=-1.0)


def test_zoh_filter_is_exact_for_a_first_order_lag() -> None:
    tau, dt = 3.0, 0.5
    y = zoh_filter([1.0], [tau, 1.0], dt, np.r_[0.0, np.ones(50)])
    t = np.arange(51) * dt
    exact = np.where(t > 0, 1 - np.exp(-(t - dt) / tau), 0.0)
    exact[0] = 0.0
    assert y == pytest.approx(exact, abs=1e-14)
    with pytest.raises(ValueError):
        zoh_filter([1.0], [1.0, 1.0], 0.0, np.ones(3))
