"""The noise fit sums its likelihood over groups of bins of one noise level: it must land
where the bin-by-bin Whittle likelihood has its maximum."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from leveler.analysis.whittle import NoiseSpectrum, Whitener


def test_grouped_fit_is_at_the_per_bin_maximum() -> None:
    """A day-long span's 216,000 bins in a few thousand groups: polishing the grouped fit
    with the textbook per-bin likelihood (sum p/S + ln S) gains under half a unit of log
    likelihood, i.e. nothing a candidate's score could notice."""
    f = np.fft.rfftfreq(432000, 0.2)
    pendulum = 1.0 / ((1 - (f / 0.5) ** 2) ** 2 + (f / 0.5 / 30.0) ** 2)
    spec = NoiseSpectrum(f, pendulum)
    assert len(spec._starts) < len(f) / 20  # the grouping is what makes it cheap
    truth = np.array([1.0, 2e-3, 1e-6, 0.3, 1e-4]) @ spec.basis
    p = truth * np.random.default_rng(5).exponential(size=len(f))
    use = np.arange(len(f)) >= 4
    use[1000:1003] = False  # a line left out: groups with holes still count right
    grouped = spec.fit(p, use)
    b, pu = spec.basis[:, use], p[use]

    def nll(alpha: np.ndarray) -> tuple[float, np.ndarray]:
        c = np.exp(alpha)
        s = c @ b
        return float(np.sum(pu / s + np.log(s))), ((1 - pu / s) / s) @ b.T * c

    start = np.log(spec.coef)
    polished = minimize(nll, start, jac=True, method="L-BFGS-B",
                        options={"ftol": 1e-15, "gtol": 1e-10})
    assert nll(start)[0] - polished.fun < 0.5
    print(f"per-bin polish gains {nll(start)[0] - polished.fun:.3g} in -ln L")
    # and it finds the truth where a hundred bins per octave pin it down
    assert np.max(np.abs(grouped[100:] / truth[100:] - 1)) < 0.05


def _square_response(n: int, dt_s: float, period_s: float) -> np.ndarray:
    """A square modulation through a Q = 20 resonance at 0.7 Hz: a dense comb of lines."""
    t = np.arange(n) * dt_s
    u = np.where(np.mod(t / period_s, 1.0) < 0.5, 1.0, -1.0)
    f = np.fft.rfftfreq(n, dt_s)
    h = 1.0 / (1 - (f / 0.7) ** 2 + 1j * f / 0.7 / 20)
    return np.fft.irfft(np.fft.rfft(u) * h, n) * 1e-6


def test_a_modulations_comb_is_no_noise() -> None:
    """A short block of a square modulation: the model's error in the response to it (here
    6 % of it, a resonance a little off) is a comb of lines dense enough to pass for
    broadband noise, and fitted to it the noise spectrum would whiten away what an
    actuator effect explains. Told the response (`drive_m`), the fit leaves its bins out
    and finds the noise; untold, it puts the noise level far too high below the
    resonance, where the comb's lines are a few bins apart."""
    n, dt = 10584, 0.1
    resp = _square_response(n, dt, 249.0)
    noise = 2e-10 * np.random.default_rng(11).standard_normal(n)
    residual = noise + 0.06 * resp

    def white(drive: np.ndarray | None) -> Whitener:
        w = Whitener(slice(0, n), n, dt, lambda f: 1.0 / ((1 - (f / 0.7) ** 2) ** 2
                                                         + (f / 0.7 / 20) ** 2),
                     drive_m=drive)
        w.fit_noise(residual)
        return w

    truth = Whitener(slice(0, n), n, dt, lambda f: np.ones_like(f))
    truth.fit_noise(noise)
    below = (truth.f_hz > 0.1) & (truth.f_hz < 0.5)
    told, untold = (np.median(w.psd[below] / truth.psd[below]) for w in (white(resp),
                                                                         white(None)))
    print(f"noise at 0.1-0.5 Hz over the truth: told {told:.2f}, untold {untold:.3g}")
    assert told < 1.5
    assert untold > 10.0
