"""The red noise a replay residual may hold by the model's own word.

A replay predicts the reading from the logged piezo voltage and temperature, so what it
leaves at the lowest frequencies is noise the model states: the sensor zero's random walk
(and, were the temperature not logged, the thermal tilt it would have predicted: no
stationary noise, with its daily cycle, so no level is put on it). A residual far redder
than the stated walk is a finding (a drift, a coupling), not noise, but a noise spectrum
fitted freely takes it for noise. The stated levels are trusted as far as the model file
says (`[plant.uncertainty] noise_rel`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from leveler.analysis.whittle import hann
from leveler.sim.params import PlantParams

#: The ceiling sits this many of the stated 1-sigma above the stated amplitude.
CEILING_SIGMA = 3.0

#: (block length, sample interval [s], bins) -> the most red noise there [m^2/Hz]
Ceiling = Callable[[int, float, np.ndarray], np.ndarray]


def random_walk_periodogram(q_per_sqrt_s: float, n: int, dt_s: float,
                            bins: np.ndarray) -> np.ndarray:
    """See `_walk_periodogram`; the same blocks are whitened again in every round of a
    search (0.24 s for a day's block), so the result is kept."""
    return _walk_periodogram(q_per_sqrt_s, n, dt_s, tuple(int(k) for k in bins))


@functools.lru_cache(maxsize=64)
def _walk_periodogram(q_per_sqrt_s: float, n: int, dt_s: float,
                      bins: tuple[int, ...]) -> np.ndarray:
    """Expected Hann periodogram [m^2/Hz, one-sided] of a random walk whose steps have
    variance q^2 dt, on a block of n samples with its mean removed (as `Whitener` takes
    it), at the given bins. Exact, not q^2 / (2 pi^2 f^2) at the bin's centre: in the
    lowest bins the window's main lobe averages that steep spectrum, 1.5x higher at the
    second bin. The block's transform is linear in the steps, X_k = sum_n a_kn e_n, so
    E|X_k|^2 = q^2 dt sum_n |a_kn|^2, with a_k the reversed cumulative sum of the
    windowed exponential less its mean."""
    w = hann(n)
    norm = float(np.sum(w**2)) / (2 * dt_s)
    m = np.arange(n)
    out = np.empty(len(bins))
    for i, k in enumerate(bins):
        h = w * np.exp(-2j * np.pi * k * m / n)
        a = np.cumsum((h - h.mean())[::-1])
        out[i] = q_per_sqrt_s**2 * dt_s * float(np.sum(np.abs(a) ** 2)) / norm
    out.flags.writeable = False  # shared by every caller
    return out


def red_ceiling(params: PlantParams, temperature_logged: bool) -> Ceiling | None:
    """The most red noise the stated terms allow in a block's lowest bins, or None when
    the model does not vouch for its noise levels (`noise_rel` = 0) or states a red term
    it cannot put a level on (an unlogged temperature's tilt)."""
    rel = params.uncertainty.noise_rel
    if rel <= 0 or (not temperature_logged and params.thermal.tilt_per_kelvin_rad_per_k != 0):
        return None
    factor = (1 + CEILING_SIGMA * rel) ** 2
    q = params.sensor.drift_m_per_sqrt_s

    def ceiling(n: int, dt_s: float, bins: np.ndarray) -> np.ndarray:
        return factor * random_walk_periodogram(q, n, dt_s, bins)

    return ceiling
