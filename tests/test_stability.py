"""The daemon's numpy-only stability check (leveler.analysis.stability) against python-control
on the same discrete loop (leveler.analysis.suggest's plant and controller transfer
functions): the same verdict and the same worst pole, over random gains and stands; and the
numpy matrix exponential behind its discretization against scipy's."""

from __future__ import annotations

import dataclasses

import control
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from leveler.analysis.stability import predicted_instability
from leveler.analysis.suggest import controller_tf, plant_tf
from leveler.settings import load_config
from leveler.sim.pendulum import discrete_matrices, expm

from conftest import REPO  # isort: skip

PLANT = load_config(REPO / "config" / "sim.toml")[0].plant


def control_poles(params: object, rate_hz: float, kp: float, ki: float, kd: float,
                  tau: float) -> np.ndarray:
    loop = controller_tf(kp, ki, kd, tau, rate_hz) * plant_tf(params, rate_hz)  # type: ignore[arg-type]
    return np.asarray(control.feedback(loop, 1).poles())


def worst(poles: np.ndarray) -> complex:
    return complex(poles[np.argmax(np.abs(poles))])


@settings(max_examples=60, deadline=None)
@given(kp=st.sampled_from([0.0, 1e5, 1e6, 3e6, 1e7, -1e6]),
       ki=st.sampled_from([0.0, 1e6, 2e7, 1e8, 1e9]),
       kd=st.sampled_from([0.0, 1e5, 1e6, 1e7]),
       tau=st.sampled_from([0.01, 0.1, 1.0]),
       rate_hz=st.sampled_from([10.0, 100.0, 1000.0]),
       resonance_scale=st.sampled_from([1.0, 1.5, 3.0]))  # k > m g L
def test_the_verdict_and_worst_pole_are_python_controls(kp: float, ki: float, kd: float,
                                                       tau: float, rate_hz: float,
                                                       resonance_scale: float) -> None:
    params = dataclasses.replace(PLANT, pendulum=dataclasses.replace(
        PLANT.pendulum, flexure_stiffness_nm_per_rad=PLANT.pendulum.flexure_stiffness_nm_per_rad
        * resonance_scale))
    why = predicted_instability(params, rate_hz, kp, ki, kd, tau)
    if not (kp or ki or kd):
        assert why is None
        return
    ref = worst(control_poles(params, rate_hz, kp, ki, kd, tau))
    assert (why is not None) == (abs(ref) >= 1.0), (why, ref)
    if why is not None:  # the message names python-control's worst pole
        assert f"|z| = {abs(ref):.4g}" in why, (why, abs(ref))


def test_the_shipped_gains_are_stable_and_a_sign_slip_is_not() -> None:
    cfg = load_config(REPO / "config" / "sim.toml")[0]
    c, rate = cfg.controller, cfg.loop.rate_hz
    assert predicted_instability(cfg.plant, rate, c.kp_v_per_m, c.ki_v_per_m_s,
                                 c.kd_v_s_per_m, c.d_filter_tau_s) is None
    why = predicted_instability(cfg.plant, rate, -c.kp_v_per_m, -c.ki_v_per_m_s,
                                -c.kd_v_s_per_m, c.d_filter_tau_s)
    assert why is not None and "unstable loop at" in why


@pytest.mark.parametrize("scale", [1e-4, 1e-2, 0.2, 1.0, 5.0])
def test_expm_is_scipys(scale: float) -> None:
    rng = np.random.default_rng(7)
    for _ in range(50):
        m = rng.normal(size=(3, 3)) * scale
        m[2] = 0.0  # held input, as the pendulum's
        ref = scipy.linalg.expm(m)  # to 1e-12 of the largest entry: scipy's own error is
        assert np.abs(expm(m) - ref).max() <= 1e-12 * np.abs(ref).max()  # about that


def test_the_pendulum_discretization_is_unchanged_at_machine_precision() -> None:
    """The sim steps with these matrices: numpy's expm leaves them as scipy's made them."""
    from leveler.sim.pendulum import linear_matrices

    for rate_hz in (10.0, 1000.0):
        dt = 1.0 / rate_hz
        a, b = linear_matrices(PLANT.pendulum)
        m = np.zeros((3, 3))
        m[:2, :2], m[:2, 2:] = a * dt, b * dt
        np.testing.assert_allclose(expm(m), scipy.linalg.expm(m), rtol=1e-14, atol=1e-18)
        assert discrete_matrices(PLANT.pendulum, dt)[0].shape == (3, 3)
