"""Independent recording generator: a hanging-pendulum (beam-balance) tiltmeter, piezo-tilted base.

It plays "a real recording from a lab instrument leveler's developers have never seen": written from
the physics alone (PHYSICS.md, last section), sharing no code or model form with leveler.

Physics. theta is the pendulum's deflection relative to the platform, phi the platform tilt and
psi = theta + phi the pendulum's absolute angle. With the centre of mass a distance d BELOW the
pivot,

    J (theta'' + phi'') + c theta' + k theta + m g d sin(theta + phi) = 0
    <=>  J psi'' + c psi' + (k + m g d) psi = c phi' + k phi        (sin psi -> psi)

Writing the equation in psi moves phi'' out of the forcing: only phi and phi' drive it. Angles stay
below ~1e-4 rad, where sin(psi) - psi is < 2e-9 of the linear term, so the linear form is used; a
test checks it against an ODE integration of the full sin() equation.

Simulation (time domain, not via the transfer function). phi is built on a sub-step grid
(SUBSTEPS per 0.5 s sample) and taken piecewise linear between grid points (first-order hold). For
a piecewise-linear input the state update over one sub-step is exact: x[n+1] = Ad x[n] + G0 a[n] +
G1 b[n], with the forcing a + b*tau inside the step, and Ad, G0, G1 taken from one augmented
matrix exponential (Van Loan). The recursion runs in modal form (one complex first-order pole,
scipy.signal.lfilter), which is fast and well conditioned even at Q = 300.

Linearised response: theta/phi = -(m g d - J w^2) / (k + m g d - J w^2 + i c w). Zero at
w_z^2 = m g d / J, static gain -m g d / (k + m g d), and -1 well above w_0^2 = (k + m g d) / J.
The sensor reads sensor_arm * theta (metres); the platform tilt per volt is piezo_gain / spacing.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter, lfilter_zi

G_M_PER_S2 = 9.81
FS_HZ = 2.0
SUBSTEPS = 8                      # sub-steps per sample for the piecewise-linear platform tilt
DELIMITER = ";"
COLUMNS = ("MJD", "tilt_counts", "pzt_V", "T_degC")
MIN_STEP_S = 2400.0               # each sweep step lasts max(15 cycles, 40 min)
MIN_CYCLES = 15.0
SNR_SEGMENT_S = MIN_STEP_S        # "noise per bin" is quoted for the shortest step
MJD_EPOCH = dt.datetime(1858, 11, 17, tzinfo=dt.UTC)

# Nominal noise levels; each is scaled per seed by a factor in [0.75, 0.9] or [1.1, 1.25].
WHITE_NOMINAL_M = 8e-9            # sensor white noise per 0.5 s sample (8 nm/sqrt(Hz) one-sided)
DRIFT_WALK_NOMINAL_M = 3e-9       # sensor-zero random-walk step per sample
PLATFORM_WALK_NOMINAL_RAD = 3e-10 # platform-tilt random-walk step per sample
PZT_MONITOR_NOISE_V = 1e-3        # piezo monitor noise; recorded with 1 mV resolution
TEMP_NOISE_K = 3e-3               # plate thermometer noise; recorded with 0.01 K resolution

# What the lab states (1-sigma, relative) and how far the truth sits from it.
STATED_SIGMA_REL = {
    "J_kg_m2": 0.03,
    "m_kg": 0.005,
    "sensor_arm_m": 0.02,
    "piezo_gain_m_per_V": 0.03,
    "support_spacing_m": 0.01,
    "k_N_m_per_rad": 0.20,
    "Q": 0.50,
    "scale_m_per_count": 0.02,
}
OFFSET_1_TO_2_SIGMA = ("J_kg_m2", "m_kg", "sensor_arm_m", "piezo_gain_m_per_V",
                       "support_spacing_m", "scale_m_per_count")


@dataclass(frozen=True)
class Pendulum:
    """Rigid hanging pendulum on a flexure: the four numbers the equation of motion needs."""

    J: float    # moment of inertia about the pivot, kg m^2
    m: float    # mass, kg
    d: float    # centre of mass below the pivot, m
    k: float    # flexure stiffness, N m/rad
    c: float    # damping, N m s/rad

    @property
    def mgd(self) -> float:
        return self.m * G_M_PER_S2 * self.d

    @property
    def f_z(self) -> float:
        return math.sqrt(self.mgd / self.J) / (2 * math.pi)

    @property
    def f_0(self) -> float:
        return math.sqrt((self.k + self.mgd) / self.J) / (2 * math.pi)

    @property
    def Q(self) -> float:
        return math.sqrt(self.J * (self.k + self.mgd)) / self.c

    def tilt_response(self, f_hz: np.ndarray | float) -> np.ndarray:
        """theta/phi at f (e^{+i w t} convention); used for the truth, never for the simulation."""
        w = 2 * np.pi * np.asarray(f_hz, dtype=float)
        return -(self.mgd - self.J * w**2) / (self.k + self.mgd - self.J * w**2 + 1j * self.c * w)


def simulate_deflection(p: Pendulum, phi: np.ndarray, h: float,
                        theta0: float = 0.0, theta_dot0: float = 0.0) -> np.ndarray:
    """theta on the grid of phi (spacing h), exact for phi piecewise linear between grid points.

    Integrates J psi'' + c psi' + (k+mgd) psi = c phi' + k phi with psi = theta + phi, so the
    platform's angular acceleration needs no numerical second derivative.
    """
    phi = np.asarray(phi, dtype=float)
    n = phi.size
    a_mat = np.array([[0.0, 1.0], [-(p.k + p.mgd) / p.J, -p.c / p.J]])
    aug = np.zeros((4, 4))
    aug[:2, :2] = a_mat
    aug[1, 2] = 1.0 / p.J          # forcing u = u0 + u1 * tau enters psi''
    aug[2, 3] = 1.0
    e = expm(aug * h)
    ad, g0, g1 = e[:2, :2], e[:2, 2], e[:2, 3]
    slope = np.diff(phi) / h
    u0 = p.c * slope + p.k * phi[:-1]
    u1 = p.k * slope
    lam, vec = np.linalg.eig(ad)
    if abs(lam[0].imag) == 0.0:
        raise ValueError("simulate_deflection expects an underdamped pendulum (Q > 0.5)")
    i = int(np.argmax(lam.imag))
    row = np.linalg.inv(vec)[i]
    x0 = np.array([theta0 + phi[0], theta_dot0 + (slope[0] if n > 1 else 0.0)])
    inp = np.empty(n, dtype=complex)
    inp[0] = row @ x0
    inp[1:] = u0 * (row @ g0) + u1 * (row @ g1)
    z = lfilter([1.0], [1.0, -lam[i]], inp)
    psi = 2.0 * (vec[0, i] * z).real
    return psi - phi


def first_order_lowpass(x: np.ndarray, h: float, tau: float) -> np.ndarray:
    """Exact first-order lag for x piecewise linear on its grid; starts settled at x[0]."""
    a = math.exp(-h / tau)
    q = tau * (1.0 - a) / h
    b = [1.0 - q, q - a]
    y, _ = lfilter(b, [1.0, -a], x, zi=lfilter_zi(b, [1.0, -a]) * x[0])
    return y


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _noise_factor(rng: np.random.Generator) -> float:
    lo, hi = (0.75, 0.9) if rng.random() < 0.5 else (1.1, 1.25)
    return float(rng.uniform(lo, hi))


def _signed(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))


@dataclass
class Setup:
    """Every per-seed draw that fixes the experiment, before any noise realisation."""

    seed: int
    drive: str
    pendulum: Pendulum
    true: dict[str, float]
    stated: dict[str, dict[str, float]]
    noise: dict[str, float]
    environment: dict[str, float]
    schedule: dict[str, Any]
    mjd_start: float
    n_samples: int
    extras: dict[str, Any] = field(default_factory=dict)


def draw_setup(seed: int, drive: str = "sine",
               drift_scale: float = 1.0) -> tuple[Setup, np.random.Generator]:
    """Draw the instrument, the lab's stated values, the noise levels and the sweep for one seed.
    drift_scale multiplies the sensor zero's random walk (after the draws: same seed, same
    instrument), for a quieter sensor than the nominal one."""
    if drive not in ("sine", "square"):
        raise ValueError("drive must be 'sine' or 'square'")
    rng = np.random.default_rng(seed)

    # Pendulum: J and m with a sensible radius of gyration, then d from the zero frequency.
    while True:
        J = _log_uniform(rng, 0.01, 0.2)
        m = _log_uniform(rng, 0.2, 5.0)
        if 0.05 <= math.sqrt(J / m) <= 0.5:
            break
    f_z = _log_uniform(rng, 2e-3, 15e-3)
    mgd = J * (2 * math.pi * f_z) ** 2
    d = mgd / (m * G_M_PER_S2)
    kappa = _log_uniform(rng, 0.3, 3.0)
    k = kappa * mgd
    Q = _log_uniform(rng, 5.0, 300.0)
    c = math.sqrt(J * (k + mgd)) / Q
    pend = Pendulum(J=J, m=m, d=d, k=k, c=c)

    noise = {
        "white_factor": _noise_factor(rng),
        "drift_walk_factor": _noise_factor(rng),
        "platform_walk_factor": _noise_factor(rng),
    }
    noise["white_sigma_m"] = WHITE_NOMINAL_M * noise["white_factor"]
    noise["drift_walk_step_m"] = DRIFT_WALK_NOMINAL_M * noise["drift_walk_factor"] * drift_scale
    noise["drift_scale"] = drift_scale
    noise["platform_walk_step_rad"] = PLATFORM_WALK_NOMINAL_RAD * noise["platform_walk_factor"]
    noise_per_bin = noise["white_sigma_m"] * math.sqrt(2.0 / (SNR_SEGMENT_S * FS_HZ))
    static_gain = abs(float(pend.tilt_response(0.0).real))

    # Readout and actuator; the drive amplitude follows from the SNR the lab aims for at DC.
    while True:
        arm = float(rng.uniform(0.08, 0.25))
        spacing = float(rng.uniform(0.4, 1.0))
        gain = _log_uniform(rng, 3e-9, 1.2e-8)
        snr_dc = _log_uniform(rng, 25.0, 45.0)
        amp = snr_dc * noise_per_bin / (arm * gain / spacing * static_gain)
        if 3.0 <= amp <= 40.0:
            break
    scale = _log_uniform(rng, 0.5e-9, 2e-9)
    bias = float(rng.uniform(50.0, 70.0))

    true = {
        "J_kg_m2": J, "m_kg": m, "d_m": d, "k_N_m_per_rad": k, "c_N_m_s_per_rad": c, "Q": Q,
        "g_m_per_s2": G_M_PER_S2, "mgd_N_m_per_rad": mgd, "kappa_k_over_mgd": kappa,
        "sensor_arm_m": arm, "piezo_gain_m_per_V": gain, "support_spacing_m": spacing,
        "scale_m_per_count": scale,
    }
    stated: dict[str, dict[str, float]] = {}
    for name, rel in STATED_SIGMA_REL.items():
        u = _signed(rng, 1.0, 2.0) if name in OFFSET_1_TO_2_SIGMA else float(rng.uniform(-1, 1))
        value = true[name] / (1.0 + u * rel)        # so (true - stated) / sigma == u exactly
        stated[name] = {"value": value, "sigma": rel * value, "sigma_rel": rel,
                        "true_offset_in_sigma": u}

    # Stepped sweep: 8-12 log-spread frequencies from ~f_z/4 to ~4 f_z, off any round grid.
    n_f = int(rng.integers(8, 13))
    f_lo = f_z / 4 * rng.uniform(0.85, 1.15)
    f_hi = 4 * f_z * rng.uniform(0.85, 1.15)
    grid = np.linspace(math.log(f_lo), math.log(f_hi), n_f)
    dlog = grid[1] - grid[0]
    grid[1:-1] += rng.uniform(-0.25, 0.25, n_f - 2) * dlog
    freqs = np.exp(grid)
    if rng.random() < 0.5:
        freqs = freqs[::-1]
    lead_in = float(rng.uniform(3600.0, 3 * 3600.0))
    t = lead_in
    steps = []
    for i, f in enumerate(freqs):
        dur = max(MIN_CYCLES / f, MIN_STEP_S)
        steps.append({"f_hz": float(f), "t_start_s": round(t, 3), "t_end_s": round(t + dur, 3),
                      "n_cycles": float(f * dur), "phase_rad": float(rng.uniform(0, 2 * np.pi))})
        t = round(t + dur, 3)
        if i < n_f - 1:
            t = round(t + rng.uniform(120.0, 360.0), 3)
    tail = max(rng.uniform(1800.0, 7200.0), rng.uniform(22 * 3600.0, 26 * 3600.0) - t)
    duration = t + tail
    n_samples = int(duration * FS_HZ) + 1

    environment = {
        "platform_offset_rad": _signed(rng, 5e-6, 50e-6),
        "thermal_tilt_rad_per_K": _signed(rng, 0.3e-6, 2e-6),
        "thermal_lag_s": float(rng.uniform(1800.0, 7200.0)),
        "T0_degC": float(rng.uniform(19.5, 23.5)),
        "T_daily_amp_K": float(rng.uniform(0.05, 0.3)),
        "T_daily_peak_utc_h": float(rng.uniform(12.0, 17.0)),
        "T_ou_sigma_K": float(rng.uniform(0.02, 0.06)),
        "T_ou_tau_s": float(rng.uniform(3600.0, 3 * 3600.0)),
        "T_trend_K_per_day": float(rng.uniform(-0.1, 0.1)),
        "drift_initial_m": float(rng.uniform(-80e-6, 80e-6)),
        "drift_linear_m_per_day": _signed(rng, 5e-6, 20e-6),
        "drift_quadratic_m_per_day2": _signed(rng, 1e-6, 6e-6),
        "initial_deflection_at_sensor_m": _signed(rng, 0.3e-6, 2e-6),
        "initial_rate_fraction": float(rng.uniform(-1.0, 1.0)),
        "amplifier_tau_s": float(rng.uniform(0.1, 0.5)),
    }
    mjd_start = round(float(rng.uniform(60000.0, 60700.0)), 8)
    schedule = {"kind": drive, "bias_V": bias, "amplitude_V": float(amp),
                "order": "descending" if freqs[0] > freqs[-1] else "ascending",
                "lead_in_s": lead_in, "tail_s": float(tail), "steps": steps,
                "snr_dc_target": snr_dc, "noise_per_bin_m": noise_per_bin}
    setup = Setup(seed=seed, drive=drive, pendulum=pend, true=true, stated=stated, noise=noise,
                  environment=environment, schedule=schedule, mjd_start=mjd_start,
                  n_samples=n_samples)
    return setup, rng


def drive_command(schedule: dict[str, Any], t: np.ndarray) -> np.ndarray:
    """Function-generator command: bias, plus the sine (or square) during each step."""
    cmd = np.full(t.size, schedule["bias_V"])
    for st in schedule["steps"]:
        i0, i1 = np.searchsorted(t, [st["t_start_s"], st["t_end_s"]])
        arg = 2 * np.pi * st["f_hz"] * (t[i0:i1] - st["t_start_s"]) + st["phase_rad"]
        wave = np.sin(arg)
        if schedule["kind"] == "square":
            wave = np.where(wave >= 0.0, 1.0, -1.0)
        cmd[i0:i1] += schedule["amplitude_V"] * wave
    return cmd


@dataclass
class Recording:
    """A simulated run: the setup, the physical arrays (for tests) and the truth dict."""

    setup: Setup
    arrays: dict[str, np.ndarray]
    truth: dict[str, Any]


def generate(seed: int, drive: str = "sine", clean: bool = False,
             drift_scale: float = 1.0) -> Recording:
    """Simulate one run. clean=True zeroes noise, drift, thermal/walk tilt, offset and initial
    deflection (the same draws are made, so the instrument and sweep are those of the seed)."""
    setup, rng = draw_setup(seed, drive, drift_scale)
    p, env, noise, sch = setup.pendulum, setup.environment, setup.noise, setup.schedule
    tr = setup.true
    n = setup.n_samples
    dt_s = 1.0 / FS_HZ
    h = dt_s / SUBSTEPS
    t = np.arange(n) * dt_s
    t_days = t / 86400.0
    on = 0.0 if clean else 1.0

    # Plate temperature: daily cycle + Ornstein-Uhlenbeck wander + trend.
    rho = math.exp(-dt_s / env["T_ou_tau_s"])
    innov = rng.normal(0.0, env["T_ou_sigma_K"] * math.sqrt(1 - rho**2), n)
    innov[0] = rng.normal(0.0, env["T_ou_sigma_K"])
    ou = lfilter([1.0], [1.0, -rho], innov)
    utc_h = ((setup.mjd_start % 1.0) + t_days) * 24.0
    temp = (env["T0_degC"] + ou + env["T_trend_K_per_day"] * t_days
            + env["T_daily_amp_K"] * np.cos(2 * np.pi * (utc_h - env["T_daily_peak_utc_h"]) / 24))
    thermal = env["thermal_tilt_rad_per_K"] * first_order_lowpass(
        temp - env["T0_degC"], dt_s, env["thermal_lag_s"])
    walk = np.cumsum(rng.normal(0.0, noise["platform_walk_step_rad"], n))
    walk -= walk[0]
    phi_slow = on * (env["platform_offset_rad"] + thermal + walk)

    # Piezo: command -> amplifier (first-order lag) -> platform tilt, on the sub-step grid.
    t_sub = np.arange((n - 1) * SUBSTEPS + 1) * h
    v_sub = first_order_lowpass(drive_command(sch, t_sub), h, env["amplifier_tau_s"])
    tilt_per_v = tr["piezo_gain_m_per_V"] / tr["support_spacing_m"]
    phi_sub = tilt_per_v * v_sub + np.interp(t_sub, t, phi_slow)

    # Start out of equilibrium: deflected from the static balance and moving.
    theta_eq = p.tilt_response(0.0).real * phi_sub[0]
    dtheta = on * env["initial_deflection_at_sensor_m"] / tr["sensor_arm_m"]
    theta0 = theta_eq + dtheta
    theta_dot0 = env["initial_rate_fraction"] * 2 * np.pi * p.f_0 * dtheta
    theta = simulate_deflection(p, phi_sub, h, theta0, theta_dot0)[::SUBSTEPS]
    phi = phi_sub[::SUBSTEPS]
    v_true = v_sub[::SUBSTEPS]

    # Sensor: arm * theta + zero drift (walk + trend, dominant) + white noise.
    dwalk = np.cumsum(rng.normal(0.0, noise["drift_walk_step_m"], n))
    dwalk -= dwalk[0]
    white = on * rng.normal(0.0, noise["white_sigma_m"], n)
    signal = tr["sensor_arm_m"] * theta
    trend_scale = 1.0
    trend = env["drift_linear_m_per_day"] * t_days + env["drift_quadratic_m_per_day2"] * t_days**2
    drift = on * (env["drift_initial_m"] + dwalk + trend)
    if not clean:  # the drift must carry >= 75 % of the raw variance: scale the trend up if not
        rest_var = float(np.var(signal + white))
        while np.var(drift) < 3.0 * rest_var and trend_scale < 1e3:
            trend_scale *= 1.5
            drift = env["drift_initial_m"] + dwalk + trend_scale * trend
    sensor_m = signal + drift + white
    counts = np.rint(sensor_m / tr["scale_m_per_count"]).astype(np.int64)
    v_rec = np.round(v_true + on * rng.normal(0.0, PZT_MONITOR_NOISE_V, n), 3)
    t_rec = np.round(temp + on * rng.normal(0.0, TEMP_NOISE_K, n), 2)

    arrays = {"t_s": t, "theta_rad": theta, "phi_rad": phi, "v_true_V": v_true, "drift_m": drift,
              "white_m": white, "signal_m": signal, "sensor_m": sensor_m, "counts": counts,
              "pzt_V": v_rec, "T_degC": t_rec, "T_true_degC": temp}
    setup.extras.update({
        "trend_scale": trend_scale,
        "drift_variance_fraction": float(np.var(drift) / np.var(sensor_m)) if not clean else 0.0,
        "theta0_rad": float(theta0), "theta_dot0_rad_per_s": float(theta_dot0),
        "clean": clean,
    })
    return Recording(setup=setup, arrays=arrays, truth=_truth(setup))


def sensor_per_volt(setup: Setup, f_hz: np.ndarray | float) -> np.ndarray:
    """Steady-state sensor metres per drive volt from the TRUE parameters."""
    tr = setup.true
    return (tr["sensor_arm_m"] * tr["piezo_gain_m_per_V"] / tr["support_spacing_m"]
            * setup.pendulum.tilt_response(f_hz))


def _truth(setup: Setup) -> dict[str, Any]:
    p, sch, noise, env = setup.pendulum, setup.schedule, setup.noise, setup.environment
    freqs = np.array([s["f_hz"] for s in sch["steps"]])
    h_mv = sensor_per_volt(setup, freqs)
    seg_n = np.array([(s["t_end_s"] - s["t_start_s"]) * FS_HZ for s in sch["steps"]])
    snr = np.abs(h_mv) * sch["amplitude_V"] / (noise["white_sigma_m"] * np.sqrt(2.0 / seg_n))
    scale = setup.true["scale_m_per_count"]
    env_out = dict(env)
    env_out["drift_linear_m_per_day"] *= setup.extras.get("trend_scale", 1.0)
    env_out["drift_quadratic_m_per_day2"] *= setup.extras.get("trend_scale", 1.0)
    return {
        "seed": setup.seed,
        "generator": "bench.independent.tiltmeter",
        "instrument": "hanging-pendulum (beam-balance) tiltmeter on a piezo-tilted platform",
        "equation": "J(theta''+phi'') + c theta' + k theta + m g d sin(theta+phi) = 0",
        "true": dict(setup.true),
        "stated": setup.stated,
        "d_true_m": p.d,
        "f_z_hz": p.f_z,
        "f_0_hz": p.f_0,
        "Q": p.Q,
        "static_gain_theta_per_phi": float(p.tilt_response(0.0).real),
        "scale_m_per_count": {"true": scale, "stated": setup.stated["scale_m_per_count"]["value"],
                              "stated_sigma": setup.stated["scale_m_per_count"]["sigma"]},
        "drive": {"kind": sch["kind"], "bias_V": sch["bias_V"], "amplitude_V": sch["amplitude_V"],
                  "order": sch["order"], "lead_in_s": sch["lead_in_s"], "tail_s": sch["tail_s"],
                  "amplifier_tau_s": env["amplifier_tau_s"],
                  "waveform": "V = bias + A*w(2 pi f (t - t_start_s) + phase_rad), w = sin or "
                              "sign(sin); the recorded pzt_V is the amplifier output",
                  "steps": sch["steps"]},
        "drive_frequencies_hz": freqs.tolist(),
        "drive_spans_s": [[s["t_start_s"], s["t_end_s"]] for s in sch["steps"]],
        "transfer_function": [
            {"f_hz": float(f), "re_m_per_V": float(hv.real), "im_m_per_V": float(hv.imag),
             "abs_m_per_V": float(abs(hv)), "phase_rad": float(np.angle(hv)),
             "re_counts_per_V": float(hv.real / scale), "im_counts_per_V": float(hv.imag / scale)}
            for f, hv in zip(freqs, h_mv, strict=True)],
        "transfer_function_convention": "sensor_m / V_drive at the fundamental; for "
            "V(t) = Re(V e^{+i 2 pi f t}), sensor(t) = Re(H V e^{+i 2 pi f t}); counts use the "
            "true scale",
        "snr": {"noise_per_bin_m": sch["noise_per_bin_m"], "segment_s": SNR_SEGMENT_S,
                "definition": "sensor amplitude / (white sigma * sqrt(2 / samples in segment))",
                "dc_response_over_noise_per_bin": sch["snr_dc_target"],
                "per_step": snr.tolist()},
        "noise": {**noise, "white_nominal_m": WHITE_NOMINAL_M,
                  "drift_walk_nominal_m": DRIFT_WALK_NOMINAL_M,
                  "platform_walk_nominal_rad": PLATFORM_WALK_NOMINAL_RAD,
                  "pzt_monitor_noise_V": PZT_MONITOR_NOISE_V, "temperature_noise_K": TEMP_NOISE_K},
        "environment": env_out,
        "initial_state": {"theta0_rad": setup.extras.get("theta0_rad"),
                          "theta_dot0_rad_per_s": setup.extras.get("theta_dot0_rad_per_s")},
        "drift_variance_fraction": setup.extras.get("drift_variance_fraction"),
        "clean": setup.extras.get("clean", False),
        "sample_rate_hz": FS_HZ,
        "n_samples_simulated": setup.n_samples,
        "duration_s": (setup.n_samples - 1) / FS_HZ,
        "mjd_start": setup.mjd_start,
        "time_column": COLUMNS[0],
        "time_unit": "days",
        "time_reference": "MJD (UTC); seconds from first sample = (MJD - mjd_start) * 86400",
        "columns": list(COLUMNS),
        "delimiter": DELIMITER,
        "simulation": f"exact first-order-hold discretisation of the linear psi equation, "
                      f"{SUBSTEPS} sub-steps per sample",
    }


def _preamble(setup: Setup, n_rows: int) -> list[str]:
    start = MJD_EPOCH + dt.timedelta(days=setup.mjd_start)
    sc = setup.stated
    return [
        f"# BBT-3 beam-balance tiltmeter, serial BBT3-{1000 + setup.seed % 9000:04d}",
        "# Logger DL-24 fw 2.7.1, free-running at 2 Hz; channels AI0 tilt, AI1 piezo monitor, "
        "RTD1 plate",
        f"# Start {start:%Y-%m-%d %H:%M:%S} UTC (MJD {setup.mjd_start:.8f})",
        "# MJD: Modified Julian Date, UTC, days",
        f"# tilt_counts: beam-end displacement, ADC counts; "
        f"{sc['scale_m_per_count']['value']:.5e} m/count (factory cal., 2 %)",
        f"# sensor arm {sc['sensor_arm_m']['value']:.4f} m from pivot",
        "# pzt_V: piezo amplifier monitor, volts (1 mV resolution)",
        "# T_degC: base plate temperature, degC (0.01 K resolution)",
        f"# operator: stepped {setup.drive} sweep about {setup.schedule['bias_V']:.1f} V bias",
        f"# delimiter '{DELIMITER}', missing value NaN",
    ]


def _pick(rng: np.random.Generator, lo: int, hi: int, taken: list[tuple[int, int]],
          sep: int, width: int = 1) -> int:
    """A start index in [lo, hi) whose span keeps `sep` samples clear of every taken span."""
    while True:
        i = int(rng.integers(lo, hi))
        if all(i + width + sep <= a or i >= b + sep for a, b in taken):
            taken.append((i, i + width))
            return i


def write_files(rec: Recording, out_dir: str | Path) -> dict[str, Any]:
    """Write the logger CSV (with its stray rows) and truth.json; return the truth dict."""
    setup, arr = rec.setup, rec.arrays
    rng = np.random.default_rng([setup.seed, 7])   # stray rows: their own stream
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n = setup.n_samples

    # Time stamps: the sampling is regular, the logger's clock reading jitters by +-5 ms.
    jitter = rng.uniform(-0.005, 0.005, n)
    mjd = setup.mjd_start + (arr["t_s"] + jitter) / 86400.0
    rows = [[f"{a:.9f}", str(b), f"{c:.3f}", f"{d:.2f}"]
            for a, b, c, d in zip(mjd.tolist(), arr["counts"].tolist(), arr["pzt_V"].tolist(),
                                  arr["T_degC"].tolist(), strict=True)]

    lo, hi, sep = int(0.05 * n), int(0.95 * n), 600
    taken: list[tuple[int, int]] = []
    gap_len = int(rng.integers(3, 21))
    gap = _pick(rng, lo, hi, taken, sep, gap_len)
    swap = _pick(rng, lo, hi, taken, sep, 2)
    dup = _pick(rng, lo, hi, taken, sep)
    hdr = _pick(rng, lo, hi, taken, sep)
    bad = {}
    for _ in range(int(rng.integers(3, 6))):
        i = _pick(rng, lo, hi, taken, sep)
        col = int(rng.integers(1, len(COLUMNS)))
        kind = "nan_field" if rng.random() < 0.6 else "empty_field"
        rows[i][col] = "NaN" if kind == "nan_field" else ""
        bad[i] = (col, kind)

    header = DELIMITER.join(COLUMNS)
    body: list[tuple[str, int | None]] = []   # (text, sample index or None for a header)
    i = 0
    while i < n:
        if gap <= i < gap + gap_len:
            i += 1
            continue
        if i == hdr:
            body.append((header, None))
        if i == swap:
            body += [(DELIMITER.join(rows[i + 1]), i + 1), (DELIMITER.join(rows[i]), i)]
            i += 2
            continue
        body.append((DELIMITER.join(rows[i]), i))
        if i == dup:
            body.append((DELIMITER.join(rows[i]), i))
        i += 1

    pre = _preamble(setup, len(body))
    first = len(pre) + 2                       # line number of the first data row
    line_of: dict[int, int] = {}
    strays: list[dict[str, Any]] = []
    for k, (_, idx) in enumerate(body):
        ln = first + k
        if idx is None:
            strays.append({"line": ln, "kind": "repeated_header"})
        elif idx in line_of:
            strays.append({"line": ln, "kind": "duplicate", "duplicate_of_line": line_of[idx],
                           "sample_index": idx})
        else:
            line_of[idx] = ln
    strays.append({"line": line_of[swap + 1], "kind": "out_of_order",
                   "swapped_with_line": line_of[swap], "sample_index": swap + 1,
                   "note": "this row and the next are swapped"})
    strays.append({"line": line_of[gap + gap_len], "kind": "gap", "n_missing": gap_len,
                   "after_line": line_of[gap - 1], "first_missing_sample_index": gap,
                   "missing_t_s": [gap / FS_HZ, (gap + gap_len - 1) / FS_HZ]})
    for idx, (col, kind) in bad.items():
        strays.append({"line": line_of[idx], "kind": kind, "column": COLUMNS[col],
                       "sample_index": idx})
    strays.sort(key=lambda s: s["line"])

    start = MJD_EPOCH + dt.timedelta(days=setup.mjd_start)
    name = f"BBT3_{start:%Y%m%d_%H%M%S}.csv"
    text = "\n".join([*pre, header, *(b for b, _ in body)]) + "\n"
    (out / name).write_text(text)

    truth = dict(rec.truth)
    truth.update({
        "csv_file": name,
        "csv_path": str((out / name).resolve()),
        "preamble_lines": len(pre),
        "header_line": len(pre) + 1,
        "first_data_line": first,
        "n_data_rows": len(body) - 1,
        "stray_rows": strays,
        "timing_jitter": {"distribution": "uniform", "half_width_s": 0.005,
                          "applies_to": "time stamps only; sampling is regular"},
    })
    (out / "truth.json").write_text(json.dumps(_plain(truth), indent=1))
    return truth


def _plain(x: Any) -> Any:
    """numpy scalars/arrays -> JSON-ready Python types."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


def write_recording(seed: int, out_dir: str | Path, drive: str = "sine",
                    drift_scale: float = 1.0) -> dict[str, Any]:
    """Simulate seed's run and write the logger CSV plus truth.json into out_dir."""
    return write_files(generate(seed, drive, drift_scale=drift_scale), out_dir)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seed", type=int)
    ap.add_argument("out_dir")
    ap.add_argument("--drive", choices=("sine", "square"), default="sine")
    ap.add_argument("--drift-scale", type=float, default=1.0,
                    help="multiply the sensor zero's random walk (default 1)")
    a = ap.parse_args(argv)
    truth = write_recording(a.seed, a.out_dir, a.drive, a.drift_scale)
    print(f"{truth['csv_path']}: f_z {truth['f_z_hz'] * 1e3:.3f} mHz, d {truth['d_true_m']:.4g} m, "
          f"{truth['n_data_rows']} rows, {len(truth['stray_rows'])} stray rows")
    return 0


if __name__ == "__main__":
    sys.exit(main())
