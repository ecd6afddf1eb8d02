"""The band gate (leveler.analysis.bandgate): a candidate that adds power the data do not
have in some band is stopped; one that only removes what is there, or changes nothing
beyond the noise's own scatter, is not."""

from __future__ import annotations

import numpy as np

from leveler.analysis.bandgate import WORSE_SIGMA, BandChange, band_changes, bin_power, worse_band
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
             ) -> dict[str, BandChange]:
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
    assert changes["10-100 mHz"].rise_sigma > WORSE_SIGMA
    assert changes["0.1-1 Hz"].rise_sigma < WORSE_SIGMA


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


def test_a_trade_is_stopped_only_when_it_gives_back_a_real_share_of_the_gain() -> None:
    """A right effect in a form a little off: it explains a strong 5 mHz line and adds a
    weak 50 mHz one (passes); a wrong form adds a 50 mHz line of half the gain (stopped)."""
    rng = np.random.default_rng(5)
    noise = rng.standard_normal(N)
    w = _blocks(noise)
    data = noise + _sine(0.005, 1.0)
    small = _changes(w, data, noise - _sine(0.05, 0.15))
    assert small["10-100 mHz"].rise_sigma > WORSE_SIGMA  # worse beyond the noise ...
    assert worse_band(small) == ""  # ... by a sliver of what it explains
    large = _changes(w, data, noise - _sine(0.05, 0.7))
    assert -large["10-100 mHz"].gain > 0.3 * large["1-10 mHz"].gain
    assert "10-100 mHz" in worse_band(large)


def test_a_band_below_the_noise_that_comes_back_to_it_is_not_worse() -> None:
    """The noise spectrum fitted to a residual that held the effect sits high: without the
    effect, a band there reads 0.5 of it. Back at 1 is not worse."""
    c = {"1-10 mHz": BandChange(before=0.5, after=1.05, rise_sigma=9.0, gain=-20.0),
         "10-100 mHz": BandChange(before=50.0, after=1.0, rise_sigma=-90.0, gain=15000.0)}
    assert worse_band(c) == ""
    c["1-10 mHz"] = BandChange(before=0.5, after=4.0, rise_sigma=60.0, gain=-4000.0)
    assert "1-10 mHz" in worse_band(c)


def test_a_candidate_that_explains_nothing_anywhere_is_refused_with_a_reason() -> None:
    """Every band's gain <= 0: the share of what it explains elsewhere is no number (it
    divided by zero and crashed a diagnosis of a thermometer-fed log)."""
    why = worse_band({"1-10 mHz": BandChange(1.0, 3.0, 10.0, -2.0, True),
                      "10-100 mHz": BandChange(1.0, 1.0, 0.0, 0.0, True)})
    assert why.startswith("makes the 1-10 mHz band worse") and why.endswith(
        "and it explains nothing elsewhere"), why
