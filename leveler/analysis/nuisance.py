"""The recalibrated numbers, refitted with every candidate effect.

Recalibration (`leveler.analysis.recalibrate`) fits the model's stated numbers to the log
before any effect is looked for. Fixed there, they would leave a candidate to explain
whatever an in-tolerance change of them could: a sawtooth at the cooler's own period is the
cooler a little stronger, a "hysteresis" that is mostly a gain is the actuator path. So
each candidate is fitted jointly with them, and so is the baseline it is compared with,
under the same Gaussian priors: a candidate then scores only what no knob within its
tolerance explains.

The knobs the reading is linear in (the path gains, the thermal coefficient, the cooler's
level) enter as columns d(reading)/d(offset) about the recalibrated model. That keeps the
joint fit a small linear solve inside the candidate's own (variable projection), cheap
enough to run in every cost evaluation. The resonance frequency and Q are not linear, and
linearized they let a candidate trade its timing for a resonance (a sawtooth's drop 5 ms
late "explained" by a Q 13 % high): they stay at their recalibrated values in a fit and
are recalibrated again once an effect is found.

The lags' states at the log's start (the table's thermal lag, a found coupling's, and a
candidate coupling's own: `with_states`) are columns too, with no prior: the replay fits
them once, to the baseline's residual, and a candidate that shares their slow shape (a
sensor drift against a log that starts out of equilibrium) would otherwise be judged
against a start the baseline bent towards itself (a strong drift's rate came out at a
third of the truth, held-out evidence -231; solved with the state, -2.7e-11 m/s against
the truth's mean -2.8e-11, held-out +44).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from leveler.analysis.predict import Measured, Predictor, sensor_noise_m
from leveler.analysis.recalibrate import Recalibration, apply, replayable
from leveler.analysis.whittle import ENBW_BINS, Blocks, Whitener
from leveler.sim.effects import Effect

_STEP = 0.1  # finite-difference step, in prior sigmas
#: A start state's column moves the reading by the sensor noise per unit; a ridge (a prior
#: of this many of those, 1-sigma) only keeps the solve regular when a state's shape has
#: decayed before a block begins.
_STATE_SIGMA = 1e4
_FREE = np.sqrt(ENBW_BINS / 2) / _STATE_SIGMA  # that prior's gain, in the whitened cost
LINEAR = ("sensor_path", "actuator_path", "thermal_tilt", "cooler_amplitude")


class Nuisance:
    """The recalibrated knobs of one model and one log as linear columns with priors."""

    def __init__(self, pred: Predictor, recal: Recalibration | None, meas: Measured) -> None:
        ks = [k for k in recal.knobs if k.name in LINEAR] if recal is not None else []
        self.knobs = ks
        self.names = tuple(k.name for k in ks)
        cols = []
        smooth = replayable(pred.params)  # a converter's staircase has no slope to take
        about = pred if smooth is pred.params or not ks else Predictor(smooth, meas)
        for i, k in enumerate(ks):
            h = _STEP * k.sigma
            step = np.where(np.arange(len(ks)) == i, h, 0.0)
            moved = Predictor(apply(smooth, ks, step), meas)
            cols.append((moved.base.y_m - about.base.y_m) / h)
        states = _scaled(pred, pred.start_shapes(pred.effects))
        self.columns = np.array(cols + states).reshape(len(ks) + len(states), len(meas.y_m))
        # A prior on the total offset from nominal, x + d (1 + x) with d the relative change
        # about the recalibrated value x, in the whitened cost's units (-2 log p = z^2 and a
        # cost is ENBW_BINS / 2 of -2 log-likelihood).
        root = np.sqrt(ENBW_BINS / 2)
        x = np.array([recal.offset[n] for n in self.names]) if recal is not None else []
        sigma = np.array([k.sigma for k in ks])
        self.prior_gain = root * (1 + np.asarray(x)) / sigma if ks else np.zeros(0)
        self.prior_shift = root * np.asarray(x) / sigma if ks else np.zeros(0)
        self.states = len(states)

    def on(self, w: Whitener | Blocks) -> Projection:
        return Projection(np.array([w.whiten(c) for c in self.columns]).T
                          if len(self.columns) else np.zeros((0, 0)),
                          self.prior_gain, self.prior_shift, self.states)


def _scaled(pred: Predictor, shapes: list[np.ndarray]) -> list[np.ndarray]:
    """Start-state shapes rescaled to move the reading by the sensor noise (rms) per unit."""
    noise = sensor_noise_m(pred.params, pred.meas.dt_s)
    return [s * (noise / rms) for s in shapes if (rms := float(np.sqrt(np.mean(s**2)))) > 0]


def with_states(proj: Projection, w: Whitener | Blocks, pred: Predictor, fx: Effect,
                keep: Any = slice(None)) -> Projection:
    """`proj` with the candidate's own start states (`Predictor.state_shapes`) free beside
    the knobs, on the whitened numbers `keep`. Fitted by plain least squares on the raw
    residual instead, a coupling's start took up slow structure the calibration left
    and turned the fit's sign (a 2.6 urad/K coupling fitted at -3.3, worse than none by
    714 where the truth gains 559)."""
    return with_shapes(proj, w, _scaled(pred, pred.state_shapes(fx)), keep)


def with_shapes(proj: Projection, w: Whitener | Blocks, shapes: list[np.ndarray],
                keep: Any = slice(None)) -> Projection:
    """`proj` with `shapes` (readings [m], scaled like `_scaled`'s) free beside the knobs."""
    if not shapes:
        return proj
    return proj.extended(np.array([w.whiten(s)[keep] for s in shapes]).T)


def part_gains(pred: Predictor, parts: list[slice]) -> list[np.ndarray]:
    """The reading's response to the logged command, one shape per part of the log (zero
    outside it; its mean in it removed): free, they are an actuator gain of each part's
    own, for an effect that must show more than a gain (`Effect.beyond_part_gains`)."""
    u = pred.meas.u_v
    response = pred.pend(pred.actuator_tilt(u - u[0]))
    shapes = []
    for part in parts:
        s = np.zeros_like(response)
        s[part] = response[part] - np.mean(response[part])
        shapes.append(s)
    return _scaled(pred, shapes)


def _joint(train: Projection, test: Projection, keep: Any = slice(None)) -> Projection:
    """The knobs of both parts at once (the held-out rows `keep` of them)."""
    return Projection(np.vstack([train.g, test.g[keep]]), train.p, train.q, train.free)


def predictive_cost(train: Projection, test: Projection, white_train: np.ndarray,
                    white_test: np.ndarray, keep: Any = slice(None)) -> float:
    """The held-out part's cost given the training part: the knobs solved on both at once,
    less the training part's own cost, so the held-out numbers (`keep` of them) are
    explained only by knobs and start states the training part also allows.

    Solved on a third of the log alone, they let the baseline take up there what a
    candidate would explain: the thermal knob and a lag's start bend to a third's trend
    as well as a drift does, and the drift's held-out evidence was lost."""
    if train.k == 0:
        wt = white_test[keep]
        return float(wt @ wt)
    return (_joint(train, test, keep).cost(np.concatenate([white_train, white_test[keep]]))
            - train.cost(white_train))


def predictive_residual(train: Projection, test: Projection, white_train: np.ndarray,
                        white_test: np.ndarray) -> np.ndarray:
    """The held-out part's whitened residual with the knobs solved as `predictive_cost`
    solves them (on both parts at once)."""
    if train.k == 0:
        return white_test
    n = len(white_train)
    e = _joint(train, test)._solve_d(np.concatenate([white_train, white_test]))
    return e[n:n + len(white_test)]


class Projection:
    """The nuisance columns whitened on one span: residuals with the knobs solved out."""

    def __init__(self, g: np.ndarray, prior_gain: np.ndarray, prior_shift: np.ndarray,
                 free: int = 0) -> None:
        """Columns of `g`: the knobs with their priors, then `free` ones without (start
        states). A free column adds no row to the residual, so the residual's length does
        not change with how many a candidate has (a least-squares fit needs it fixed)."""
        self.g = g
        self.k = len(prior_gain) + free
        self.free = free
        self.p = prior_gain
        self.q = prior_shift
        # the free columns' tiny ridge only keeps the solve regular
        ridge = np.concatenate([prior_gain**2, np.full(free, _FREE**2)])
        self.gtg = g.T @ g + np.diag(ridge) if self.k else np.zeros((0, 0))
        self.shift = np.concatenate([prior_gain * prior_shift, np.zeros(free)])

    def residual(self, white: np.ndarray, c: np.ndarray | None = None,
                 bounds: tuple[float, float] | None = None) -> tuple[float, np.ndarray]:
        """Minimise |white - beta c - G d|^2 + |q + P d|^2 over d (and beta, if a column
        `c` is given, kept within `bounds`): (beta, the residual with the prior rows
        appended). Its squared norm is the cost the candidate is scored by."""
        if c is None:
            return 0.0, self._solve_d(white)
        if self.k == 0:
            cc = float(c @ c)
            beta = float(c @ white) / cc if cc > 0 else 0.0
        else:
            gc = self.g.T @ c
            a = np.block([[np.array([[c @ c]]), gc[None, :]], [gc[:, None], self.gtg]])
            b = np.concatenate([[c @ white], self.g.T @ white - self.shift])
            try:
                beta = float(np.linalg.solve(a, b)[0])
            except np.linalg.LinAlgError:
                beta = 0.0
        if bounds is not None:
            beta = min(max(beta, bounds[0]), bounds[1])
        return beta, self._solve_d(white - beta * c)

    def extended(self, cols: np.ndarray) -> Projection:
        """These knobs and, free, the whitened columns `cols` (one per column)."""
        g = cols if self.k == 0 else np.hstack([self.g, cols])
        return Projection(g, self.p, self.q, self.free + cols.shape[1])

    def restricted(self, keep: np.ndarray) -> Projection:
        """The same knobs on a subset of the whitened numbers (a coarse fit's low bins)."""
        return Projection(self.g[keep] if self.k else self.g, self.p, self.q, self.free)

    def knobs(self, white: np.ndarray) -> np.ndarray:
        """The knobs' relative changes d that best explain `white` under their priors (the
        calibration knobs first, then the start states')."""
        if self.k == 0:
            return np.zeros(0)
        return np.linalg.solve(self.gtg, self.g.T @ white - self.shift)

    def _solve_d(self, white: np.ndarray) -> np.ndarray:
        if self.k == 0:
            return white
        d = self.knobs(white)
        return np.concatenate([white - self.g @ d, self.q + self.p * d[:len(self.p)]])

    def cost(self, white: np.ndarray) -> float:
        e = self._solve_d(white)
        return float(e @ e)
