"""Torsion pendulum (TP) thrust stand with gravity coupling from base tilt (paper eqs. 1-3, 7-9).

    J theta'' + lambda theta' + K0 theta = F L + M g sin(pitch) l_cm,y + M g sin(roll) l_cm,x

theta is the pendulum's angle from its rest position with the base level and no thrust (where
the displacement sensor is zeroed). The gravity term is a torque that does not depend on theta,
exactly as in the paper's quasi-static balance F L + M g sin(alpha) l_cm = K0 theta: tilt moves
the pendulum's rest point, it does not change the pivot's restoring torque. The paper's
tilt-dependent "stiffness" K = F L / theta therefore comes from measuring theta from the level
zero, not from a change of the pendulum's dynamics (see leveler.procedures.stiffness).

The model is linear in the torque, so a run is one ZOH-discretized second-order filter over the
torque series (scipy.signal.cont2discrete + lfilter): exact for inputs held over each sample,
with sin() applied to the tilt exactly, and fast for long runs.

Defaults (the paper gives no frame data; these are a plausible micro-Newton stand): a 2 kg
balanced frame (m1) plus a 0.2 kg counterweight (m2) 3 mm off the axis along y, so
l_cm,y = 0.27 mm and the tilt sensitivity M g l_cm = 5.9e-3 N m/rad = 0.006 uN m/urad (the paper:
"0.01 uN m/urad or lower"); J = 0.05 kg m^2 (2.2 kg within about 0.15 m of the axis), the pivot
K0 = 0.2 N m/rad (f0 = 0.32 Hz, and 0.10 Hz at the paper's other K0 = 0.02 N m/rad), damping
0.01 N m s/rad (Q = 10 at K0 = 0.2, a 10 s decay time), thrust lever arm L = 0.25 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import cont2discrete, lfilter, lfilter_zi

from leveler.sim.params import G_STANDARD


def com_offset_m(balanced_mass_kg: float, counterweight_kg: float,
                 counterweight_offset_m: float) -> float:
    """Frame centre-of-mass offset l_cm = m2 / (m1 + m2) * l_cm2 (paper eq. 7).

    m1 is balanced about the axis, so the frame's whole gravity torque M g sin(tilt) l_cm equals
    the counterweight's m2 g sin(tilt) l_cm2 (eqs. 8, 9).
    """
    if balanced_mass_kg < 0 or counterweight_kg < 0 or balanced_mass_kg + counterweight_kg <= 0:
        raise ValueError("masses must be >= 0 with a positive total, got "
                         f"m1={balanced_mass_kg!r} kg, m2={counterweight_kg!r} kg")
    return counterweight_kg / (balanced_mass_kg + counterweight_kg) * counterweight_offset_m


DEFAULT_BALANCED_MASS_KG = 2.0
DEFAULT_COUNTERWEIGHT_KG = 0.2
DEFAULT_COUNTERWEIGHT_OFFSET_M = 3.0e-3


@dataclass(frozen=True, slots=True)
class TorsionParams:
    """One torsion pendulum in SI units; defaults in the module docstring."""

    stiffness_nm_per_rad: float = 0.2  # K0, the pivot's elastic stiffness
    inertia_kgm2: float = 0.05  # J
    damping_nms_per_rad: float = 0.01  # lambda
    arm_m: float = 0.25  # L: thrust lever arm, also where the displacement is sensed
    mass_kg: float = DEFAULT_BALANCED_MASS_KG + DEFAULT_COUNTERWEIGHT_KG  # M = m1 + m2
    com_x_m: float = 0.0  # l_cm,x: couples roll
    com_y_m: float = com_offset_m(DEFAULT_BALANCED_MASS_KG, DEFAULT_COUNTERWEIGHT_KG,
                                  DEFAULT_COUNTERWEIGHT_OFFSET_M)  # l_cm,y: couples pitch
    gravity_m_per_s2: float = G_STANDARD

    def __post_init__(self) -> None:
        for name in ("stiffness_nm_per_rad", "inertia_kgm2", "arm_m", "mass_kg",
                     "gravity_m_per_s2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value!r}")
        for name in ("damping_nms_per_rad", "com_x_m", "com_y_m"):
            value = getattr(self, name)
            if not math.isfinite(value) or (name == "damping_nms_per_rad" and value < 0):
                raise ValueError(f"{name} must be finite (damping >= 0), got {value!r}")

    @classmethod
    def with_counterweight(cls, balanced_mass_kg: float, counterweight_kg: float,
                           offset_y_m: float, offset_x_m: float = 0.0,
                           **kwargs: float) -> TorsionParams:
        """A frame of balanced mass m1 plus counterweight m2 at (offset_x_m, offset_y_m)."""
        return cls(mass_kg=balanced_mass_kg + counterweight_kg,
                   com_x_m=com_offset_m(balanced_mass_kg, counterweight_kg, offset_x_m),
                   com_y_m=com_offset_m(balanced_mass_kg, counterweight_kg, offset_y_m),
                   **kwargs)

    @property
    def natural_frequency_hz(self) -> float:
        """Undamped eigenfrequency sqrt(K0 / J) / 2 pi."""
        return math.sqrt(self.stiffness_nm_per_rad / self.inertia_kgm2) / (2 * math.pi)

    @property
    def quality_factor(self) -> float:
        """Q = sqrt(K0 J) / lambda (inf without damping)."""
        lam = self.damping_nms_per_rad
        return math.inf if lam == 0 else math.sqrt(self.stiffness_nm_per_rad
                                                   * self.inertia_kgm2) / lam

    @property
    def tilt_sensitivity_nm_per_rad(self) -> float:
        """M g l_cm,y: gravity torque per radian of pitch (the paper's "uN m per urad")."""
        return self.mass_kg * self.gravity_m_per_s2 * self.com_y_m

    def gravity_torque_nm(self, pitch_rad: ArrayLike, roll_rad: ArrayLike = 0.0) -> np.ndarray:
        """M g sin(pitch) l_cm,y + M g sin(roll) l_cm,x [N m]; positive adds to the thrust."""
        mg = self.mass_kg * self.gravity_m_per_s2
        return mg * (np.sin(pitch_rad) * self.com_y_m + np.sin(roll_rad) * self.com_x_m)

    def torque_nm(self, thrust_n: ArrayLike, pitch_rad: ArrayLike = 0.0,
                  roll_rad: ArrayLike = 0.0) -> np.ndarray:
        """Total external torque F L + gravity torque [N m]."""
        return np.asarray(thrust_n, dtype=float) * self.arm_m + self.gravity_torque_nm(
            pitch_rad, roll_rad)

    def static_deflection_rad(self, thrust_n: ArrayLike, pitch_rad: ArrayLike = 0.0,
                              roll_rad: ArrayLike = 0.0) -> np.ndarray:
        """theta at rest: (F L + M g sin(alpha) l_cm) / K0 (paper eq. 3)."""
        return self.torque_nm(thrust_n, pitch_rad, roll_rad) / self.stiffness_nm_per_rad

    def coupling_ratio(self, thrust_n: float, pitch_rad: float, roll_rad: float = 0.0) -> float:
        """r = M g sin(alpha) l_cm / (F L): gravity over thrust torque (paper eqs. 5, 6)."""
        return float(self.gravity_torque_nm(pitch_rad, roll_rad)) / (thrust_n * self.arm_m)

    def torque_to_angle(self) -> tuple[np.ndarray, np.ndarray]:
        """Continuous transfer function theta / tau = 1 / (J s^2 + lambda s + K0) as (num, den)."""
        return (np.array([1.0]), np.array([self.inertia_kgm2, self.damping_nms_per_rad,
                                           self.stiffness_nm_per_rad]))


def zoh_filter(num: ArrayLike, den: ArrayLike, dt_s: float, u: ArrayLike) -> np.ndarray:
    """Response of the continuous transfer function num/den to `u` held over each sample.

    Exact at the sample times (zero-order-hold discretization); starts at rest in the
    equilibrium of u[0]. One lfilter call, so a day of samples takes milliseconds.
    """
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be finite and > 0, got {dt_s!r}")
    x = np.atleast_1d(np.asarray(u, dtype=float))
    numd, dend, _ = cont2discrete((np.asarray(num, float), np.asarray(den, float)), dt_s,
                                  method="zoh")
    b = np.ravel(numd)
    y, _ = lfilter(b, dend, x, zi=lfilter_zi(b, dend) * x[0])
    return np.asarray(y)


def simulate(p: TorsionParams, dt_s: float, thrust_n: ArrayLike, pitch_rad: ArrayLike = 0.0,
             roll_rad: ArrayLike = 0.0) -> np.ndarray:
    """theta [rad] at t = k dt for inputs held over each sample (exact ZOH solution).

    The pendulum starts at rest in the equilibrium of the first sample's torque: a run starts
    after the (slow, thermal) tilt has been there a while and the thrust has been steady.
    Inputs broadcast against each other; the longest sets the length.
    """
    torque = p.torque_nm(*np.broadcast_arrays(thrust_n, pitch_rad, roll_rad))
    return zoh_filter(*p.torque_to_angle(), dt_s, torque)


def sensor_noise(rng: np.random.Generator, n: int, asd_per_rthz: float,
                 fs_hz: float) -> np.ndarray:
    """White noise of one-sided ASD `asd_per_rthz` sampled at fs: sigma = ASD sqrt(fs / 2)."""
    return rng.normal(0.0, asd_per_rthz * math.sqrt(fs_hz / 2), n)
