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
"""

from __future__ import annotations

import numpy as np

from leveler.analysis.predict import Measured, Predictor
from leveler.analysis.recalibrate import Recalibration, apply
from leveler.analysis.whittle import ENBW_BINS, Whitener

_STEP = 0.1  # finite-difference step, in prior sigmas
LINEAR = ("sensor_path", "actuator_path", "thermal_tilt", "cooler_amplitude")


class Nuisance:
    """The recalibrated knobs of one model and one log as linear columns with priors."""

    def __init__(self, pred: Predictor, recal: Recalibration | None, meas: Measured) -> None:
        ks = [k for k in recal.knobs if k.name in LINEAR] if recal is not None else []
        self.knobs = ks
        self.names = tuple(k.name for k in ks)
        cols = []
        for i, k in enumerate(ks):
            h = _STEP * k.sigma
            step = np.where(np.arange(len(ks)) == i, h, 0.0)
            moved = Predictor(apply(pred.params, ks, step), meas)
            cols.append((moved.base.y_m - pred.base.y_m) / h)
        self.columns = np.array(cols).reshape(len(ks), len(meas.y_m))
        # A prior on the total offset from nominal, x + d (1 + x) with d the relative change
        # about the recalibrated value x, in the whitened cost's units (-2 log p = z^2 and a
        # cost is ENBW_BINS / 2 of -2 log-likelihood).
        root = np.sqrt(ENBW_BINS / 2)
        x = np.array([recal.offset[n] for n in self.names]) if recal is not None else []
        sigma = np.array([k.sigma for k in ks])
        self.prior_gain = root * (1 + np.asarray(x)) / sigma if ks else np.zeros(0)
        self.prior_shift = root * np.asarray(x) / sigma if ks else np.zeros(0)

    def on(self, w: Whitener) -> Projection:
        return Projection(np.array([w.whiten(c) for c in self.columns]).T
                          if len(self.names) else np.zeros((0, 0)),
                          self.prior_gain, self.prior_shift)


class Projection:
    """The nuisance columns whitened on one span: residuals with the knobs solved out."""

    def __init__(self, g: np.ndarray, prior_gain: np.ndarray, prior_shift: np.ndarray):
        self.g = g
        self.k = len(prior_gain)
        self.p = prior_gain
        self.q = prior_shift
        self.gtg = g.T @ g + np.diag(prior_gain**2) if self.k else np.zeros((0, 0))

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
            b = np.concatenate([[c @ white], self.g.T @ white - self.p * self.q])
            try:
                beta = float(np.linalg.solve(a, b)[0])
            except np.linalg.LinAlgError:
                beta = 0.0
        if bounds is not None:
            beta = min(max(beta, bounds[0]), bounds[1])
        return beta, self._solve_d(white - beta * c)

    def restricted(self, keep: np.ndarray) -> Projection:
        """The same knobs on a subset of the whitened numbers (a coarse fit's low bins)."""
        return Projection(self.g[keep] if self.k else self.g, self.p, self.q)

    def knobs(self, white: np.ndarray) -> np.ndarray:
        """The knobs' relative changes d that best explain `white` under their priors."""
        if self.k == 0:
            return np.zeros(0)
        return np.linalg.solve(self.gtg, self.g.T @ white - self.p * self.q)

    def _solve_d(self, white: np.ndarray) -> np.ndarray:
        if self.k == 0:
            return white
        d = self.knobs(white)
        return np.concatenate([white - self.g @ d, self.q + self.p * d])

    def cost(self, white: np.ndarray) -> float:
        e = self._solve_d(white)
        return float(e @ e)
