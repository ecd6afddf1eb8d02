"""A fit's Jacobian steps by a fixed share of each parameter's scale
(`steps.stepped_least_squares`), not relative to the parameter: a fit starts at x = 0, where
a relative step is scipy's 1.5e-8 fallback, below the rounding of a replay's solve."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from leveler.analysis.steps import FIT_STEP, stepped_least_squares

TARGET = np.array([3.0, -2.0])
BOX = (np.full(2, -50.0), np.full(2, 50.0))


def _rounded(x: np.ndarray) -> np.ndarray:
    """A cost whose residuals are known to 1e-7 only, as a solve's rounding leaves them."""
    return np.round(np.concatenate([x - TARGET, 0.3 * (x - TARGET) ** 2]), 7)


def test_a_fit_at_its_start_steps_by_its_scale_and_finds_the_minimum() -> None:
    assert least_squares(_rounded, np.zeros(2), diff_step=FIT_STEP, bounds=BOX,
                         max_nfev=60).x == pytest.approx(np.zeros(2))  # scipy's: stuck
    fit = stepped_least_squares(_rounded, np.zeros(2), BOX, 60)
    assert fit.x == pytest.approx(TARGET, abs=1e-3)


def test_at_the_upper_bound_it_steps_back_and_never_outside() -> None:
    """A minimum beyond the box: the fit ends on the bound, and no residual is asked for
    outside it (a play width or a lag past its bound is no model)."""
    seen: list[np.ndarray] = []

    def fun(x: np.ndarray) -> np.ndarray:
        seen.append(x.copy())
        return x - np.array([80.0, -2.0])

    x = stepped_least_squares(fun, np.zeros(2), BOX, 60).x
    assert x == pytest.approx([50.0, -2.0], abs=1e-3)
    assert max(float(v[0]) for v in seen) <= 50.0
