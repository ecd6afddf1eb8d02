"""LPSD against spectra known in closed form, a direct per-segment computation and scipy's welch.

Normalisation under test (see leveler.analysis.spectral): one-sided PSD = 2/(fs*S2) * mean |DFT|^2,
so white noise of standard deviation sigma reads sigma*sqrt(2/fs) and a sine of amplitude A reads
PSD(f0) * ENBW = A^2/2 with ENBW = fs*S2/S1^2 (1.5*fs/L for Hann).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from leveler.analysis.plots import plot_asd
from leveler.analysis.spectral import Spectrum, asd_at, lpsd

FS = 10.0
WHITE_ASD = np.sqrt(2 / FS)  # one-sided ASD of unit-variance white noise


def _white(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal(n)


def _random_walk_asd(f_hz: np.ndarray) -> np.ndarray:
    """Exact ASD of cumsum(unit white): |1/(1 - exp(-2j*pi*f/fs))| = 1/(2 sin(pi f/fs))."""
    return WHITE_ASD / (2 * np.sin(np.pi * f_hz / FS))


def test_white_noise_reads_its_known_level() -> None:
    x = _white(200_000, seed=1)
    s = lpsd(x, FS)
    assert np.mean(s.asd) / WHITE_ASD == pytest.approx(1, abs=0.1)
    np.testing.assert_allclose(asd_at(x, FS, [0.05, 0.5, 2.0]) / WHITE_ASD, 1, atol=0.2)


def test_sine_amplitude_from_peak_psd_times_enbw() -> None:
    amp, f0 = 2.0, 0.3
    t = np.arange(50_000) / FS
    x = amp * np.sin(2 * np.pi * f0 * t + 0.4) + 1e-3 * _white(t.size, seed=2)
    s = lpsd(x, FS, fmin_hz=f0 / 1.1, fmax_hz=f0 * 1.1, n_freqs=41)  # s.freq_hz[20] == f0
    assert s.freq_hz[20] == pytest.approx(f0, rel=1e-12)
    enbw_hz = 1.5 * FS / s.segment_len[20]
    assert s.asd[20] ** 2 * enbw_hz == pytest.approx(amp**2 / 2, rel=0.1)
    assert max(s.asd[0], s.asd[-1]) < 1e-2 * s.asd[20]  # 10 % off f0: Hann sidelobes only


def test_random_walk_follows_one_over_f_down_to_the_lowest_frequency() -> None:
    """Averaged over 100 walks, so the check is on bias, not on the scatter of 2 averages."""
    rng = np.random.default_rng(3)
    walks = np.cumsum(rng.standard_normal((100, 4000)), axis=1)
    spectra = [lpsd(w, FS) for w in walks]
    asd = np.sqrt(np.mean([s.asd**2 for s in spectra], axis=0))
    f = spectra[0].freq_hz
    idx = [0, 5, 20, 60, 120, 199]
    np.testing.assert_allclose(asd[idx] / _random_walk_asd(f[idx]), 1, atol=0.25)


@pytest.mark.parametrize(
    ("overlap", "detrend"), [(0.5, "linear"), (0.0, "constant"), (0.75, "none"), (0.6, "linear")]
)
def test_equals_direct_per_segment_computation(overlap: float, detrend: str) -> None:
    """The blocked matrix products reproduce detrend -> window -> DFT at f, segment by segment."""
    n = 3001
    x = _white(n, seed=4) + 1e-3 * np.arange(n) ** 1.5
    s = lpsd(x, FS, n_freqs=15, overlap=overlap, detrend=detrend)
    for f, seg, k, got in zip(s.freq_hz, s.segment_len, s.n_averages, s.asd, strict=True):
        step = max(1, round(seg * (1 - overlap)))
        assert k == (n - seg) // step + 1 >= 2
        start = (n - seg - (k - 1) * step) // 2  # segments centred in the record
        window = signal.get_window("hann", seg)
        phasor = np.exp(-2j * np.pi * f * np.arange(seg) / FS)
        power = []
        for i in range(k):
            seg_x = x[start + i * step : start + i * step + seg]
            if detrend != "none":
                seg_x = signal.detrend(seg_x, type=detrend)
            power.append(abs(np.sum(window * seg_x * phasor)) ** 2)
        want = np.sqrt(2 * np.mean(power) / (FS * np.sum(window**2)))
        assert got == pytest.approx(want, rel=1e-8)


def test_agrees_with_scipy_welch_at_the_same_segment_length() -> None:
    x = signal.lfilter([1.0], [1.0, -0.95], _white(200_000, seed=5))  # smooth red spectrum
    s = lpsd(x, FS)
    for j in (80, 110, 140, 170):
        seg = int(s.segment_len[j])
        f, psd = signal.welch(
            x, FS, window="hann", nperseg=seg, noverlap=seg // 2, detrend="linear"
        )
        assert s.asd[j] == pytest.approx(np.sqrt(np.interp(s.freq_hz[j], f, psd)), rel=0.15)


def test_asd_at_is_lpsd_at_the_same_frequencies() -> None:
    x = np.cumsum(_white(30_000, seed=6))
    s = lpsd(x, FS)
    idx = [0, 57, 123, 199]
    np.testing.assert_allclose(asd_at(x, FS, s.freq_hz[idx]), s.asd[idx], rtol=1e-12)


def test_day_long_record_at_10_hz() -> None:
    n = 864_000  # 24 h at 10 Hz
    x = 1e-3 * np.cumsum(_white(n, seed=7)) + _white(n, seed=8)
    t0 = time.perf_counter()
    s = lpsd(x, FS)
    elapsed_s = time.perf_counter() - t0
    assert s.freq_hz.shape == s.asd.shape == (200,)
    assert np.all(np.diff(s.freq_hz) > 0) and 0 < s.freq_hz[0] <= 1e-4 < 1 < s.freq_hz[-1] < FS / 2
    assert np.all(np.isfinite(s.asd) & (s.asd > 0))
    assert np.all(s.n_averages >= 2) and np.all(s.segment_len * 1.5 <= n + 1)
    assert elapsed_s < 15, f"lpsd took {elapsed_s:.1f} s (about 1 s expected)"
    mhz = asd_at(x, FS, [1e-4, 1e-3, 1e-2])
    assert np.all(np.isfinite(mhz) & (mhz > 0))
    # 1e-5 Hz needs 2 segments of 2 periods (2e6 samples each), 50 % overlapped: 3e6 samples.
    with pytest.raises(ValueError, match=r"1e-05 Hz is too low.*at least 3000000 samples"):
        asd_at(x, FS, [1e-5])


@pytest.mark.parametrize(
    ("x", "fs_hz", "message"),
    [
        (np.r_[np.zeros(99), np.nan], FS, "non-finite"),
        (np.r_[np.zeros(99), np.inf], FS, "non-finite"),
        (np.zeros(15), FS, "at least 16 samples"),
        (np.zeros(100), 0.0, "fs_hz must be positive"),
        (np.zeros(100), -1.0, "fs_hz must be positive"),
        (np.zeros((10, 10)), FS, "one-dimensional"),
    ],
)
def test_rejects_bad_input(x: np.ndarray, fs_hz: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        lpsd(x, fs_hz)
    with pytest.raises(ValueError, match=message):
        asd_at(x, fs_hz, [1.0])


def test_rejects_frequencies_outside_the_record() -> None:
    x = _white(1000, seed=9)
    with pytest.raises(ValueError, match="below Nyquist"):
        asd_at(x, FS, [5.0])
    with pytest.raises(ValueError, match="positive"):
        asd_at(x, FS, [0.0])
    with pytest.raises(ValueError, match="too low"):
        lpsd(x, FS, fmin_hz=1e-3)


def test_plot_asd_writes_a_png(tmp_path: Path) -> None:
    open_loop = lpsd(np.cumsum(_white(40_000, seed=10)), FS)
    closed_loop = Spectrum(
        open_loop.freq_hz, open_loop.asd / 10, open_loop.n_averages, open_loop.segment_len
    )
    target = tmp_path / "asd.png"
    out = plot_asd(
        [("open loop", open_loop), ("closed loop", closed_loop)],
        target,
        ylabel="Sensor ASD [m/√Hz]",
        title="Open vs closed loop",
    )
    assert out == target
    data = target.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    with pytest.raises(ValueError, match="at least one"):
        plot_asd([], tmp_path / "empty.png", ylabel="x")
