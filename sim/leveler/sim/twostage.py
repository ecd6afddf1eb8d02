"""Two-stage torsion pendulum (paper sec. 4.2, Figs. 16, 17): TP2 hangs on TP1, TP1 held at null.

Both pendulums turn about one vertical axis, TP1 on its pivot K1 to the base, TP2 on its pivot K2
to TP1 (springs in series: 1/Kc = 1/K1 + 1/K2). With phi1, phi2 their angles from the base:

    J1 phi1'' = -K1 phi1 - lambda1 phi1' + K2 (phi2 - phi1) + lambda2 (phi2' - phi1')
                + (tau_A - tau_2) + u
    J2 phi2'' = -K2 (phi2 - phi1) - lambda2 (phi2' - phi1') + F L + tau_2

tau_2 = M2 g sin(alpha) L_cm2 is the gravity torque on TP2 and tau_A = (M1 + M2) g sin(alpha) L_cm1
the one on the whole assembly (paper's tau_1), so TP1's own frame carries tau_A - tau_2. u is the
null-control torque: a discrete PID at the sample rate holds phi1 at zero, which makes K1
effectively infinite at low frequency and Kc = K2. Quasi-statically TP2 then reads
K2 (phi2 - phi1) = F L + tau_2 and the controller balances u = -(F L + tau_A): TP1's null-control
signal is dominated by tilt when (M1 + M2) L_cm1 >> M2 L_cm2, and the pair of readings separates
thrust from tilt (leveler.procedures.two_stage).

The plant is ZOH-discretized; with the PID the closed loop is one discrete linear system, run
mode by mode (eigen-decomposition, one complex first-order lfilter per mode), so it is exact for
inputs held over each sample and needs no Python loop over samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import expm
from scipy.signal import lfilter

from leveler.sim.torsion import TorsionParams, sensor_noise


def _front_stage() -> TorsionParams:
    """TP1: a 4 kg frame (J1 0.2 kg m^2) carrying TP2; assembly 5 kg, its CoM 5 mm off axis."""
    return TorsionParams(stiffness_nm_per_rad=0.02, inertia_kgm2=0.2, damping_nms_per_rad=0.02,
                         arm_m=0.25, mass_kg=5.0, com_y_m=5e-3)


def _rear_stage() -> TorsionParams:
    """TP2: a light 1 kg thrust balance (J2 0.01 kg m^2, f0 0.23 Hz), CoM 1 mm off axis.

    Damped to Q = 1 (eddy-current damping, usual on thrust balances) so it settles within a
    few seconds of a thrust step. M2 g L_cm2 = 0.0098 N m/rad is the paper's "0.01 uN m per
    urad"; the assembly's coupling on TP1 is 25x that.
    """
    return TorsionParams(stiffness_nm_per_rad=0.02, inertia_kgm2=0.01,
                         damping_nms_per_rad=math.sqrt(0.02 * 0.01), arm_m=0.25,
                         mass_kg=1.0, com_y_m=1e-3)


@dataclass(frozen=True, slots=True)
class NullPID:
    """TP1's null controller, torque per radian: u = kp e + ki sum(e) dt + kd d(e)/dt filtered.

    Defaults place the closed-loop poles of J1 = 0.2 kg m^2 near -1, -1.5 and -2 rad/s (0.3 Hz
    bandwidth, well below the 5 Hz Nyquist of the 10 Hz loop): kd = 4.5 J1, kp = 6.5 J1 - K1,
    ki = 3 J1. The derivative is low-passed with time constant tf_s (a "dirty" derivative),
    which must exceed the sample period. Faster designs leave a lightly damped loop mode that
    turns sensor noise into large torque noise.
    """

    kp_nm_per_rad: float = 1.28
    ki_nm_per_rad_s: float = 0.6
    kd_nms_per_rad: float = 0.9
    tf_s: float = 0.2


@dataclass(frozen=True, slots=True)
class TwoStageParams:
    """TP1 (front, null-controlled) and TP2 (rear, displacement mode, carries the thruster).

    tp1.mass_kg and tp1.com_y_m describe the whole assembly, (M1 + M2) and L_cm1, as in the
    paper's tau_1; tp1.arm_m is where TP1's null sensor reads. tp2.arm_m is the thrust lever arm.
    """

    tp1: TorsionParams = field(default_factory=_front_stage)
    tp2: TorsionParams = field(default_factory=_rear_stage)
    pid: NullPID = field(default_factory=NullPID)

    @property
    def coupling_ratio(self) -> float:
        """M2 L_cm2 / ((M1 + M2) L_cm1): TP2's tilt torque per unit of TP1's (paper: << 1)."""
        return self.tp2.tilt_sensitivity_nm_per_rad / self.tp1.tilt_sensitivity_nm_per_rad


@dataclass(frozen=True)
class TwoStageRun:
    """Sampled truth and readings of one run; torques in N m, angles in rad, displacement in m."""

    t_s: np.ndarray
    thrust_n: np.ndarray
    tilt_rad: np.ndarray
    phi1_rad: np.ndarray  # TP1 from the base (truth): the null loop's residual
    tp2_displacement_m: np.ndarray  # TP2's sensor: L2 (phi2 - phi1) + noise
    null_torque_nm: np.ndarray  # u, the null-control signal


def _plant(p: TwoStageParams) -> tuple[np.ndarray, np.ndarray]:
    """Continuous x = [phi1, phi1', phi2, phi2'], inputs [u, F L, tau_A - tau_2, tau_2]."""
    j1, k1, l1 = p.tp1.inertia_kgm2, p.tp1.stiffness_nm_per_rad, p.tp1.damping_nms_per_rad
    j2, k2, l2 = p.tp2.inertia_kgm2, p.tp2.stiffness_nm_per_rad, p.tp2.damping_nms_per_rad
    a = np.array([[0, 1, 0, 0],
                  [-(k1 + k2) / j1, -(l1 + l2) / j1, k2 / j1, l2 / j1],
                  [0, 0, 0, 1],
                  [k2 / j2, l2 / j2, -k2 / j2, -l2 / j2]])
    b = np.array([[0, 0, 0, 0],
                  [1 / j1, 0, 1 / j1, 0],
                  [0, 0, 0, 0],
                  [0, 1 / j2, 0, 1 / j2]])
    return a, b


def closed_loop(p: TwoStageParams, dt_s: float) -> tuple[np.ndarray, ...]:
    """Discrete closed loop X = [x, I, s]; inputs [F L, tau_A - tau_2, tau_2, null sensor noise];
    outputs [phi1, phi2 - phi1, u]. Raises ValueError if the null loop is unstable."""
    if not dt_s < p.pid.tf_s:
        raise ValueError(f"derivative filter tf_s={p.pid.tf_s} s must exceed dt={dt_s} s")
    a, b = _plant(p)
    m = np.zeros((8, 8))
    m[:4, :4], m[:4, 4:] = a * dt_s, b * dt_s
    e = expm(m)
    ad, bd = e[:4, :4], e[:4, 4:]
    c1 = np.array([1.0, 0, 0, 0])
    g = p.pid
    kt = g.kd_nms_per_rad / g.tf_s
    ke = g.kp_nm_per_rad + kt
    # u = ke e + I - kt s with e = -(phi1 + n1)
    u_x = np.concatenate((-ke * c1, [1.0, -kt]))
    u_n = -ke
    acl = np.zeros((6, 6))
    acl[:4, :] = np.column_stack((ad, np.zeros((4, 2)))) + np.outer(bd[:, 0], u_x)
    acl[4, :] = np.concatenate((-g.ki_nm_per_rad_s * dt_s * c1, [1.0, 0.0]))
    acl[5, :] = np.concatenate((-(dt_s / g.tf_s) * c1, [0.0, 1 - dt_s / g.tf_s]))
    bcl = np.zeros((6, 4))
    bcl[:4, :3] = bd[:, 1:]
    bcl[:4, 3] = bd[:, 0] * u_n
    bcl[4, 3] = -g.ki_nm_per_rad_s * dt_s
    bcl[5, 3] = -dt_s / g.tf_s
    ccl = np.zeros((3, 6))
    ccl[0, 0] = 1.0
    ccl[1, 0], ccl[1, 2] = -1.0, 1.0
    ccl[2, :] = u_x
    dcl = np.zeros((3, 4))
    dcl[2, 3] = u_n
    radius = float(np.max(np.abs(np.linalg.eigvals(acl))))
    if radius >= 1:
        raise ValueError(f"TP1's null loop is unstable (spectral radius {radius:.4f}): lower "
                         "the PID gains or sample faster")
    return acl, bcl, ccl, dcl


def discrete_response(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray,
                      w: np.ndarray) -> np.ndarray:
    """Outputs (n, outputs) of x[k+1] = a x + b w[k], y = c x + d w[k] from rest.

    In modal coordinates (a = V diag(z) V^-1) every mode is a first-order recursion, one
    complex lfilter each; needs distinct eigenvalues, which a tuned loop has.
    """
    z, v = np.linalg.eig(a)
    if np.linalg.cond(v) > 1e10:
        raise ValueError("closed loop is (nearly) defective: move repeated poles apart")
    q = np.linalg.solve(v, b) @ w.T  # (modes, n): input to each mode
    modes = np.stack([lfilter([0.0, 1.0], [1.0, -zi], qi) for zi, qi in zip(z, q, strict=True)])
    return ((c @ v) @ modes).real.T + w @ d.T


def simulate(p: TwoStageParams, fs_hz: float, thrust_n: ArrayLike, tilt_rad: ArrayLike,
             rng: np.random.Generator, noise_m_per_rthz: float = 0.0) -> TwoStageRun:
    """Run from rest with thrust and pitch held over each sample; both sensors get white noise
    of `noise_m_per_rthz` at their arm ends (TP1's goes through the PID into u)."""
    thrust, tilt = (np.asarray(x, dtype=float) for x in np.broadcast_arrays(thrust_n, tilt_rad))
    n = thrust.size
    tau_2 = p.tp2.gravity_torque_nm(tilt)
    tau_a = p.tp1.gravity_torque_nm(tilt)
    n1 = sensor_noise(rng, n, noise_m_per_rthz, fs_hz) / p.tp1.arm_m
    w = np.column_stack((thrust * p.tp2.arm_m, tau_a - tau_2, tau_2, n1))
    y = discrete_response(*closed_loop(p, 1 / fs_hz), w)
    n2 = sensor_noise(rng, n, noise_m_per_rthz, fs_hz)
    return TwoStageRun(t_s=np.arange(n) / fs_hz, thrust_n=thrust, tilt_rad=tilt,
                       phi1_rad=y[:, 0], tp2_displacement_m=p.tp2.arm_m * y[:, 1] + n2,
                       null_torque_nm=y[:, 2])
