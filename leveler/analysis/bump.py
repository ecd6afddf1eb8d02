"""A mode rung by its own noise: a bump in the residual's spectrum, not a line in it.

A table top or a mount shaken by the floor, by air or by the piezo's own noise rings at
its resonance whatever the command does, and replay cannot predict a single sample of
it: the effect lives only in the residual's power. So it is scored the way the noise
is, by Whittle's likelihood: the block's fitted noise spectrum S0 against S0 plus a
band-pass bump of the mode's noise,

    S1(f) = S0(f) + rms^2 |H(f)|^2 / (pi f0 / (2 Q)),  |H|^2 = (x/Q)^2 / ((1 - x^2)^2 + (x/Q)^2),

x = f / f0 (|H| = 1 at f0; pi f0 / (2 Q) is its noise bandwidth, so the bump holds rms^2).
The bump's frequency and Q are fitted (a grid, then a simplex), its level solved for
each, over the smooth noise terms, and those are fitted again with the bump held in the
spectrum, twice over. The blocks' own noise spectra were fitted to a residual holding
the bump, whose shoulders lifted them: scored against those, a Q of 25 came out 38 and
one of 8 came out 18. A held-out block is scored with the bump fixed and its smooth
terms fitted with it; the no-bump side of every comparison is the block's own spectrum.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from leveler.analysis.whittle import ENBW_BINS, Blocks, NoiseSpectrum

#: Q values the search starts from (a mount's mode: a few to a few hundred)
Q_GRID = (3.0, 6.0, 12.0, 25.0, 50.0, 100.0)
Q_BOUNDS = (2.0, 1e3)
#: times the smooth noise terms are fitted again with the bump, and the bump with them
JOINT_ROUNDS = 2


def band_pass_power(f_hz: np.ndarray, f0_hz: float, q: float) -> np.ndarray:
    """|H(f)|^2 of a unit-peak second-order band-pass."""
    x = f_hz / f0_hz
    r = (x / q) ** 2
    return r / ((1 - x * x) ** 2 + r)


def mode_psd(f_hz: np.ndarray, f0_hz: float, q: float, rms_m: float) -> np.ndarray:
    """One-sided PSD [m^2/Hz] of a mode's noise of this rms at the sensor."""
    return rms_m**2 * band_pass_power(f_hz, f0_hz, q) / (math.pi * f0_hz / (2 * q))


@dataclass(frozen=True)
class Bump:
    f0_hz: float
    q: float
    rms_m: float
    deviance: float  # 2 ln of the likelihood ratio against no bump, on the blocks it was fit


class Spectra:
    """The periodograms and noise spectra of a set of blocks, flattened to one grid sorted
    by frequency, with the bins the noise was fitted on (the extrapolated lowest ones say
    nothing here). Sorted, the bins near a bump are one slice: a search scores thousands
    of bumps, and masking a day's 200,000 bins for each took most of its time."""

    def __init__(self, w: Blocks, residual: np.ndarray) -> None:
        self._parts = [(part, part.periodogram(residual), ~part.extrapolated())
                       for part in w.parts]
        keep = np.concatenate([use for *_, use in self._parts])
        self._order = np.argsort(w.f_hz[keep], kind="stable")
        self.f_hz = w.f_hz[keep][self._order]
        self.p = np.concatenate([p for _, p, _ in self._parts])[keep][self._order]
        self.s0 = np.concatenate([part.psd for part in w.parts])[keep][self._order]
        self.under = self.s0  # the smooth terms under the bump, refitted with it

    def _between(self, lo_hz: float, hi_hz: float) -> slice:
        """The bins with lo < f < hi."""
        return slice(int(np.searchsorted(self.f_hz, lo_hz, side="right")),
                     int(np.searchsorted(self.f_hz, hi_hz, side="left")))

    def _refit_under(self, f0_hz: float, q: float, rms_m: float) -> None:
        """The blocks' smooth noise terms fitted again with this bump held in the
        spectrum (`NoiseSpectrum.fit`'s known part): its shoulders no longer lift them."""
        under = []
        for part, p, use in self._parts:
            known = mode_psd(part.f_hz, f0_hz, q, rms_m)
            spectrum = NoiseSpectrum(part.f_hz, part.spectrum.basis[3])
            under.append((spectrum.fit(p, use, known) - known)[use])
        self.under = np.concatenate(under)[self._order]

    def _deviance(self, f0_hz: float, q: float, rms_m: float) -> float:
        return self._by_level(f0_hz, q)(rms_m)

    def _by_level(self, f0_hz: float, q: float) -> Callable[[float], float]:
        """`_deviance` at this frequency and Q as a function of the level alone: the
        level's search calls it a dozen times a point, and the band's shape, its bins and
        the no-bump side, sum(ln s0 + p / s0), are the same each time. Summed apart, the
        bump side is four passes over the band where the ratio's terms took eight (a null
        day's run scores 4,000 levels: 4.0 -> 1.7 s); the two sides agree to ~1e-15 of
        either."""
        reach = math.exp(8.0 / q + 0.5)  # |ln(f / f0)| < 8 / q + 0.5
        near = self._between(f0_hz / reach, f0_hz * reach)
        s0, p, under = self.s0[near], self.p[near], self.under[near]
        shape, width = band_pass_power(self.f_hz[near], f0_hz, q), math.pi * f0_hz / (2 * q)
        without = float(np.sum(np.log(s0))) + float(np.sum(p / s0))

        def deviance(rms_m: float) -> float:
            s1 = shape * (rms_m**2 / width)
            s1 += under
            p_s1 = np.divide(p, s1)
            np.log(s1, out=s1)
            return 2.0 * (without - float(np.sum(s1)) - float(np.sum(p_s1))) / ENBW_BINS

        return deviance

    def deviance(self, f0_hz: float, q: float, rms_m: float) -> float:
        """2 ln L(smooth terms + bump) - 2 ln L(the blocks' own spectra), the smooth terms
        fitted with this bump held, corrected for the window's correlated bins."""
        self._refit_under(f0_hz, q, rms_m)
        return self._deviance(f0_hz, q, rms_m)

    def spread(self, bump: Bump) -> float:
        """How much of the bump's excess power the typical bin of its half-power band
        carries: about 1 for noise rung in the band, near 0 for a comb of lines (a
        sawtooth's harmonics) that a broad bump would also raise the likelihood for. The
        median of an exponential periodogram bin is ln 2 of its mean."""
        half = 0.5 * bump.f0_hz / bump.q
        band = self._between(bump.f0_hz - half, bump.f0_hz + half)
        if band.stop - band.start < 8:
            return 0.0
        s0 = self.under[band]
        excess = float(np.mean(mode_psd(self.f_hz[band], bump.f0_hz, bump.q, bump.rms_m) / s0))
        typical = float(np.median(self.p[band] / s0)) / math.log(2) - 1.0
        return typical / excess if excess > 0 else 0.0

    def best_rms(self, f0_hz: float, q: float) -> tuple[float, float]:
        """The level that fits best at this frequency and Q: (rms_m, deviance)."""
        near = self._between(f0_hz - f0_hz / q, f0_hz + f0_hz / q)
        if near.stop <= near.start:
            return 0.0, 0.0
        # the bump's excess over the noise at its peak, in power, gives the scale
        excess = max(float(np.mean(self.p[near] - self.under[near])), 0.0)
        scale = math.sqrt(excess * math.pi * f0_hz / (2 * q)) or math.sqrt(
            float(np.mean(self.under[near])) * f0_hz / q)
        deviance = self._by_level(f0_hz, q)
        res = minimize_scalar(lambda a: -deviance(scale * math.exp(a)),
                              bounds=(-8.0, 4.0), method="bounded", options={"xatol": 1e-3})
        dev = -float(res.fun)
        return (scale * math.exp(float(res.x)), dev) if dev > 0 else (0.0, 0.0)

    def fit(self, f_guess_hz: float, f_lo_hz: float, f_hi_hz: float,
            q_bounds: tuple[float, float] = Q_BOUNDS, joint: bool = True) -> Bump:
        """The best bump near `f_guess_hz`, kept within [f_lo, f_hi] and `q_bounds`;
        `joint=False`: over the blocks' own noise spectra alone (a first look, some
        seconds faster, its Q high)."""
        self.under = self.s0
        best = max(((q, *self.best_rms(f_guess_hz, q)) for q in Q_GRID), key=lambda r: r[2])
        x = np.array([math.log(f_guess_hz), math.log(best[0])])
        lo = np.array([math.log(f_lo_hz), math.log(q_bounds[0])])
        hi = np.array([math.log(f_hi_hz), math.log(q_bounds[1])])

        def cost(x: np.ndarray) -> float:
            x = np.clip(x, lo, hi)
            return -self.best_rms(math.exp(x[0]), math.exp(x[1]))[1]

        bump = Bump(f_guess_hz, best[0], 0.0, 0.0)
        for rounds in range(JOINT_ROUNDS + 1 if joint else 1):
            if rounds:
                self._refit_under(bump.f0_hz, bump.q, bump.rms_m)
            res = minimize(cost, x, method="Nelder-Mead",
                           options={"xatol": 1e-4, "fatol": 1e-3, "maxfev": 200})
            x = np.clip(res.x, lo, hi)
            f0, q = math.exp(x[0]), math.exp(x[1])
            bump = Bump(f0, q, *self.best_rms(f0, q))
        return bump

    def sigma(self, bump: Bump) -> dict[str, float]:
        """1-sigma of the bump's frequency, Q and rms from the curvature of the deviance
        (twice the log-likelihood) at the fit: the inverse of half its Hessian."""
        x = np.array([bump.f0_hz, bump.q, bump.rms_m])
        h = np.array([0.05 * bump.f0_hz / bump.q, 0.05 * bump.q, 0.05 * bump.rms_m])

        def dev(v: np.ndarray) -> float:
            return self._deviance(float(v[0]), float(v[1]), float(v[2]))

        hess = np.zeros((3, 3))
        for i in range(3):
            for j in range(i, 3):
                ei, ej = np.eye(3)[i] * h[i], np.eye(3)[j] * h[j]
                hess[i, j] = hess[j, i] = (dev(x + ei + ej) - dev(x + ei - ej) - dev(x - ei + ej)
                                           + dev(x - ei - ej)) / (4 * h[i] * h[j])
        try:
            var = np.diag(np.linalg.inv(-hess / 2))
        except np.linalg.LinAlgError:
            var = np.full(3, np.inf)
        keys = ("frequency_hz", "q", "noise_rms_m")
        return {k: float(math.sqrt(v)) if v > 0 else math.inf
                for k, v in zip(keys, var, strict=True)}
