"""What of a replay's residual the model itself calls unpredictable, and the slow drift in it.

A tiltmeter's record is dominated by its slow drift: the sensor zero wanders, and without the
temperature logged so does the table. "Variance explained 0 %" then says nothing about the
drive lines the model tracks, and "27 %" on leveler's own log hides that the rest is drift the
model states it cannot predict. So the residual is compared, band by band, with the model's
own noise spectrum (white sensor noise, the zero's random walk, the unlogged temperature's
lagged walk), and the slow drift is estimated and set aside, by the user's choice:

- `model`: the random-walk terms the model states, through the steady-state Kalman smoother
  of a random walk in white noise (a two-sided exponential kernel), so the drift
  is what those levels make of the residual and no more;
- `poly:N`: a polynomial of order N over the analysed span;
- `none`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.signal import lfilter

from leveler.analysis.predict import sensor_noise_m
from leveler.analysis.told import random_walk_periodogram
from leveler.analysis.whittle import hann_psd
from leveler.sim.params import PlantParams

EXACT_BINS = 32  # lowest periodogram bins given the random walk's exact windowed level
#: A band's residual power over the model's noise that is still the model's own noise: the
#: stated levels' own tolerance (25 % in amplitude is 1.56 in power), or the band's scatter.
UNPREDICTABLE_RATIO = 1.6
SCATTER_SIGMA = 3.0


def walks(params: PlantParams, temperature_logged: bool) -> tuple[float, float]:
    """(sensor zero walk, unlogged thermal tilt's walk at the sensor) [m/sqrt(s)]."""
    th, pe = params.thermal, params.pendulum
    thermal = 0.0
    if not temperature_logged:
        thermal = abs(pe.sensor_arm_m * pe.amplification * th.tilt_per_kelvin_rad_per_k
                      * th.random_walk_k_per_sqrt_s)
    return params.sensor.drift_m_per_sqrt_s, thermal


def noise_periodogram(params: PlantParams, temperature_logged: bool, n: int,
                      dt_s: float) -> np.ndarray:
    """Expected Hann periodogram of the model's unpredictable terms on n samples [m^2/Hz,
    one-sided], at every bin: white sensor noise (ADC rounding included), the zero's random
    walk (exact in the lowest bins, where the window's main lobe averages its steep
    spectrum) and the unlogged temperature's walk through its lag."""
    f = np.fft.rfftfreq(n, dt_s)
    zero, thermal = walks(params, temperature_logged)
    white = 2 * sensor_noise_m(params, dt_s) ** 2 * dt_s
    fp = np.where(f > 0, f, np.inf)  # the mean's bin: set below
    walk = zero**2 / (2 * math.pi**2 * fp**2)
    walk += thermal**2 / (2 * math.pi**2 * fp**2) / (1 + (2 * math.pi * fp
                                                         * params.thermal.lag_s) ** 2)
    low = np.arange(1, min(EXACT_BINS, len(f)))
    walk[low] = random_walk_periodogram(math.hypot(zero, thermal), n, dt_s, low)
    walk[0] = walk[1] if len(f) > 1 else 0.0
    return white + walk


def smoothed_walk(r: np.ndarray, q_per_sqrt_s: float, white_m: float, dt_s: float) -> np.ndarray:
    """The steady-state Kalman smoother's estimate of a random walk (steps q^2 dt) under
    white noise (white_m^2 per sample) in `r`: the symmetric kernel alpha^|k|, alpha from
    alpha + 1/alpha = 2 + q^2 dt / white^2, run forward and back."""
    if q_per_sqrt_s <= 0:
        return np.full_like(r, float(np.mean(r)))
    lam = q_per_sqrt_s**2 * dt_s / max(white_m**2, np.finfo(float).tiny)
    p = 0.5 * (lam + math.sqrt(lam * lam + 4 * lam))
    alpha = 1 / (1 + p)
    b, a = [1 - alpha], [1.0, -alpha]
    forward = lfilter(b, a, r, zi=[alpha * r[0]])[0]  # each pass starts settled at its end
    return lfilter(b, a, forward[::-1], zi=[alpha * forward[-1]])[0][::-1]


def drift(r: np.ndarray, method: str, params: PlantParams, temperature_logged: bool,
          dt_s: float) -> np.ndarray:
    """The slow drift in the residual `r` by `method` (module docstring); raises ValueError
    naming the accepted forms."""
    if method == "none":
        return np.zeros_like(r)
    if method == "model":
        zero, thermal = walks(params, temperature_logged)
        return smoothed_walk(r, math.hypot(zero, thermal), sensor_noise_m(params, dt_s), dt_s)
    if method.startswith("poly:"):
        try:
            order = int(method[5:])
        except ValueError:
            order = -1
        if 0 <= order <= 20:
            x = np.linspace(-1, 1, len(r))
            return np.polynomial.legendre.legval(x, np.polynomial.legendre.legfit(x, r, order))
    raise ValueError(f"--drift {method!r}: use model, poly:N (N = 0..20) or none")


def bands(y: np.ndarray, r: np.ndarray, d: np.ndarray, dt_s: float,
          noise: np.ndarray, bands_hz: dict[str, tuple[float, float]]) -> dict[str, Any]:
    """Per band: the measured and residual power, the variance explained as is and with the
    drift `d` set aside from both, and the residual over the model's noise."""
    def power(x: np.ndarray) -> np.ndarray:
        return hann_psd(x - x.mean(), dt_s)

    f = np.fft.rfftfreq(len(r), dt_s)
    py, pr, pyd, prd, pd = power(y), power(r), power(y - d), power(r - d), power(d)
    out: dict[str, Any] = {}
    for name, (lo, hi) in bands_hz.items():
        sel = (f >= lo) & (f < hi)
        n = int(np.count_nonzero(sel))
        if n < 2:
            out[name] = None
            continue
        ratio = float(np.mean(pr[sel] / noise[sel]))
        out[name] = {
            "bins": n,
            "variance_explained": 1 - float(np.sum(pr[sel]) / np.sum(py[sel])),
            "variance_explained_less_drift": 1 - float(np.sum(prd[sel]) / np.sum(pyd[sel])),
            "drift_share": float(np.sum(pd[sel]) / np.sum(py[sel])),
            "residual_over_noise": ratio,
            "unpredictable": ratio < max(UNPREDICTABLE_RATIO, 1 + SCATTER_SIGMA / math.sqrt(n)),
        }
    return out


def verdict(per_band: dict[str, Any], terms: str) -> str:
    """One plain sentence: is the residual what the model calls unpredictable, and if not,
    where it is not. Against the model as written: no recalibration, the stated noise levels
    (bench/verdict_score.py: every independent log flagged, the 20 nulls with in-tolerance
    offsets too; recalibrated, nulls still stood 3-190x over the stated noise)."""
    judged = {k: v for k, v in per_band.items() if v is not None}
    over = {k: v["residual_over_noise"] for k, v in judged.items() if not v["unpredictable"]}
    if not judged:
        return "The log is too short for any band."
    if not over:
        return (f"The residual is what the model itself calls unpredictable ({terms}) in "
                "every band: it explains all that its noise leaves to explain.")
    worst = ", ".join(f"{k} ({v:.3g}x its noise power)" for k, v in
                      sorted(over.items(), key=lambda kv: -kv[1]))
    return (f"The residual exceeds what the model calls unpredictable ({terms}) in {worst}: "
            "the model as written, its calibrated numbers and stated noise included, does not "
            "account for it there. A calibration offset within its tolerance does this too "
            "(independent null logs: flagged 20 of 20); `leveler diagnose` recalibrates and "
            "tells a calibration from a missing effect.")


def terms(params: PlantParams, temperature_logged: bool) -> str:
    """The model's unpredictable terms, named for the sentence."""
    zero, thermal = walks(params, temperature_logged)
    out = ["sensor noise"]
    if zero > 0:
        out.append("its zero's drift")
    if thermal > 0:
        out.append("the unlogged temperature's tilt")
    return ", ".join(out)


__all__ = ["bands", "drift", "noise_periodogram", "smoothed_walk", "terms", "verdict", "walks"]
