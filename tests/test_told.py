"""The red noise a model states (issue 17, part 3): the lowest bins of a residual hold no
more of it than the model's noise terms allow, so a trend is not whitened away."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from leveler.analysis.told import CEILING_SIGMA, random_walk_periodogram, red_ceiling
from leveler.analysis.whittle import Whitener, deviance
from leveler.sim.params import PlantParams, ThermalParams, UncertaintyParams

DT_S = 0.1
N = 2**16  # 1.8 h at 10 Hz
Q = 9e-12  # the sensor zero's random walk [m/sqrt(s)], config/sim.toml
WHITE = 5e-10  # [m/sqrt(Hz)]


def _noise(rng: np.random.Generator, q: float = Q) -> np.ndarray:
    walk = np.cumsum(q * np.sqrt(DT_S) * rng.standard_normal(N))
    return walk + WHITE * np.sqrt(0.5 / DT_S) * rng.standard_normal(N)


def _whitener(ceiling: bool) -> Whitener:
    params = PlantParams(uncertainty=UncertaintyParams(noise_rel=0.25))
    return Whitener(slice(0, N), N, DT_S, lambda f: np.ones_like(f),
                    red_ceiling(params, True) if ceiling else None)


def test_a_random_walk_has_the_stated_periodogram() -> None:
    """The exact expected periodogram in the lowest bins agrees with simulated walks, and
    further up with q^2 / (2 pi^2 f^2): the factor and the one-sided convention."""
    n, rng = 2**14, np.random.default_rng(5)
    w = Whitener(slice(0, n), n, DT_S, lambda f: np.ones_like(f))
    bins = np.arange(1, 6)
    sims = np.mean([w.periodogram(np.cumsum(Q * np.sqrt(DT_S) * rng.standard_normal(n)))[bins]
                    for _ in range(400)], axis=0)
    exact = random_walk_periodogram(Q, n, DT_S, bins)
    np.testing.assert_allclose(sims, exact, rtol=0.15)  # 400 draws: 5 % 1-sigma
    assert exact[1] > 1.3 * Q**2 / (2 * np.pi**2 * w.f_hz[2] ** 2)  # the main lobe's average
    far = random_walk_periodogram(Q, n, DT_S, np.array([200]))[0]
    assert far == pytest.approx(Q**2 / (2 * np.pi**2 * w.f_hz[200] ** 2), rel=0.02)


def test_a_trend_is_not_whitened_away() -> None:
    """A 200 nm trend with some curvature over 1.8 h, on noise at the stated levels: its
    leakage into the fitted bins steepens a free fit's red terms, whose extrapolation
    then swallows the trend (measured: 104 of 2 ln L); held to the stated walk, the
    lowest bins keep it (19,000)."""
    rng = np.random.default_rng(7)
    t = np.arange(N) * DT_S
    trend = 200e-9 * (t / t[-1] + 0.2 * (t / t[-1]) ** 2)
    x = _noise(rng) + trend
    gains = {}
    for ceiling in (False, True):
        w = _whitener(ceiling)
        w.fit_noise(x)
        gains[ceiling] = deviance(w.cost(x), w.cost(x - trend))
    assert gains[True] > 10 * gains[False], gains


def test_noise_above_the_stated_level_makes_no_trend() -> None:
    """No trend, the noise 25 % above the stated levels (the independent generator's
    spread): the best trend a fit finds gains no more than chance would, within one
    parameter's BIC penalty, ln(2 n_bins) = 11."""
    t = np.arange(N) * DT_S
    for seed in range(8):
        x = _noise(np.random.default_rng(100 + seed), 1.25 * Q)
        w = _whitener(True)
        w.fit_noise(x)
        c = w.whiten(t - t.mean())
        e = w.whiten(x)
        best = e - (c @ e) / (c @ c) * c
        assert deviance(float(e @ e), float(best @ best)) < np.log(2 * len(w.f_hz)), seed


def test_the_ceiling_is_the_stated_walk_three_sigma_up() -> None:
    params = PlantParams(uncertainty=UncertaintyParams(noise_rel=0.2))
    bins = np.arange(4)
    np.testing.assert_allclose(
        red_ceiling(params, True)(N, DT_S, bins),  # type: ignore[misc]
        (1 + CEILING_SIGMA * 0.2) ** 2
        * random_walk_periodogram(params.sensor.drift_m_per_sqrt_s, N, DT_S, bins))


def test_no_ceiling_where_the_model_does_not_vouch_for_its_noise() -> None:
    """A model that states no noise tolerance, or whose red noise includes a thermal tilt
    it cannot predict (no temperature logged: a daily cycle, no stationary noise), keeps
    the free fit."""
    assert red_ceiling(PlantParams(), True) is None
    vouched = PlantParams(uncertainty=UncertaintyParams(noise_rel=0.25))
    assert red_ceiling(vouched, False) is None
    no_thermal = dataclasses.replace(vouched, thermal=ThermalParams(tilt_per_kelvin_rad_per_k=0.0))
    assert red_ceiling(no_thermal, False) is not None
