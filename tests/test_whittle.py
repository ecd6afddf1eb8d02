"""The noise fit sums its likelihood over groups of bins of one noise level: it must land
where the bin-by-bin Whittle likelihood has its maximum."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from leveler.analysis.whittle import NoiseSpectrum


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
