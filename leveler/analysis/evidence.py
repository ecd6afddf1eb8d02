"""What a replay residual says about the model, in the terms effects ask for their guesses.

Each effect's `guesses` reads this: spectral lines standing out of the fitted noise
spectrum, the best phase or lag from a small grid with the amplitude solved linearly
(coherence with an input, in effect), how far the command moved (hysteresis needs
reversals), and whether the raw readings sit on a lattice coarser than the model's ADC.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.ndimage import median_filter
from scipy.signal import czt

from leveler.analysis.bump import Spectra
from leveler.analysis.nuisance import Nuisance, with_shapes
from leveler.analysis.predict import (
    Measured,
    Predictor,
    actuator_excited,
    modulation_v,
)
from leveler.analysis.recalibrate import PULL_LIMIT
from leveler.analysis.whittle import ENBW_BINS, EXTRAPOLATED_BINS, Blocks, hann
from leveler.sim.effects import Effect

_LINE_Z = 12.0  # a line must stand this far (in ln p-value) above the noise spectrum
#: how a line's power is spread over neighbouring bins for `line_deviance` (its sum is 1):
#: a period that wanders by a few per cent moves a line's harmonics by a bin or two
LINE_SPREAD = np.array([1.0, 2.0, 3.0, 2.0, 1.0]) / 9.0
#: bins over which the noise level around a line is taken (a running median)
LINE_LEVEL_BINS = 31
#: the fewest cycles in a block that make a line
LINE_MIN_CYCLES = 8
#: the lowest bin of the longest block a periodic disturbance's fundamental is guessed at
GUESS_MIN_BINS = 4
#: a bump's mean z must stand this many standard errors above 1 (searched over some
#: ten thousand overlapping bands of a 3 h log: well beyond chance)
BUMP_SIGMA = 8.0
#: bins either side of a line that `line_deviance` weighs, and how far beside it the
#: line is tried, to see that the power is on it
LINE_WINDOW = 4
LINE_OFFSET_BINS = 3
#: a modulation whose largest moves, in this share of its samples, make most of its
#: travel steps the actuator (a square's edges), where a sweep's are spread (a triangle's)
STEP_SHARE = 0.05


class Evidence:
    def __init__(self, meas: Measured, pred: Predictor, blocks: Blocks,
                 nuisance: Nuisance, part_gains: list[np.ndarray] | None = None) -> None:
        """`part_gains`: `nuisance.part_gains`, solved out for the families that must show
        more than a gain (`Effect.beyond_part_gains`) where their evidence is weighed."""
        self.meas = meas
        self.part_gains = part_gains or []
        self.sig = meas.sig
        self.pred = pred
        self.w = blocks
        self.nuisance = nuisance
        # Lines are read off the longest block alone: one frequency grid, the finest.
        self.spec = blocks.longest
        self.residual = meas.y_m - pred.base.y_m
        self.white = blocks.whiten(self.residual)
        self._z = self.spec.zscores(self.residual)

    def fmin_hz(self) -> float:
        """Lowest frequency a periodic disturbance is looked for at: LINE_MIN_CYCLES
        cycles in the whole log (a waveform is fitted in phase over all of it), and
        GUESS_MIN_BINS bins into the longest block, whose spectrum the lines are read
        from (the lowest bins are where unmodeled drift lives)."""
        span_s = self.sig.t_s[-1] - self.sig.t_s[0] if len(self.sig.t_s) > 1 else 0.0
        block_s = self.spec.n * self.sig.dt_s
        return max(LINE_MIN_CYCLES / span_s if span_s > 0 else 0.0, GUESS_MIN_BINS / block_s)

    def bin_hz(self) -> float:
        """The frequency grid's step (of the longest block, where lines are read)."""
        return 1.0 / (self.spec.n * self.sig.dt_s)

    def peaks(self, fmin_hz: float, fmax_hz: float, most: int = 3) -> list[float]:
        """Frequencies of the strongest lines in [fmin, fmax], harmonics of a stronger line
        left out (a sawtooth is one disturbance, not ten): up to `most` from each block's
        spectrum, the longest block's first. A slow disturbance that the closed loop
        holds down shows only in the open loop's shorter block: a 748 s sawtooth stood
        at z = 296 there and at nothing in the closed loop's, and was never fitted."""
        found: list[float] = []
        for part in sorted(self.w.parts, key=lambda p: -p.n):
            z = self._z if part is self.spec else part.zscores(self.residual)
            found += self._lines(part.f_hz, z, fmin_hz, fmax_hz, most, found)
        return sorted(set(found))

    def _lines(self, f: np.ndarray, z: np.ndarray, fmin_hz: float, fmax_hz: float,
               most: int, known: list[float]) -> list[float]:
        """Up to `most` lines of one block's z-scores (`f`, `z`) that are neither a line
        in `known` nor a harmonic of one."""
        df = f[1] - f[0]
        threshold = math.log(len(z)) + _LINE_Z
        idx = np.flatnonzero((f >= fmin_hz) & (f <= fmax_hz) & (z > threshold))
        found: list[float] = []

        def harmonic(fx: float) -> bool:  # of a line already found (refined to ~df/10)
            return any(abs(fx - h * g) <= df * (2.0 + 0.1 * h)
                       for g in known + found for h in range(1, int(fx / g) + 2))

        for k in idx[np.argsort(z[idx])[::-1]]:
            if harmonic(float(f[k])):
                continue
            fk = _refine(f, z, _fundamental(f, z, int(k), threshold, fmin_hz))
            if harmonic(fk):
                continue
            found.append(fk)
            if len(found) >= most:
                break
        return found

    def bumps(self, fmin_hz: float, fmax_hz: float, most: int = 2) -> list[float]:
        """Centres of bands where the residual's power stands above the noise spectrum on
        average, though perhaps in no single bin (a mode rung by noise: a bump, not a
        line): the mean z over 16 to 1,024 bins, BUMP_SIGMA standard errors above 1."""
        f, z = self.spec.f_hz, self._z
        inside = (f >= fmin_hz) & (f <= fmax_hz)
        found: list[tuple[float, float]] = []
        for m in (16, 64, 256, 1024):
            if np.count_nonzero(inside) < 4 * m:
                break
            mean = np.convolve(z, np.ones(m) / m, mode="same")
            score = np.where(inside, (mean - 1.0) * math.sqrt(m), 0.0)
            for k in np.argsort(score)[::-1][:50]:
                if score[k] > BUMP_SIGMA:
                    found.append((float(score[k]), float(f[k])))
        found.sort(reverse=True)
        out: list[float] = []
        for _, fk in found:
            if all(abs(math.log(fk / g)) > 0.2 for g in out):
                out.append(fk)
            if len(out) >= most:
                break
        return out

    def spectra(self) -> Spectra:
        """The blocks' periodograms of the residual with their noise spectra (for a mode
        rung by its own noise)."""
        return Spectra(self.w, self.residual)

    def contribution(self, fx: Effect) -> np.ndarray:
        return self.pred.with_candidate(fx) - self.pred.base.y_m

    def best_linear(self, starts: Sequence[Effect], amp_key: str | None, keep: int) -> list[Effect]:
        """Each start with its amplitude solved by whitened least squares (or as it is if
        amp_key is None); the `keep` that leave the smallest cost."""
        scored: list[tuple[float, Effect]] = []
        for fx in starts:
            if amp_key is None:
                e = self.w.whiten(self.meas.y_m - self.pred.with_candidate(fx))
                scored.append((float(e @ e), fx))
                continue
            unit = fx.scale(amp_key)
            c = self.w.whiten(self.contribution(fx.replace(**{amp_key: unit})))
            cc = float(c @ c)
            if not cc > 0 or not math.isfinite(cc):
                continue
            lo, hi = fx.bounds(amp_key)
            beta = min(max(float(c @ self.white) / cc * unit, lo), hi) / unit
            e = self.white - beta * c
            scored.append((float(e @ e), fx.replace(**{amp_key: beta * unit})))
        scored.sort(key=lambda s: s[0])
        return [fx for _, fx in scored[:keep]]

    def best_phase(self, template: Effect, phase_key: str, period_s: float,
                   amp_key: str, steps: int = 12) -> list[Effect]:
        starts = [template.replace(**{phase_key: period_s * k / steps}) for k in range(steps)]
        return self.best_linear(starts, amp_key, keep=1)

    def command_spread_v(self) -> float:
        """How far the actuator voltage moved (5th to 95th percentile) over the blocks."""
        u = self.meas.u_v[self.w.index()]
        return float(np.percentile(u, 95) - np.percentile(u, 5))

    def command_blocks_v(self) -> list[np.ndarray]:
        """The actuator voltage, block by block (each within one part of the log)."""
        return self._spans(self.meas.u_v)

    def block_gains(self, fx: Effect) -> list[float]:
        """What the effect takes off the whitened cost in each block (none below 0), the
        recalibrated knobs solved out in each: where its evidence lies. (Without them an
        offset the effect adds would cost it everything in the lowest bins.)"""
        after = self.meas.y_m - self.pred.with_candidate(fx)
        gains = []
        for p in self.w.parts:
            proj = self.nuisance.on(p)
            cost = (with_shapes(proj, p, self.part_gains) if fx.beyond_part_gains
                    else proj).cost
            gains.append(max(0.0, cost(p.whiten(self.residual)) - cost(p.whiten(after))))
        return gains

    def lattice(self) -> tuple[float, float] | None:
        """(step, offset) if the readings sit on a lattice clearly coarser than the model's
        ADC count; None otherwise (`find_lattice`)."""
        return find_lattice(self._spans(self.meas.y_m), self.pred.params.sensor.lsb_m,
                            self._spans(self.pred.base.y_m))

    def lattice_deviance(self, step_m: float) -> float:
        """The score test of the readings on the blocks for a lattice of `step_m`
        (`lattice_deviance`)."""
        return lattice_deviance(self._spans(self.meas.y_m), self.pred.params.sensor.lsb_m,
                                step_m, self._spans(self.pred.base.y_m))

    def readings_on_levels(self, step_m: float) -> list[tuple[int, float]]:
        """`readings_on_levels` (the function) of each block."""
        return [readings_on_levels(y, step_m) for y in self._spans(self.meas.y_m)]

    def line_deviance(self, fx: Effect, f0_hz: float, harmonics: int) -> float:
        """Evidence for `fx`'s lines (its first `harmonics` of `f0_hz`), not its waveform,
        on the blocks: Whittle's likelihood of the residual's periodogram with the
        effect's own power added, smoothed over LINE_SPREAD (a wandering period broadens
        a line), against the noise alone, in a window of LINE_WINDOW bins either side of
        each line; 2 ln of the ratio, corrected for the window's correlated bins.
        Negative where the effect predicts power the residual does not have.

        Each bin is taken over the level of the bins around it, not over the smooth
        spectrum: where that spectrum misses the red noise by a factor of 2, a line would
        be found in any power there (an 877 s "disturbance" in a log without its
        temperature: held-out evidence 3,503). A line counts only where the power is on
        it rather than LINE_OFFSET_BINS beside it, not where a stronger line's skirt
        reaches (a 173 s sawtooth scored 752 on a 240 s one's lines without that), and
        only with at least LINE_MIN_CYCLES cycles in the block, as for `fmin_hz`."""
        change = self.pred.with_candidate(fx) - self.pred.base.y_m
        total = 0.0
        for part in self.w.parts:
            first = max(EXTRAPOLATED_BINS, LINE_MIN_CYCLES)
            z = (np.abs(part.transform(self.residual) * part.weight) ** 2)[first:]
            power = (np.abs(part.transform(change) * part.weight) ** 2)[first:]
            level = np.maximum(median_filter(z, LINE_LEVEL_BINS, mode="reflect")
                               / math.log(2.0), 1e-300)
            z = z / level
            spread = np.convolve(power, LINE_SPREAD, mode="same")

            def gain(lo: int, hi: int, shift: int, z: np.ndarray = z,
                     level: np.ndarray = level, spread: np.ndarray = spread) -> float:
                mu = 1.0 + spread[lo - shift:hi + 1 - shift] / level[lo:hi + 1]
                return float(np.sum(z[lo:hi + 1] * (1.0 - 1.0 / mu) - np.log(mu)))

            df = float(part.f_hz[1])
            s = LINE_OFFSET_BINS
            for h in range(1, harmonics + 1):
                centre = h * f0_hz / df - first
                # the window holds the line tried beside it too
                lo, hi = math.floor(centre) - LINE_WINDOW - s, math.ceil(centre) + LINE_WINDOW + s
                if lo - s < 0 or hi + s >= len(z):
                    continue
                here = gain(lo, hi, 0)
                beside = max(gain(lo, hi, -s), gain(lo, hi, s))
                total += here if here > beside else min(here, 0.0)
        return 2.0 * total / ENBW_BINS

    def cooler_hz(self) -> float | None:
        """The modelled cooler's fundamental; None if the model has no cooler."""
        co = self.pred.params.cooler
        return 1.0 / co.period_s if co.peak_to_peak_rad > 0 else None

    def modulation_hz(self) -> float | None:
        """The fundamental of what moved the actuator besides feedback (`excitation_v`):
        its strongest line (`modulation_hz`); None without one, or when it moved the
        actuator too little to be seen at the sensor (`actuator_excited`)."""
        if not hasattr(self, "_modulation"):
            exc = modulation_v(self.meas)
            moved = exc is None or actuator_excited(self.meas, self.pred, slice(None))
            self._modulation = (modulation_hz(exc[_moving(exc)], self.sig.dt_s)
                                if moved and exc is not None else None)
        return self._modulation

    def modulation_span_s(self) -> float:
        """How long the excitation moved the actuator [s] (first to last of its changes
        above a thousandth of its largest): the span over which the lines of a
        modulation can be told from those of anything else."""
        exc = modulation_v(self.meas)
        if exc is None:
            return 0.0
        span = _moving(exc)
        return (span.stop - span.start) * self.sig.dt_s

    @property
    def pull_limit(self) -> float:
        """The pull (offset / sigma) the recalibration accepts as a calibration."""
        return PULL_LIMIT

    def sensor_path_pull(self, gain_error: float) -> float | None:
        """The pull of the sensor path from nominal with `gain_error` on top of the
        recalibrated one (the knob scales the sensor arm); None if no tolerance is stated."""
        sigma = self.meas.config.plant.uncertainty.sensor_path_rel
        if not sigma > 0:
            return None
        path = (self.pred.params.pendulum.sensor_arm_m
                / self.meas.config.plant.pendulum.sensor_arm_m)
        return (path * (1.0 + gain_error) - 1.0) / sigma

    def _spans(self, x: np.ndarray) -> list[np.ndarray]:
        return [x[s] for s in self.w.spans]

    def noise_std_m(self) -> float:
        """The model's white sensor noise per sample."""
        return self.pred.params.sensor.noise_m_per_rthz * math.sqrt(0.5 / self.sig.dt_s)

    def natural_frequency_hz(self) -> float:
        """The model pendulum's: a line near it means its frequency or Q is off."""
        return self.pred.params.pendulum.natural_frequency_hz


def _fundamental(f: np.ndarray, z: np.ndarray, k: int, threshold: float,
                 fmin_hz: float) -> int:
    """The lowest significant subharmonic of bin k of the z-scores `z` (on `f`): a
    sawtooth's second or third harmonic can stand out more than its fundamental."""
    for div in (5, 4, 3, 2):
        j = round(k / div)
        if j < 4 or f[j] < fmin_hz:
            continue
        lo = j - 1
        peak = lo + int(np.argmax(z[lo:j + 2]))
        around = np.median(z[max(peak - 12, 1):peak + 13])
        # A line, not the red noise a subharmonic of a line may sit in.
        if z[peak] > threshold and z[peak] > 30 * around:
            return peak
    return k


def _refine(f: np.ndarray, z: np.ndarray, k: int) -> float:
    """Line frequency between bins: the centroid of the power around the peak."""
    lo, hi = max(k - 2, 1), min(k + 3, len(z))
    p = z[lo:hi]
    return float(np.sum(f[lo:hi] * p) / np.sum(p))


def _moving(exc: np.ndarray) -> slice:
    """From the first to the last change of `exc` above a thousandth of its largest."""
    step = np.abs(np.diff(exc))
    moved = np.flatnonzero(step > 1e-3 * step.max()) if len(step) and step.max() > 0 else []
    return slice(int(moved[0]), int(moved[-1]) + 2) if len(moved) else slice(0, 0)


def modulation_steps(meas: Measured) -> bool:
    """Whether the log's modulation (`modulation_v`) steps the actuator and holds it
    between its edges (a square: `leveler modulate`'s), rather than sweeping it (a
    triangle, a sine: its travel is spread over its samples, however slow). Held, a
    piezo's hysteresis is an offset per edge, a gain the recalibration takes: only the
    closed loop's reversals can show a loop then (an independent Bouc-Wen stand's, named
    in 1 of 9 square-modulated logs and 9 of 9 triangle-modulated ones)."""
    exc = modulation_v(meas)
    if exc is None:
        return False
    seg = exc[_moving(exc)]
    if modulation_hz(seg, meas.dt_s) is None:
        return False
    step = np.sort(np.abs(np.diff(seg)))[::-1]
    return bool(np.sum(step[:max(1, int(STEP_SHARE * len(step)))]) > 0.5 * np.sum(step))


def modulation_hz(x: np.ndarray | None, dt_s: float) -> float | None:
    """The frequency of the strongest line of `x` with at least eight cycles in it
    (refined between bins to 1/50 of one), or None when there is no line 100x above the
    median of the octaves around it (no modulation; a drift is no line). The refinement's
    101 trial frequencies are one chirp-z transform: a sum of complex exponentials over
    the whole log for each took 0.46 s a call on a null day (two a run), the transform
    0.09 s; the frequency picked is the same."""
    if x is None or len(x) < 64:
        return None
    x = x - np.mean(x)
    p = np.abs(np.fft.rfft(x * hann(len(x)))) ** 2
    k = int(np.argmax(p[8:])) + 8
    if not p[k] > 100 * np.median(p[k // 2 + 1:2 * k]):
        return None
    trial = (k + np.linspace(-1.0, 1.0, 101)) / (len(x) * dt_s)
    step_hz = trial[1] - trial[0]
    power = np.abs(czt(x, m=len(trial), w=np.exp(-2j * np.pi * step_hz * dt_s),
                       a=np.exp(2j * np.pi * trial[0] * dt_s)))
    return float(trial[int(np.argmax(power))])


#: Steps tried by the lattice scan: from 3 counts of the model's ADC (below that its own
#: counts alias) up to 300, 1 % apart.
_LATTICE_COUNTS = np.geomspace(3.0, 300.0, 464)
#: Rayleigh statistic a step's coherence must beat: chance odds 1e-4 over the scan.
_LATTICE_Z = math.log(len(_LATTICE_COUNTS) / 1e-4)
#: and this share of the strongest step's (its halves and thirds come close to it)
LATTICE_SHARE = 0.1


def _changes(spans: list[np.ndarray], lsb_m: float, predicted: list[np.ndarray] | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """|changes| between consecutive readings within each span, larger than 1.5 counts,
    and the model's predicted |change| at each (zero without a prediction)."""
    d = np.concatenate([np.abs(np.diff(y)) for y in spans])
    dp = (np.zeros_like(d) if predicted is None
          else np.concatenate([np.abs(np.diff(y)) for y in predicted]))
    big = d > 1.5 * lsb_m
    return d[big], dp[big]


def _unpredicted(d: np.ndarray, dp: np.ndarray, q: float) -> np.ndarray:
    """The changes a lattice of step q is sought in: larger than half a step, where the
    model predicts less than a quarter of one. A modulation's steps and the ringing after
    them repeat with the same sizes every cycle, and a set of repeated sizes lines up on
    some divisor of them (a 5 V square was a "112 nm converter" before); a converter's
    own changes come where a slow signal crosses a level, unpredicted."""
    return d[(d > 0.5 * q) & (dp < 0.25 * q)]


def find_lattice(spans: list[np.ndarray], lsb_m: float,
                 predicted: list[np.ndarray] | None = None) -> tuple[float, float] | None:
    """(step, offset) of a lattice the readings (in `spans`) sit on, coarser than
    `lsb_m`; or None.

    Seen in the changes between consecutive readings: on a lattice they are whole
    multiples of its step, whatever the signal does between samples. A little analog noise
    after a coarse converter, read by a finer one, blurs each change by a count or two of
    the fine converter, so the step is found by phase coherence: for each trial step q the
    changes larger than q/2 (and not predicted by the model, `_unpredicted`) are mapped to
    phases 2 pi d/q, and a lattice makes them line up (|mean of exp(i phase)| near 1) where
    smooth noise leaves them spread. The largest step that lines them up in phase is the
    lattice (its halves and thirds line them up too).
    """
    d, dp = _changes(spans, lsb_m, predicted)
    if len(d) < 50:
        return None
    steps = lsb_m * _LATTICE_COUNTS
    coherence = np.full(len(steps), -1.0)
    z = np.zeros(len(steps))
    for i, q in enumerate(steps):
        sel = _unpredicted(d, dp, q)
        # Not a `break` at the first step with too few: a closed loop hunting across a
        # coarse converter's levels makes changes the model predicts (it replays the
        # commands), and only a larger step's quarter lets them through (a strong 23.6 nm
        # converter: none at 4.6 nm, 18,757 at 23.6 nm; quantization was never fitted).
        if len(sel) < 50:
            continue
        # The real part: changes of one step at a trial step of two line up in antiphase.
        c = float(np.mean(np.cos(2 * np.pi * sel / q)))
        if c > 0.3 and len(sel) * c * c > _LATTICE_Z:
            coherence[i], z[i] = c, len(sel) * c * c
    # The largest step that lines up, but among those that line up nearly as strongly as
    # the strongest: large changes line up on a multiple of the step as well, and a
    # square-modulated strong converter's 23.6 nm steps (z about 16,000) lost to 145 nm,
    # six of them, where 1,100 changes of four steps and more lined up (z 159).
    lined_up = np.flatnonzero((coherence > 0) & (z >= LATTICE_SHARE * z.max()))
    if not len(lined_up):
        return None
    # The coherence peak is broad (a trial step 10 % long still lines changes of one step
    # up fairly well): the step is its top below the largest step that lines up, refined
    # between grid points on the same changes.
    near = np.flatnonzero((steps > steps[lined_up[-1]] / 1.3) & (coherence > 0))
    best = float(steps[near[np.argmax(coherence[near])]])
    sel = _unpredicted(d, dp, best)
    trial = best * np.linspace(0.985, 1.015, 61)
    step = float(trial[np.argmax([np.mean(np.cos(2 * np.pi * sel / q)) for q in trial])])
    y = np.concatenate(spans)
    offset = float(np.angle(np.mean(np.exp(2j * np.pi * y / step)))) / (2 * np.pi) * step
    return step, offset


#: readings are looked at in windows of this many (a slow signal spans a few steps in one,
#: so a step a few per cent off still lines them up), those that span two steps or more,
#: and the step is scanned this far either way (a fit's step was 4 % off)
LEVEL_WINDOW = 64
LEVEL_SCAN = np.linspace(0.94, 1.06, 61)


def readings_on_levels(y: np.ndarray, step_m: float) -> tuple[int, float]:
    """(how many windows of LEVEL_WINDOW readings span two steps of `step_m` or more; the
    mean over them of Rayleigh's statistic LEVEL_WINDOW |mean exp(2 pi i y / step)|^2,
    the largest over steps within LEVEL_SCAN): about 1 where the readings fall anywhere,
    up to LEVEL_WINDOW where they sit on a converter's levels."""
    m = len(y) // LEVEL_WINDOW
    win = y[:m * LEVEL_WINDOW].reshape(m, LEVEL_WINDOW)
    win = win[np.ptp(win, axis=1) >= 2 * step_m]
    if not len(win):
        return 0, math.nan
    z = max(float(np.mean(np.abs(np.mean(np.exp(2j * np.pi * win / (step_m * k)), axis=1))
                          ** 2)) for k in LEVEL_SCAN)
    return len(win), LEVEL_WINDOW * z


def lattice_deviance(spans: list[np.ndarray], lsb_m: float, step_m: float,
                     predicted: list[np.ndarray] | None = None) -> float:
    """2 n c |c|, with c the mean of cos(2 pi d / step) over the n changes d between
    consecutive readings (within each span) larger than half a step and not predicted
    (`_unpredicted`): the score test for a lattice of that step against phases spread
    evenly (chi-squared with one degree of freedom under that null, like a deviance);
    negative when the changes sit between lattice points."""
    d, dp = _changes(spans, lsb_m, predicted)
    d = _unpredicted(d, dp, step_m)
    if not len(d):
        return 0.0
    c = float(np.mean(np.cos(2 * np.pi * d / step_m)))
    return 2.0 * len(d) * c * abs(c)
