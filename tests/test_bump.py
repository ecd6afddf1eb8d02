"""A mode rung by its own noise, found as a bump in the residual's spectrum
(leveler.analysis.bump): its frequency, Q and rms recovered from band-pass noise on top
of white noise, and no bump where there is none."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lfilter

from leveler.analysis.bump import Spectra, band_pass_power, mode_psd
from leveler.analysis.whittle import Blocks, Whitener

DT_S = 0.1


def _blocks(x: np.ndarray) -> Blocks:
    w = Whitener(slice(0, len(x)), len(x), DT_S, lambda f: np.ones_like(f))
    w.fit_noise(x)
    return Blocks([w])


def _mode_noise(rng: np.random.Generator, n: int, f0_hz: float, q: float,
                rms_m: float) -> np.ndarray:
    """White noise through a resonator (a damped oscillator sampled at DT_S), scaled to
    `rms_m`: written apart from the module's continuous band-pass on purpose."""
    r = math.exp(-math.pi * f0_hz * DT_S / q)
    theta = 2 * math.pi * f0_hz * DT_S
    y = lfilter([1.0, -1.0], [1.0, -2 * r * math.cos(theta), r * r], rng.standard_normal(n))
    y = y[2000:]
    return rms_m * y / np.std(y)


def test_the_band_pass_holds_its_rms_and_peaks_at_one() -> None:
    f = np.linspace(1e-4, 50.0, 2_000_000)
    assert band_pass_power(np.array([1.3]), 1.3, 20.0)[0] == pytest.approx(1.0)
    power = float(np.sum(mode_psd(f, 1.3, 20.0, 2e-9)) * (f[1] - f[0]))
    assert power == pytest.approx((2e-9) ** 2, rel=0.01)


@pytest.mark.parametrize("f0_hz,q", [(2.2, 25.0), (1.4, 8.0)])
def test_a_noise_rung_mode_is_recovered(f0_hz: float, q: float) -> None:
    rng = np.random.default_rng(7)
    n = 40_000
    white = 1.2e-9 * rng.standard_normal(n)
    x = white + _mode_noise(rng, n + 2000, f0_hz, q, 2.5e-9)
    bump = Spectra(_blocks(x), x).fit(1.05 * f0_hz, 0.8 * f0_hz, 1.25 * f0_hz)
    assert bump.f0_hz == pytest.approx(f0_hz, rel=0.01)
    # fitted with the smooth noise terms (against the blocks' own spectra, whose floor
    # the bump's shoulders lifted, Q came out 38 for 25 and 18 for 8)
    assert bump.q == pytest.approx(q, rel=0.3)
    assert bump.rms_m == pytest.approx(2.5e-9, rel=0.2)
    assert bump.deviance > 1000
    # another stretch of the same stand: the bump fitted on the first holds there
    y = 1.2e-9 * rng.standard_normal(n) + _mode_noise(rng, n + 2000, f0_hz, q, 2.5e-9)
    assert Spectra(_blocks(y), y).deviance(bump.f0_hz, bump.q, bump.rms_m) > 1000


def test_white_noise_holds_no_bump() -> None:
    rng = np.random.default_rng(8)
    x = 1.2e-9 * rng.standard_normal(40_000)
    bump = Spectra(_blocks(x), x).fit(2.0, 1.6, 2.5)
    assert bump.deviance < 3 * math.log(40_000)  # below a penalty for its 3 parameters
    y = 1.2e-9 * rng.standard_normal(40_000)
    assert Spectra(_blocks(y), y).deviance(bump.f0_hz, bump.q, bump.rms_m) < 3.0


def test_a_levels_deviance_is_whittles_ratio_summed_directly() -> None:
    """`Spectra._by_level` sums the no-bump side once and the bump side per level; the
    difference must be Whittle's log-likelihood ratio of S0 + bump against S0, bin by bin,
    on the bins near the mode, to far below the tolerance a level search works to (here
    over the blocks' own spectra, before any refit of the smooth terms)."""
    from leveler.analysis.whittle import ENBW_BINS

    rng = np.random.default_rng(9)
    x = 1.2e-9 * rng.standard_normal(40_000) + _mode_noise(rng, 42_000, 2.0, 12.0, 2e-9)
    spectra = Spectra(_blocks(x), x)
    f0, q = 2.0, 12.0
    reach = math.exp(8.0 / q + 0.5)
    near = (spectra.f_hz > f0 / reach) & (spectra.f_hz < f0 * reach)
    s0, p = spectra.s0[near], spectra.p[near]
    for rms in (1e-10, 2e-9, 5e-9):
        s1 = s0 + mode_psd(spectra.f_hz[near], f0, q, rms)
        direct = 2.0 * float(np.sum(np.log(s0 / s1) + p / s0 - p / s1)) / ENBW_BINS
        assert spectra._deviance(f0, q, rms) == pytest.approx(direct, rel=1e-9, abs=1e-9)
    assert spectra._deviance(f0, q, 2e-9) > 100  # a level the data hold gains


def test_the_spread_gate_tells_a_mode_rung_by_noise_from_a_comb_of_lines() -> None:
    """A broad bump raises the likelihood for a comb of harmonics too; only a mode rung by
    noise lifts the typical bin of its band (`Spectra.spread` against diagnose's
    MIN_SPREAD)."""
    from leveler.analysis.diagnose import MIN_SPREAD

    rng = np.random.default_rng(10)
    n = 40_000
    mode = 1.2e-9 * rng.standard_normal(n) + _mode_noise(rng, n + 2000, 1.9, 9.0, 3e-9)
    t = np.arange(n) * DT_S
    # a sawtooth of 4 s: harmonics 0.25 Hz apart, eight of them within 1.9 Hz / 9 either way
    comb = 1.2e-9 * rng.standard_normal(n) + 2e-8 * (np.mod(t / 4.0, 1.0) - 0.5)
    for x, lines in ((mode, False), (comb, True)):
        spectra = Spectra(_blocks(x), x)
        bump = spectra.fit(1.9, 1.5, 2.4, (2.0, 50.0))
        share = spectra.spread(bump)
        assert (share < MIN_SPREAD) == lines, (bump, share)
        if lines:
            assert share < 0.1
        else:
            assert share > 0.7
