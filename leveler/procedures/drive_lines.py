"""Drive lines in a recording: where a sine or square drive of the actuator ran, and the
transfer function from command to reading at each, with its uncertainty.

A lab's stepped sine sweep or square modulation leaves lines in the command that come and go.
They are found one at a time, strongest first (as CLEAN finds point sources): the highest peak
of the command's periodogram over its local floor is put in time by demodulating the command
at its frequency, the span kept where its amplitude holds steady, its frequency refined there,
the sinusoid (and its harmonics) taken out of the command, and the search goes on until the
candidates are no longer lines (LINE_Z). Each line's reading is then fitted on its span with
every other line running there (a square's harmonics), a polynomial for the slow drift that
dominates a real tiltmeter's record and, given the pendulum's resonance, its ringing; the
uncertainty is what the same fit finds in the residual beside the line, so a drifting,
coloured record is not credited with white-noise precision.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter
from scipy.optimize import minimize_scalar

CANDIDATE_RATIO = 10.0  # a periodogram peak over its local median worth a look
LINE_Z = 100.0  # a line's power on its span over the residual's per frequency (20 dB)
MAX_REJECTED = 8  # candidates in a row that were no line: the search is over
FLOOR_BINS = 257  # the running median's width in periodogram bins
ENVELOPE_CYCLES = 3.0  # demodulation window in cycles of the line
STEADY_CYCLES = 2.0  # windows in which a line's amplitude must hold
STEADY_TOL = 0.25  # how far (relative) from the span's median amplitude it may stray
MIN_CYCLES = 3.0  # a span shorter than this many cycles is not a drive line
MIN_SAMPLES = 64  # nor one of fewer samples
SETTLE_FRACTION = 0.25  # of each span, left for the pendulum to ring down
DRIFT_ORDER = 3  # polynomial for the slow drift under each span
MAX_LINES = 60  # fundamentals
MAX_HARMONIC = 31  # a line's harmonics taken out of the command with it
MAX_HARMONIC_LINE = 9  # and kept as lines of their own up to this one
HARMONIC_MIN_REL = 0.05  # of the fundamental's amplitude to be a line (a square's 9th: 11 %)
RESOLUTION = 1e-6  # of the command's RMS: what a residual is taken to hold at least
MIN_LINE_REL = 1e-3  # of the strongest line's amplitude: less is a subtraction's leftover
NYQUIST_FRACTION = 0.8  # harmonics above this fraction of the Nyquist frequency are left


@dataclass(frozen=True, slots=True)
class DriveLine:
    """One line of the drive on its span: command and reading as complex amplitudes
    (x(t) = Re(X exp(i 2 pi f t)), t from the log's start)."""

    frequency_hz: float
    start_s: float  # the settled span the reading was fitted on
    end_s: float
    command_v: complex
    reading_m: complex
    reading_sigma_m: float  # 1 sigma of each quadrature of `reading_m`
    harmonic: int = 1  # n of a square's n-th harmonic
    waveform: str = "sine"  # "square" when harmonics run with it on its span

    @property
    def transfer_m_per_v(self) -> complex:
        return self.reading_m / self.command_v

    @property
    def transfer_sigma_m_per_v(self) -> float:
        return self.reading_sigma_m / abs(self.command_v)

    @property
    def snr(self) -> float:
        return abs(self.reading_m) / self.reading_sigma_m


@dataclass(frozen=True, slots=True)
class _Span:
    frequency_hz: float
    a: int  # first sample
    b: int  # one past the last
    harmonic: int = 1  # n of a line running at n times another's frequency on its span


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[a, b) of each run of True."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def _peak(r: np.ndarray, dt: float) -> tuple[float, float]:
    """(frequency, power over the local floor) of the strongest line-like peak in `r`: the
    highest periodogram bin among those CANDIDATE_RATIO over their local median (the highest
    of all is a red noise's lowest bin; the highest ratio a square's faint far harmonic)."""
    n = len(r)
    p = np.abs(np.fft.rfft(r)) ** 2  # no taper: it would hide a line at either end
    floor = median_filter(p, size=FLOOR_BINS, mode="nearest")
    ratio = p / np.maximum(floor, 1e-12 * float(p.max()) + np.finfo(float).tiny)
    ratio[:max(3, math.ceil(MIN_CYCLES))] = 0.0  # fewer cycles than a line needs
    ratio[int(NYQUIST_FRACTION * (len(p) - 1)):] = 0.0  # a sinusoid there is barely sampled
    peaky = ratio >= CANDIDATE_RATIO
    if not peaky.any():
        return math.nan, 0.0
    k = int(np.argmax(np.where(peaky, p, -1.0)))
    if 0 < k < len(p) - 1:  # a parabola through the log powers: between bins
        lo, mid, hi = np.log(p[k - 1:k + 2] + np.finfo(float).tiny)
        den = lo - 2 * mid + hi
        shift = 0.5 * (lo - hi) / den if den < 0 else 0.0
    else:
        shift = 0.0
    return (k + shift) / (n * dt), float(ratio[k])


def _span(r: np.ndarray, t: np.ndarray, f: float, dt: float) -> tuple[int, int]:
    """Roughly where the line at f runs: the run of its demodulated envelope above half its
    peak (`_steady` then finds where it really is steady)."""
    width = min(max(round(ENVELOPE_CYCLES / (f * dt)), 8), len(r))
    z = np.concatenate([[0], np.cumsum(r * np.exp(-2j * np.pi * f * t))])
    lo = np.clip(np.arange(len(r)) - width // 2, 0, len(r))
    env = np.abs(z[np.minimum(lo + width, len(r))] - z[lo]) / width  # moving mean, centred
    top = int(np.argmax(env))
    for a, b in _runs(env > 0.5 * env[top]):
        if a <= top < b:
            return a, b
    return top, top + 1  # pragma: no cover - the peak is in its own run


def _steady(r: np.ndarray, t: np.ndarray, f: float, a: int, b: int,
            dt: float) -> tuple[int, int]:
    """The run of STEADY_CYCLES windows around [a, b) where the line's complex amplitude stays
    within STEADY_TOL of its median: a neighbouring step at a close frequency turns its phase
    (3.03 and 3.51 mHz merged in one envelope), a pause or a step's edge shrinks it, and a
    span reaching into either would put a piece of the line there when it is taken out."""
    width = max(round(STEADY_CYCLES / (f * dt)), 8)
    lo = max(a - 2 * width, 0)
    starts = np.arange(lo, min(b + 2 * width, len(r)) - width + 1, width)
    if len(starts) == 0:
        return a, b
    idx = starts[:, None] + np.arange(width)[None, :]
    c = 2 * np.mean(r[idx] * np.exp(-2j * np.pi * f * t[idx]), axis=1)
    inside = (starts >= a) & (starts + width <= b)
    pick = c[inside] if inside.any() else c
    ref = complex(np.median(pick.real), np.median(pick.imag))
    ok = np.abs(c - ref) < STEADY_TOL * abs(ref)
    runs = _runs(ok)
    if not runs:
        return a, a
    first, last = max(runs, key=lambda jk: jk[1] - jk[0])
    return int(starts[first]), int(starts[last - 1] + width)


def _refine(r: np.ndarray, t: np.ndarray, f: float) -> float:
    """The frequency that maximises the line's power on its span."""
    span = t[-1] - t[0]
    x = r - r.mean()

    def neg_power(fr: float) -> float:
        return -abs(np.dot(x, np.exp(-2j * np.pi * fr * t))) ** 2

    res = minimize_scalar(neg_power, bounds=(f - 1 / span, f + 1 / span), method="bounded",
                          options={"xatol": 1e-4 / span})
    return float(res.x)


def _design(t: np.ndarray, freqs: list[float]) -> np.ndarray:
    """Drift polynomial (Legendre on the span) and a cosine and sine per frequency."""
    x = 2 * (t - t[0]) / max(t[-1] - t[0], 1e-12) - 1
    cols = [np.polynomial.legendre.legval(x, np.eye(DRIFT_ORDER + 1)[j])
            for j in range(DRIFT_ORDER + 1)]
    for f in freqs:
        w = 2 * np.pi * f * t
        cols += [np.cos(w), np.sin(w)]
    return np.column_stack(cols)


def _amplitudes(coef: np.ndarray, nfreq: int) -> list[complex]:
    """Complex amplitudes X of x = Re(X e^{iwt}) = Re(X) cos - Im(X) sin."""
    c = coef[DRIFT_ORDER + 1:]
    return [complex(c[2 * j], -c[2 * j + 1]) for j in range(nfreq)]


def _noise_sigma(res: np.ndarray, t: np.ndarray, f: float) -> float:
    """1 sigma of one quadrature of a fitted amplitude at f: the RMS of what the same fit
    (sinusoid and drift polynomial) finds in the residual at the 14 frequencies 2 to 8 of
    the span's bins away from f on either side. Under a red drift the estimator's noise
    is the spectrum leaking in through its sidelobes, not the level at f (a periodogram's
    median there put the low steps of an independent sweep 2-3.6 of their sigmas off)."""
    span = t[-1] - t[0] + (t[1] - t[0])
    probes = [f + k / span for k in (*range(-8, -1), *range(2, 9)) if f + k / span > 0]
    power = []
    for fp in probes:
        design = _design(t, [fp])
        coef, *_ = np.linalg.lstsq(design, res, rcond=None)
        power.append(float(coef[-2] ** 2 + coef[-1] ** 2))
    return math.sqrt(0.5 * float(np.mean(power)))


def _take(r: np.ndarray, t: np.ndarray, f: float, seg: slice,
          floor: float) -> tuple[float, float]:
    """Fit a sinusoid at f on `seg` and take it out of `r`; (its amplitude, its z: its power
    over what the span's residual leaves per frequency, that residual's variance at least
    `floor`: a synthesiser's clean sine leaves only rounding, and its z is then noise)."""
    design = _design(t[seg], [f])
    coef, *_ = np.linalg.lstsq(design, r[seg], rcond=None)
    rest = r[seg] - design @ coef
    power = 0.5 * float(coef[DRIFT_ORDER + 1] ** 2 + coef[DRIFT_ORDER + 2] ** 2)
    r[seg] -= design[:, DRIFT_ORDER + 1:] @ coef[DRIFT_ORDER + 1:]
    return math.sqrt(2 * power), power * len(rest) / max(float(np.var(rest)), floor)


def _known(spans: list[_Span], f: float, a: int, b: int, dt: float) -> bool:
    """A line at f on [a, b) that is one already found: what its subtraction left over."""
    return any(abs(f - s.frequency_hz) < 2 / ((b - a) * dt)
               and min(b, s.b) - max(a, s.a) > 0.5 * (b - a) for s in spans)


def _search(u: np.ndarray, t: np.ndarray, dt: float, usable: np.ndarray) -> list[_Span]:
    """The command's lines, strongest first, each with its span.

    A candidate is the periodogram's highest line-like peak (`_peak`); it is a line when, on
    its span, its power stands LINE_Z above what the span's residual leaves per frequency (a
    drive's sinusoid stands thousands above; noise's best peak about ln of the bins). The
    floor of a stepped sweep's periodogram is the other steps' leakage, not noise, so the
    floor only picks candidates and the span's own residual judges them. What is left of a
    line found already (its frequency refined to a span's precision, not exactly) or below a
    thousandth of the strongest is taken out but is no line of its own; a span too short to
    hold MIN_CYCLES (a square's edge that a span missed) is blanked. A line's harmonics
    on its span (a square's, a pulse's) are taken with it, and the first few are lines where
    they stand LINE_Z above too."""
    r = np.where(usable, u - np.median(u[usable]), 0.0)
    floor = (RESOLUTION * float(np.std(r)) + np.finfo(float).tiny) ** 2
    spans: list[_Span] = []
    rejected = found = 0
    strongest = 0.0
    for _ in range(3 * MAX_LINES):
        f, ratio = _peak(r, dt)
        if ratio < CANDIDATE_RATIO or found >= MAX_LINES or rejected >= MAX_REJECTED:
            break
        a, b = _span(r, t, f, dt)
        runs = _runs(usable[a:b])  # the loop's closed parts cut a span
        if runs:
            c, d = max(runs, key=lambda cd: cd[1] - cd[0])
            a, b = a + c, a + d
        if (b - a) * dt * f >= MIN_CYCLES and b - a >= MIN_SAMPLES:
            f = _refine(r[a:b], t[a:b], f)
            a0, b0 = a, b
            a, b = _steady(r, t, f, a, b, dt)
            a, b = max(a, a0), min(b, b0)
        if (b - a) * dt * f < MIN_CYCLES or b - a < MIN_SAMPLES:  # a span's edge: blanked
            rejected += not np.any(r[a:b])  # nothing left to blank: no progress
            r[a:b] = 0.0
            continue
        f = _refine(r[a:b], t[a:b], f)
        amplitude, z = _take(r, t, f, slice(a, b), floor)
        if z < LINE_Z or amplitude < MIN_LINE_REL * strongest or _known(spans, f, a, b, dt):
            rejected += 1
            continue
        strongest = max(strongest, amplitude)
        rejected, found = 0, found + 1
        spans.append(_Span(f, a, b))
        for n in range(2, MAX_HARMONIC + 1):
            if n * f > NYQUIST_FRACTION / (2 * dt):
                break
            size, z = _take(r, t, n * f, slice(a, b), floor)
            if z >= LINE_Z and size >= HARMONIC_MIN_REL * amplitude and n <= MAX_HARMONIC_LINE:
                spans.append(_Span(n * f, a, b, n))
    return spans


def free_ringing(t: np.ndarray, f0_hz: float, q: float) -> list[np.ndarray]:
    """The pendulum's free motion from the span's start: e^(-s t) cos and sin of its
    resonance (two real decays when it is overdamped)."""
    w0, t = 2 * np.pi * f0_hz, t - t[0]
    if q > 0.5:
        s, wd = w0 / (2 * q), w0 * math.sqrt(1 - 1 / (4 * q * q))
        return [np.exp(-s * t) * np.cos(wd * t), np.exp(-s * t) * np.sin(wd * t)]
    root = w0 * math.sqrt(1 / (4 * q * q) - 1)
    return [np.exp((-w0 / (2 * q) + root) * t), np.exp((-w0 / (2 * q) - root) * t)]


def drive_spans(t_s: np.ndarray, u_v: np.ndarray,
                usable: np.ndarray | None = None) -> list[_Span]:
    """Where each drive line of the command runs (`_search`), for `measure` to read."""
    t = np.asarray(t_s, float) - float(t_s[0])
    usable = np.ones(len(t), bool) if usable is None else np.asarray(usable, bool)
    return _search(np.asarray(u_v, float), t, float(np.median(np.diff(t))), usable)


def measure(t_s: np.ndarray, u_v: np.ndarray, y_m: np.ndarray, spans: list[_Span],
            settle_fraction: float = SETTLE_FRACTION,
            ringing: tuple[float, float] | None = None) -> list[DriveLine]:
    """Each span's line in the command and the reading, by frequency.

    The reading is fitted on the span less its first `settle_fraction` (the pendulum rings
    after each change), with every other line running there, the drift polynomial and, when
    `ringing` gives the pendulum's (resonance, Q), its free motion: then the span can be
    used whole. The uncertainty is what the same fit finds in the residual beside the line
    (`_noise_sigma`), scaled by the fit's own normal matrix, so a line sharing its span with
    a collinear one (its own ringing near the resonance) is not credited with an orthogonal
    line's precision."""
    t = np.asarray(t_s, float) - float(t_s[0])
    u, y = np.asarray(u_v, float), np.asarray(y_m, float)
    dt = float(np.median(np.diff(t)))
    with_harmonics = {(s.a, s.b) for s in spans if s.harmonic > 1}
    lines = []
    for s in spans:
        a = s.a + int(settle_fraction * (s.b - s.a))
        if (s.b - a) * dt * s.frequency_hz < MIN_CYCLES:
            continue
        seg = slice(a, s.b)
        # every line running on most of this span is fitted with it
        others = [o.frequency_hz for o in spans if o is not s
                  and min(o.b, s.b) - max(o.a, a) > 0.5 * (s.b - a)]
        design = _design(t[seg], [s.frequency_hz, *others])
        if ringing is not None:
            design = np.column_stack([design, *free_ringing(t[seg], *ringing)])
        cu, *_ = np.linalg.lstsq(design, u[seg], rcond=None)
        cy, *_ = np.linalg.lstsq(design, y[seg], rcond=None)
        res = y[seg] - design @ cy
        inv = np.linalg.pinv(design.T @ design)
        j = DRIFT_ORDER + 1
        inflation = math.sqrt(0.25 * (s.b - a) * (inv[j, j] + inv[j + 1, j + 1]))
        lines.append(DriveLine(
            s.frequency_hz, float(t_s[a]), float(t_s[s.b - 1]), _amplitudes(cu, 1)[0],
            _amplitudes(cy, 1)[0], _noise_sigma(res, t[seg], s.frequency_hz) * inflation,
            s.harmonic, "square" if (s.a, s.b) in with_harmonics else "sine"))
    return sorted(lines, key=lambda line: line.frequency_hz)


def drive_lines(t_s: np.ndarray, u_v: np.ndarray, y_m: np.ndarray,
                usable: np.ndarray | None = None,
                settle_fraction: float = SETTLE_FRACTION,
                ringing: tuple[float, float] | None = None) -> list[DriveLine]:
    """Every drive line of the command `u_v` with the reading's response to it, by frequency
    (`drive_spans`, then `measure`).

    `usable`: samples the search may use (the loop open: in a closed loop the command is the
    controller's answer to the reading, not a drive)."""
    return measure(t_s, u_v, y_m, drive_spans(t_s, u_v, usable), settle_fraction, ringing)


__all__ = ["DriveLine", "drive_lines", "drive_spans", "measure"]
