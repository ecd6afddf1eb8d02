"""The simulated plant against the paper's equations and python-control."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest

from leveler.sim.params import PendulumParams, PlantParams, SensorParams
from leveler.sim.pendulum import PendulumModel, equilibrium_angle, linear_matrices
from leveler.sim.plant import Plant
from leveler.typed_config import ConfigError, build


def paper_pendulum(**kw: object) -> PendulumParams:
    """k = 0.1 N m/rad and m g L_cm = 0.09 N m/rad exactly (the paper's example)."""
    base = {"mass_kg": 0.1, "com_length_m": 0.09 / (0.1 * 9.80665)}
    base.update(kw)
    return PendulumParams(**base)  # type: ignore[arg-type]


def test_amplification_is_the_papers_nine() -> None:
    p = paper_pendulum()
    assert p.amplification == pytest.approx(9.0, rel=1e-9)


@pytest.mark.parametrize("phi", [1e-9, 1e-7, 1e-6, 2e-5])
def test_small_angle_equilibrium_matches_n_within_1_percent(phi: float) -> None:
    p = paper_pendulum()
    theta = equilibrium_angle(p, phi)
    assert theta / phi == pytest.approx(p.amplification, rel=0.01)


def test_nonlinear_equilibrium_solves_the_transcendental_equation() -> None:
    p = paper_pendulum()
    phi = 1e-3  # the paper's reference tilt for the counterweight sweep
    theta = equilibrium_angle(p, phi)
    mgl, k = p.gravity_stiffness_nm_per_rad, p.flexure_stiffness_nm_per_rad
    assert mgl * math.sin(theta + phi) == pytest.approx(k * theta, rel=1e-12)
    # At 1 mrad the sin() curvature already shows: a little below the small-angle N.
    assert 0.99 * p.amplification < theta / phi < p.amplification


def test_nonlinear_dynamics_settle_at_the_root_solve() -> None:
    p = paper_pendulum(model="nonlinear", damping_nms_per_rad=2e-3)
    model = PendulumModel(p, dt_s=0.01)
    phi = 5e-3
    for _ in range(20000):
        model.step(phi)
    assert model.theta == pytest.approx(equilibrium_angle(p, phi), rel=1e-6)


def test_linear_and_nonlinear_agree_at_micro_radians() -> None:
    lin = PendulumModel(paper_pendulum(), 0.1)
    nl = PendulumModel(paper_pendulum(model="nonlinear"), 0.1)
    phis = 1e-6 * np.sin(np.arange(2000) * 0.05)
    a, b = [], []
    for phi in phis:
        a.append(lin.step(float(phi)))
        b.append(nl.step(float(phi)))
    assert np.max(np.abs(np.subtract(a, b))) < 2e-3 * np.max(np.abs(a))


def test_refuses_a_pendulum_with_no_stable_equilibrium() -> None:
    with pytest.raises(ConfigError, match="no stable equilibrium") as err:
        build(PlantParams, {"pendulum": {"mass_kg": 0.3}}, "plant")
    assert "plant.pendulum" in str(err.value)
    assert "m g L_cm" in str(err.value)


def test_linear_step_response_matches_python_control() -> None:
    p = PendulumParams()
    dt = 0.1
    a, b = linear_matrices(p)
    sys_c = control.ss(a, b, [[1.0, 0.0]], [[0.0]])
    n = 600
    t = np.arange(n) * dt
    phi = 1e-6
    resp = control.step_response(sys_c, T=t)
    expected = phi * np.squeeze(resp.outputs)
    model = PendulumModel(p, dt)
    got = [0.0]
    for _ in range(n - 1):
        got.append(model.step(phi))
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6 * phi * p.amplification)
    # and its DC gain is the amplification
    assert control.dcgain(sys_c) == pytest.approx(p.amplification, rel=1e-9)


def test_forced_response_with_random_tilt_matches_python_control() -> None:
    p = PendulumParams()
    dt = 0.1
    a, b = linear_matrices(p)
    sys_d = control.c2d(control.ss(a, b, [[1.0, 0.0]], [[0.0]]), dt, method="zoh")
    rng = np.random.default_rng(3)
    u = 1e-7 * rng.standard_normal(500)
    resp = control.forced_response(sys_d, U=u)
    model = PendulumModel(p, dt)
    got = [0.0]
    for val in u[:-1]:
        got.append(model.step(float(val)))
    np.testing.assert_allclose(got, np.squeeze(resp.outputs), rtol=1e-9, atol=1e-18)


def test_piezo_is_clamped_and_slew_limited() -> None:
    plant = Plant(PlantParams(), dt_s=0.1)
    pz = plant.params.piezo
    assert plant.command(1000.0) == pytest.approx(pz.ref_v + pz.slew_v_per_s * 0.1)
    for _ in range(100):
        plant.command(1000.0)
        plant.step()
    assert plant.v_applied == pz.max_v
    plant.command(-5.0)
    plant.step()
    assert plant.v_applied == pytest.approx(pz.max_v - pz.slew_v_per_s * 0.1)


QUIET = {
    "thermal": {"random_walk_k_per_sqrt_s": 0.0, "daily_amplitude_k": 0.0},
    "cooler": {"peak_to_peak_rad": 0.0},
    "sensor": {"noise_m_per_rthz": 0.0, "drift_m_per_sqrt_s": 0.0},
}


def test_piezo_tilt_is_stroke_over_spacing() -> None:
    plant = Plant(build(PlantParams, QUIET), dt_s=0.1)
    t0 = plant.tilt_rad()
    plant.command(plant.v_applied + 5.0)
    plant.step()
    pz = plant.params.piezo
    assert plant.tilt_rad() - t0 == pytest.approx(
        5.0 * pz.gain_m_per_v / plant.params.platform.support_spacing_m, rel=1e-6)


def test_adc_quantizes_and_rails() -> None:
    se = SensorParams()
    params = PlantParams(sensor=se)
    plant = Plant(params, 0.1)
    counts, value, railed = plant.measure()
    assert not railed
    assert value == pytest.approx((counts * se.lsb_v + se.adc_min_v) / se.gain_v_per_m)
    assert se.lsb_m == pytest.approx(20.0 / 65535 / 2e5)  # 1.53 nm per count
    tilted = Plant(build(PlantParams, {"platform": {"initial_tilt_rad": 1e-3}}), 0.1)
    counts, _, railed = tilted.measure()
    assert railed and counts == 2**16 - 1


def test_cooler_shows_10_to_15_nm_at_the_pendulum_end() -> None:
    quiet = build(PlantParams, {
        "thermal": {"random_walk_k_per_sqrt_s": 0.0, "daily_amplitude_k": 0.0},
        "sensor": {"noise_m_per_rthz": 0.0, "drift_m_per_sqrt_s": 0.0, "adc_bits": 32},
    })
    plant = Plant(quiet, 0.1)
    xs = []
    for _ in range(round(3 * quiet.cooler.period_s / 0.1)):
        xs.append(plant.measure()[1])
        plant.step()
    settled = np.array(xs[len(xs) // 3:])
    assert 10e-9 <= settled.max() - settled.min() <= 15e-9


def test_same_seed_same_realization_other_seed_differs() -> None:
    def trace(seed: int) -> list[float]:
        plant = Plant(PlantParams(), 0.1, seed)
        out = []
        for _ in range(20000):
            out.append(plant.measure()[1])
            plant.step()
        return out

    assert trace(5) == trace(5)
    assert trace(5) != trace(6)
