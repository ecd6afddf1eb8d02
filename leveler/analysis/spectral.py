"""Spectral densities on a logarithmic frequency axis (LPSD).

Tilt and displacement noise of a torsion-pendulum stand matter from 0.1 mHz to 1 Hz, i.e. over
four decades, from records of up to days at 10 Hz (~10^6 samples). A Welch estimate with one
segment length is either too coarse at the low end or too noisy at the high end, so this module
implements LPSD (M. Tröbs and G. Heinzel, "Improved spectrum estimation from digitized time
series on a logarithmic frequency axis", Measurement 39 (2006) 120-129; the method of LTPDA's
``lpsd``): every frequency of a log-spaced axis gets its own segment length, chosen so that
the resolution matches the axis spacing while averaging as many segments as the record allows.

Estimator at one frequency f with segment length L (window w = periodic Hann, S2 = sum w^2):
segments of L samples overlapping by ``overlap``, each detrended (least squares), windowed and
Fourier-transformed at exactly f (the bin m = f*L/fs need not be an integer), then

    PSD(f) = 2 / (fs * S2) * mean_k |X_k(f)|^2        (one-sided, units^2/Hz)

so white noise of standard deviation sigma reads sigma*sqrt(2/fs) in the ASD, and a sine of
amplitude A at f reads PSD(f) * ENBW = A^2/2 with ENBW = fs*S2/S1^2 (S1 = sum w).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike

# Lowest bin (cycles per segment) estimated. Closer to DC the Hann main lobe and the per-segment
# detrending, which removes part of the signal itself, make the estimate unreliable; even at 2
# cycles a random walk (1/f ASD) reads ~15 % high (leakage from below), ~7 % at 3, ~3 % at 4.
_MIN_BIN = 2.0
# Default top of the axis, as a fraction of Nyquist: right at fs/2 the one-sided factor of 2
# is wrong and the Hann main lobe folds over.
_FMAX_OF_NYQUIST = 0.9
_DETRENDS = ("none", "constant", "linear")
_MIN_SAMPLES = 16
_DEFAULT_N_FREQS = 200


@dataclass(frozen=True, eq=False)  # eq=False: field-wise == on arrays would be ambiguous
class Spectrum:
    """An LPSD estimate; ``n_averages`` and ``segment_len`` tell how much to trust each point."""

    freq_hz: np.ndarray
    asd: np.ndarray  # one-sided amplitude spectral density, units/sqrt(Hz)
    n_averages: np.ndarray  # segments averaged at each frequency
    segment_len: np.ndarray  # samples per segment at each frequency


@dataclass(frozen=True)
class _Params:
    """The checked estimator settings shared by `lpsd` and `asd_at`."""

    n: int
    fs_hz: float
    k_des: int
    k_min: int
    overlap: float
    detrend: str

    def step(self, seg: int) -> int:
        """Samples between segment starts for segments of `seg` samples."""
        return max(1, round(seg * (1 - self.overlap)))

    def record_len(self, seg: int) -> int:
        """Samples that k_min segments of `seg` samples span."""
        return (self.k_min - 1) * self.step(seg) + seg

    @cached_property
    def max_segment_len(self) -> int:
        """Longest segment that still leaves k_min segments in the record."""
        seg = int(self.n / (1 + (1 - self.overlap) * (self.k_min - 1)))
        while seg > 0 and self.record_len(seg) > self.n:  # at most a few steps (rounding)
            seg -= 1
        return seg

    @property
    def fmin_hz(self) -> float:
        """Lowest frequency the record supports: _MIN_BIN cycles in the longest segment."""
        return _MIN_BIN * self.fs_hz / self.max_segment_len

    def segment_lengths(self, freqs_hz: np.ndarray, spacing: float) -> np.ndarray:
        """Segment length per frequency (Tröbs & Heinzel 2006, sec. 4).

        `spacing` is the ratio f[j+1]/f[j] of the log axis. The resolution r' = f*(spacing-1)
        would make neighbouring points independent; if that leaves fewer than k_des averages
        (r' below r'' = resolution with k_des segments), the geometric mean of r' and r'' trades
        resolution for averages; finally r is bounded so that k_min segments fit (r >= fs/L_max).
        """
        r_axis = freqs_hz * (spacing - 1)
        r_avg = self.fs_hz / self.n * (1 + (1 - self.overlap) * (self.k_des - 1))
        r = np.where(r_axis >= r_avg, r_axis, np.sqrt(r_axis * r_avg))
        seg = np.round(self.fs_hz / r)
        # At least _MIN_BIN cycles per segment (matters only for a very coarse axis).
        seg = np.maximum(seg, np.ceil(_MIN_BIN * self.fs_hz / freqs_hz))
        return np.minimum(seg, self.max_segment_len).astype(np.int64)

    def check_freqs(self, freqs_hz: np.ndarray) -> None:
        """Reject frequencies outside (fmin_hz, fs/2) with the record length they would need."""
        nyquist = self.fs_hz / 2
        if np.any(~np.isfinite(freqs_hz)) or np.any(freqs_hz >= nyquist):
            raise ValueError(f"frequencies must be finite and below Nyquist ({nyquist:g} Hz)")
        too_low = freqs_hz[freqs_hz < self.fmin_hz * (1 - 1e-12)]
        if too_low.size:
            f = float(too_low.min())
            if f <= 0:
                raise ValueError(f"frequencies must be positive, got {f:g} Hz")
            need = self.record_len(int(np.ceil(_MIN_BIN * self.fs_hz / f)))
            need_s = need / self.fs_hz
            raise ValueError(
                f"{f:g} Hz is too low for a record of {self.n} samples "
                f"({self.n / self.fs_hz:g} s; lowest usable {self.fmin_hz:.4g} Hz): it needs at "
                f"least {need} samples ({need_s:g} s = {need_s / 3600:.3g} h) for "
                f"{self.k_min} segments of {_MIN_BIN:g} periods with {self.overlap:g} overlap"
            )


def _params(
    x: ArrayLike, fs_hz: float, k_des: int, k_min: int, overlap: float, detrend: str
) -> tuple[np.ndarray, _Params]:
    """Validate inputs; return the data as contiguous float64, without its mean if detrending.

    Removing the mean keeps the per-segment sums small (a random walk or raw sensor counts can
    sit far from zero) and changes nothing else when every segment is detrended anyway.
    """
    data = np.asarray(x, dtype=np.float64)
    if data.ndim != 1:
        raise ValueError(f"x must be one-dimensional, got shape {data.shape}")
    if data.size < _MIN_SAMPLES:
        raise ValueError(f"x needs at least {_MIN_SAMPLES} samples, got {data.size}")
    if not np.all(np.isfinite(data)):
        bad = int(np.count_nonzero(~np.isfinite(data)))
        raise ValueError(f"x contains {bad} non-finite samples (NaN/inf); cut or fill gaps first")
    if not (np.isfinite(fs_hz) and fs_hz > 0):
        raise ValueError(f"fs_hz must be positive and finite, got {fs_hz!r}")
    if not 0 <= overlap < 1:
        raise ValueError(f"overlap must be in [0, 1), got {overlap!r}")
    if not 1 <= k_min <= k_des:
        raise ValueError(f"need 1 <= k_min <= k_des, got k_min={k_min}, k_des={k_des}")
    if detrend not in _DETRENDS:
        raise ValueError(f"detrend must be one of {_DETRENDS}, got {detrend!r}")
    p = _Params(data.size, float(fs_hz), k_des, k_min, overlap, detrend)
    if p.max_segment_len < 2 * _MIN_BIN:
        raise ValueError(f"{data.size} samples are too few for {k_min} segments")
    return (data if detrend == "none" else data - data.mean()), p


def _default_axis(p: _Params, fmin_hz: float | None, fmax_hz: float | None) -> tuple[float, float]:
    """Default axis: from the lowest supported frequency to 0.9 * Nyquist."""
    lo = p.fmin_hz if fmin_hz is None else float(fmin_hz)
    hi = _FMAX_OF_NYQUIST * p.fs_hz / 2 if fmax_hz is None else float(fmax_hz)
    p.check_freqs(np.array([lo, hi]))
    if not lo < hi:
        raise ValueError(f"need fmin_hz < fmax_hz, got {lo:g} >= {hi:g}")
    return lo, hi


def _cis(omega: float, n: int) -> np.ndarray:
    """exp(1j*omega*t) for t = 0..n-1 from ~2*sqrt(n) complex exponentials and one outer product.

    Transcendentals dominated the run time (the segment lengths of a 200-point axis add up to
    ~14 record lengths); the product of a coarse and a fine phasor costs one multiply instead.
    """
    width = int(np.ceil(np.sqrt(n)))
    fine = np.exp(1j * omega * np.arange(width))
    coarse = np.exp(1j * (omega * width) * np.arange(-(-n // width)))
    return np.multiply.outer(coarse, fine).ravel()[:n]


def _kernel(p: _Params, f_hz: float, seg: int) -> np.ndarray:
    """Detrended Hann-windowed cosine and sine at `f_hz`, as the rows of a (2, seg) array.

    Least-squares detrending is an orthogonal projection P, so <P x, w e> = <x, P(w e)>:
    detrending the kernel once per frequency equals detrending every segment.
    """
    cis = _cis(2 * np.pi * f_hz / p.fs_hz, seg)
    cis *= 0.5 - 0.5 * _cis(2 * np.pi / seg, seg).real  # periodic Hann, as scipy's welch
    kern = np.stack((cis.real, cis.imag))
    if p.detrend != "none":
        kern -= kern.mean(axis=1, keepdims=True)
    if p.detrend == "linear":
        tc = np.arange(seg) - (seg - 1) / 2
        kern -= np.outer(np.einsum("ij,j->i", kern, tc) / (seg * (seg**2 - 1) / 12), tc)
    return kern


def _psd_at(xp: np.ndarray, p: _Params, f_hz: float, seg: int) -> tuple[float, int]:
    """PSD at one frequency from all segments of length `seg`, and the number of segments.

    Segments start every `step` samples (centred in the record). Viewing the data as rows of
    `step` samples and cutting the kernel into chunks of `step` samples turns all segment DFTs
    into a few matrix products: segment k is rows k, k+1, ... times chunks 0, 1, ...
    `xp` is the data zero-padded by >= step samples so that the last row is complete.

    The products use einsum, not BLAS: these are matrix-vector shaped, memory-bound products,
    and multithreaded OpenBLAS slowed them down ~5x on a loaded 2-core machine.
    """
    step = p.step(seg)
    n_seg = (p.n - seg) // step + 1
    n_chunks = -(-seg // step)
    start = (p.n - seg - (n_seg - 1) * step) // 2
    rows = xp[start : start + (n_seg - 1 + n_chunks) * step].reshape(-1, step)
    kern = _kernel(p, f_hz, seg)
    dft = np.zeros((n_seg, 2))
    for j in range(n_chunks):
        chunk = kern[:, j * step : (j + 1) * step]
        dft += np.einsum("ij,kj->ik", rows[j : j + n_seg, : chunk.shape[1]], chunk)
    power = np.einsum("ij,ij->", dft, dft) / n_seg
    s2 = 3 * seg / 8  # sum of the periodic Hann window squared
    return 2 * power / (p.fs_hz * s2), n_seg


def _spectrum(xc: np.ndarray, p: _Params, freqs_hz: np.ndarray, spacing: float) -> Spectrum:
    """The shared per-frequency loop of `lpsd` and `asd_at`."""
    segs = p.segment_lengths(freqs_hz, spacing)
    xp = np.concatenate((xc, np.zeros(p.step(int(segs.max())))))
    psd = np.empty(freqs_hz.size)
    n_avg = np.empty(freqs_hz.size, dtype=np.int64)
    for i, (f, seg) in enumerate(zip(freqs_hz, segs, strict=True)):
        psd[i], n_avg[i] = _psd_at(xp, p, float(f), int(seg))
    return Spectrum(freqs_hz, np.sqrt(psd), n_avg, segs)


def lpsd(
    x: ArrayLike,
    fs_hz: float,
    *,
    fmin_hz: float | None = None,
    fmax_hz: float | None = None,
    n_freqs: int = _DEFAULT_N_FREQS,
    k_des: int = 100,
    k_min: int = 2,
    overlap: float = 0.5,
    detrend: str = "linear",
) -> Spectrum:
    """One-sided ASD of `x` at `n_freqs` log-spaced frequencies (Tröbs & Heinzel's LPSD).

    Defaults: fmin_hz is the lowest frequency with k_min segments of >= 2 periods each,
    2*fs/L_max with L_max ~ N/(1 + (1-overlap)*(k_min-1)), i.e. 3/T for a record of T seconds
    with 50 % overlap and k_min=2; fmax_hz is 0.9 * fs/2.
    `detrend` ("linear", "constant", "none") is applied per segment; linear keeps the leakage of
    steep red spectra (drifts, random walks) out of the low end.
    """
    if n_freqs < 2:
        raise ValueError(f"n_freqs must be >= 2, got {n_freqs}")
    xc, p = _params(x, fs_hz, k_des, k_min, overlap, detrend)
    lo, hi = _default_axis(p, fmin_hz, fmax_hz)
    spacing = (hi / lo) ** (1 / (n_freqs - 1))
    freqs = lo * spacing ** np.arange(n_freqs)
    freqs[-1] = hi
    return _spectrum(xc, p, freqs, spacing)


def asd_at(
    x: ArrayLike,
    fs_hz: float,
    freqs_hz: Sequence[float],
    *,
    k_des: int = 100,
    k_min: int = 2,
    overlap: float = 0.5,
    detrend: str = "linear",
) -> np.ndarray:
    """One-sided ASD at exactly `freqs_hz`, e.g. to quote noise at 0.1, 1 and 10 mHz.

    Each frequency gets the segment length `lpsd` with its default axis would give it, so the
    result equals ``lpsd(x, fs_hz, ...)`` wherever a frequency is on that axis. Raises
    ValueError, naming the record length needed, for a frequency the record is too short for.
    """
    xc, p = _params(x, fs_hz, k_des, k_min, overlap, detrend)
    freqs = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    if freqs.ndim != 1 or freqs.size == 0:
        raise ValueError("freqs_hz must be a non-empty sequence of frequencies")
    p.check_freqs(freqs)
    lo, hi = _default_axis(p, None, None)
    spacing = (hi / lo) ** (1 / (_DEFAULT_N_FREQS - 1))
    return _spectrum(xc, p, freqs, spacing).asd


#: the paper's frequencies, where `sim`, `replay` and the reports quote an ASD
REPORT_FREQS_HZ = (1e-4, 1e-3, 1e-2)


def asd_or_none(x: ArrayLike, fs_hz: float,
                freqs_hz: Sequence[float] = REPORT_FREQS_HZ) -> list[float | None]:
    """ASD at each frequency; None where the record is too short to reach it (a report
    says "n/a" there rather than refusing the whole run)."""
    out: list[float | None] = []
    for f in freqs_hz:
        try:
            out.append(float(asd_at(x, fs_hz, [f])[0]))
        except ValueError:
            out.append(None)
    return out
