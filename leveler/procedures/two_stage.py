"""Thrust from a two-stage torsion pendulum (paper sec. 4.2, Fig. 17), on the simulator.

Quasi-statically (leveler.sim.twostage) TP2's torque reading and TP1's balancing torque are

    y2 = K2 (phi2 - phi1) = F L + tau_2,     b = -u = F L + tau_A,     tau_2 = kappa tau_A,

kappa = M2 L_cm2 / ((M1 + M2) L_cm1). TP2 alone (the single-stage estimate F = y2 / L) cannot tell
the tilt torque tau_2 from thrust. With both readings, F L = (y2 - kappa b) / (1 - kappa): the
"differential" signal of the paper. kappa is calibrated, not taken from the model: a run with the
thruster off and the base tilt modulated gives kappa as the least-squares slope of y2 on b.

b is low-passed (NULL_LOWPASS_HZ) before use: above the null loop's bandwidth u is the PID's
high-frequency gain times sensor noise, not a torque balance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt

from leveler.procedures.stiffness import SENSOR_NOISE_M_PER_RTHZ, square_wave_thrust
from leveler.sim.twostage import TwoStageParams, TwoStageRun, simulate

TILT_AMPLITUDE_RAD = 3e-6  # paper, Fig. 17
TILT_FREQUENCY_HZ = 0.01  # paper, Fig. 17
# Thrust: 0 / 0.1 uN (the paper's resolution force), twice the tilt period so that each plateau
# outlasts TP2's settling by far; the paper gives no thrust amplitude or period for Fig. 17.
THRUST_N = 1e-7
THRUST_PERIOD_S = 200.0
DURATION_S = 1000.0
FS_HZ = 10.0
NULL_LOWPASS_HZ = 0.05  # 5x the tilt frequency, 1/6 of the null loop's ~0.3 Hz bandwidth


@dataclass(frozen=True)
class TwoStageResult:
    """A calibration run (thrust off) and a measurement run, with both thrust estimates."""

    params: TwoStageParams
    run: TwoStageRun
    balance_torque_nm: np.ndarray  # b = -u, low-passed
    tp2_torque_nm: np.ndarray  # y2 = K2 x2 / L2
    kappa: float  # calibrated
    single_stage_n: np.ndarray
    decoupled_n: np.ndarray

    @property
    def correlation_single(self) -> float:
        return float(np.corrcoef(self.single_stage_n, self.run.thrust_n)[0, 1])

    @property
    def correlation_decoupled(self) -> float:
        return float(np.corrcoef(self.decoupled_n, self.run.thrust_n)[0, 1])

    def rms_error_n(self, estimate_n: np.ndarray) -> float:
        return float(np.sqrt(np.mean((estimate_n - self.run.thrust_n) ** 2)))


def readings(p: TwoStageParams, run: TwoStageRun, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """TP2's torque reading y2 and TP1's low-passed balancing torque b = -u [N m]."""
    y2 = p.tp2.stiffness_nm_per_rad * run.tp2_displacement_m / p.tp2.arm_m
    sos = butter(4, NULL_LOWPASS_HZ, fs=fs_hz, output="sos")
    return y2, -sosfiltfilt(sos, run.null_torque_nm)


def run_two_stage(p: TwoStageParams | None = None, *,
                  tilt_amplitude_rad: float = TILT_AMPLITUDE_RAD,
                  tilt_frequency_hz: float = TILT_FREQUENCY_HZ, thrust_n: float = THRUST_N,
                  thrust_period_s: float = THRUST_PERIOD_S, duration_s: float = DURATION_S,
                  fs_hz: float = FS_HZ, noise_m_per_rthz: float = SENSOR_NOISE_M_PER_RTHZ,
                  seed: int = 0) -> TwoStageResult:
    """Calibrate kappa with the thruster off, then measure a square-wave thrust under tilt."""
    p = TwoStageParams() if p is None else p
    n = round(duration_s * fs_hz)
    if n < 64:
        raise ValueError(f"{duration_s} s at {fs_hz} Hz is too short a run")
    t = np.arange(n) / fs_hz
    tilt = tilt_amplitude_rad * np.sin(2 * math.pi * tilt_frequency_hz * t)
    thrust = square_wave_thrust(n, fs_hz, thrust_period_s, thrust_n)
    rng = np.random.default_rng(seed)
    cal_y2, cal_b = readings(p, simulate(p, fs_hz, np.zeros(n), tilt, rng, noise_m_per_rthz),
                             fs_hz)
    kappa = float(np.dot(cal_y2, cal_b) / np.dot(cal_b, cal_b))
    run = simulate(p, fs_hz, thrust, tilt, rng, noise_m_per_rthz)
    y2, b = readings(p, run, fs_hz)
    arm = p.tp2.arm_m
    return TwoStageResult(params=p, run=run, balance_torque_nm=b, tp2_torque_nm=y2,
                          kappa=kappa, single_stage_n=y2 / arm,
                          decoupled_n=(y2 - kappa * b) / ((1 - kappa) * arm))
