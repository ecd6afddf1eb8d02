"""Independent recording generator: a torsion-pendulum thrust stand on a base whose pitch varies.

It plays "a lab whose recordings leveler's developers never saw": written from the physics
alone (PHYSICS.md, "The stand" and "Equations"; Cong et al. 2024), sharing no code with leveler.

Physics (the paper's symbols). theta is the pendulum angle, F(t) the thrust at arm L, alpha(t)
the base pitch, M the pendulum mass and l_cm the signed offset of its centre of mass from the
rotation axis:

    J theta'' + lambda theta' + K0 theta = F(t) L + M g sin(alpha(t)) l_cm

sin(alpha) is used as is. The gravity torque does not depend on theta, so it shifts the zero;
the paper's "effective" quantities refer to the total static deflection theta = (F L + M g
sin(alpha) l_cm) / K0: with r = M g sin(alpha) l_cm / (F L), the compliance is S = theta / (F L)
= (1 + r) / K0 and the stiffness K = F L / theta = K0 / (1 + r). r > 0 softens, -1 < r < 0
stiffens, r < -1 is the paper's "negative stiffness" regime (reported per plateau as
`regime`). The displacement sensor reads x = L_s theta at its own arm; here L_s = L (the true
thrust arm), as in the paper.

Per-seed draws (the "stand" stream, shared by all scenarios of a seed unless noted):
    K0            log-uniform 0.01 .. 0.5 N m/rad
    J             log-uniform 0.01 .. 0.2 kg m^2, redrawn until f0 = sqrt(K0/J)/2pi is in
                  0.05 .. 1 Hz
    Q             log-uniform 3 .. 50; lambda = sqrt(K0 J) / Q
    L             stated uniform 0.1 .. 0.4 m with 1-sigma 0.5 %; true = stated (1 + u 0.005),
                  u uniform in [-1, 1] (within 1 sigma); L_s = L_true
    M             stated uniform 1 .. 5 kg with 1-sigma 0.2 %; true within 1 sigma
    l_cm          log-uniform 0.05 .. 1 mm, random sign (M g l_cm 0.0005 .. 0.05 N m/rad);
                  exactly 0 in the `null` scenario
    sample rate   2, 5 or 10 Hz
    thrust cal.   logged = true / (1 + e_F), e_F uniform in +-2 % (stated tolerance 2 %)
    tiltmeter     reading = (1 + e_T) alpha + offset + white noise; e_T uniform in +-3 %
                  (stated 3 %), offset uniform +-(0.1 .. 0.5) urad (stated bound 0.5 urad),
                  white noise 10 nrad/sqrt(Hz) x factor
    displacement  white 1 nm/sqrt(Hz) one-sided x factor; zero random walk 3 nm rms after 1 h
                  x factor; zero offset +-(0.5 .. 5) um; thermal drift of the zero
                  c1 t + c2 t^2, |c1| 5 .. 30 nm/h, |c2| 0.2 .. 1 nm/h^2, random signs
    noise factors each uniform in [0.75, 0.9] or [1.1, 1.25]
    start state   theta0 = (torque(0) / K0) + dtheta, L dtheta = +-(0.3 .. 2) x the static
                  thrust deflection at the sensor; theta_dot0 = u w0 dtheta, u in [-1, 1]
    file style    time column (ms since start, s since start, days since start, or Unix
                  seconds), thrust in uN or nN, displacement in um, nm or offset-binary 24-bit
                  ADC counts (0.125/0.25/0.5 nm per count), tilt in urad, one or two extra
                  columns to ignore, column order, delimiter (comma, semicolon, tab, space)

Scenarios (`--scenario`), drawn from a per-scenario stream:
    stepped  5..9 pitch plateaus evenly spread over +-A, A uniform 10..25 urad (jittered by
             +-20 % of a spacing, shuffled), raised-cosine ramps of 20..60 s between them, each
             flat part (4..6) x P long (the first one P/2..3P/2 longer: the start rings down).
             Thrust: unipolar trapezoidal square wave 0/F, F log-uniform 0.3..5 uN, rise time
             0.2..1 s, period P uniform in [max(100, 40 tau), 600] s with tau = 2Q/w0 the decay
             time (>= 20 decay times per half period), or P = 600 s when 40 tau > 600 s
             (recorded: `half_period_over_decay_time`).
    drift    thrust as `stepped` for 12..24 h; pitch = a thermal day (3..4 sinusoids, periods
             log-uniform 2..24 h, scaled to a peak |alpha| of 5..25 urad) plus a water-cooler
             asymmetric triangle (period 200..800 s, 0.1..0.5 urad peak-to-peak, rising for
             70..95 % of the period).
    dual     the centre-of-mass calibration: a section of 1..3 h with pitch alpha0 + A sin(2 pi f1
             (t - t_s)) (A 10..30 urad, alpha0 +-5 urad) and thrust F_a (1 - cos(2 pi f2
             (t - t_s))) (F_a log-uniform 0.3..2.5 uN, so 0..2 F_a: unipolar), f1 uniform in
             0.05..min(0.15, 0.7 f0 / rho), f2 = rho f1, rho uniform 1.05..1.2 (both < 0.7 f0;
             if f0 is too low for that the pendulum is drawn again and `pendulum_redrawn` says
             so); and, before or after it, a square-wave section (F 0.3..5 uN, P as above,
             3..6 periods) at constant pitch alpha0. Lead-in, gap and tail 120..600 s.
    null     `stepped` with l_cm = 0 exactly (same seed: same stand, schedule and noise).

Simulation (time domain, not via the transfer function): the torque is evaluated on a sub-step
grid of h = 25 ms (5 ms for `dual`, whose sines are faster) and taken piecewise linear between
grid points. For a piecewise-linear torque the state update over one sub-step is exact:
x[n+1] = Ad x[n] + G0 a + G1 b for a torque a + b s inside the step, with Ad, G0, G1 from one
augmented (Van Loan) matrix exponential. The thrust trapezoid's corners lie on the grid, so it
is represented exactly; the smooth pitch is interpolated with a relative error < (w h)^2 / 8.
The recursion runs in modal form: the sub-steps of one sample collapse into fixed weights, and
a complex first-order recursion at the sample rate (scipy.signal.lfilter) carries the state.

CLI: python -m bench.independent.thrust_stand SEED OUT_DIR [--scenario stepped|drift|dual|null]
writes OUT_DIR/thrust_stand_<seed>_<scenario>.csv and OUT_DIR/truth_<seed>_<scenario>.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import itertools
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.linalg import expm
from scipy.signal import lfilter
from scipy.special import j1

G_M_PER_S2 = 9.81
SCENARIOS = ("stepped", "drift", "dual", "null")
_SCENARIO_CODE = {"stepped": 1, "null": 1, "drift": 2, "dual": 3}   # null shares stepped's draws
H_SUB_S = {"stepped": 0.025, "null": 0.025, "drift": 0.025, "dual": 0.005}
SAMPLE_RATES_HZ = (2, 5, 10)

# Nominal noise levels; each is scaled per seed by a factor in [0.75, 0.9] or [1.1, 1.25].
DISP_ASD_NOMINAL = 1e-9            # displacement white noise, m/sqrt(Hz) one-sided
DISP_WALK_NOMINAL_M_PER_SQRT_H = 3e-9   # zero random walk: rms after one hour
TILT_ASD_NOMINAL = 10e-9           # tiltmeter white noise, rad/sqrt(Hz) one-sided

THRUST_CAL_TOL = 0.02
TILT_GAIN_TOL = 0.03
TILT_OFFSET_BOUND_RAD = 0.5e-6
L_SIGMA_REL = 0.005
M_SIGMA_REL = 0.002
ADC_MID = 2**23

DELIMITERS = {"comma": ",", "semicolon": ";", "tab": "\t", "space": " "}


# --------------------------------------------------------------------------------------------
# The stand and its exact discretisation
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Stand:
    """The numbers the equation of motion needs (true values), and the sensor arm."""

    K0: float      # torsion stiffness, N m/rad
    J: float       # moment of inertia, kg m^2
    lam: float     # damping, N m s/rad
    L: float       # thrust arm, m
    M: float       # pendulum mass, kg
    l_cm: float    # centre-of-mass offset from the axis, m (signed)

    @property
    def L_s(self) -> float:            # displacement sensor arm: the thrust arm (paper)
        return self.L

    @property
    def w0(self) -> float:
        return math.sqrt(self.K0 / self.J)

    @property
    def f0(self) -> float:
        return self.w0 / (2 * math.pi)

    @property
    def Q(self) -> float:
        return math.sqrt(self.K0 * self.J) / self.lam

    @property
    def gamma(self) -> float:          # amplitude decay rate, 1/s
        return self.lam / (2 * self.J)

    @property
    def decay_time(self) -> float:     # 2Q/w0 = 1/gamma
        return 2 * self.Q / self.w0

    @property
    def f_damped(self) -> float:
        return math.sqrt(self.w0**2 - self.gamma**2) / (2 * math.pi)

    @property
    def Mgl(self) -> float:            # tilt sensitivity of the torque, N m/rad
        return self.M * G_M_PER_S2 * self.l_cm

    def theta_per_torque(self, f_hz: float) -> complex:
        """Steady-state theta / torque at f (e^{+i w t} convention). Truth only."""
        w = 2 * math.pi * f_hz
        return 1.0 / complex(self.K0 - self.J * w * w, self.lam * w)


def simulate(stand: Stand, torque: np.ndarray, h: float, substeps: int,
             theta0: float = 0.0, theta_dot0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """theta and theta' at every `substeps`-th grid point of `torque` (grid spacing h).

    Exact for the torque piecewise linear between grid points: J th'' + lam th' + K0 th = torque.
    len(torque) must be (n - 1) * substeps + 1; returns arrays of length n.
    """
    u = np.asarray(torque, dtype=float)
    S = int(substeps)
    if (u.size - 1) % S:
        raise ValueError("len(torque) must be (n - 1) * substeps + 1")
    n = (u.size - 1) // S + 1
    a_mat = np.array([[0.0, 1.0], [-stand.K0 / stand.J, -stand.lam / stand.J]])
    aug = np.zeros((4, 4))
    aug[:2, :2] = a_mat
    aug[1, 2] = 1.0 / stand.J          # torque a + b s enters theta''
    aug[2, 3] = 1.0
    e = expm(aug * h)
    g0, g1 = e[:2, 2], e[:2, 3]
    s_eig, vec = np.linalg.eig(a_mat)
    if abs(s_eig[0].imag) == 0.0:
        raise ValueError("simulate expects an underdamped pendulum (Q > 0.5)")
    i = int(np.argmax(s_eig.imag))
    row = np.linalg.inv(vec)[i]
    lam_sub = complex(np.exp(s_eig[i] * h))          # eigenvalue of Ad = expm(A h)
    # One sub-step: z+ = lam z + (row.g0 - row.g1/h) u_j + (row.g1/h) u_{j+1}.
    a = complex(row @ g0 - (row @ g1) / h)
    b = complex((row @ g1) / h)
    powers = lam_sub ** np.arange(S, -1, -1)          # lam^S .. lam^0
    w = np.zeros(S + 1, dtype=complex)
    w[:S] += a * powers[1:]                           # u_j with lam^(S-1-j)
    w[1:] += b * powers[1:]                           # u_{j+1} with lam^(S-1-j)
    inp = np.empty(n, dtype=complex)
    inp[0] = row @ np.array([theta0, theta_dot0])
    if n > 1:
        win = sliding_window_view(u, S + 1)[::S]
        inp[1:] = win @ w.real + 1j * (win @ w.imag)
    z = lfilter([1.0], [1.0, -lam_sub**S], inp)
    theta = 2.0 * (vec[0, i] * z).real
    theta_dot = 2.0 * (vec[1, i] * z).real
    return theta, theta_dot


# --------------------------------------------------------------------------------------------
# Schedules: thrust and pitch as functions of time (vectorised, also scalar)
# --------------------------------------------------------------------------------------------

def _square_wave(t: np.ndarray, seg: dict[str, Any]) -> np.ndarray:
    """Unipolar trapezoid 0/F: rises at t_first_rise_s + k P over rise_s, falls at +P/2."""
    P, tr, F = seg["period_s"], seg["rise_s"], seg["F_N"]
    ph = np.mod(t - seg["t_first_rise_s"], P)
    y = F * np.interp(ph, [0.0, tr, P / 2, P / 2 + tr, P], [0.0, 1.0, 1.0, 0.0, 0.0])
    lo, hi = seg.get("t_from_s"), seg.get("t_to_s")
    if lo is not None:
        y = np.where((t >= lo) & (t <= hi), y, 0.0)
    return y


def _sine_thrust(t: np.ndarray, seg: dict[str, Any]) -> np.ndarray:
    arg = 2 * np.pi * seg["f_hz"] * (t - seg["t_from_s"])
    y = seg["F_amp_N"] * (1.0 - np.cos(arg))
    return np.where((t >= seg["t_from_s"]) & (t <= seg["t_to_s"]), y, 0.0)


def thrust_true(t: np.ndarray | float, schedule: dict[str, Any]) -> np.ndarray:
    """True thrust in N at times t (s from the first sample)."""
    t = np.asarray(t, dtype=float)
    out = np.zeros(t.shape)
    for seg in schedule["thrust"]:
        out = out + (_square_wave(t, seg) if seg["kind"] == "square" else _sine_thrust(t, seg))
    return out


def _smoothstep(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return 0.5 * (1.0 - np.cos(np.pi * s))


def tilt_true(t: np.ndarray | float, schedule: dict[str, Any]) -> np.ndarray:
    """True base pitch alpha in rad at times t (s from the first sample)."""
    t = np.asarray(t, dtype=float)
    p = schedule["pitch"]
    if p["kind"] == "plateaus":
        pl = p["plateaus"]
        out = np.full(t.shape, pl[0]["alpha_rad"])
        for a, b in itertools.pairwise(pl):
            ramp = b["t_start_s"] - a["t_end_s"]
            out = out + (b["alpha_rad"] - a["alpha_rad"]) * _smoothstep((t - a["t_end_s"]) / ramp)
        return out
    if p["kind"] == "thermal_day":
        out = np.zeros(t.shape)
        for c in p["components"]:
            out = out + c["amp_rad"] * np.sin(2 * np.pi * t / c["period_s"] + c["phase_rad"])
        saw = p["cooler"]
        P, rise = saw["period_s"], saw["rise_fraction"] * saw["period_s"]
        half = saw["peak_to_peak_rad"] / 2
        ph = np.mod(t - saw["t0_s"], P)
        return out + np.interp(ph, [0.0, rise, P], [-half, half, -half])
    if p["kind"] == "sine":
        arg = 2 * np.pi * p["f_hz"] * (t - p["t_from_s"])
        inside = (t >= p["t_from_s"]) & (t <= p["t_to_s"])
        return p["alpha0_rad"] + np.where(inside, p["amp_rad"] * np.sin(arg), 0.0)
    raise ValueError(p["kind"])


def torque_true(t: np.ndarray | float, schedule: dict[str, Any], stand: Stand) -> np.ndarray:
    """F L + M g sin(alpha) l_cm (N m)."""
    return (thrust_true(t, schedule) * stand.L
            + stand.M * G_M_PER_S2 * np.sin(tilt_true(t, schedule)) * stand.l_cm)


# --------------------------------------------------------------------------------------------
# Draws
# --------------------------------------------------------------------------------------------

def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _noise_factor(rng: np.random.Generator) -> float:
    lo, hi = (0.75, 0.9) if rng.random() < 0.5 else (1.1, 1.25)
    return float(rng.uniform(lo, hi))


def _signed(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))


def _draw_pendulum(rng: np.random.Generator) -> tuple[float, float, float]:
    while True:
        K0 = _log_uniform(rng, 0.01, 0.5)
        J = _log_uniform(rng, 0.01, 0.2)
        if 0.05 <= math.sqrt(K0 / J) / (2 * math.pi) <= 1.0:
            break
    Q = _log_uniform(rng, 3.0, 50.0)
    return K0, J, math.sqrt(K0 * J) / Q


def _square_period(rng: np.random.Generator, decay_time: float) -> float:
    lo = max(100.0, 40.0 * decay_time)
    P = float(rng.uniform(lo, 600.0)) if lo <= 600.0 else 600.0
    return round(P, 1)


@dataclass
class Setup:
    """Every per-seed draw that fixes the recording, before any noise realisation."""

    seed: int
    scenario: str
    stand: Stand
    stated: dict[str, dict[str, float]]
    fs: int
    h: float
    substeps: int
    n: int
    calibration: dict[str, Any]
    noise: dict[str, float]
    zero: dict[str, float]
    start: dict[str, float]
    style: dict[str, Any]
    epoch_s: int
    schedule: dict[str, Any]
    extras: dict[str, Any] = field(default_factory=dict)


def _draw_style(rng: np.random.Generator) -> dict[str, Any]:
    """How this lab writes its file: names, units, resolutions, column order, delimiter."""
    time = [
        {"column": "time_ms", "unit": "ms", "scale": 1e-3, "fmt": "int", "res": 1.0,
         "absolute": False, "text": "milliseconds since the first sample"},
        {"column": "elapsed_s", "unit": "s", "scale": 1.0, "fmt": "{:.3f}", "res": 1e-3,
         "absolute": False, "text": "seconds since the first sample"},
        {"column": "t_days", "unit": "days", "scale": 86400.0, "fmt": "{:.10f}", "res": 1e-10,
         "absolute": False, "text": "days since the first sample"},
        {"column": "unix_time", "unit": "s", "scale": 1.0, "fmt": "{:.3f}", "res": 1e-3,
         "absolute": True, "text": "POSIX time, s (UTC)"},
    ][int(rng.integers(4))]
    thrust = [
        {"column": "F_cmd_uN", "unit": "uN", "scale": 1e-6, "fmt": "{:.5f}", "res": 1e-5},
        {"column": "thrust_nN", "unit": "nN", "scale": 1e-9, "fmt": "{:.2f}", "res": 1e-2},
    ][int(rng.integers(2))]
    kind = int(rng.integers(3))
    if kind == 0:
        disp = {"column": "x_cap_um", "unit": "um", "scale": 1e-6, "offset": 0.0,
                "fmt": "{:.6f}", "res": 1e-6}
    elif kind == 1:
        disp = {"column": "disp_nm", "unit": "nm", "scale": 1e-9, "offset": 0.0,
                "fmt": "{:.3f}", "res": 1e-3}
    else:
        q = float(rng.choice([0.125e-9, 0.25e-9, 0.5e-9]))
        disp = {"column": "cap_adc", "unit": "counts", "scale": q, "offset": -ADC_MID * q,
                "fmt": "int", "res": 1.0}
    tilt = {"column": ["tilt_urad", "pitch_TM_urad", "IP_pitch_urad"][int(rng.integers(3))],
            "unit": "urad", "scale": 1e-6, "fmt": "{:.4f}", "res": 1e-4}
    pool = ["T_plate_degC", "p_vac_mbar", "status"]
    extras = [pool[i] for i in sorted(rng.choice(3, size=int(rng.integers(1, 3)), replace=False))]
    order = [thrust["column"], disp["column"], tilt["column"], *extras]
    order = [order[i] for i in rng.permutation(len(order))]
    delim_name = list(DELIMITERS)[int(rng.integers(4))]
    return {"t": time, "thrust": thrust, "displacement": disp, "tilt": tilt, "extras": extras,
            "columns": [time["column"], *order], "delimiter_name": delim_name,
            "delimiter": DELIMITERS[delim_name]}


def draw_setup(seed: int, scenario: str = "stepped") -> tuple[Setup, np.random.Generator]:
    """All draws for one seed and scenario; returns the setup and the noise-realisation stream."""
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {SCENARIOS}")
    rng = np.random.default_rng([seed, 0])                 # the stand: same for all scenarios
    K0, J, lam = _draw_pendulum(rng)
    L_stated = round(float(rng.uniform(0.1, 0.4)), 4)          # as printed: 0.1 mm
    uL = float(rng.uniform(-1.0, 1.0))
    L = L_stated * (1.0 + uL * L_SIGMA_REL)
    M_stated = round(float(rng.uniform(1.0, 5.0)), 3)          # as printed: 1 g
    uM = float(rng.uniform(-1.0, 1.0))
    M = M_stated * (1.0 + uM * M_SIGMA_REL)
    l_cm_sign = float(rng.choice([-1.0, 1.0]))
    l_cm_drawn = l_cm_sign * _log_uniform(rng, 0.05e-3, 1e-3)
    fs = int(rng.choice(SAMPLE_RATES_HZ))
    calibration = {
        "thrust_e_F": float(rng.uniform(-THRUST_CAL_TOL, THRUST_CAL_TOL)),
        "tilt_gain_error": float(rng.uniform(-TILT_GAIN_TOL, TILT_GAIN_TOL)),
        "tilt_offset_rad": _signed(rng, 0.1e-6, 0.5e-6),
    }
    noise = {"disp_white_factor": _noise_factor(rng), "disp_walk_factor": _noise_factor(rng),
             "tilt_white_factor": _noise_factor(rng)}
    noise["disp_asd_m_per_rtHz"] = DISP_ASD_NOMINAL * noise["disp_white_factor"]
    noise["disp_white_sigma_m"] = noise["disp_asd_m_per_rtHz"] * math.sqrt(fs / 2.0)
    noise["disp_walk_rms_after_1h_m"] = (DISP_WALK_NOMINAL_M_PER_SQRT_H
                                         * noise["disp_walk_factor"])
    noise["disp_walk_step_m"] = noise["disp_walk_rms_after_1h_m"] / math.sqrt(3600.0 * fs)
    noise["tilt_asd_rad_per_rtHz"] = TILT_ASD_NOMINAL * noise["tilt_white_factor"]
    noise["tilt_white_sigma_rad"] = noise["tilt_asd_rad_per_rtHz"] * math.sqrt(fs / 2.0)
    zero = {"offset_m": _signed(rng, 0.5e-6, 5e-6),
            "c1_m_per_h": _signed(rng, 5e-9, 30e-9),
            "c2_m_per_h2": _signed(rng, 0.2e-9, 1e-9)}
    zero["c1_m_per_s"] = zero["c1_m_per_h"] / 3600.0
    zero["c2_m_per_s2"] = zero["c2_m_per_h2"] / 3600.0**2
    start = {"ring_over_static": _signed(rng, 0.3, 2.0), "rate_fraction": float(rng.uniform(-1, 1))}
    style = _draw_style(rng)
    epoch_s = int(dt.datetime(2023, 1, 1, tzinfo=dt.UTC).timestamp()
                  + rng.integers(0, 700 * 86400))

    srng = np.random.default_rng([seed, _SCENARIO_CODE[scenario]])
    redrawn = False
    if scenario == "dual":
        rho = float(srng.uniform(1.05, 1.2))
        while min(0.15, 0.7 * math.sqrt(K0 / J) / (2 * math.pi) / rho) < 0.052:
            K0, J, lam = _draw_pendulum(srng)
            redrawn = True
    l_cm = 0.0 if scenario == "null" else l_cm_drawn
    stand = Stand(K0=K0, J=J, lam=lam, L=L, M=M, l_cm=l_cm)
    stated = {"L_m": {"value": L_stated, "sigma": L_SIGMA_REL * L_stated,
                      "sigma_rel": L_SIGMA_REL, "true_offset_in_sigma": uL},
              "M_kg": {"value": M_stated, "sigma": M_SIGMA_REL * M_stated,
                       "sigma_rel": M_SIGMA_REL, "true_offset_in_sigma": uM}}

    h = H_SUB_S[scenario]
    substeps = round(1.0 / (fs * h))
    if scenario in ("stepped", "null"):
        schedule, duration = _schedule_stepped(srng, stand)
    elif scenario == "drift":
        schedule, duration = _schedule_drift(srng, stand)
    else:
        schedule, duration = _schedule_dual(srng, stand, rho)
    n = math.floor(duration * fs) + 1
    setup = Setup(seed=seed, scenario=scenario, stand=stand, stated=stated, fs=fs, h=h,
                  substeps=substeps, n=n, calibration=calibration, noise=noise, zero=zero,
                  start=start, style=style, epoch_s=epoch_s, schedule=schedule,
                  extras={"pendulum_redrawn": redrawn, "l_cm_drawn_m": l_cm_drawn})
    return setup, np.random.default_rng([seed, _SCENARIO_CODE[scenario], 1])


def _thrust_square(srng: np.random.Generator, stand: Stand) -> dict[str, Any]:
    P = _square_period(srng, stand.decay_time)
    return {"kind": "square", "F_N": _log_uniform(srng, 0.3e-6, 5e-6), "period_s": P,
            "rise_s": round(round(float(srng.uniform(0.2, 1.0)) / 0.05) * 0.05, 2),
            "t_first_rise_s": round(float(srng.uniform(0.0, P)), 1),
            "t_from_s": None, "t_to_s": None}


def _schedule_stepped(srng: np.random.Generator, stand: Stand) -> tuple[dict[str, Any], float]:
    sq = _thrust_square(srng, stand)
    P = sq["period_s"]
    n_lv = int(srng.integers(5, 10))
    span = float(srng.uniform(10e-6, 25e-6))
    levels = np.linspace(-span, span, n_lv)
    spacing = levels[1] - levels[0]
    levels = levels + srng.uniform(-0.2, 0.2, n_lv) * spacing
    levels = levels[srng.permutation(n_lv)]
    t = 0.0
    plateaus = []
    for i, a in enumerate(levels):
        if i > 0:
            t += float(srng.uniform(20.0, 60.0))          # ramp
        flat = float(srng.uniform(4.0, 6.0)) * P
        if i == 0:
            flat += float(srng.uniform(0.5, 1.5)) * P
        plateaus.append({"index": i, "t_start_s": round(t, 3), "t_end_s": round(t + flat, 3),
                         "alpha_rad": float(a)})
        t = round(t + flat, 3)
    pitch = {"kind": "plateaus", "span_rad": span, "n_levels": n_lv, "plateaus": plateaus,
             "ramp": "raised cosine from t_end_s of one plateau to t_start_s of the next"}
    return {"thrust": [sq], "pitch": pitch}, t


def _schedule_drift(srng: np.random.Generator, stand: Stand) -> tuple[dict[str, Any], float]:
    sq = _thrust_square(srng, stand)
    duration = round(float(srng.uniform(12.0, 24.0)) * 3600.0, 1)
    k = int(srng.integers(3, 5))
    comps = [{"period_s": _log_uniform(srng, 2 * 3600.0, 24 * 3600.0),
              "rel_amp": float(srng.uniform(0.3, 1.0)),
              "phase_rad": float(srng.uniform(0, 2 * np.pi))} for _ in range(k)]
    peak = float(srng.uniform(5e-6, 25e-6))
    tt = np.linspace(0.0, duration, 20001)
    c = sum(cc["rel_amp"] * np.sin(2 * np.pi * tt / cc["period_s"] + cc["phase_rad"])
            for cc in comps)
    norm = peak / float(np.max(np.abs(c)))
    for cc in comps:
        cc["amp_rad"] = cc["rel_amp"] * norm
    cooler = {"period_s": float(srng.uniform(200.0, 800.0)),
              "peak_to_peak_rad": float(srng.uniform(0.1e-6, 0.5e-6)),
              "rise_fraction": float(srng.uniform(0.7, 0.95)),
              "t0_s": float(srng.uniform(0.0, 800.0))}
    pitch = {"kind": "thermal_day", "peak_rad": peak, "components": comps, "cooler": cooler,
             "form": "sum amp sin(2 pi t / period + phase) + cooler triangle (-pp/2 at "
                     "t0 + k period, rising linearly to +pp/2 at rise_fraction, back)"}
    return {"thrust": [sq], "pitch": pitch}, duration


def _schedule_dual(srng: np.random.Generator, stand: Stand,
                   rho: float) -> tuple[dict[str, Any], float]:
    f1_hi = min(0.15, 0.7 * stand.f0 / rho)
    f1 = math.floor(float(srng.uniform(0.05, f1_hi)) * 1e4) / 1e4     # 0.1 mHz settings,
    f2 = math.floor(rho * f1 * 1e4) / 1e4                             # rounded down
    sine_len = float(srng.uniform(1.0, 3.0)) * 3600.0
    n1, n2 = round(sine_len * f1), round(sine_len * f2)
    sine_dur = max(n1 / f1, n2 / f2)
    sq = _thrust_square(srng, stand)
    n_sq = int(srng.integers(3, 7))
    lead, gap, tail = (float(srng.uniform(120.0, 600.0)) for _ in range(3))
    order = "sine_first" if srng.random() < 0.5 else "square_first"
    F_a = _log_uniform(srng, 0.3e-6, 2.5e-6)
    amp = float(srng.uniform(10e-6, 30e-6))
    alpha0 = float(srng.uniform(-5e-6, 5e-6))
    sq_dur = n_sq * sq["period_s"]
    if order == "sine_first":
        t_s = round(lead, 1)
        t_q = round(t_s + sine_dur + gap, 1)
        end = t_q + sq_dur + tail
    else:
        t_q = round(lead, 1)
        t_s = round(t_q + sq_dur + gap, 1)
        end = t_s + sine_dur + tail
    sq.update({"t_first_rise_s": t_q, "t_from_s": t_q, "t_to_s": t_q + sq_dur, "n_periods": n_sq})
    sine = {"kind": "sine_unipolar", "F_amp_N": F_a, "f_hz": f2, "t_from_s": t_s,
            "t_to_s": t_s + n2 / f2, "n_cycles": n2,
            "form": "F_amp (1 - cos(2 pi f (t - t_from))) inside [t_from, t_to], else 0"}
    pitch = {"kind": "sine", "alpha0_rad": alpha0, "amp_rad": amp, "f_hz": f1, "t_from_s": t_s,
             "t_to_s": t_s + n1 / f1, "n_cycles": n1,
             "form": "alpha0 + amp sin(2 pi f (t - t_from)) inside [t_from, t_to], else alpha0"}
    return {"thrust": [sine, sq], "pitch": pitch, "order": order, "rho_f2_over_f1": rho}, end


# --------------------------------------------------------------------------------------------
# Generation
# --------------------------------------------------------------------------------------------

@dataclass
class Recording:
    """A simulated run: the setup, the physical and logged arrays (SI), and the truth dict."""

    setup: Setup
    arrays: dict[str, np.ndarray]
    truth: dict[str, Any]


def generate(seed: int, scenario: str = "stepped", clean: bool = False) -> Recording:
    """Simulate one recording. clean=True zeroes the sensor noise, the displacement zero (offset,
    walk, drift) and the tiltmeter offset and noise (same draws: same stand and schedule)."""
    setup, rng = draw_setup(seed, scenario)
    st, sch, S, h, n = setup.stand, setup.schedule, setup.substeps, setup.h, setup.n
    on = 0.0 if clean else 1.0
    t_sub = np.arange((n - 1) * S + 1) * h
    tau_sub = torque_true(t_sub, sch, st)
    del t_sub
    t = np.arange(n) / setup.fs
    F = thrust_true(t, sch)
    alpha = tilt_true(t, sch)

    # Start out of equilibrium: deflected from the static balance and moving.
    F_ref = max(seg.get("F_N", 0.0) or 0.0 for seg in sch["thrust"])
    F_ref = max(F_ref, max(seg.get("F_amp_N", 0.0) for seg in sch["thrust"]))
    dtheta = setup.start["ring_over_static"] * F_ref * st.L / st.K0
    theta0 = float(tau_sub[0] / st.K0 + dtheta)
    theta_dot0 = float(setup.start["rate_fraction"] * st.w0 * dtheta)
    theta, theta_dot = simulate(st, tau_sub, h, S, theta0, theta_dot0)
    del tau_sub

    nz = setup.noise
    white = on * rng.normal(0.0, nz["disp_white_sigma_m"], n)
    walk = np.cumsum(rng.normal(0.0, nz["disp_walk_step_m"], n))
    walk = on * (walk - walk[0])
    zero = on * (setup.zero["offset_m"] + setup.zero["c1_m_per_s"] * t
                 + setup.zero["c2_m_per_s2"] * t**2) + walk
    x_true = st.L_s * theta
    x_meas = x_true + zero + white
    cal = setup.calibration
    tilt_noise = on * rng.normal(0.0, nz["tilt_white_sigma_rad"], n)
    tilt_read = (1.0 + cal["tilt_gain_error"]) * alpha + on * cal["tilt_offset_rad"] + tilt_noise
    F_logged = F / (1.0 + cal["thrust_e_F"])

    # Extra columns (for the importer to ignore).
    erng = np.random.default_rng([seed, _SCENARIO_CODE[scenario], 2])
    ex: dict[str, np.ndarray] = {}
    T0 = float(erng.uniform(19.5, 23.5))
    ex["T_plate_degC"] = (T0 + float(erng.uniform(0.05, 0.3)) * np.sin(
        2 * np.pi * t / 86400.0 + erng.uniform(0, 2 * np.pi)) + erng.normal(0, 2e-3, n))
    p0 = _log_uniform(erng, 1e-6, 5e-5)
    ex["p_vac_mbar"] = p0 * (1.0 + 0.05 * np.sin(2 * np.pi * t / 20000.0)) * (
        1.0 + 0.01 * erng.normal(0, 1, n))
    status = np.zeros(n, dtype=np.int64)
    status[erng.integers(0, n, max(1, n // 5000))] = 4
    ex["status"] = status

    arrays = {"t_s": t, "thrust_true_N": F, "thrust_logged_N": F_logged, "alpha_rad": alpha,
              "tilt_read_rad": tilt_read, "theta_rad": theta, "theta_dot_rad_per_s": theta_dot,
              "x_true_m": x_true, "zero_m": zero, "white_m": white, "x_meas_m": x_meas, **ex}
    setup.extras.update({"theta0_rad": theta0, "theta_dot0_rad_per_s": theta_dot0,
                         "dtheta0_rad": dtheta, "F_ref_N": F_ref, "clean": clean})
    return Recording(setup=setup, arrays=arrays, truth=_truth(setup))


def _regime(r: float) -> str:
    if r == 0.0:
        return "none (no tilt coupling)"
    if r > 0.0:
        return "softening (0 < K < K0)"
    if r > -1.0:
        return "stiffening (K > K0)"
    return "negative stiffness (r < -1, out of scope: unstable)"


def _truth(setup: Setup) -> dict[str, Any]:
    st, sch, cal = setup.stand, setup.schedule, setup.calibration
    scen = setup.scenario
    duration = (setup.n - 1) / setup.fs
    truth: dict[str, Any] = {
        "generator": "bench.independent.thrust_stand",
        "seed": setup.seed,
        "scenario": scen,
        "instrument": "torsion-pendulum thrust stand, displacement readout, separate tiltmeter",
        "equation": "J theta'' + lambda theta' + K0 theta = F L + M g sin(alpha) l_cm; "
                    "x = L_s theta with L_s = L",
        "pendulum": {
            "K0_N_m_per_rad": st.K0, "J_kg_m2": st.J, "lambda_N_m_s_per_rad": st.lam,
            "f0_hz": st.f0, "w0_rad_per_s": st.w0, "Q": st.Q, "f_damped_hz": st.f_damped,
            "decay_time_s": st.decay_time, "decay_time_definition": "2 Q / w0 (amplitude 1/e)",
            "M_kg": st.M, "l_cm_m": st.l_cm, "g_m_per_s2": G_M_PER_S2,
            "Mgl_cm_N_m_per_rad": st.Mgl, "Mgl_cm_uN_m_per_urad": st.Mgl,
            "l_cm_drawn_m": setup.extras["l_cm_drawn_m"],
            "pendulum_redrawn": setup.extras["pendulum_redrawn"],
        },
        "arm": {"L_true_m": st.L, "L_stated_m": setup.stated["L_m"]["value"],
                "L_sigma_m": setup.stated["L_m"]["sigma"], "L_sigma_rel": L_SIGMA_REL,
                "L_true_offset_in_sigma": setup.stated["L_m"]["true_offset_in_sigma"],
                "L_sensor_m": st.L_s, "sensor_arm": "L_s = L (the displacement sensor sits at "
                                                    "the thrust arm)"},
        "stated": setup.stated,
        "sampling": {"fs_hz": setup.fs, "dt_s": 1.0 / setup.fs, "n_samples": setup.n,
                     "duration_s": duration, "substeps_per_sample": setup.substeps,
                     "h_sub_s": setup.h, "start_unix_s": setup.epoch_s,
                     "start_utc": dt.datetime.fromtimestamp(setup.epoch_s, dt.UTC).isoformat()},
        "schedule": sch,
        "calibration": {
            "thrust": {"e_F": cal["thrust_e_F"], "tolerance_rel": THRUST_CAL_TOL,
                       "relation": "F_logged = F_true / (1 + e_F)"},
            "tiltmeter": {"gain_error": cal["tilt_gain_error"], "gain_tolerance_rel": TILT_GAIN_TOL,
                          "offset_rad": cal["tilt_offset_rad"],
                          "offset_stated_bound_rad": TILT_OFFSET_BOUND_RAD,
                          "relation": "tilt_read = (1 + gain_error) alpha + offset + white noise"},
        },
        "noise": {**setup.noise, "disp_asd_nominal_m_per_rtHz": DISP_ASD_NOMINAL,
                  "disp_walk_nominal_rms_after_1h_m": DISP_WALK_NOMINAL_M_PER_SQRT_H,
                  "tilt_asd_nominal_rad_per_rtHz": TILT_ASD_NOMINAL,
                  "asd_convention": "one-sided; per-sample sigma = asd sqrt(fs / 2)"},
        "displacement_zero": {**setup.zero, "form": "offset + c1 t + c2 t^2 + random walk "
                                                     "(t in s from the first sample)"},
        "initial_state": {"theta0_rad": setup.extras.get("theta0_rad"),
                          "theta_dot0_rad_per_s": setup.extras.get("theta_dot0_rad_per_s"),
                          "theta_eq0_rad": (setup.extras.get("theta0_rad", 0.0)
                                            - setup.extras.get("dtheta0_rad", 0.0)),
                          "dtheta0_rad": setup.extras.get("dtheta0_rad"),
                          "x_ring0_m": st.L_s * setup.extras.get("dtheta0_rad", 0.0)},
        "clean": setup.extras.get("clean", False),
        "simulation": "exact (Van Loan) discretisation for the torque piecewise linear between "
                      f"sub-steps of {setup.h} s, {setup.substeps} sub-steps per sample; "
                      "sin(alpha) as is",
    }
    sq = [s for s in sch["thrust"] if s["kind"] == "square"]
    if sq:
        P = sq[0]["period_s"]
        truth["settling"] = {"period_s": P, "decay_time_s": st.decay_time,
                             "half_period_over_decay_time": P / 2 / st.decay_time,
                             "settled_each_half_period": P / 2 >= 20 * st.decay_time}
        truth["square_wave"] = {"F_N": sq[0]["F_N"], "F_logged_N": sq[0]["F_N"] / (
            1 + cal["thrust_e_F"]), "period_s": P, "t_first_rise_s": sq[0]["t_first_rise_s"],
            "rise_s": sq[0]["rise_s"], "static_step_theta_rad": sq[0]["F_N"] * st.L / st.K0,
            "static_step_x_m": st.L_s * sq[0]["F_N"] * st.L / st.K0}
    if scen in ("stepped", "null"):
        F, L = sq[0]["F_N"], st.L
        rows = []
        for p in sch["pitch"]["plateaus"]:
            a = p["alpha_rad"]
            grav = st.Mgl * math.sin(a)
            r = grav / (F * L)
            rows.append({**p, "alpha_urad": a * 1e6, "gravity_torque_N_m": grav, "r": r,
                         "K_N_m_per_rad": st.K0 / (1.0 + r) if r != -1.0 else math.inf,
                         "S_rad_per_N_m": (1.0 + r) / st.K0, "regime": _regime(r),
                         "tilt_read_expected_rad": (1 + cal["tilt_gain_error"]) * a
                         + cal["tilt_offset_rad"],
                         "theta_off_rad": grav / st.K0, "theta_on_rad": (F * L + grav) / st.K0,
                         "x_off_m": st.L_s * grav / st.K0,
                         "x_on_m": st.L_s * (F * L + grav) / st.K0})
        truth["plateaus"] = rows
        truth["plateau_definitions"] = ("r = M g sin(alpha) l_cm / (F L), K = K0 / (1 + r), "
                                        "S = (1 + r) / K0 with F the TRUE square-wave thrust; "
                                        "theta/x on/off: settled values without sensor zero")
    if scen == "dual":
        pt = sch["pitch"]
        sine = sch["thrust"][0]
        tq_tilt = st.Mgl * 2.0 * float(j1(pt["amp_rad"])) * math.cos(pt["alpha0_rad"])
        tq_thr = sine["F_amp_N"] * st.L
        lines = []
        for src, f, tq, ph in (("tilt", pt["f_hz"], tq_tilt, 0.0),
                               ("thrust", sine["f_hz"], tq_thr, -math.pi / 2)):
            H = st.L_s * st.theta_per_torque(f)
            lines.append({"source": src, "f_hz": f, "t_from_s": pt["t_from_s"],
                          "drive_phase_rad": ph, "torque_amp_N_m": tq,
                          "x_amp_m": abs(H) * tq, "x_phase_rad": float(np.angle(H)),
                          "x_per_torque_m_per_N_m": abs(H),
                          "dynamic_factor": abs(H) * st.K0 / st.L_s})
        lines[0]["tilt_amp_rad"] = pt["amp_rad"]
        lines[0]["tilt_read_amp_rad"] = (1 + cal["tilt_gain_error"]) * pt["amp_rad"]
        lines[1]["thrust_amp_N"] = sine["F_amp_N"]
        lines[1]["thrust_logged_amp_N"] = sine["F_amp_N"] / (1 + cal["thrust_e_F"])
        truth["dual_lines"] = lines
        truth["dual_definitions"] = (
            "steady state in the sine section, per line: torque = torque_amp sin(2 pi f "
            "(t - t_from) + drive_phase) and x = x_amp sin(2 pi f (t - t_from) + drive_phase + "
            "x_phase), x_phase = arg(L_s / (K0 - J w^2 + i lambda w)) (a lag); amplitudes are "
            "signed (the sign of l_cm); tilt torque amplitude = M g l_cm 2 J1(amp) cos(alpha0) "
            "(fundamental of sin(alpha)); thrust torque amplitude = F_amp L (the thrust also has "
            "a mean F_amp: x gets a static F_amp L L_s / K0)")
    if scen == "drift":
        tt = np.linspace(0.0, duration, 200001)
        a = tilt_true(tt, sch)
        truth["drift_stats"] = {"alpha_min_rad": float(a.min()), "alpha_max_rad": float(a.max()),
                                "gravity_torque_max_abs_N_m": float(np.max(np.abs(
                                    st.Mgl * np.sin(a))))}
    return truth


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def _fmt(values: np.ndarray, fmt: str) -> list[str]:
    if fmt == "int":
        return [str(v) for v in np.rint(values).astype(np.int64).tolist()]
    return [fmt.format(v) for v in values.tolist()]


def import_block(setup: Setup) -> dict[str, Any]:
    """How to turn the CSV back into SI: value_SI = raw * scale + offset, per role."""
    sty = setup.style
    t, th, d, ti = sty["t"], sty["thrust"], sty["displacement"], sty["tilt"]
    t_off = -float(setup.epoch_s) if t["absolute"] else 0.0
    return {
        "delimiter": sty["delimiter"], "delimiter_name": sty["delimiter_name"],
        "comment_prefix": "#", "header": "first line not starting with '#'",
        "columns": sty["columns"], "ignore": sty["extras"],
        "convention": "value_SI = raw * scale + offset",
        "roles": {
            "t": {"column": t["column"], "unit": t["unit"], "scale": t["scale"],
                  "offset": t_off, "si_unit": "s since the first sample",
                  "resolution_raw": t["res"], "resolution_si": t["res"] * t["scale"],
                  "absolute_epoch_s": float(setup.epoch_s) if t["absolute"] else None},
            "thrust": {"column": th["column"], "unit": th["unit"], "scale": th["scale"],
                       "offset": 0.0, "si_unit": "N", "resolution_raw": th["res"],
                       "resolution_si": th["res"] * th["scale"],
                       "note": "logged thrust = true / (1 + e_F): see calibration"},
            "displacement": {"column": d["column"], "unit": d["unit"], "scale": d["scale"],
                             "offset": d["offset"], "si_unit": "m at the sensor arm L_s = L",
                             "resolution_raw": d["res"], "resolution_si": d["res"] * d["scale"]},
            "tilt": {"column": ti["column"], "unit": ti["unit"], "scale": ti["scale"],
                     "offset": 0.0, "si_unit": "rad (base pitch, tiltmeter reading)",
                     "resolution_raw": ti["res"], "resolution_si": ti["res"] * ti["scale"]},
        },
    }


def raw_columns(rec: Recording) -> dict[str, np.ndarray]:
    """The numbers written to each column, before formatting (raw units)."""
    s, a, sty = rec.setup, rec.arrays, rec.setup.style
    t = sty["t"]
    d = sty["displacement"]
    cols = {t["column"]: a["t_s"] / t["scale"] + (s.epoch_s if t["absolute"] else 0.0),
            sty["thrust"]["column"]: a["thrust_logged_N"] / sty["thrust"]["scale"],
            d["column"]: (a["x_meas_m"] - d["offset"]) / d["scale"],
            sty["tilt"]["column"]: a["tilt_read_rad"] / sty["tilt"]["scale"]}
    for e in sty["extras"]:
        cols[e] = a[e]
    return cols


def _preamble(setup: Setup, name: str) -> list[str]:
    sty, st_ = setup.style, setup.stated
    start = dt.datetime.fromtimestamp(setup.epoch_s, dt.UTC)
    t, th, d, ti = sty["t"], sty["thrust"], sty["displacement"], sty["tilt"]
    dtext = {"um": "micrometres", "nm": "nanometres"}.get(d["unit"], "")
    if d["unit"] == "counts":
        dtext = (f"24-bit ADC counts, offset binary (zero at {ADC_MID}), "
                 f"{d['scale'] * 1e9:.3f} nm/count")
    extra_text = {"T_plate_degC": "base plate temperature, degC (monitor only)",
                  "p_vac_mbar": "chamber pressure, mbar (monitor only)",
                  "status": "DAQ status flags (bit 2: buffer warning); not a measurement"}
    sch = setup.schedule
    note = {"stepped": "pitch stepped through plateaus by the leveler; square-wave thrust",
            "null": "pitch stepped through plateaus by the leveler; square-wave thrust "
                    "(frame balanced)",
            "drift": "free-running base (no leveling) overnight; square-wave thrust",
            "dual": "CoM calibration: pitch sine + thrust sine, then/before square-wave thrust"}
    lines = [
        f"# Torsion-pendulum thrust stand TPS-2 / run {name}",
        f"# start {start:%Y-%m-%d %H:%M:%S} UTC, sample rate {setup.fs} Hz",
        f"# delimiter: {sty['delimiter_name']}; comment lines start with '#'",
        f"# {t['column']}: {t['text']}",
        f"# {th['column']}: thrust from the thruster calibration, {th['unit']} "
        f"(calibration tolerance {THRUST_CAL_TOL * 100:.0f} %)",
        f"# {d['column']}: capacitive displacement sensor at the thrust arm, {dtext}",
        f"# {ti['column']}: base pitch from tiltmeter TM-1, urad (gain tolerance "
        f"{TILT_GAIN_TOL * 100:.0f} %, zero offset within +-{TILT_OFFSET_BOUND_RAD * 1e6:.1f} "
        "urad, not subtracted)",
        *(f"# {e}: {extra_text[e]}" for e in sty["extras"]),
        f"# thrust arm L = {st_['L_m']['value']:.4f} m +- {L_SIGMA_REL * 100:.1f} % (1 sigma); "
        "displacement sensor at the same arm",
        f"# pendulum mass M = {st_['M_kg']['value']:.3f} kg +- {M_SIGMA_REL * 100:.1f} %",
        f"# operator: {note[setup.scenario]}",
    ]
    sq = [s for s in sch["thrust"] if s["kind"] == "square"]
    if sq:
        f_nom = sq[0]["F_N"] / (1 + setup.calibration["thrust_e_F"]) * 1e6
        lines.append(f"# thrust square wave 0/{f_nom:.3f} uN (nominal), period "
                     f"{sq[0]['period_s']:.1f} s")
    return lines


def write_recording(seed: int, out_dir: str | Path, scenario: str = "stepped",
                    clean: bool = False) -> dict[str, Any]:
    """Simulate and write OUT_DIR/thrust_stand_<seed>_<scenario>.csv and truth_<...>.json."""
    return write_files(generate(seed, scenario, clean=clean), out_dir)


def write_files(rec: Recording, out_dir: str | Path) -> dict[str, Any]:
    setup = rec.setup
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    name = f"thrust_stand_{setup.seed}_{setup.scenario}.csv"
    tname = f"truth_{setup.seed}_{setup.scenario}.json"
    sty = setup.style
    raw = raw_columns(rec)
    fmts = {sty["t"]["column"]: sty["t"]["fmt"], sty["thrust"]["column"]: sty["thrust"]["fmt"],
            sty["displacement"]["column"]: sty["displacement"]["fmt"],
            sty["tilt"]["column"]: sty["tilt"]["fmt"],
            "T_plate_degC": "{:.3f}", "p_vac_mbar": "{:.3e}", "status": "int"}
    cols = [_fmt(raw[c], fmts[c]) for c in sty["columns"]]
    delim = sty["delimiter"]
    pre = _preamble(setup, name.removesuffix(".csv"))
    body = [delim.join(r) for r in zip(*cols, strict=True)]
    (out / name).write_text("\n".join([*pre, delim.join(sty["columns"]), *body]) + "\n")

    truth = dict(rec.truth)
    truth["import"] = import_block(setup)
    truth["file"] = {"csv_file": name, "truth_file": tname, "preamble_lines": len(pre),
                     "header_line": len(pre) + 1, "first_data_line": len(pre) + 2,
                     "n_data_rows": len(body), "columns": sty["columns"],
                     "extra_columns": sty["extras"]}
    (out / tname).write_text(json.dumps(_plain(truth), indent=1))
    return truth


def _plain(x: Any) -> Any:
    """numpy scalars/arrays -> JSON-ready Python types (inf -> None)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seed", type=int)
    ap.add_argument("out_dir")
    ap.add_argument("--scenario", choices=SCENARIOS, default="stepped")
    a = ap.parse_args(argv)
    truth = write_recording(a.seed, a.out_dir, a.scenario)
    p = truth["pendulum"]
    print(f"{Path(a.out_dir) / truth['file']['csv_file']}: {a.scenario}, f0 {p['f0_hz']:.4g} Hz, "
          f"Q {p['Q']:.3g}, K0 {p['K0_N_m_per_rad']:.4g} N m/rad, M g l_cm "
          f"{p['Mgl_cm_N_m_per_rad']:.3g} N m/rad, {truth['file']['n_data_rows']} rows at "
          f"{truth['sampling']['fs_hz']} Hz")
    return 0


if __name__ == "__main__":
    sys.exit(main())
