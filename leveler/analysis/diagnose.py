"""Find what the plant model is missing: detect, fit, hold out, accept only what holds up.

First the model's calibrated numbers are fitted within their stated tolerances
(`leveler.analysis.recalibrate`): an in-tolerance offset is a calibration, not an effect.
They stay free, under the same priors, in every fit below (`leveler.analysis.nuisance`):
a candidate is scored only on what no in-tolerance knob explains. Then, per round:
1. replay the log against the current model; the residual's noise spectrum is fitted on
   training blocks (the first two thirds of each part of the usable log: the loop open
   under a modulation, the loop closed) and on the held-out rest of each (`split`);
2. every effect not yet in the model reads its starting guesses off the residual
   (`leveler.analysis.evidence`) and is fitted on the training part by least squares on the
   whitened residual (`leveler.analysis.whittle`);
3. each fit is scored: the gain in log-likelihood must beat a BIC penalty (k ln n) on the
   training part, and on the held-out part (scored given the training part: the knobs
   solved on both, `nuisance.predictive_cost`) the penalty or, where null logs of the model
   show it too low for the family's search, the threshold calibrated on them
   (`nullcal`), or the effect is not real; of those that pass, the best must also fit
   the held-out part on its own with a compatible size (same sign, within 2x); when the
   best of another family does too and its evidence is within AMBIGUITY, the answer is
   "ambiguous between A and B" and the search stops there, taking neither;
4. the winner is refitted on the whole log and, if that fit agrees with the one that held
   out (else the next that held out takes its place), added to the model, and the round
   repeats; when nothing passes, the search stops and says so: no effect is invented.
A family that must show more than a gain (hysteresis: `Effect.beyond_part_gains`) is
fitted and scored with a free actuator gain in each part of the log, its baseline too.
Lines left in the held-out residual beyond a look-elsewhere threshold are then reported
as unexplained structure (`leveler.analysis.leftover`), never given the nearest name.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.signal import freqz
from threadpoolctl import threadpool_limits

from leveler.analysis.bandgate import BandChange, band_changes, bin_power, worse_band
from leveler.analysis.bump import Bump, Spectra, mode_psd
from leveler.analysis.evidence import Evidence, modulation_steps
from leveler.analysis.leftover import Leftover, leftover
from leveler.analysis.nuisance import (
    Nuisance,
    Projection,
    part_gains,
    predictive_cost,
    predictive_residual,
    with_shapes,
    with_states,
)
from leveler.analysis.predict import (
    Measured,
    Predictor,
    actuator_excited,
    modulation_v,
    pendulum_filter,
    sensor_noise_m,
)
from leveler.analysis.recalibrate import Recalibration, apply, recalibrate, replayable
from leveler.analysis.steps import stepped_least_squares
from leveler.analysis.told import red_ceiling
from leveler.analysis.whittle import ENBW_BINS, Blocks, Whitener, deviance, hann_psd
from leveler.analysis.workers import one_blas_thread
from leveler.sim.effects import (
    EFFECTS,
    ActuatorHysteresis,
    Effect,
    EffectsParams,
    ExtraResonance,
)
from leveler.sim.params import PlantParams

#: An accepted effect moves the reading by this share of the sensor's white noise, rms
#: over the held-out part: where its evidence needs the extrapolated lowest bins, and
#: where the fitted bins alone hold it.
_MIN_NOISE_SHARE = 0.5
_MIN_NOISE_SHARE_FITTED = 0.2
#: A mode rung by noise raises the typical bin of its band by at least this share of its
#: power; a comb of lines raises a few (leveler.analysis.bump's `spread`). Over the
#: tuning logs, modes gave 0.43-1.55, the lowest strong ones near 1.9 Hz that the closed
#: loop shapes (at 0.5 a 1.77 Hz one was rejected at 0.49, and a 10 ms delay was named in
#: its place), and combs of lines 0.00-0.03.
MIN_SPREAD = 0.35
#: Two families whose held-out evidence (2 ln of the likelihood ratio) is closer than this
#: are not told apart: 10 is "very strong" on Kass & Raftery's scale; for strong effects 5 %
#: of the better one's, as the forms and the fitted noise spectrum are approximations.
AMBIGUITY = 10.0
AMBIGUITY_REL = 0.05
BANDS_HZ: dict[str, tuple[float, float]] = {
    "0.1-1 mHz": (1e-4, 1e-3),
    "1-10 mHz": (1e-3, 1e-2),
    "10-100 mHz": (1e-2, 1e-1),
    "0.1-1 Hz": (1e-1, 1.0),
    "1 Hz-Nyquist": (1.0, math.inf),
}
#: the band gate's bands (`bandgate`): every bin counts, a day's lowest too
GATE_BANDS_HZ = {"under 0.1 mHz": (0.0, 1e-4), **BANDS_HZ}


@dataclass
class Fit:
    effect: Effect
    sigma: dict[str, float]
    cost: float


@dataclass
class Candidate:
    """One effect tried in one round, with the numbers that decided it."""

    name: str
    params: dict[str, Any]
    deviance_train: float
    deviance_test: float
    penalty: float
    accepted: bool = False
    note: str = ""
    sigma: dict[str, float] = field(default_factory=dict)
    round: int = 0
    threshold: float = math.nan  # held-out evidence to beat (default: the penalty)
    size_ok: bool = False  # found in training, not degenerate, no gate but the threshold stops it
    bands: dict[str, BandChange] = field(default_factory=dict)  # held out (`bandgate`)

    def __post_init__(self) -> None:
        if math.isnan(self.threshold):
            self.threshold = self.penalty

    @property
    def score(self) -> float:
        """Held-out evidence beyond the threshold: what candidates are ranked by."""
        return self.deviance_test - self.threshold


@dataclass
class Found:
    effect: Effect
    sigma: dict[str, float]
    deviance_test: float


@dataclass
class Diagnosis:
    effects: list[Found]
    model: EffectsParams
    gap_before: dict[str, Any]
    gap_after: dict[str, Any]
    candidates: list[Candidate] = field(default_factory=list)
    span_s: tuple[float, float] = (0.0, 0.0)
    wall_s: float = 0.0
    params: PlantParams | None = None  # the recalibrated plant (effects aside)
    recalibration: Recalibration | None = None
    ambiguous: list[Candidate] = field(default_factory=list)  # the two it could not tell apart
    leftover: Leftover | None = None  # lines no family explained
    # per band: residual power over the noise spectrum, nominal and final model (held out)
    gap_normalised: dict[str, dict[str, float] | None] = field(default_factory=dict)
    # per family this log cannot show (or hardly): why (`unseen`)
    unseen: dict[str, str] = field(default_factory=dict)


def warmup_samples(meas: Measured, pred: Predictor) -> int:
    """Samples to skip at the start: the log may start out of equilibrium."""
    pe = pred.params.pendulum
    decay_s = 2 * pe.inertia_kgm2 / max(pe.damping_nms_per_rad, 1e-12)
    skip_s = min(max(300.0, 5 * decay_s), 0.1 * (meas.t_s[-1] - meas.t_s[0]))
    return int(skip_s / meas.dt_s)


def _pendulum_shape(pred: Predictor, meas: Measured, f_hz: np.ndarray) -> np.ndarray:
    b, a = pendulum_filter(pred.params, meas.dt_s)
    _, h = freqz(b, a, worN=f_hz, fs=1.0 / meas.dt_s)
    dc = np.sum(b) / np.sum(a)
    return np.abs(h / dc) ** 2


def _known_psd(pred: Predictor) -> Callable[[np.ndarray], np.ndarray] | None:
    """The noise of the modes found rung by their own noise: the model holds it."""
    modes = [fx for fx in pred.effects.of("response")
             if isinstance(fx, ExtraResonance) and fx.noise_rms_m > 0]
    if not modes:
        return None
    return lambda f: sum((mode_psd(f, m.frequency_hz, m.q, m.noise_rms_m) for m in modes),
                         np.zeros_like(f))


def make_whitener(meas: Measured, pred: Predictor, span: slice, driven: bool = False
                  ) -> Whitener:
    """`driven`: the bins of the response to the modulation are left out of the noise fit
    (`Whitener`'s `drive_m`), as the blocks candidates are scored on need: a short one
    had fitted its noise to the comb a model a little wrong leaves there. The whole-log
    whitener of the recalibration has the modulation's bins told apart its own way
    (`recalibrate`)."""
    exc = modulation_v(meas) if driven else None
    w = Whitener(span, len(meas.y_m), meas.dt_s,
                 functools.partial(_pendulum_shape, pred, meas),
                 red_ceiling(pred.params, meas.sig.temperature_k is not None),
                 _known_psd(pred),
                 None if exc is None else pred.pend(pred.actuator_tilt(exc)))
    w.fit_noise(meas.y_m - pred.base.y_m)
    return w


def make_blocks(meas: Measured, pred: Predictor, spans: list[slice]) -> Blocks:
    return Blocks([make_whitener(meas, pred, s, driven=True) for s in spans])


#: a knob the first recalibration puts within this many sigma, and that it finds correlated
#: with no disputed knob by more than APART, is the log's own calibration: a refit that
#: flings it beyond PULL_LIMIT is taking up what a disputed knob held
KEEP_PULL = 2.5
APART = 0.5


#: A part of the log (the loop open, the loop closed) shorter than this is not split into
#: its own training and held-out blocks but joined to its neighbour: too short to say
#: anything about the slow effects on its own.
MIN_PART_S = 1200.0


def split(meas: Measured, skip: int) -> tuple[list[slice], list[slice]]:
    """Training and held-out blocks: each part of the log where the loop stayed open (a
    modulation) or closed, its first two thirds for training and the rest held out.

    One held-out block at the end of the log would be the closed loop alone in a log that
    starts with a modulation, and an actuator effect (hysteresis above all) shows mostly
    while the modulation drives the piezo: fitted on it, it could only fail there."""
    n = len(meas.y_m)
    on = (np.zeros(n - skip, dtype=bool) if meas.engaged is None
          else np.asarray(meas.engaged[skip:], dtype=bool))
    edges = [0, *(np.flatnonzero(np.diff(on)) + 1).tolist(), n - skip]
    runs = [[a, b, bool(on[a])] for a, b in itertools.pairwise(edges)]
    # A run too short to stand alone (a fault, a hand on the knob) takes the state of
    # the run before it (the first one, of the run after), and equal neighbours join.
    short = [(b - a) * meas.dt_s < MIN_PART_S for a, b, _ in runs]
    for i, run in enumerate(runs):
        if short[i] and len(runs) > 1:
            run[2] = runs[i - 1][2] if i else runs[1][2]
    parts: list[list[int]] = []
    for a, b, state in runs:
        if parts and parts[-1][2] == state:
            parts[-1][1] = b
        else:
            parts.append([a, b, state])
    parts = [[a + skip, b + skip] for a, b, _ in parts]
    cut = [a + 2 * (b - a) // 3 for a, b in parts]
    return ([slice(a, c) for (a, _), c in zip(parts, cut, strict=True)],
            [slice(c, b) for (_, b), c in zip(parts, cut, strict=True)])


def fit_effect(start: Effect, pred: Predictor, w: Whitener | Blocks, meas: Measured,
               nuis: Projection) -> Fit:
    """Least squares on the whitened residual over the effect's free parameters, jointly
    with the recalibrated knobs (`leveler.analysis.nuisance`).

    The magnitude of an effect that is linear in it is solved in closed form inside, with
    the knobs (variable projection): the search is then only over shapes, periods, lags
    and frequencies, which is where the local minima are. Uncertainties come from the
    Jacobian at the optimum, with the residual's own scatter.

    An effect whose cost is a needle in its parameters (a sawtooth's sharp drop: a period
    0.01 % off is as bad as none) says so with `fit_bands_hz`: it is fitted first on the
    bins below each of those frequencies in turn, coarse to fine, each landscape wide
    enough for the previous stage's precision.
    """
    y = meas.y_m
    white = w.whiten(y - pred.base.y_m)
    mag = start.magnitude if start.linear else None
    keys = tuple(k for k in start.free if k != mag)
    theta0 = np.array([float(getattr(start, k)) for k in keys])
    scale = np.array([start.scale(k) for k in keys])
    lo = np.array([start.bounds(k)[0] for k in keys])
    hi = np.array([start.bounds(k)[1] for k in keys])
    theta0 = np.clip(theta0, lo + 1e-6 * scale, hi - 1e-6 * scale)
    unit = start.scale(mag) if mag else 0.0

    def shaped(x: np.ndarray) -> Effect:
        return start.replace(**{k: float(v) for k, v in zip(keys, theta0 + x * scale,
                                                             strict=True)})

    def solve(x: np.ndarray, proj: Projection = nuis, keep: Any = slice(None)
              ) -> tuple[np.ndarray, Effect]:
        fx = shaped(x)
        proj = with_states(proj, w, pred, fx, keep)
        if mag is None:
            return proj.residual(w.whiten(y - pred.with_candidate(fx))[keep])[1], fx
        c = w.whiten(pred.with_candidate(fx.replace(**{mag: unit})) - pred.base.y_m)[keep]
        lo_m, hi_m = fx.bounds(mag)
        beta, e = proj.residual(white[keep], c, (lo_m / unit, hi_m / unit))
        return e, fx.replace(**{mag: beta * unit})

    x = np.zeros(len(keys))
    if len(keys) == 1 and theta0[0] > 0:
        # One shape parameter (a width, a lag, a delay): a log-spaced scan over a factor
        # of 8 either way, then a bracketed search around the best point. Least squares
        # alone stalls on hysteresis' ridges; a delay has local minima a pendulum period
        # apart.
        grid = np.geomspace(max(lo[0], theta0[0] / 8), min(hi[0], theta0[0] * 8), 25)
        xs = (grid - theta0[0]) / scale[0]

        def cost(v: float) -> float:
            return float(np.sum(solve(np.array([v]))[0] ** 2))

        i = int(np.argmin([cost(v) for v in xs]))
        best = minimize_scalar(cost, bounds=(xs[max(i - 1, 0)], xs[min(i + 1, len(xs) - 1)]),
                               method="bounded", options={"xatol": 1e-4})
        x = np.array([best.x])
    box = ((lo - theta0) / scale, (hi - theta0) / scale)
    for f_max in start.fit_bands_hz() if keys else ():
        keep = w.below(f_max)
        proj = nuis.restricted(keep)
        x = stepped_least_squares(lambda v, p=proj, k=keep: solve(v, p, k)[0], x, box,
                                  10 * (len(keys) + 1)).x
    if keys:
        x = stepped_least_squares(lambda v: solve(v)[0], x, box, 40 * (len(keys) + 1)).x
    e, fitted = solve(x)
    fitted = fitted.canonical()
    return Fit(fitted, _sigma(fitted, pred, w, meas, e, nuis), float(e @ e))


def _sigma(fx: Effect, pred: Predictor, w: Whitener | Blocks, meas: Measured,
           e: np.ndarray, nuis: Projection) -> dict[str, float]:
    """1-sigma uncertainties of all free parameters from a finite-difference Jacobian."""
    keys = fx.free
    cols = []
    for k in keys:
        h = 1e-3 * fx.scale(k)
        _, hi = fx.bounds(k)
        v = float(getattr(fx, k))
        if v + h > hi:
            h = -h
        moved = fx.replace(**{k: v + h})
        plus = with_states(nuis, w, pred, moved).residual(
            w.whiten(meas.y_m - pred.with_candidate(moved)))
        cols.append((plus[1] - e) / h)
    jac = np.array(cols).T
    s2 = float(e @ e) / max(len(e) - len(keys), 1) * ENBW_BINS
    try:
        cov = np.linalg.inv(jac.T @ jac) * s2
        sig = np.sqrt(np.abs(np.diag(cov)))
    except np.linalg.LinAlgError:
        sig = np.full(len(keys), math.inf)
    return {k: float(s) for k, s in zip(keys, sig, strict=True)}


def _stable(a: Effect, b: Effect) -> bool:
    """Same effect on both parts of the log: same sign, size within a factor of 2."""
    x, y = a.size(), b.size()
    return x * y > 0 and 0.5 <= abs(y / x) <= 2.0


def _recalibrated(meas: Measured, plant: PlantParams, whole: slice, excited: bool,
                  refine: Effect | None = None
                  ) -> tuple[Predictor, Recalibration | None, Nuisance]:
    """`plant` (nominal values, the effects found so far) recalibrated within its stated
    tolerances: an in-tolerance offset is no missing effect. A knob the fit puts beyond
    PULL_LIMIT sigma is held at nominal and the rest refitted, until none is: what pulled
    it (a sensor gain error, or an effect that mimics one, such as a coarse converter) is
    then for the candidates to compete for on held-out data, not taken for granted.
    A knob the first fit put well within its tolerance (KEEP_PULL) and found independent
    of the disputed ones (posterior correlation under APART) that a refit then flung
    beyond it took up what was held, and goes back where the first fit put it: an extra
    1.9 Hz mode's log had both paths disputed, and refitted without them its resonance
    frequency went from 2.1 sigma (the truth's 1.9) to 7.1 and was held, leaving every
    candidate a baseline 62 nm off (the mode was named, 48 -> 3.8 nm, once it was not).
    A knob tied to a disputed one stays held: the two paths and the thermal tilt are
    correlated by 0.96-1.0 (the log pins their products), so next to a sensor path that a
    gain error disputes an actuator path of -2.2 sigma has taken up part of the error,
    and kept there it hid the error from the held-out part (two medium gain errors went
    unnamed); released beside a disputed thermal tilt, the paths gained two couplings
    and lost two others (gaps of 130 and 250 nm left).
    `refine`, the effect just found, is refitted with the knobs (see `recalibrate`).

    The first fit is also checked where every comparison of candidates will solve its
    linear knobs (`_settled`: all bins, the noise spectrum of what it leaves). The fit
    itself leaves lines out and whitens with the nominal residual's spectrum, which a
    slow effect reddens and hides in: a lagged temperature coupling put the thermal tilt
    at +23 % (pull 1.2) there and +118 % (pull 5.9) settled, where it was no candidate's
    to explain. Only the first fit, and only of the baseline: a knob the refit moves
    takes up what was held, and once an effect is found the knobs are refitted with it
    (a strong periodic case had its sensor path held then, and a sensor gain error
    taken second made the gap worse, 12.9 -> 15.8 nm)."""
    pred = Predictor(plant, meas)
    smooth = replayable(plant)
    w = make_whitener(meas, pred if smooth is plant else Predictor(smooth, meas), whole)
    recal = first = recalibrate(meas, plant, w, excited, refine=refine)
    disputed = set() if first is None else set(first.disputed)
    if recal is not None and not recal.disputed and refine is None:
        at = Predictor(recal.params, meas)
        settled = _settled(meas, at, recal, Nuisance(at, recal, meas), whole)[1]
        if settled is not None and settled.disputed:
            disputed |= set(settled.disputed)
            recal = recalibrate(meas, plant, w, excited, omit=tuple(settled.disputed),
                                refine=refine)
    while recal is not None and recal.disputed:  # the next knob may take up what was held
        recal = recalibrate(meas, plant, w, excited, omit=recal.held + tuple(recal.disputed),
                            refine=refine)
    if recal is not None and first is not None:
        for k in first.knobs:
            if (k.name in recal.held and k.name not in disputed
                    and abs(first.pull(k.name)) <= KEEP_PULL
                    and all(abs(first.correlation.get((k.name, d), 1.0)) < APART
                            for d in disputed)):
                recal = recal.releasing(k, first.offset[k.name], first.sigma_post[k.name])
    if recal is None:
        return pred, None, Nuisance(pred, None, meas)
    pred = Predictor(recal.params, meas)
    return pred, recal, Nuisance(pred, recal, meas)


def diagnose(meas: Measured, max_effects: int = 4,
             thresholds: dict[str, float] | None = None, jobs: int = 1,
             progress: Callable[[str, int, int], None] | None = None) -> Diagnosis:
    """`thresholds`: per family, the held-out evidence a candidate must beat, calibrated
    on null data (`leveler.analysis.nullcal`) where that is above its BIC penalty; every
    candidate must beat the penalty, on the training part and on the held-out part.
    `jobs`: processes the families of each round are fitted in. `progress` is told
    (stage, done, total) as the minute-long search goes.

    BLAS keeps to one thread throughout, as in a round's family processes and the null
    calibration's runs, so its rounding depends neither on `jobs` nor on the machine's
    cores. With the parent's threads, a strong hysteresis log's flat fit went elsewhere:
    named at --jobs 1, "none" at --jobs 2 (now "none" at both). numpy's own sums still
    round with their arrays' alignment in memory, which differs between processes: a
    weak fit's end can move by 3e-4 of its deviance (`tests/test_diagnose.py`)."""
    with threadpool_limits(limits=1):
        return _diagnose(meas, max_effects, thresholds, jobs, progress)


def _diagnose(meas: Measured, max_effects: int, thresholds: dict[str, float] | None,
              jobs: int, progress: Callable[[str, int, int], None] | None) -> Diagnosis:
    def stage(name: str, done: int = 0, total: int = 1) -> None:
        if progress is not None:
            progress(name, done, total)

    stage("recalibrating the model")
    start_wall = time.perf_counter()
    pred = Predictor(meas.config.plant, meas)
    n = len(meas.y_m)
    skip = warmup_samples(meas, pred)
    train, test = split(meas, skip)
    parts = [slice(a.start, b.stop) for a, b in zip(train, test, strict=True)]
    whole = slice(skip, n)
    gap_before = gap(meas, pred, whole)
    act_excited = actuator_excited(meas, pred, whole)
    pred, recal, nuisance = _recalibrated(meas, meas.config.plant, whole, act_excited)
    found: list[Found] = []
    tried: list[Candidate] = []
    ambiguous: list[Candidate] = []
    skipped = not_looked_for(meas, act_excited)
    noise = sensor_noise_m(pred.params, meas.dt_s)
    while len(found) < max_effects:
        w_train = make_blocks(meas, pred, train)
        w_test = make_blocks(meas, pred, test)
        n_train, n_test = nuisance.on(w_train), nuisance.on(w_test)
        white0_train = w_train.whiten(meas.y_m - pred.base.y_m)
        cost0_train = n_train.cost(white0_train)
        white0_test = w_test.whiten(meas.y_m - pred.base.y_m)
        cost0_test = predictive_cost(n_train, n_test, white0_train, white0_test)
        gains = part_gains(pred, parts)
        ev = Evidence(meas, pred, w_train, nuisance, gains)
        ev_test = Evidence(meas, pred, w_test, nuisance, gains)
        r = _Round(meas, pred, w_train, w_test, n_train, n_test, white0_train, white0_test,
                   cost0_train, cost0_test, ev, ev_test, len(found), noise, thresholds, gains)
        families = [cls for cls in EFFECTS.values()
                    if getattr(pred.effects, cls.name) is None and cls.name not in skipped]
        passed: list[tuple[Fit, Candidate]] = []
        name = f"round {len(found) + 1}: fitting each family of effects"
        total = len(families)
        stage(name, 0, total)
        for family_tried, family_passed in _each_family(
                families, r, jobs, lambda done, name=name, total=total: stage(name, done, total)):
            tried += family_tried
            passed += family_passed
        # The best candidate that held out, confirmed on the whole log; one the whole log
        # disagrees with gives way to the next (a jittered sawtooth's best fit came out at
        # 0.497 of its size there, and its sine and its other sawtooth, both right, were
        # never looked at).
        outcome: tuple[tuple[Predictor, Recalibration | None, Nuisance], Found] | None = None
        while passed and outcome is None:
            stable = _select(passed, lambda f, r=r: _refit(f, r.pred, r.w_test, r.meas,
                                                           r.scored_on(type(f.effect))[1]))
            if not stable:
                break
            if len(stable) == 2:  # two families the log cannot tell apart: neither is taken
                ambiguous = [stable[0][1], stable[1][1]]
                for c in ambiguous:
                    c.note = "ambiguous: " + " / ".join(a.name for a in ambiguous)
                break
            f, cand, check = stable[0]
            confirmed = _confirm(r, f, check, cand.score, nuisance, parts, whole,
                                 act_excited)
            if isinstance(confirmed, str):
                cand.note = confirmed
                passed = [p for p in passed if p[1] is not cand]
                continue
            cand.accepted = True
            outcome = confirmed[0], Found(confirmed[1].canonical(), confirmed[2],
                                          cand.deviance_test)
        if outcome is None:
            break
        (pred, recal, nuisance), found_one = outcome
        found.append(found_one)
    stage("recalibrating with what was found")
    found, (pred, recal, nuisance) = _calibration_after_all(
        meas, found, (pred, recal, nuisance), whole, act_excited, tried)
    settled = _settled(meas, pred, recal, nuisance, whole)
    # Unbounded, the linear solve can run where no tolerance allows: an independent strong
    # hysteresis log, taken for a sensor gain error, had its sensor path settled at +102 %
    # and its piezo gain at -105 % (a sign flip), and the fitted model could not be
    # written. Such a settling is not a calibration; the model stays as it was scored.
    if settled[1] is None or not settled[1].disputed:
        pred, recal, nuisance = settled
    w_tr, w_te = make_blocks(meas, pred, train), make_blocks(meas, pred, test)
    stage("looking for what is left")
    rest = None
    if not ambiguous:  # lines are looked for on one frequency grid: the longest blocks
        def mode_near(spectra: Spectra, f_hz: float) -> tuple[Bump, str]:
            _, bump, why = _mode_near(Evidence(meas, pred, w_tr, nuisance), spectra, f_hz)
            return bump, why

        rest = leftover(meas, meas.y_m - pred.base.y_m,
                        (w_tr.longest, nuisance.on(w_tr.longest)),
                        (w_te.longest, nuisance.on(w_te.longest)), BANDS_HZ, mode_near)
    nominal = Predictor(meas.config.plant, meas)
    return Diagnosis(found, pred.effects, gap_before, gap(meas, pred, whole), tried,
                     (float(meas.t_s[skip]), float(meas.t_s[-1])),
                     time.perf_counter() - start_wall,
                     dataclasses.replace(pred.params, effects=EffectsParams()), recal,
                     ambiguous, rest,
                     normalised_gap(w_te, meas.y_m - nominal.base.y_m, meas.y_m - pred.base.y_m),
                     unseen(meas, act_excited, [f.effect.name for f in found]))


def not_looked_for(meas: Measured, act_excited: bool) -> dict[str, str]:
    """The families this log cannot show at all, and why."""
    temperature = meas.sig.temperature_k is not None
    out = {}
    for cls in EFFECTS.values():
        if cls.needs_temperature and not temperature:
            out[cls.name] = "not looked for: no temperature was logged"
        elif cls.needs_excitation and not (temperature or act_excited):
            out[cls.name] = ("not looked for: nothing moved the actuator but the loop, "
                             "and no temperature was logged (`leveler modulate` moves it)")
    return out


def unseen(meas: Measured, act_excited: bool, found: list[str]) -> dict[str, str]:
    """Per family this log cannot show, or hardly, why: a physicist reading "no missing
    effect" should know what was never looked for, and what to record to look for it."""
    out = not_looked_for(meas, act_excited)
    if (act_excited and ActuatorHysteresis.name not in found + list(out)
            and modulation_steps(meas)):
        out[ActuatorHysteresis.name] = (
            "hardly testable here: a square modulation holds the piezo between its edges, "
            "where a hysteresis is only an offset, a gain the recalibration takes; only the "
            "closed loop's reversals can show its loop, and a modulation that sweeps would "
            "(`leveler modulate --shape triangle`, which also measures the opening)")
    return out


def _confirm(r: _Round, f: Fit, check: Fit, evidence: float, nuisance: Nuisance,
             parts: list[slice], whole: slice, act_excited: bool
             ) -> tuple[tuple[Predictor, Recalibration | None, Nuisance], Effect,
                        dict[str, float]] | str:
    """`f`, the best fit that held out (`check`: its fit to the held-out part; `evidence`:
    its held-out deviance), refitted on the whole log and the knobs recalibrated around
    it: (the model with it, the effect as kept, its 1-sigma uncertainties), or why the
    whole log does not confirm it."""
    meas, pred, ev = r.meas, r.pred, r.ev
    # Refit on the whole log with the noise spectrum of what the effect leaves: the
    # spectrum fitted before it was found has soaked up part of a broadband effect
    # (a temperature coupling is red), which would blunt the fit where it matters.
    # One noise spectrum for the whole log, open loop and closed, whitens the closed
    # loop's small reversals with the modulation's noise: a strong independent
    # Bouc-Wen log's play, 0.076 V and 0.17 held out, came out 0.018 V and 0.035 so,
    # and 0.076 V and 0.14 on a spectrum per part.
    w_whole: Whitener | Blocks = (make_blocks(meas, pred, parts)
                                  if f.effect.beyond_part_gains
                                  else make_whitener(meas, pred, whole))
    final = f
    for _ in range(1 if _noise_rung(f.effect) else 2):  # its residual does not change
        w_whole.fit_noise(meas.y_m - pred.with_candidate(final.effect))
        if f.effect.own_score_only:  # see `refined` below
            break
        on_whole = nuisance.on(w_whole)
        if f.effect.beyond_part_gains:
            on_whole = with_shapes(on_whole, w_whole, r.part_gains)
        refit = _refit(final, pred, w_whole, meas, on_whole)
        if refit.effect.degenerate(ev) or f.effect.moved_off(refit.effect, ev):
            break  # what held out was the fit before this one
        if not _stable(f.effect, refit.effect) and deviance(
                _effect_cost(f.effect, pred, w_whole, meas, on_whole),
                _effect_cost(refit.effect, pred, w_whole, meas, on_whole)
        ) < max(AMBIGUITY, AMBIGUITY_REL * evidence):
            # A move along a ridge the whole log hardly prefers, away from what both parts
            # agreed on: a strong two-lag coupling (13.8 urad/K through 398 s and 1,648 s)
            # held out at 17.4 through 1,991 s and 296 s (16.8 through 1,969 s and 317 s
            # on the held-out part alone) went to 49 urad/K through 7,768 s, 1,683 better
            # on this whitening, under 1 % of its held-out evidence (287,593), and was
            # then "the whole log's fit disagrees".
            break
        final = refit
    # The noise model's 1-sigma misses systematic errors; how far the fits to the two
    # parts of the log, and to the whole, disagree is an honest floor under it.
    sigma = {k: math.hypot(v, 0.5 * f.effect.difference(check.effect, k),
                           final.effect.difference(f.effect, k))
             for k, v in final.sigma.items()}
    # The baseline again, with what was found: an effect not yet in the model biased it,
    # and the effect's fit on that biased baseline is refined with it.
    plant = dataclasses.replace(meas.config.plant,
                                effects=pred.effects.with_effect(final.effect))
    around = _recalibrated(meas, plant, whole, act_excited)  # the knobs around the fit
    # A mode rung by noise alone changes no prediction: nothing to refine with the knobs.
    # An effect scored by its own evidence is not refined by replay's likelihood either:
    # that is not what found it. Refined so, converters ran to no converter at all
    # (steps of 1e-6 nm under 14 nm of replay noise, 5 of 9 independent logs) once
    # their replay was exact enough for the fit to get there. Nor is one scored beyond
    # a gain per part: with the knobs alone it would take up a gain again.
    refined = (_recalibrated(meas, plant, whole, act_excited, final.effect)
               if _refined_by_knobs(final.effect) else around)
    # The refinement may wander where no held-out fit went: a day's null log had a
    # 3.4 V play become 37 V (a gain); a jittered sawtooth's sine moved from 183 to
    # 187 s at a quarter of its size, fitted on the bins its lines leave quiet: a gap
    # of 54 nm, where the fit that held out leaves 3.5. It is kept where it does
    # better on all bins, or where it agrees with both fits that held out and the
    # whole log's refit without it does not: that refit, on one noise spectrum for both
    # parts, took a medium two-lag coupling (-5.4 urad/K through 853 s and 355 s; held
    # out at -5.7 through 941 s and 316 s, -5.3 on the held-out part alone) to -14.1
    # through 1,344 s and 172 s, with the cooler 56 % stronger and the thermal
    # coefficient held; refined with the knobs it came back to -5.4 through 916 s and
    # 308 s, but cost more on that refit's whitening.
    moved = getattr(refined[0].effects, final.effect.name)
    if moved.degenerate(ev) or (
            _cost(meas, around, w_whole) < _cost(meas, refined, w_whole)
            and not (_stable(f.effect, moved) and _stable(check.effect, moved)
                     and not _stable(f.effect, final.effect))):
        refined = around
    kept = getattr(refined[0].effects, final.effect.name)
    if not _stable(f.effect, kept):
        # The whole log does not confirm what held out: a null log's coupling held
        # out at -0.18 urad/K through a 52 s lag and became +0.49 through 727 s.
        return (f"the whole log's fit disagrees: size {kept.size():.3g} for "
                f"{f.effect.size():.3g}")
    return refined, kept, sigma


def _calibration_after_all(meas: Measured, found: list[Found],
                           model: tuple[Predictor, Recalibration | None, Nuisance],
                           whole: slice, excited: bool, tried: list[Candidate]
                           ) -> tuple[list[Found], tuple[Predictor, Recalibration | None,
                                                          Nuisance]]:
    """The effects found, less a sensor gain error that the sensor path's recalibration
    takes within its tolerance once the others are in the model. Taken while an effect
    not yet found pulled the path beyond it (and the path was held at nominal), it is a
    calibration: a strong independent temperature coupling (-15 urad/K) held the path,
    a "sensor gain error" of -16 % was named first and the coupling second, where the
    truth's path was -11 % (2.7 sigma) and no gain error at all."""
    gain = model[0].effects.sensor_gain_error
    if gain is None or len(found) < 2:
        return found, model
    others = [fx for fx in model[0].effects if fx.name != gain.name]
    # The other effect's size was fitted against the gain error: refitted with the knobs
    # (one of them, as `_recalibrated` can), or the path bends to its old size instead.
    # A hysteresis too, unlike `_refined_by_knobs`: here the knobs must take up the gain the
    # error held (strong independent Bouc-Wen 9003: refined, the gain error is dropped and
    # the gap is 12.9 nm; not, it stays first and the gap is 40 nm).
    refine = (others[0] if len(others) == 1 and not _noise_rung(others[0])
              and not others[0].own_score_only else None)
    again = _recalibrated(meas, dataclasses.replace(
        meas.config.plant, effects=model[0].effects.without(gain.name)), whole, excited, refine)
    recal = again[1]
    if recal is None or "sensor_path" not in {k.name for k in recal.knobs}:
        return found, model  # held: the log disputes the path even with the others
    for c in tried:
        if c.accepted and c.name == gain.name:
            c.accepted = False
            c.note = (f"dropped: with the other effects found, the sensor path recalibrates "
                      f"within its tolerance (pull {recal.pull('sensor_path'):+.1f} sigma)")
    kept = [dataclasses.replace(f, effect=getattr(again[0].effects, f.effect.name).canonical())
            for f in found if f.effect.name != gain.name]
    return kept, again


def normalised_gap(w: Blocks, before: np.ndarray, after: np.ndarray,
                   bands_hz: dict[str, tuple[float, float]] = BANDS_HZ
                   ) -> dict[str, dict[str, float] | None]:
    """Per band, the mean of the residual's periodogram over the noise spectrum `w` holds
    (fitted to what the final model leaves, on the held-out blocks), for the nominal model
    and the final one: 1 is as good as the noise allows, and the number says how far a
    model is from it in that band, which nm alone do not."""
    out: dict[str, dict[str, float] | None] = {}
    zb, za = w.zscores(before, known=False), w.zscores(after)
    low = np.concatenate([p.extrapolated() for p in w.parts])
    for name, (lo, hi) in bands_hz.items():
        sel = (w.f_hz >= lo) & (w.f_hz < hi) & ~low
        out[name] = (None if np.count_nonzero(sel) < 2 else
                     {"before": float(np.mean(zb[sel])), "after": float(np.mean(za[sel]))})
    return out


def _settled(meas: Measured, pred: Predictor, recal: Recalibration | None, nuisance: Nuisance,
             whole: slice) -> tuple[Predictor, Recalibration | None, Nuisance]:
    """The final model with its linear knobs where every comparison put them: solved on
    all bins of the whole log (the recalibration left lines out; the cooler's level lives
    in its lines). Without it the report's model and gap would be of a cooler level no
    score was computed with."""
    if recal is None or not nuisance.names:
        return pred, recal, nuisance
    w = make_whitener(meas, pred, whole)
    d = nuisance.on(w).knobs(w.whiten(meas.y_m - pred.base.y_m))[:len(nuisance.knobs)]
    params = apply(pred.params, nuisance.knobs, d)
    offset = dict(recal.offset)
    for k, dk in zip(nuisance.knobs, d, strict=True):
        offset[k.name] = (1 + offset[k.name]) * (1 + float(dk)) - 1
    recal = dataclasses.replace(recal, params=params, offset=offset)
    pred = Predictor(params, meas)
    return pred, recal, Nuisance(pred, recal, meas)


def _cost(meas: Measured, model: tuple[Predictor, Recalibration | None, Nuisance],
          w: Whitener | Blocks) -> float:
    """The whitened cost of a recalibrated model on `w`, its linear knobs solved out."""
    pred, _, nuisance = model
    return nuisance.on(w).cost(w.whiten(meas.y_m - pred.base.y_m))


def _effect_cost(fx: Effect, pred: Predictor, w: Whitener | Blocks, meas: Measured,
                 nuis: Projection) -> float:
    """The whitened cost on `w` of the model with `fx` as it is, its linear terms solved."""
    return with_states(nuis, w, pred, fx).cost(w.whiten(meas.y_m - pred.with_candidate(fx)))


def _refit(f: Fit, pred: Predictor, w: Whitener | Blocks, meas: Measured,
           nuis: Projection) -> Fit:
    """`f`'s effect fitted again on `w`: a mode rung by its own noise on its spectrum."""
    if isinstance(f.effect, ExtraResonance) and _noise_rung(f.effect):
        spectra = Spectra(w if isinstance(w, Blocks) else Blocks([w]),
                          meas.y_m - pred.base.y_m)
        fx, bump = _fit_bump(spectra, f.effect, meas.dt_s)
        return Fit(fx, spectra.sigma(bump), math.nan)
    return fit_effect(f.effect, pred, w, meas, nuis)


def _fit_bump(spectra: Spectra, start: ExtraResonance, dt_s: float, joint: bool = True
              ) -> tuple[ExtraResonance, Bump]:
    """A mode rung by its own noise, fitted to the bump in `spectra` near `start` (with
    `joint`, the blocks' smooth noise terms with it: see `Spectra.fit`)."""
    lo, hi = start.bounds("frequency_hz")
    bump = spectra.fit(start.frequency_hz, lo, min(hi, 0.95 * 0.5 / dt_s), start.bounds("q"),
                       joint)
    fx = start.replace(frequency_hz=bump.f0_hz, q=bump.q, gain=0.0, noise_rms_m=bump.rms_m)
    return fx, bump  # type: ignore[return-value]


@dataclass
class _Round:
    """What every family's candidates in one round are fitted on and scored against."""

    meas: Measured
    pred: Predictor
    w_train: Blocks
    w_test: Blocks
    n_train: Projection
    n_test: Projection
    white0_train: np.ndarray
    white0_test: np.ndarray
    cost0_train: float
    cost0_test: float
    ev: Evidence
    ev_test: Evidence
    round: int
    noise: float
    thresholds: dict[str, float] | None
    part_gains: list[np.ndarray]  # `nuisance.part_gains` of the log's parts
    _with_gains: tuple[Projection, Projection, float, float] | None = None

    def scored_on(self, cls: type[Effect]) -> tuple[Projection, Projection, float, float]:
        """The knobs on the training and held-out blocks, and the baseline's costs there,
        that `cls`'s candidates are fitted and scored with: for a family that must show
        more than a gain (`Effect.beyond_part_gains`), with a free gain per part (made
        once a round: each candidate's held-out check asks again)."""
        if not cls.beyond_part_gains:
            return self.n_train, self.n_test, self.cost0_train, self.cost0_test
        if self._with_gains is None:
            n_train = with_shapes(self.n_train, self.w_train, self.part_gains)
            n_test = with_shapes(self.n_test, self.w_test, self.part_gains)
            self._with_gains = (n_train, n_test, n_train.cost(self.white0_train),
                                predictive_cost(n_train, n_test, self.white0_train,
                                                self.white0_test))
        return self._with_gains


#: the round the forked workers of `_each_family` read (fork shares it, no pickling: its
#: whiteners hold closures)
_ROUND: tuple[list[type[Effect]], _Round] | None = None


def _family_at(i: int) -> tuple[list[Candidate], list[tuple[Fit, Candidate]]]:
    assert _ROUND is not None
    families, r = _ROUND
    return _family(families[i], r)


def _each_family(families: list[type[Effect]], r: _Round, jobs: int,
                 done: Callable[[int], None]
                 ) -> list[tuple[list[Candidate], list[tuple[Fit, Candidate]]]]:
    """`_family` of each, in order; over `jobs` forked processes when there are several
    (the families' fits are independent, and most of a round's time). `done` is told
    how many have finished."""
    global _ROUND
    out = []
    if jobs <= 1 or len(families) < 2:
        for cls in families:
            out.append(_family(cls, r))
            done(len(out))
        return out
    _ROUND = (families, r)
    try:
        with ProcessPoolExecutor(min(jobs, len(families)), mp_context=get_context("fork"),
                                 initializer=one_blas_thread) as pool:
            for result in pool.map(_family_at, range(len(families))):
                out.append(result)
                done(len(out))
            return out
    finally:
        _ROUND = None


def _family(cls: type[Effect], r: _Round) -> tuple[list[Candidate], list[tuple[Fit, Candidate]]]:
    """One family's fits in this round, each scored: (every candidate tried, those that
    passed the training, held-out, size and threshold tests)."""
    meas, pred, ev, ev_test, noise = r.meas, r.pred, r.ev, r.ev_test, r.noise
    w_train, w_test = r.w_train, r.w_test
    n_train, n_test, cost0_train, cost0_test = r.scored_on(cls)
    white0_train, white0_test, thresholds = r.white0_train, r.white0_test, r.thresholds
    tried: list[Candidate] = []
    passed: list[tuple[Fit, Candidate]] = []
    fits = []
    # the held-out whitened residual without a candidate, for `bandgate`
    e0 = predictive_residual(n_train, n_test, white0_train, white0_test)
    def penalty_of(fx: Effect) -> float:
        return len(fx.free) * math.log(2 * len(w_test.f_hz))

    for guess in cls.guesses(ev):
        f = fit_effect(guess, pred, w_train, meas, n_train)
        fits.append(f)
        # A variant refines what its fit found (a second play; a sine's sawtooth); where the
        # fit found nothing in the training part there is nothing to refine. On the
        # tuning logs every variant that held out came from a fit found there; on a null
        # day the rest were a quarter of the detector's time.
        if deviance(cost0_train, f.cost) > penalty_of(f.effect):
            fits += [fit_effect(v, pred, w_train, meas, n_train)
                     for v in f.effect.variants()]
    if cls is ExtraResonance:
        modes, ok = _rung_by_noise(ev, ev_test, len(w_test.f_hz), r.round, noise,
                                   (thresholds or {}).get(cls.name, 0.0))
        tried += modes
        passed += ok
    for f in fits:
        if why := f.effect.degenerate(ev):
            tried.append(Candidate(cls.name, f.effect.values(), 0.0, 0.0, 0.0,
                                   note=f"rejected: {why}", round=r.round))
            continue
        n_cand = with_states(n_test, w_test, pred, f.effect)
        n_cand_train = with_states(n_train, w_train, pred, f.effect)
        r_cand = meas.y_m - pred.with_candidate(f.effect)
        white_train = w_train.whiten(r_cand)
        white_test = w_test.whiten(r_cand)
        cost_test = predictive_cost(n_cand_train, n_cand, white_train, white_test)
        own = f.effect.held_out_deviance(ev_test)
        only_own = own is not None and f.effect.own_score_only
        own_score = -math.inf if own is None else own
        coherent = deviance(cost0_test, cost_test)
        penalty = penalty_of(f.effect)
        cand = Candidate(cls.name, f.effect.values(), deviance(cost0_train, f.cost),
                         own_score if only_own else max(coherent, own_score),
                         penalty, sigma=f.sigma, round=r.round,
                         threshold=max(penalty, (thresholds or {}).get(cls.name, 0.0)))
        tried.append(cand)
        if cand.deviance_train <= penalty:
            # Not found where it was fitted: what it gains on the held-out part is
            # chance (a null log's 0.3 % temperature coupling: 0.8 there, 22 held out).
            cand.note = "not found in the training part"
            continue
        if cand.deviance_test <= 0:  # no evidence at any threshold
            continue
        if only_own:  # the replay cannot weigh it: no size in bins to check
            cand.size_ok = True
            if cand.deviance_test > cand.threshold:
                passed.append((f, cand))
            continue
        # Statistically real is not enough: the forms and the noise spectrum are
        # approximations, and an effect must also move the reading by a share of
        # the sensor's own noise (rms over the held-out block where it moves it
        # most: an actuator effect acts where the modulation drives the piezo,
        # and a long closed-loop block would dilute it; a medium 17 ms delay,
        # 0.22 of the noise there and 0.197 over both, gave way to a 0.2 V play
        # with a tenth of its held-out evidence). Half of it where
        # the evidence needs the lowest bins of each block, whose noise level is
        # extrapolated, not fitted (a 70 pm drift over a night is not a finding,
        # however well a fit pins it down); a fifth where the fitted bins alone
        # hold it (a 32 ms delay moves it by 0.4 of the noise at the modulation's
        # lines and the resonance; a null log's 64 mV play, by 0.06).
        fitted = w_test.fitted()
        in_fitted = max(deviance(predictive_cost(n_train, n_test, white0_train,
                                                 white0_test, fitted),
                                 predictive_cost(n_cand_train, n_cand, white_train,
                                                 white_test, fitted)),
                        own_score) > cand.penalty
        # An exact form (a delay) half of that in the fitted bins: the triangle-modulated
        # weak delays of four tuning logs (12.3-17.0 ms) were fitted within 25 % and held
        # out at 111-288, and moved the reading by 0.12-0.16 of the noise.
        share = (_MIN_NOISE_SHARE_FITTED * (0.5 if f.effect.exact_form else 1.0)
                 if in_fitted else _MIN_NOISE_SHARE)
        change = pred.physical_change(f.effect)
        size = max(float(np.std(change[span])) for span in w_test.spans)
        if size > share * noise:
            e = predictive_residual(n_cand_train, n_cand, white_train, white_test)
            cand.bands = band_changes(w_test.f_hz, bin_power(w_test, e0), bin_power(w_test, e),
                                      bin_power(w_test, e0 - e), GATE_BANDS_HZ)
            if why := worse_band(cand.bands):
                cand.note = f"rejected: it {why}"
                continue
            cand.size_ok = True
            if cand.deviance_test > cand.threshold:
                passed.append((f, cand))
        else:
            where = ("" if in_fitted else
                     ", its evidence in the lowest bins, where the noise is a guess")
            cand.note = (f"changes the reading by only {size * 1e9:.2g} nm rms, "
                         f"{size / noise:.2g} of the sensor noise{where}")
    return tried, passed


def _not_a_mode(ev: Evidence, spectra: Spectra, fx: ExtraResonance, bump: Bump) -> str:
    """Why a bump fitted to `spectra` is no mode rung by noise ("" if it is one): the
    form's own rule (the pendulum's band, a band under a few bins: a line) or a comb of
    lines that a broad bump also raises the likelihood for."""
    if why := fx.degenerate(ev):
        return why
    if (share := spectra.spread(bump)) < MIN_SPREAD:
        return (f"the typical bin of its band carries {share:.0%} of its power: lines "
                "(a comb of harmonics), not a mode rung by noise")
    return ""


def _mode_near(ev: Evidence, spectra: Spectra, f_hz: float, joint: bool = True
               ) -> tuple[ExtraResonance, Bump, str]:
    """A mode rung by noise fitted to `spectra` near `f_hz`, and why it is none."""
    start = ExtraResonance(frequency_hz=f_hz, noise_rms_m=1e-12)
    lo, hi = start.bounds("frequency_hz")
    if lo >= hi:
        return start, Bump(f_hz, start.q, 0.0, 0.0), (
            f"at {f_hz * 1e3:.3g} mHz it is in the drifts' band, below any mode's")
    fx, bump = _fit_bump(spectra, start, ev.sig.dt_s, joint)
    return fx, bump, _not_a_mode(ev, spectra, fx, bump)


def _rung_by_noise(ev: Evidence, ev_test: Evidence, bins_test: int, round_: int,
                   noise_m: float, calibrated: float
                   ) -> tuple[list[Candidate], list[tuple[Fit, Candidate]]]:
    """Modes rung by their own noise, fitted as bumps of the training blocks' spectra
    and scored on the held-out blocks' with all three numbers fixed (`leveler.analysis.
    bump`): replay cannot predict a sample of them, so their evidence is in the power
    alone. (tried, passed), judged like every candidate: found in training, a penalty
    or the calibrated threshold held out, and a size of a fifth of the sensor noise."""
    tried: list[Candidate] = []
    passed: list[tuple[Fit, Candidate]] = []
    train, test = ev.spectra(), ev_test.spectra()
    penalty = 3 * math.log(2 * bins_test)
    for f_hz in ExtraResonance.noise_guesses(ev):
        fx, bump, why = _mode_near(ev, train, f_hz, joint=False)
        if not why and bump.deviance > penalty:  # worth the joint fit's seconds
            fx, bump = _fit_bump(train, fx, ev.sig.dt_s)
            why = _not_a_mode(ev, train, fx, bump)
        if why:
            tried.append(Candidate(fx.name, fx.values(), 0.0, 0.0, 0.0,
                                   note=f"rejected: {why}", round=round_))
            continue
        cand = Candidate(fx.name, fx.values(), bump.deviance,
                         test.deviance(bump.f0_hz, bump.q, bump.rms_m), penalty,
                         sigma=train.sigma(bump), round=round_,
                         threshold=max(penalty, calibrated))
        tried.append(cand)
        if cand.deviance_train <= penalty:
            cand.note = "not found in the training part"
        elif bump.rms_m <= _MIN_NOISE_SHARE_FITTED * noise_m:
            cand.note = (f"rings by only {bump.rms_m * 1e9:.2g} nm rms, "
                         f"{bump.rms_m / noise_m:.2g} of the sensor noise")
        else:
            cand.size_ok = True
            if cand.deviance_test > cand.threshold:
                passed.append((Fit(fx, cand.sigma, math.nan), cand))
    return tried, passed


def _select(passed: list[tuple[Fit, Candidate]], held_out: Callable[[Fit], Fit]
            ) -> list[tuple[Fit, Candidate, Fit]]:
    """The best candidate whose fit to the held-out part alone (`held_out`) agrees with it,
    and the best of another family that also does if its evidence is within the ambiguity
    margin: [] (none holds up), [best] or [best, rival] (the log cannot tell them apart)."""
    stable: list[tuple[Fit, Candidate, Fit]] = []
    for f, cand in sorted(passed, key=lambda p: -p[1].score):
        if stable and (cand.name == stable[0][1].name or not _close(stable[0][1], cand)):
            continue  # only a rival family within the margin needs checking
        check = held_out(f)
        if _stable(f.effect, check.effect):
            stable.append((f, cand, check))
            if len(stable) == 2:
                break
        else:
            cand.note = f"held-out part disagrees: size {check.effect.size():.3g}"
    noisy = [_noise_rung(f.effect) for f, _, _ in stable]
    if len(stable) == 2 and noisy[0] != noisy[1]:
        # What a replay predicts sample by sample is no noise, and its misprediction is a
        # bump of power too: a strong 44 ms delay tied with a 1.14 Hz mode rung by noise.
        return [s for s, n in zip(stable, noisy, strict=True) if not n]
    told = [_size_told(f) for f, _, _ in stable]
    if len(stable) == 2 and told[0] != told[1]:
        # A fit whose own uncertainty cannot tell its size from nothing holds the other's
        # shape by a ridge of its parameters, not as itself: a strong curved drift (32
        # pm/s) tied with a coupling of 2.6 +- 14.6 urad/K through lags of 17,400 s and
        # 3,860 s, which together only make a slow bend of the temperature.
        return [s for s, t in zip(stable, told, strict=True) if t]
    return stable


#: a fit's size within this many of its own 1-sigma of zero is not told by the log
SIZE_TOLD_Z = 2.0


def _size_told(f: Fit) -> bool:
    """Does the fit's uncertainty tell its size from zero (SIZE_TOLD_Z)? A fit that
    gives no uncertainty for it (a bump's) is taken at its word."""
    fx = f.effect
    sigma = f.sigma.get(fx.magnitude)
    return sigma is None or abs(float(getattr(fx, fx.magnitude))) > SIZE_TOLD_Z * sigma


def _noise_rung(fx: Effect) -> bool:
    return isinstance(fx, ExtraResonance) and fx.rung_by_noise


def _refined_by_knobs(fx: Effect) -> bool:
    """Is a found effect refitted with the knobs by replay's likelihood alone? Not a mode
    rung by noise (it changes no prediction), not one scored by its own evidence or beyond
    a gain per part: that is not what found it (see `_confirm`)."""
    return not (_noise_rung(fx) or fx.own_score_only or fx.beyond_part_gains)


def _close(best: Candidate, other: Candidate) -> bool:
    """Is `other`'s held-out evidence within the ambiguity margin of `best`'s?"""
    return best.score - other.score < max(AMBIGUITY, AMBIGUITY_REL * best.score)


def residual(meas: Measured, pred: Predictor, span: slice) -> np.ndarray:
    """Measured minus predicted on `span`, offset removed: what the model leaves
    unexplained."""
    r = (meas.y_m - pred.base.y_m)[span]
    return r - r.mean()


def gap(meas: Measured, pred: Predictor, span: slice,
        bands_hz: dict[str, tuple[float, float]] = BANDS_HZ) -> dict[str, Any]:
    """Residual RMS overall and in the paper's bands (RMS and mean ASD per band)."""
    r = residual(meas, pred, span)
    y = meas.y_m[span] - meas.y_m[span].mean()
    dt = meas.dt_s
    p = hann_psd(r, dt)
    f = np.fft.rfftfreq(len(r), dt)
    df = f[1] - f[0]
    bands: dict[str, float | None] = {}
    asd: dict[str, float | None] = {}
    for name, (lo, hi) in bands_hz.items():
        sel = (f >= lo) & (f < hi)
        if np.count_nonzero(sel) < 2:
            bands[name] = asd[name] = None
            continue
        bands[name] = float(math.sqrt(np.sum(p[sel]) * df))
        asd[name] = float(math.sqrt(np.mean(p[sel])))
    var_y = float(np.var(y))
    return {
        "rms_m": float(np.sqrt(np.mean(r**2))),
        "band_rms_m": bands,
        "band_asd_m_rthz": asd,
        "variance_explained": 1.0 - float(np.var(r)) / var_y if var_y > 0 else None,
    }
