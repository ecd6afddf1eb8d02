"""The band gate (leveler.analysis.bandgate): a candidate that adds power the data do not
have in some band is stopped; one that only removes what is there, or changes nothing
beyond the noise's own scatter, is not."""

from __future__ import annotations

import numpy as np

from leveler.analysis.bandgate import WORSE_SIGMA, band_changes, bin_power, worse_band
from leveler.analysis.whittle import Blocks, Whitener

DT_S = 0.1
N = 36_000  # an hour at 10 Hz
BANDS = {"1-10 mHz": (1e-3, 1e-2), "10-100 mHz": (1e-2, 1e-1), "0.1-1 Hz": (0.1, 1.0),
         "1 Hz-Nyquist": (1.0, np.inf)}


def _blocks(noise: np.ndarray) -> Blocks:
    """Two blocks of the log, each with its noise spectrum fitted to the noise alone."""
    parts = []
    for span in (slice(0, N // 3), slice(N // 3, N)):
        w = Whitener(span, N, DT_S, lambda f: np.ones_like(f))
        w.fit_noise(noise)
        parts.append(w)
    return Blocks(parts)


def _sine(f_hz: float, amp: float) -> np.ndarray:
    return amp * np.sin(2 * np.pi * f_hz * DT_S * np.arange(N))


def _changes(w: Blocks, before: np.ndarray, after: np.ndarray
             ) -> dict[str, tuple[float, float, float]]:
    wb, wa = w.whiten(before), w.whiten(after)
    return band_changes(w.f_hz, bin_power(w, wb), bin_power(w, wa), bin_power(w, wb - wa),
                        BANDS)


def test_white_noise_whitens_to_one_per_bin_in_every_band() -> None:
    noise = np.random.default_rng(3).standard_normal(N)
    w = _blocks(noise)
    power = bin_power(w, w.whiten(noise))
    assert power.shape == w.f_hz.shape
    for lo, hi in BANDS.values():
        sel = (w.f_hz >= lo) & (w.f_hz < hi)
        assert 0.8 < np.mean(power[sel]) < 1.25


def test_a_line_the_data_do_not_have_makes_its_band_worse() -> None:
    rng = np.random.default_rng(4)
    noise = rng.standard_normal(N)
    w = _blocks(noise)
    wrong = noise - _sine(0.05, 0.3)  # a candidate's 50 mHz line, absent from the data
    changes = _changes(w, noise, wrong)
    assert "10-100 mHz" in worse_band(changes)
    assert changes["10-100 mHz"][2] > WORSE_SIGMA
    assert changes["0.1-1 Hz"][2] < WORSE_SIGMA


def test_removing_a_line_the_data_have_passes_and_noise_alone_never_trips_it() -> None:
    trips = 0
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        noise = rng.standard_normal(N)
        line = _sine(0.05, 0.3)
        w = _blocks(noise)
        # the candidate explains the line
        assert worse_band(_changes(w, noise + line, noise)) == ""
        # a candidate of no consequence: a tiny line, scatter only
        trips += worse_band(_changes(w, noise + line, noise + line - _sine(0.2, 0.01))) != ""
    assert trips == 0
