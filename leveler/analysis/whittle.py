"""A likelihood for residuals that knows their noise: Whittle, with a fitted noise spectrum.

A replay residual is not white: below the sensor's white noise floor sit the sensor's
random-walk drift (1/f^2) and the tilt nobody predicted (random walk through a thermal
lag, 1/f^2 to 1/f^4, shaped by the pendulum's resonance). Least squares on the raw
residual would let that red noise pick any effect it likes. So the residual is
Hann-windowed, Fourier transformed and divided bin by bin by the amplitude of a smooth
parametric noise spectrum fitted to it (Whittle's approximation of the Gaussian
likelihood). Narrow lines and bumps the smooth spectrum cannot follow are exactly what
stands out then, and a candidate effect is scored by how much of that it removes.

The unknown constant offset is removed from each span before the window, so no effect
gets credit for it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize

# Hann window: equivalent noise bandwidth in bins; neighbouring bins are correlated, so
# a sum over bins overcounts independent information by about this factor.
ENBW_BINS = 1.5
# A periodogram bin is exponentially distributed about the spectrum: exceeding it 12-fold
# happens by chance once in 160,000 bins.
_OUTLIER_Z = 12.0
#: Neighbouring bins whose basis terms all differ by less than this (relative) share one
#: value of the fitted spectrum in the likelihood the fit maximises: half a day at 10 Hz
#: has 216,000 bins but some 4,500 distinct noise levels, so the fit runs on sums over
#: such groups (exact where the spectrum is flat over a group), 17x faster.
GROUP_REL = 0.01
#: The lowest bins of a span are left out of the noise fit and get its extrapolation: a
#: trend (a drift) lives there, and fitted to them the 1/f^4 term would soak it up.
EXTRAPOLATED_BINS = 4
#: A bin where a 10 % error of the excitation's response (1e-2 of its power) would stand
#: above the noise carries that response, not noise: it is left out of the noise fit. A
#: resonance 0.5 % off with Q 18 is already that wrong near it: at 1 % (29 of a short
#: block's 5,293 bins left out) the held-out evidence of a strong delay was still -1,864,
#: at 3 % (96 bins) -2,137, at 10 % (661 bins) +42,314, its training part's 590,000.
DRIVEN_REL = 1e-2


def hann(n: int) -> np.ndarray:
    return 0.5 - 0.5 * np.cos(2 * np.pi * (np.arange(n) + 0.5) / n)


def hann_psd(x: np.ndarray, dt_s: float) -> np.ndarray:
    """One-sided PSD [x^2/Hz] of `x` through a Hann window, at np.fft.rfftfreq's bins: the
    per-band figures of a replay (its gap, its residual against the model's noise)."""
    win = hann(len(x))
    return np.abs(np.fft.rfft(win * x)) ** 2 * 2 * dt_s / np.sum(win**2)


class NoiseSpectrum:
    """S(f) = sum_j c_j B_j(f): white, 1/f^2, 1/f^4, and tilt noise through the pendulum."""

    def __init__(self, f_hz: np.ndarray, pendulum_shape: np.ndarray) -> None:
        f = np.maximum(f_hz, f_hz[1] if len(f_hz) > 1 else 1.0)
        self.basis = np.vstack([np.ones_like(f), f**-2.0, f**-4.0, pendulum_shape,
                                pendulum_shape * f**-2.0])
        self.basis /= self.basis.mean(axis=1, keepdims=True)
        self.coef = np.zeros(len(self.basis))
        # group starts: wherever the accumulated change of the basis reaches GROUP_REL
        change = np.abs(np.diff(np.log(self.basis), axis=1)).max(axis=0)
        group = np.floor(np.concatenate([[0.0], np.cumsum(change)]) / GROUP_REL)
        self._starts = np.concatenate([[0], np.flatnonzero(np.diff(group)) + 1])

    def fit(self, p: np.ndarray, use: np.ndarray, known: np.ndarray | None = None
            ) -> np.ndarray:
        """Robust Whittle fit: bins far above the last fit (lines, a comb of harmonics) are
        left out and the fit repeated, so the noise spectrum describes the noise rather
        than the effect it should make stand out. `known`: a part of the spectrum already
        accounted for (a found mode's noise), added to the smooth terms, not fitted."""
        keep = use & ~self._far_above_octave_median(p)
        for _ in range(6):
            s = self._fit(p, keep, known)
            out = use & (p / s > _OUTLIER_Z)
            if np.array_equal(~out & use, keep):
                break
            keep = use & ~out
        return s

    def flat(self) -> np.ndarray:
        """The fitted spectrum's terms that are not red: white, and tilt noise through the
        pendulum (flat below its resonance)."""
        return self.coef[0] * self.basis[0] + self.coef[3] * self.basis[3]

    def _far_above_octave_median(self, p: np.ndarray) -> np.ndarray:
        """Bins 20x above the median of their octave: a first, fit-free guess at the lines
        (a sawtooth's comb of harmonics would otherwise pass for a 1/f^2 noise)."""
        return p > 20.0 * octave_median(p)

    def _fit(self, p: np.ndarray, use: np.ndarray, known: np.ndarray | None = None
             ) -> np.ndarray:
        """Whittle fit of the coefficients to periodogram p on bins `use`; returns S.
        The likelihood is summed per group of bins of one noise level (`GROUP_REL`): a
        group's m used bins with periodogram sum P count m ln S + P / S."""
        scale = float(np.median(p[use])) or 1.0
        w = use.astype(float)
        m = np.add.reduceat(w, self._starts)
        keep = m > 0
        m = m[keep]
        pg = np.add.reduceat(p * w, self._starts)[keep] / scale
        b = np.add.reduceat(self.basis * w, self._starts, axis=1)[:, keep] / m
        fixed = (0.0 if known is None else
                 np.add.reduceat(known * w, self._starts)[keep] / m / scale)

        def nll(alpha: np.ndarray) -> tuple[float, np.ndarray]:
            c = np.exp(alpha)
            s = c @ b + fixed
            ratio = pg / s
            grad = ((m - ratio) / s) @ b.T * c
            return float(np.sum(ratio + m * np.log(s))), grad

        best = None
        for start in (np.log([1.0, 1e-3, 1e-6, 1e-3, 1e-6]), np.full(len(b), np.log(0.2))):
            res = minimize(nll, start, jac=True, method="L-BFGS-B",
                           bounds=[(-60.0, 30.0)] * len(b))
            if best is None or res.fun < best.fun:
                best = res
        assert best is not None
        self.coef = np.exp(best.x) * scale
        return self.coef @ self.basis + (0.0 if known is None else known)


def octave_median(p: np.ndarray) -> np.ndarray:
    """Per bin, the median of `p` over the bin's octave (bins 2^j to 2^(j+1)-1)."""
    k = np.arange(len(p))
    octave = np.floor(np.log2(np.maximum(k, 1))).astype(int)
    med = np.array([np.median(p[octave == o]) for o in range(octave.max() + 1)])
    return med[octave]


#: how much of a block `fast_length` gives up for a length of factors 2, 3 and 5 alone
SMOOTHEST_REACH = 0.005


def _smooth(m: int, primes: tuple[int, ...]) -> bool:
    for p in primes:
        while m % p == 0:
            m //= p
    return m == 1


def fast_length(n: int) -> int:
    """The longest length <= n whose prime factors are all 2, 3 and 5 if one is within
    SMOOTHEST_REACH of n, else all <= 11: a block trimmed to it (by under 1 % at the
    sizes diagnose uses) transforms 10-20x faster than one of a length with a large prime
    factor, and whitening is most of diagnose's time. Sevens and elevens cost too: a
    day's block of 384,160 (2^5 x 5 x 7^4) took 6.4 ms a transform, one of 384,000 3.6 ms,
    and a null day's run makes ~500 of them."""
    for m in range(n, int(n * (1 - SMOOTHEST_REACH)), -1):
        if _smooth(m, (2, 3, 5)):
            return m
    for m in range(n, 1, -1):
        if _smooth(m, (2, 3, 5, 7, 11)):
            return m
    return n


class Whitener:
    """Maps a time-domain residual on one span to a real vector of unit-variance numbers."""

    def __init__(self, span: slice, n_total: int, dt_s: float,
                 pendulum_response: Callable[[np.ndarray], np.ndarray],
                 red_ceiling: Callable[[int, float, np.ndarray], np.ndarray] | None = None,
                 known_psd: Callable[[np.ndarray], np.ndarray] | None = None,
                 drive_m: np.ndarray | None = None) -> None:
        """`pendulum_response(f_hz)`: |H(f)/H(0)|^2 of the pendulum. `red_ceiling(n, dt_s,
        bins)`: the most red noise [m^2/Hz] the model's stated noise terms allow in those
        bins of a block, if it states them (`leveler.analysis.told`). `known_psd(f_hz)`:
        noise the model already holds [m^2/Hz] (a found mode rung by its own noise), added
        to the fitted terms. `drive_m`: the reading's response to the excitation (a
        modulation), whose bins are no noise (`DRIVEN_REL`). The span is cut to
        `fast_length`."""
        start, stop, _ = span.indices(n_total)
        self.n = fast_length(stop - start)
        self.span = slice(start, start + self.n)
        self.dt_s = dt_s
        self.window = hann(self.n)
        self.f_hz = np.fft.rfftfreq(self.n, dt_s)
        self.norm = float(np.sum(self.window**2)) / (2 * dt_s)
        self.spectrum = NoiseSpectrum(self.f_hz, pendulum_response(self.f_hz))
        self.ceiling = (None if red_ceiling is None else
                        red_ceiling(self.n, dt_s, np.flatnonzero(self.extrapolated())))
        self.known = None if known_psd is None else known_psd(self.f_hz)
        self.drive = None if drive_m is None else DRIVEN_REL * self.periodogram(drive_m)
        self.weight = np.ones(len(self.f_hz))

    def transform(self, x: np.ndarray) -> np.ndarray:
        """rfft of the Hann-windowed span of a full-length series."""
        seg = x[self.span]
        centred = seg - seg.mean()
        centred *= self.window
        return np.fft.rfft(centred)

    def periodogram(self, x: np.ndarray) -> np.ndarray:
        return np.abs(self.transform(x)) ** 2 / self.norm

    def fit_noise(self, residual: np.ndarray) -> None:
        """Fit the noise spectrum to this residual; bin 0 (the mean) carries nothing."""
        p = self.periodogram(residual)
        use = ~self.extrapolated()
        if self.drive is None:
            s = self.spectrum.fit(p, use, self.known)
        else:
            # A modulation's comb of harmonics, seen through a model a little wrong, is
            # dense enough in a short block to pass for noise, and the fit then whitens
            # away what an actuator effect explains there: a strong delay's held-out
            # evidence was -3,000 where its training part's was +121,000. First guess
            # at the noise: the residual's octave medians.
            driven = self.drive > octave_median(p)
            for _ in range(4):
                s = self.spectrum.fit(p, use & ~driven, self.known)
                now = self.drive > s
                if np.array_equal(now, driven):
                    break
                driven = now
        if self.ceiling is not None:
            # The lowest bins get the fit's extrapolation, and a steep red term fitted to
            # the leakage of a trend extrapolates to whiten the trend away: no more red
            # noise there than the stated terms allow.
            low = ~use
            top = self.spectrum.flat()[low] + self.ceiling
            s[low] = np.minimum(s[low], top if self.known is None else top + self.known[low])
        self.psd = s
        self.weight = minimum_phase(1.0 / np.sqrt(s * self.norm), self.n)
        self.weight[0] = 0.0  # the mean: removed before the window, carries nothing

    def _stack(self, spec: np.ndarray) -> np.ndarray:
        """`spec` (a transform's own array, changed in place) weighted, real parts then
        imaginary ones."""
        spec *= self.weight
        return np.concatenate([spec.real, spec.imag])

    def whiten(self, residual: np.ndarray) -> np.ndarray:
        """Whitened residual: about unit variance per number where the noise model holds."""
        return self._stack(self.transform(residual))

    def cost(self, residual: np.ndarray) -> float:
        """Sum of squared whitened residuals: under the noise model, about one per bin."""
        e = self.whiten(residual)
        return float(e @ e)

    def zscores(self, residual: np.ndarray, known: bool = True) -> np.ndarray:
        """Periodogram over the fitted noise spectrum, per bin (about 1 where it fits);
        `known=False`: over its fitted terms alone, as a model without the found modes'
        noise would see it."""
        psd = self.psd if known or self.known is None else self.psd - self.known
        return self.periodogram(residual) / psd

    def extrapolated(self) -> np.ndarray:
        """Bins whose noise level is the fit's extrapolation, not fitted to them."""
        return np.arange(len(self.f_hz)) < EXTRAPOLATED_BINS

    def fitted(self) -> np.ndarray:
        """Which whitened numbers (real parts, then imaginary) are of bins the noise
        spectrum was fitted to."""
        return np.tile(~self.extrapolated(), 2)

    def below(self, f_max_hz: float) -> np.ndarray:
        """Which whitened numbers (real parts, then imaginary) are of bins below f_max."""
        return np.tile(self.f_hz < f_max_hz, 2)


class Blocks:
    """Whiteners on several spans of one log, used as one: a training or held-out set
    made of a block of each part of the log (its modulated, open-loop part and its
    closed-loop part), so an effect is scored where it shows. Each block has its own
    noise spectrum: the noise of an open and a closed loop differ."""

    def __init__(self, parts: list[Whitener]) -> None:
        self.parts = parts
        self.f_hz = np.concatenate([p.f_hz for p in parts])
        self.longest = max(parts, key=lambda p: p.n)

    @property
    def spans(self) -> list[slice]:
        return [p.span for p in self.parts]

    def index(self) -> np.ndarray:
        """The samples the blocks cover, in order."""
        return np.concatenate([np.arange(p.span.start, p.span.stop) for p in self.parts])

    def fit_noise(self, residual: np.ndarray) -> None:
        for p in self.parts:
            p.fit_noise(residual)

    def whiten(self, residual: np.ndarray) -> np.ndarray:
        return np.concatenate([p.whiten(residual) for p in self.parts])

    def cost(self, residual: np.ndarray) -> float:
        e = self.whiten(residual)
        return float(e @ e)

    def zscores(self, residual: np.ndarray, known: bool = True) -> np.ndarray:
        return np.concatenate([p.zscores(residual, known) for p in self.parts])

    def below(self, f_max_hz: float) -> np.ndarray:
        return np.concatenate([p.below(f_max_hz) for p in self.parts])

    def fitted(self) -> np.ndarray:
        return np.concatenate([p.fitted() for p in self.parts])


def minimum_phase(gain: np.ndarray, n: int) -> np.ndarray:
    """The causal, minimum-phase filter with this gain on the rfft grid (real cepstrum).

    Whitening with a zero-phase gain would be non-causal, and in closed loop that matters:
    the actuator voltage answers the disturbance, so a non-causal whitening correlates
    an actuator effect with the very disturbance it reacts to and blames the piezo for
    the table's tilt. The innovations of a causal whitening do not depend on the voltage
    applied at the same time (prediction-error identification's consistency argument).
    """
    log_gain = np.log(np.maximum(gain, np.max(gain) * 1e-300))
    log_gain[0] = log_gain[1]
    cep = np.fft.irfft(log_gain, n)
    fold = np.zeros(n)
    fold[0] = cep[0]
    half = (n + 1) // 2
    fold[1:half] = 2 * cep[1:half]
    if n % 2 == 0:
        fold[n // 2] = cep[n // 2]
    return np.exp(np.fft.rfft(fold))


def deviance(cost_before: float, cost_after: float) -> float:
    """Twice the log-likelihood gain, corrected for the window's correlated bins."""
    return 2.0 * (cost_before - cost_after) / ENBW_BINS
