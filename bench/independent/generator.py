"""Write one "measured" leveler log whose plant differs from the model the lab believes.

    generate(family, severity, seed, out) -> truth dict

The log's metadata `config` is the NOMINAL config text (what the lab believes); the plant
that made the data is the nominal one with:

- calibration offsets in every log (piezo gain, support spacing, sensor arm and gain,
  amplification, resonance frequency: |offset| drawn in [1, 2] sigma of the tolerances in
  `[plant.uncertainty]`; Q and the thermal tilt coefficient within 1 sigma);
- noise levels scaled by a factor drawn in [0.75, 0.9] or [1.1, 1.25] (sensor white noise,
  sensor drift, the temperature's random walk and daily cycle, the cooler's amplitude);
- a start out of equilibrium (table tilt, pendulum deflection and rate, thermal lag state,
  integrator);
- for an effect log, ONE missing effect (`effects.py`: forms and sizes).

The nominal gains must keep the TRUE loop stable (0.3 dB of gain to spare, checked by a
noise-free kick of this very loop): with the platform's angular acceleration in the pendulum's
equation they leave only about 1 dB of gain margin near 2 Hz (a 27 ms delay margin), so some
calibration draws, and large positive sensor gain errors, would oscillate; those are drawn
again (`calibration_redraws` in the truth). An actuator delay is drawn as a fraction of the
drawn loop's own delay margin.

The stand (PHYSICS.md): platform tilt phi = piezo stroke / support spacing + thermal tilt
(plate temperature through a first-order lag) + cooler sawtooth + constant offset; the
inverted pendulum's full linear equation including the platform's angular acceleration;
the sensor reads arm x deflection + drift + white noise, then the configured ADC. The
loop is this module's own PID (nominal gains, limits and slew of `[controller]`) at
`[loop] rate_hz`, the plant stepped between samples in sub-steps exact for the piezo's
slew ramps. With `modulated`, the first third is open loop with a square or triangle
modulation of the piezo (as in the paper), then the loop closes bumplessly.

The plate temperature is logged on `/leveler/environment` (with a thermometer's noise);
no truth topic is written: a measured log has none.
"""

from __future__ import annotations

import datetime as dt
import math
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from . import effects as fx
from .plant import (
    Mode,
    Pendulum,
    jittered_sawtooth,
    lag,
    random_walk,
    sawtooth,
)

# The documented defaults (docs/configuration.md) for keys a config may omit.
DEFAULTS: dict[str, dict[str, Any]] = {
    "loop": {"rate_hz": 10.0},
    "controller": {"kp_v_per_m": 0.0, "ki_v_per_m_s": 7.0e5, "kd_v_s_per_m": 0.0,
                   "setpoint_m": 0.0, "output_min_v": 0.0, "output_max_v": 150.0,
                   "slew_v_per_s": 10.0, "d_filter_tau_s": 0.5},
    "actuator": {"safe_v": 75.0},
    "plant.pendulum": {"mass_kg": 0.185, "com_length_m": 0.0496,
                       "flexure_stiffness_nm_per_rad": 0.1, "inertia_kgm2": 5.0e-4,
                       "damping_nms_per_rad": 1.2e-4, "sensor_arm_m": 0.05,
                       "gravity_m_per_s2": 9.80665},
    "plant.platform": {"support_spacing_m": 0.5, "initial_tilt_rad": 0.0},
    "plant.thermal": {"mean_k": 295.15, "random_walk_k_per_sqrt_s": 6.7e-4,
                      "daily_amplitude_k": 0.3, "daily_phase_rad": 0.0, "lag_s": 1800.0,
                      "tilt_per_kelvin_rad_per_k": 1.0e-5},
    "plant.cooler": {"period_s": 300.0, "peak_to_peak_rad": 2.8e-8, "fall_fraction": 0.1,
                     "phase_s": 0.0},
    "plant.piezo": {"min_v": 0.0, "max_v": 150.0, "gain_m_per_v": 1.0e-7,
                    "slew_v_per_s": 100.0, "ref_v": 75.0},
    "plant.sensor": {"gain_v_per_m": 2.0e5, "offset_v": 0.0, "noise_m_per_rthz": 5.0e-10,
                     "drift_m_per_sqrt_s": 9.0e-12, "adc_bits": 16, "adc_min_v": -10.0,
                     "adc_max_v": 10.0},
    "plant.uncertainty": {"piezo_gain_rel": 0.03, "support_spacing_rel": 0.01,
                          "sensor_arm_rel": 0.02, "sensor_gain_rel": 0.02,
                          "amplification_rel": 0.03, "natural_frequency_rel": 0.02,
                          "q_rel": 0.2, "thermal_tilt_rel": 0.2},
}

SUBSTEPS = 50  # plant sub-steps per loop sample (2 ms at 10 Hz: the piezo's slew ramps)
THERMOMETER_NOISE_K = 1e-3
FULL_SCALE_M = 1e-5  # the sensor nonlinearity's reference displacement (10 um)


def _section(cfg: dict[str, Any], dotted: str) -> dict[str, Any]:
    node: Any = cfg
    for part in dotted.split("."):
        node = node.get(part, {}) if isinstance(node, dict) else {}
    merged = dict(DEFAULTS[dotted])
    merged.update({k: v for k, v in node.items() if not isinstance(v, dict)})
    return merged


def nominal_parameters(text: str) -> dict[str, dict[str, Any]]:
    """The nominal config's tables this generator uses, defaults filled in."""
    cfg = tomllib.loads(text)
    return {name: _section(cfg, name) for name in DEFAULTS}


def _noise_factor(rng: np.random.Generator) -> float:
    lo, hi = (0.75, 0.9) if rng.random() < 0.5 else (1.1, 1.25)
    return float(rng.uniform(lo, hi))


def _offset(rng: np.random.Generator, sigma: float, lo: float, hi: float) -> float:
    """A relative offset of |z| in [lo, hi] sigma, random sign."""
    z = rng.uniform(lo, hi) * (1.0 if rng.random() < 0.5 else -1.0)
    return float(z * sigma)


def _rngs(seed: int, family: str | None, severity: str) -> list[np.random.Generator]:
    """Independent streams: six shared by every log of this seed (calibration, noise
    scalings, initial state, modulation, temperature, sensor noise: an effect log and the
    null of the same seed differ only by the effect) and two for the effect itself."""
    base = np.random.SeedSequence([int(seed)]).spawn(6)
    fam = 0 if family is None else 1 + fx.FAMILIES.index(family)
    sev = fx.SEVERITIES.index(severity) if family is not None else 0
    own = np.random.SeedSequence([int(seed), 1000 + fam, sev]).spawn(2)
    return [np.random.Generator(np.random.PCG64(s)) for s in (*base, *own)]


@dataclass
class TruePlant:
    """The plant that makes the data: the nominal one plus the drawn calibration offsets."""

    pend: Pendulum
    arm: float  # sensor arm [m]
    tilt_per_v: float  # piezo stroke per volt / support spacing [rad/V]
    gain_v_per_m: float  # sensor gain [V/m]
    thermal_coef: float  # [rad/K]

    @property
    def amplification(self) -> float:
        return self.pend.amplification


def _draw_calibration(p: dict[str, dict[str, Any]], rng: np.random.Generator,
                      platform_inertia: bool) -> tuple[dict[str, float], TruePlant]:
    unc = p["plant.uncertainty"]
    cal = {
        "piezo_gain_rel": _offset(rng, unc["piezo_gain_rel"], 1, 2),
        "support_spacing_rel": _offset(rng, unc["support_spacing_rel"], 1, 2),
        "sensor_arm_rel": _offset(rng, unc["sensor_arm_rel"], 1, 2),
        "sensor_gain_rel": _offset(rng, unc["sensor_gain_rel"], 1, 2),
        "amplification_rel": _offset(rng, unc["amplification_rel"], 1, 2),
        "natural_frequency_rel": _offset(rng, unc["natural_frequency_rel"], 1, 2),
        "q_rel": _offset(rng, unc["q_rel"], 0, 1),
        "thermal_tilt_rel": _offset(rng, unc["thermal_tilt_rel"], 0, 1),
    }
    pp = p["plant.pendulum"]
    nominal = Pendulum(pp["inertia_kgm2"], pp["damping_nms_per_rad"],
                       pp["flexure_stiffness_nm_per_rad"],
                       pp["mass_kg"] * pp["gravity_m_per_s2"] * pp["com_length_m"])
    pend = Pendulum.from_targets(nominal.amplification * (1 + cal["amplification_rel"]),
                                 nominal.f0_hz * (1 + cal["natural_frequency_rel"]),
                                 nominal.q * (1 + cal["q_rel"]), pp["inertia_kgm2"],
                                 platform_inertia)
    pz = p["plant.piezo"]
    spacing = p["plant.platform"]["support_spacing_m"] * (1 + cal["support_spacing_rel"])
    plant = TruePlant(
        pend=pend,
        arm=pp["sensor_arm_m"] * (1 + cal["sensor_arm_rel"]),
        tilt_per_v=pz["gain_m_per_v"] * (1 + cal["piezo_gain_rel"]) / spacing,
        gain_v_per_m=p["plant.sensor"]["gain_v_per_m"] * (1 + cal["sensor_gain_rel"]),
        thermal_coef=(p["plant.thermal"]["tilt_per_kelvin_rad_per_k"]
                      * (1 + cal["thermal_tilt_rel"])),
    )
    return cal, plant


def _decay(p, plant: TruePlant, family: str | None, eff: dict[str, Any], mode: Mode | None,
           gain_scale: float, dt_s: float) -> float:
    """Closed-loop test without noise, disturbance or ADC: the rms of the sensor reading in
    the last 40 s of 240 over that in 2-12 s after a small kick (< 0.5: the loop is stable)."""
    n = round(240.0 / dt_s)
    z = np.zeros(n + 1)
    kicked = replace(plant, gain_v_per_m=plant.gain_v_per_m * gain_scale)
    lin_family = family if family in ("actuator_delay", "actuator_hysteresis",
                                      "extra_resonance", "sensor_gain_error") else None
    rec = _run_loop(
        n=n, dt_s=dt_s, plant=kicked, p=p, dist_tilt=z, white=z, drift=z, analog=z,
        mode=mode if lin_family else None, mode_noise=z, mod=None, n_open=0,
        v_start=p["plant.piezo"]["ref_v"], family=lin_family, eff=eff,
        init={"pendulum_extra_rad": 2e-8, "pendulum_rate_rad_per_s": 0.0}, ideal_adc=True)
    y = rec["sensor_m"]
    i2, i12, i40 = int(2 / dt_s), int(12 / dt_s), int(40 / dt_s)
    early = float(np.sqrt(np.mean(y[i2:i12] ** 2)))
    late = float(np.sqrt(np.mean(y[-i40:] ** 2)))
    if not math.isfinite(late):
        return math.inf
    return late / early if early > 0 else 0.0


STABILITY_MARGIN_DB = 0.3  # the true loop must stay stable with its gain this much higher


def _stable(p, plant, family, eff, mode, dt_s) -> bool:
    g = 10 ** (STABILITY_MARGIN_DB / 20)
    return all(_decay(p, plant, family, eff, mode, k, dt_s) < 0.5 for k in (1.0, g))


def _delay_margin(p, plant: TruePlant, dt_s: float) -> float:
    """The largest transport delay of the piezo command the true loop survives [s]."""
    lo, hi = 0.0, 0.4
    if _decay(p, plant, "actuator_delay", {"delay_s": hi}, None, 1.0, dt_s) < 0.5:
        return hi
    while hi - lo > 0.5 * dt_s / SUBSTEPS:
        mid = 0.5 * (lo + hi)
        if _decay(p, plant, "actuator_delay", {"delay_s": mid}, None, 1.0, dt_s) < 0.5:
            lo = mid
        else:
            hi = mid
    return lo


def generate(family: str | None, severity: str, seed: int, out: Path, *, hours: float = 6.0,
             modulated: bool = True,
             nominal_config: Path = Path("config/sim.toml"),
             platform_inertia: bool = True) -> dict[str, Any]:
    """Write one measured MCAP log to `out`; return the truth (JSON-able dict).

    `family` None (or "none") writes a null log. `platform_inertia=False` drops the
    J phi'' term of the pendulum's equation (a comparison only: the physics keeps it).
    """
    if family == "none":
        family = None
    if family is not None and family not in fx.FAMILIES:
        raise ValueError(f"unknown family {family!r}; one of {', '.join(fx.FAMILIES)}")
    if severity not in fx.SEVERITIES:
        raise ValueError(f"unknown severity {severity!r}")
    text = Path(nominal_config).read_text()
    p = nominal_parameters(text)
    r_cal, r_noise, r_init, r_mod, r_thermal, r_sensor, r_eff, r_effnoise = _rngs(
        seed, family, severity)

    rate = float(p["loop"]["rate_hz"])
    dt_s = 1.0 / rate
    n = round(hours * 3600.0 * rate)
    t = np.arange(n + 1) * dt_s  # one extra point: the plant runs to the end of the last sample

    # ---- modulation (open loop) then closed loop
    mod: dict[str, Any] | None = None
    n_open = 0
    if modulated:
        period = float(r_mod.uniform(60.0, 300.0))
        cycles = max(1, round(hours * 3600.0 / 3.0 / period))
        mod = {"shape": "square" if r_mod.random() < 0.5 else "triangle",
               "amplitude_v": float(r_mod.uniform(3.0, 6.0)), "period_s": period,
               "cycles": cycles, "center_v": float(p["actuator"]["safe_v"]),
               "start_t_s": 0.0, "end_t_s": cycles * period}
        n_open = min(n, math.ceil(mod["end_t_s"] / dt_s))

    # ---- calibration offsets and the effect, redrawn together until the nominal
    # controller keeps the true loop stable with a margin (the truth says how many tries)
    co = p["plant.cooler"]
    redraws = 0
    for redraws in range(200):  # noqa: B007 (reported in the truth)
        cal, plant = _draw_calibration(p, r_cal, platform_inertia)
        eff: dict[str, Any] = {}
        if family is not None:
            avoid = [co["period_s"]] + ([mod["period_s"]] if mod else [])
            eff = fx.draw(family, severity, r_eff, avoid_periods_s=avoid)
        mode = None
        if family == "extra_resonance":
            mode = Mode(eff["frequency_hz"], eff["q"], eff["gain"])
        if family == "actuator_delay":
            if not _stable(p, plant, None, {}, None, dt_s):
                continue
            eff["delay_margin_s"] = _delay_margin(p, plant, dt_s)
            eff["delay_s"] = eff["margin_fraction"] * eff["delay_margin_s"]
        if _stable(p, plant, family, eff, mode, dt_s):
            break
    else:
        raise RuntimeError(f"no stable draw for {family} {severity} seed {seed} in 200 tries")
    amp, arm = plant.amplification, plant.arm

    # ---- noise scalings
    scales = {k: _noise_factor(r_noise) for k in
              ("sensor_noise", "sensor_drift", "thermal_random_walk", "thermal_daily",
               "cooler")}

    # ---- start out of equilibrium
    th = p["plant.thermal"]

    def signed(lo: float, hi: float) -> float:
        return float(r_init.uniform(lo, hi) * (1.0 if r_init.random() < 0.5 else -1.0))

    init = {
        "table_tilt_rad": float(p["plant.platform"]["initial_tilt_rad"]
                                + r_init.uniform(-1.5e-6, 1.5e-6)),
        "pendulum_extra_rad": signed(0.3e-6, 2e-6),
        "pendulum_rate_rad_per_s": float(r_init.uniform(-2e-6, 2e-6)),
        "thermal_lag_offset_k": signed(0.02, 0.1),
        "integrator_offset_v": signed(1.0, 4.0),
        "daily_phase_rad": float(r_init.uniform(0, 2 * math.pi)),
        "mean_temperature_k": float(th["mean_k"] + r_init.uniform(-0.5, 0.5)),
    }
    # the piezo holds the modulation's centre, or (closed loop from the start) a voltage the
    # integrator starts from, away from the steady state
    if mod:
        v_start = mod["center_v"]
    else:
        v_start = float(p["actuator"]["safe_v"]) + init["integrator_offset_v"]

    # ---- disturbances at the sample instants (tilt linear between them)
    temp = (init["mean_temperature_k"]
            + random_walk(n + 1, th["random_walk_k_per_sqrt_s"] * scales["thermal_random_walk"]
                          * math.sqrt(dt_s), r_thermal)
            + th["daily_amplitude_k"] * scales["thermal_daily"]
            * np.sin(2 * math.pi * t / 86400.0 + init["daily_phase_rad"]))
    temp_logged = temp + THERMOMETER_NOISE_K * r_thermal.standard_normal(n + 1)
    lagged = lag(temp, dt_s, th["lag_s"], temp[0] + init["thermal_lag_offset_k"])
    thermal_tilt = plant.thermal_coef * (lagged - th["mean_k"])
    cooler_tilt = (co["peak_to_peak_rad"] * scales["cooler"]
                   * sawtooth(t - co["phase_s"], co["period_s"], co["fall_fraction"]))
    effect_tilt = np.zeros(n + 1)
    if family == "periodic_disturbance":
        wave, _starts = jittered_sawtooth(t, eff["period_s"], eff["rise_fraction"],
                                          eff["period_jitter_rel"], r_effnoise,
                                          eff["first_start_s"])
        wave = lag(wave, dt_s, eff["corner_tau_s"], wave[0])  # rounded corners
        effect_tilt = eff["peak_to_peak_rad"] * wave
    elif family == "temperature_coupling":
        first = lag(temp, dt_s, eff["lag1_s"], temp[0])
        second = lag(first, dt_s, eff["lag2_s"], temp[0])
        effect_tilt = eff["tilt_per_kelvin_rad_per_k"] * (second - init["mean_temperature_k"])
    dist_tilt = init["table_tilt_rad"] + thermal_tilt + cooler_tilt + effect_tilt

    # ---- sensor noises per sample (metres at the pendulum end)
    sen = p["plant.sensor"]
    white = (sen["noise_m_per_rthz"] * scales["sensor_noise"] * math.sqrt(rate / 2.0)
             * r_sensor.standard_normal(n + 1))
    drift = random_walk(n + 1, sen["drift_m_per_sqrt_s"] * scales["sensor_drift"]
                        * math.sqrt(dt_s), r_sensor)
    if family == "sensor_drift":
        span = t[-1]
        drift = (drift + eff["rate_m_per_s"] * t * (1 + eff["curvature"] * t / span)
                 + random_walk(n + 1, sen["drift_m_per_sqrt_s"] * eff["extra_walk_factor"]
                               * math.sqrt(dt_s), r_effnoise))
    analog = np.zeros(n + 1)
    if family == "adc_quantization":
        lsb_v = (sen["adc_max_v"] - sen["adc_min_v"]) / 2 ** int(sen["adc_bits"])
        analog = (eff["analog_noise_counts"] * lsb_v / sen["gain_v_per_m"]
                  * r_effnoise.standard_normal(n + 1))
    mode_noise = np.zeros(n + 1)
    if mode is not None:
        # the noise-driven bump, given as metres at the sensor -> mode units (rad of tilt)
        mode_noise = mode.noise(n + 1, dt_s, eff["noise_rms_m"] / (arm * amp), r_effnoise)

    rec = _run_loop(n=n, dt_s=dt_s, plant=plant, p=p, dist_tilt=dist_tilt, white=white,
                    drift=drift, analog=analog, mode=mode, mode_noise=mode_noise, mod=mod,
                    n_open=n_open, v_start=v_start, family=family, eff=eff, init=init)

    _write(out, text, nominal_config, t[:n], rec, temp_logged[:n], mod, n_open, hours)

    closed = slice(n_open, n)
    return {
        "family": family or "none",
        "severity": severity if family else None,
        "seed": int(seed),
        "hours": hours,
        "modulated": modulated,
        "platform_inertia": platform_inertia,
        "params": eff,
        "calibration_rel": cal,
        "calibration_redraws": redraws,
        "noise_scale": scales,
        "initial": init,
        "modulation": mod,
        "true_plant": {"amplification": amp, "f0_hz": plant.pend.f0_hz, "q": plant.pend.q,
                       "sensor_arm_m": arm, "tilt_per_v_rad": plant.tilt_per_v,
                       "sensor_gain_v_per_m": plant.gain_v_per_m,
                       "thermal_coef_rad_per_k": plant.thermal_coef},
        "nominal_cooler_period_s": co["period_s"],
        "samples": n,
        "closed_loop_from_s": n_open * dt_s,
        "railed_samples": int(np.sum(rec["status"] == 3)),
        "saturated_samples": int(np.sum(rec["saturated"])),
        "closed_loop_sensor_rms_m": float(np.std(rec["sensor_m"][closed])),
        "closed_loop_d_term_rms_v": float(np.std(rec["d_v"][closed])),
        "log": str(out),
    }


def _run_loop(*, n: int, dt_s: float, plant: TruePlant, p: dict[str, dict[str, Any]],
              dist_tilt: np.ndarray, white: np.ndarray, drift: np.ndarray,
              analog: np.ndarray, mode: Mode | None, mode_noise: np.ndarray,
              mod: dict[str, Any] | None, n_open: int, v_start: float, family: str | None,
              eff: dict[str, Any], init: dict[str, float],
              ideal_adc: bool = False) -> dict[str, np.ndarray]:
    """The sample-by-sample loop: read the sensor, control, step the plant to the next sample."""
    pend = plant.pend
    amp, arm, tilt_per_v, gain_true = (plant.amplification, plant.arm, plant.tilt_per_v,
                                       plant.gain_v_per_m)
    ctl, pz, sen = p["controller"], p["plant.piezo"], p["plant.sensor"]
    ref_v = pz["ref_v"]
    h = dt_s / SUBSTEPS
    steps = [pend.step(h * m) for m in range(SUBSTEPS + 1)]  # steps[m]: m sub-steps at once
    mode_steps = [mode.step(h * m) for m in range(SUBSTEPS + 1)] if mode else None

    # controller constants
    kp, ki, kd = ctl["kp_v_per_m"], ctl["ki_v_per_m_s"], ctl["kd_v_s_per_m"]
    tau_d = ctl["d_filter_tau_s"]
    sp = ctl["setpoint_m"]
    u_min, u_max = ctl["output_min_v"], ctl["output_max_v"]
    u_slew = ctl["slew_v_per_s"] * dt_s
    pz_min, pz_max, pz_slew = pz["min_v"], pz["max_v"], pz["slew_v_per_s"] * h

    # sensor/ADC constants
    vmin = sen["adc_min_v"]
    lsb_v = (sen["adc_max_v"] - vmin) / 2 ** int(sen["adc_bits"])
    top = 2 ** int(sen["adc_bits"]) - 1
    gain_nom, off_v = sen["gain_v_per_m"], sen["offset_v"]
    scale_err = quad = 0.0
    q_step = q_off = 0.0
    if family == "sensor_gain_error":
        scale_err, quad = eff["gain_error"], eff["quadratic_per_10um"] / FULL_SCALE_M
    if family == "adc_quantization":
        q_step, q_off = eff["step_m"], eff["offset_m"]
    mode_to_m = arm * amp

    # actuator effects
    delay_whole = delay_sub = 0
    if family == "actuator_delay":
        delay_whole, delay_sub = divmod(round(eff["delay_s"] / h), SUBSTEPS)
    hyst = family == "actuator_hysteresis"
    bw_a = bw_beta = bw_gamma = 0.0
    if hyst:
        total = 1.0 / eff["saturation_v"]  # beta + gamma: h saturates at A / (beta + gamma)
        bw_gamma = total / (1.0 + eff["beta_over_gamma"])
        bw_beta = total - bw_gamma
        bw_a = eff["a"]

    # outputs
    out_counts = np.zeros(n, dtype=np.int64)
    out_sensor = np.zeros(n)
    out_status = np.zeros(n, dtype=np.int64)
    out_p = np.zeros(n)
    out_i = np.zeros(n)
    out_d = np.zeros(n)
    out_cmd = np.zeros(n)
    out_sat = np.zeros(n, dtype=bool)
    commands = np.zeros(n)

    # state
    v_pz = v_start  # piezo voltage
    hb = 0.0  # Bouc-Wen internal variable [V]
    phi_p = tilt_per_v * (v_pz - ref_v)
    phi = float(dist_tilt[0]) + phi_p
    psi = pend.equilibrium(phi) + init["pendulum_extra_rad"]
    inertial = pend.platform_inertia
    psid = init["pendulum_rate_rad_per_s"]
    m_det = m_detd = 0.0
    integ = v_start
    d_term = 0.0
    y_prev = None
    u_prev = v_start
    dist = dist_tilt.tolist()
    white_l, drift_l, analog_l, mnoise = (white.tolist(), drift.tolist(), analog.tolist(),
                                          mode_noise.tolist())
    mod_shape = mod["shape"] if mod else ""
    mod_amp = mod["amplitude_v"] if mod else 0.0
    mod_period = mod["period_s"] if mod else 1.0
    mod_center = mod["center_v"] if mod else 0.0

    for k in range(n):
        # ---- sensor at t_k
        x = arm * (psi - phi if inertial else psi) + mode_to_m * (m_det + mnoise[k])
        if scale_err or quad:
            x = x * (1.0 + scale_err) + quad * x * x
        xs = x + drift_l[k] + white_l[k]
        if q_step:
            xs = q_off + q_step * round((xs - q_off) / q_step) + analog_l[k]
        volts = gain_true * xs + off_v
        status = 0
        if ideal_adc:
            c, y = 0, (volts - off_v) / gain_nom
        else:
            c = round((volts - vmin) / lsb_v)
            if c < 0:
                c, status = 0, 3
            elif c > top:
                c, status = top, 3
            y = (vmin + c * lsb_v - off_v) / gain_nom
        out_counts[k], out_sensor[k], out_status[k] = c, y, status

        # ---- control
        if k < n_open:
            ph = (k * dt_s / mod_period) % 1.0
            if mod_shape == "square":
                w = 1.0 if ph < 0.5 else -1.0
            else:
                w = 4.0 * ph - 1.0 if ph < 0.5 else 3.0 - 4.0 * ph
            u = min(max(mod_center + mod_amp * w, u_min), u_max)
            pt = it = dterm_out = 0.0
            sat = False
            y_prev = y
        else:
            e = sp - y
            pt = kp * e
            if y_prev is not None:
                d_term = (tau_d * d_term - kd * (y - y_prev)) / (tau_d + dt_s)
            y_prev = y
            if k == n_open and n_open > 0:
                integ = u_prev - pt - d_term  # bumpless engage from the held voltage
            cand = integ + ki * e * dt_s
            raw = pt + cand + d_term
            u = min(max(raw, u_min), u_max)
            u = min(max(u, u_prev - u_slew), u_prev + u_slew)
            sat = u != raw
            # conditional integration: no wind-up against a limit or the slew
            if not (sat and (raw - u) * e > 0):
                integ = cand
            it, dterm_out = integ, d_term
        u_prev = u
        commands[k] = u
        out_p[k], out_i[k], out_d[k], out_cmd[k], out_sat[k] = pt, it, dterm_out, u, sat

        # ---- plant from t_k to t_k+1
        d0, d1 = dist[k], dist[k + 1]
        if delay_whole or delay_sub:
            i_before = k - delay_whole - 1
            i_after = k - delay_whole
            tgt_before = commands[i_before] if i_before >= 0 else v_start
            tgt_after = commands[i_after] if i_after >= 0 else v_start
            switch = delay_sub
        else:
            tgt_before = tgt_after = u
            switch = 0
        j = 0
        while j < SUBSTEPS:
            target = tgt_before if j < switch else tgt_after
            if j >= switch and v_pz == target:
                m = SUBSTEPS - j  # nothing changes in the actuator for the rest: one step
            else:
                m = 1
                dv = min(max(target - v_pz, -pz_slew), pz_slew)
                v_new = min(max(v_pz + dv, pz_min), pz_max)
                if abs(target - v_new) < 1e-12:
                    v_new = target
                if hyst and v_new != v_pz:
                    dvt = v_new - v_pz
                    nch = int(abs(dvt) / 0.02) + 1
                    dvc = dvt / nch
                    adv = abs(dvc)
                    for _ in range(nch):
                        hb += bw_a * dvc - bw_beta * adv * hb - bw_gamma * dvc * abs(hb)
                v_pz = v_new
                phi_p = tilt_per_v * ((v_pz - ref_v) - hb)
            j += m
            phi_new = d0 + (d1 - d0) * j / SUBSTEPS + phi_p
            r = (phi_new - phi) / (m * h)
            s = steps[m]
            psi, psid = (s[0, 0] * psi + s[0, 1] * psid + s[0, 2] * phi + s[0, 3] * r,
                         s[1, 0] * psi + s[1, 1] * psid + s[1, 2] * phi + s[1, 3] * r)
            if mode_steps is not None:
                ms = mode_steps[m]
                m_det, m_detd = (ms[0, 0] * m_det + ms[0, 1] * m_detd + ms[0, 2] * r,
                                 ms[1, 0] * m_det + ms[1, 1] * m_detd + ms[1, 2] * r)
            phi = phi_new
    return {"raw_counts": out_counts, "sensor_m": out_sensor, "status": out_status,
            "p_v": out_p, "i_v": out_i, "d_v": out_d, "command_v": out_cmd,
            "applied_v": out_cmd, "saturated": out_sat, "setpoint_m": np.full(n, sp)}


def _write(out: Path, text: str, config_path: Path, t: np.ndarray, rec: dict[str, np.ndarray],
           temp_logged: np.ndarray, mod: dict[str, Any] | None, n_open: int,
           hours: float) -> None:
    import leveler
    from leveler.log.writer import LogWriter
    from leveler.records import Environment, Event, Sample

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    start = dt.datetime(2024, 5, 1, 20, 0, 0, tzinfo=dt.UTC)
    t0_ns = int(start.timestamp()) * 10**9
    meta = {"config": text, "config_path": str(config_path),
            "version": str(getattr(leveler, "__version__", "")),
            "start_time": start.isoformat(), "duration_s": repr(hours * 3600.0),
            "source": "bench/independent/generator.py"}
    n = len(t)
    ts = t.tolist()
    ns = [t0_ns + round(x * 1e9) for x in ts]
    cols = {k: v.tolist() for k, v in rec.items()}
    states = ["modulating" if k < n_open else "engaged" for k in range(n)]
    end_t = ts[-1]
    with LogWriter(out, metadata=meta, environment=True) as log:
        log.event(Event(0.0, "start", "independent generator", {}), ns[0])
        if mod:
            log.event(Event(0.0, "state", "modulation", {"old": "idle", "new": "modulating"}),
                      ns[0])
            detail = {k: mod[k] for k in ("center_v", "amplitude_v", "period_s", "cycles",
                                          "start_t_s", "end_t_s")}
            detail["shape"] = mod["shape"]
            log.event(Event(0.0, "procedure", "modulation started", detail), ns[0])
        else:
            log.event(Event(0.0, "state", "engage_on_start",
                            {"old": "idle", "new": "engaged"}), ns[0])
        for k in range(n):
            if k == n_open and mod and n_open < n:
                log.event(Event(ts[k], "procedure", "modulation done", {}), ns[k])
                log.event(Event(ts[k], "state", "modulation done",
                                {"old": "modulating", "new": "engaged"}), ns[k])
            log.sample(Sample(k, ts[k], int(cols["raw_counts"][k]), cols["sensor_m"][k],
                              int(cols["status"][k]), cols["setpoint_m"][k],
                              cols["setpoint_m"][k] - cols["sensor_m"][k], cols["p_v"][k],
                              cols["i_v"][k], cols["d_v"][k], cols["command_v"][k],
                              cols["applied_v"][k], bool(cols["saturated"][k]), states[k]),
                       ns[k])
            log.environment(Environment(k, ts[k], float(temp_logged[k])), ns[k])
            if k % 20000 == 0:
                log.wait_drained(50000)
        log.event(Event(end_t, "stop", "end of recording",
                        {"overruns": 0, "sensor_errors": 0, "actuator_errors": 0}), ns[-1])
