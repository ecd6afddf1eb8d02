"""The missing effects, each in this generator's own form, and their draws per severity.

Sizes are chosen against the stand's noise (sensor white noise ~1.1 nm rms per 10 Hz sample,
one ADC count 1.53 nm, a pendulum-end response of N * arm = 0.45 m per rad of tilt): "weak"
sits near what a night of data can just show, "strong" is unmistakable. Every size is
further multiplied by a factor drawn in [0.8, 1.25] so no two logs share a value.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

FAMILIES = (
    "periodic_disturbance",
    "temperature_coupling",
    "actuator_delay",
    "actuator_hysteresis",
    "extra_resonance",
    "sensor_gain_error",
    "sensor_drift",
    "adc_quantization",
)
SEVERITIES = ("weak", "medium", "strong")

# Per family and severity: the headline sizes (units in the key names).
SIZES: dict[str, dict[str, dict[str, float]]] = {
    # asymmetric, period-jittered sawtooth of tilt (a second cooler or a pump cycling)
    "periodic_disturbance": {
        "weak": {"peak_to_peak_rad": 2.5e-9},  # ~1.1 nm p-p at the pendulum end
        "medium": {"peak_to_peak_rad": 1.0e-8},
        "strong": {"peak_to_peak_rad": 4.0e-8},
    },
    # two first-order lags in series from the plate temperature to tilt
    "temperature_coupling": {
        "weak": {"tilt_per_kelvin_rad_per_k": 2.5e-6},  # 25 % of the modelled path
        "medium": {"tilt_per_kelvin_rad_per_k": 6.0e-6},
        "strong": {"tilt_per_kelvin_rad_per_k": 1.5e-5},
    },
    # transport delay of the piezo command, as a fraction of the true closed loop's delay
    # margin (the generator measures it): beyond the margin the nominal loop oscillates
    "actuator_delay": {
        "weak": {"margin_fraction": 0.15},
        "medium": {"margin_fraction": 0.35},
        "strong": {"margin_fraction": 0.6},
    },
    # Bouc-Wen: h' = A V' - beta |V'| h - gamma V' |h|, stroke = gain (V - ref - h)
    "actuator_hysteresis": {
        "weak": {"a": 0.03, "saturation_v": 1.5},
        "medium": {"a": 0.08, "saturation_v": 2.5},
        "strong": {"a": 0.18, "saturation_v": 4.0},
    },
    # band-pass mode driven by the total tilt rate and by its own force noise
    "extra_resonance": {
        "weak": {"gain": 0.02, "noise_rms_m": 0.4e-9},
        "medium": {"gain": 0.06, "noise_rms_m": 1.0e-9},
        "strong": {"gain": 0.2, "noise_rms_m": 3.0e-9},
    },
    # reading = (1 + e) x + e2 x^2 / 10 um, on top of the calibration offsets
    "sensor_gain_error": {
        "weak": {"gain_error": 0.07},
        "medium": {"gain_error": 0.15},
        "strong": {"gain_error": 0.25},
    },
    # trend (with a little curvature) plus an extra random walk of the sensor zero
    "sensor_drift": {
        "weak": {"rate_m_per_s": 3e-12, "extra_walk_factor": 1.5},
        "medium": {"rate_m_per_s": 1e-11, "extra_walk_factor": 2.5},
        "strong": {"rate_m_per_s": 4e-11, "extra_walk_factor": 4.0},
    },
    # coarse converter (step), a little analog noise, then the configured fine ADC
    "adc_quantization": {
        "weak": {"step_m": 4e-9},
        "medium": {"step_m": 1e-8},
        "strong": {"step_m": 2.5e-8},
    },
}


def _scale(rng: np.random.Generator) -> float:
    return float(rng.uniform(0.8, 1.25))


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def _avoid(period: float, others: list[float], tol: float = 0.06) -> bool:
    """True if `period`'s first harmonics stay clear of those of every period in `others`."""
    for other in others:
        for a in (1, 2, 3):
            for b in (1, 2, 3):
                if abs(period / a - other / b) < tol * other / b:
                    return False
    return True


def draw(family: str, severity: str, rng: np.random.Generator, *,
         avoid_periods_s: list[float]) -> dict[str, Any]:
    """The effect's parameters (JSON-able), drawn at `severity`; a periodic disturbance keeps
    its harmonics clear of those of `avoid_periods_s` (the cooler, the modulation)."""
    if family not in SIZES:
        raise ValueError(f"unknown family {family!r}; one of {', '.join(FAMILIES)}")
    if severity not in SEVERITIES:
        raise ValueError(f"unknown severity {severity!r}; one of {', '.join(SEVERITIES)}")
    size = dict(SIZES[family][severity])
    s = _scale(rng)
    if family == "periodic_disturbance":
        while True:
            period = float(math.exp(rng.uniform(math.log(90.0), math.log(900.0))))
            if _avoid(period, avoid_periods_s):
                break
        return {"peak_to_peak_rad": _sign(rng) * size["peak_to_peak_rad"] * s,
                "period_s": period, "rise_fraction": float(rng.uniform(0.65, 0.9)),
                "period_jitter_rel": float(rng.uniform(0.01, 0.04)),
                "corner_tau_s": float(rng.uniform(2.0, 10.0)),
                "first_start_s": float(-rng.uniform(0.0, period))}
    if family == "temperature_coupling":
        return {"tilt_per_kelvin_rad_per_k":
                _sign(rng) * size["tilt_per_kelvin_rad_per_k"] * s,
                "lag1_s": float(rng.uniform(120.0, 600.0)),
                "lag2_s": float(rng.uniform(600.0, 2400.0))}
    if family == "actuator_delay":
        return {"margin_fraction": min(0.8, size["margin_fraction"] * s)}
    if family == "actuator_hysteresis":
        return {"a": size["a"] * s, "saturation_v": size["saturation_v"] * _scale(rng),
                "beta_over_gamma": float(rng.uniform(0.7, 1.4))}
    if family == "extra_resonance":
        return {"frequency_hz": float(rng.uniform(1.1, 3.8)), "q": float(rng.uniform(6.0, 30.0)),
                "gain": size["gain"] * s, "noise_rms_m": size["noise_rms_m"] * _scale(rng)}
    if family == "sensor_gain_error":
        e = _sign(rng) * size["gain_error"] * s
        return {"gain_error": e,
                "quadratic_per_10um": float(rng.uniform(-0.3, 0.3)) * abs(e)}
    if family == "sensor_drift":
        return {"rate_m_per_s": _sign(rng) * size["rate_m_per_s"] * s,
                "curvature": float(rng.uniform(-0.3, 0.3)),
                "extra_walk_factor": size["extra_walk_factor"] * _scale(rng)}
    # adc_quantization
    step = size["step_m"] * s
    return {"step_m": step, "offset_m": float(rng.uniform(0.0, step)),
            "analog_noise_counts": float(rng.uniform(0.1, 0.3))}
