"""Least squares whose Jacobian steps by a fixed share of each parameter's scale.

Every fit here works in scale units and starts at x = 0 (its start, or the nominal
model). scipy's `diff_step` is relative to x, and at x = 0 it falls back to steps of
1.5e-8, below the rounding of a replay's solve: a lag moved by microseconds, and the
first Jacobian was noise."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.optimize import OptimizeResult, least_squares

#: the finite-difference step of a fit's Jacobian, in units of each parameter's scale
FIT_STEP = 1e-3


def stepped_least_squares(fun: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
                          box: tuple[np.ndarray, np.ndarray], max_nfev: int,
                          x_scale: str | float = 1.0) -> OptimizeResult:
    """`scipy.optimize.least_squares` from `x0` within `box`, its Jacobian by forward
    differences of FIT_STEP (backwards at the upper bound, so no residual is asked for
    outside the box). A two-lag coupling fitted with scipy's steps stopped at its start
    (1,800 s and 120 s, the truth's 853 s and 355 s) with the lags "known" to 2 and 11 s;
    stepped by its scale it goes to 941 s and 316 s. The residual least_squares has just
    computed at x is reused for the Jacobian there."""
    last: dict[str, np.ndarray] = {}

    def f(x: np.ndarray) -> np.ndarray:
        last["x"], last["e"] = x.copy(), fun(x)
        return last["e"]

    def jac(x: np.ndarray) -> np.ndarray:
        e0 = last["e"] if "x" in last and np.array_equal(last["x"], x) else fun(x)
        cols = []
        for i in range(len(x)):
            h = FIT_STEP if x[i] + FIT_STEP <= box[1][i] else -FIT_STEP
            moved = x.copy()
            moved[i] += h
            cols.append((fun(moved) - e0) / h)
        return np.column_stack(cols)

    return least_squares(f, x0, jac=jac, bounds=box, x_scale=x_scale, max_nfev=max_nfev)
