"""Inverted-pendulum dynamics: J theta'' + c theta' + k theta = m g L_cm sin(theta + phi).

theta is the pendulum's deflection relative to the platform (what the sensor on the
platform sees, times the arm), phi the platform tilt. Two forms share one interface:
the linear one (exact zero-order-hold discretization, fast and exact for micro-radians)
and the full non-linear one (RK4), which the equilibrium and design tools need.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import expm
from scipy.optimize import brentq

from leveler.sim.params import PendulumParams


def equilibrium_angle(p: PendulumParams, phi_rad: float) -> float:
    """Solve m g L_cm sin(theta + phi) = k theta for the stable theta (rad).

    With k > m g L_cm the left side minus the right is strictly decreasing in theta, so the
    root is unique and bracketed by [-pi, pi].
    """
    mgl, k = p.gravity_stiffness_nm_per_rad, p.flexure_stiffness_nm_per_rad

    def torque(theta: float) -> float:
        return mgl * math.sin(theta + phi_rad) - k * theta

    return float(brentq(torque, -math.pi, math.pi, xtol=1e-18, rtol=4 * np.finfo(float).eps))


def linear_matrices(p: PendulumParams) -> tuple[np.ndarray, np.ndarray]:
    """Continuous state space x = [theta, omega], input phi: x' = A x + B phi."""
    j, c = p.inertia_kgm2, p.damping_nms_per_rad
    mgl, k = p.gravity_stiffness_nm_per_rad, p.flexure_stiffness_nm_per_rad
    a = np.array([[0.0, 1.0], [-(k - mgl) / j, -c / j]])
    b = np.array([[0.0], [mgl / j]])
    return a, b


class PendulumModel:
    """Advances the pendulum by a fixed dt with the platform tilt held over the step."""

    __slots__ = ("_a11", "_a12", "_a21", "_a22", "_b1", "_b2", "_c", "_dt", "_j", "_k",
                 "_linear", "_mgl", "_substeps", "omega", "theta")

    def __init__(self, p: PendulumParams, dt_s: float, substeps: int = 4) -> None:
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        self._linear = p.model == "linear"
        self._dt = dt_s
        self._substeps = substeps
        self._j, self._c = p.inertia_kgm2, p.damping_nms_per_rad
        self._k, self._mgl = p.flexure_stiffness_nm_per_rad, p.gravity_stiffness_nm_per_rad
        a, b = linear_matrices(p)
        m = np.zeros((3, 3))
        m[:2, :2], m[:2, 2:] = a * dt_s, b * dt_s
        e = expm(m)
        self._a11, self._a12, self._a21, self._a22 = (float(v) for v in e[:2, :2].ravel())
        self._b1, self._b2 = float(e[0, 2]), float(e[1, 2])
        self.theta = 0.0
        self.omega = 0.0

    def settle(self, p: PendulumParams, phi_rad: float) -> None:
        """Start at rest at the static equilibrium for tilt phi."""
        if self._linear:
            self.theta = p.amplification * phi_rad
        else:
            self.theta = equilibrium_angle(p, phi_rad)
        self.omega = 0.0

    def step(self, phi_rad: float) -> float:
        """Advance one dt; returns the new theta."""
        if self._linear:
            th, om = self.theta, self.omega
            self.theta = self._a11 * th + self._a12 * om + self._b1 * phi_rad
            self.omega = self._a21 * th + self._a22 * om + self._b2 * phi_rad
            return self.theta
        return self._step_rk4(phi_rad)

    def _accel(self, th: float, om: float, phi: float) -> float:
        return (self._mgl * math.sin(th + phi) - self._k * th - self._c * om) / self._j

    def _step_rk4(self, phi: float) -> float:
        h = self._dt / self._substeps
        th, om = self.theta, self.omega
        acc = self._accel
        for _ in range(self._substeps):
            k1t, k1o = om, acc(th, om, phi)
            k2t, k2o = om + 0.5 * h * k1o, acc(th + 0.5 * h * k1t, om + 0.5 * h * k1o, phi)
            k3t, k3o = om + 0.5 * h * k2o, acc(th + 0.5 * h * k2t, om + 0.5 * h * k2o, phi)
            k4t, k4o = om + h * k3o, acc(th + h * k3t, om + h * k3o, phi)
            th += h / 6.0 * (k1t + 2 * k2t + 2 * k3t + k4t)
            om += h / 6.0 * (k1o + 2 * k2o + 2 * k3o + k4o)
        self.theta, self.omega = th, om
        return th
