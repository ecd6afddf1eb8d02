"""The recalibrated knobs solved with a candidate's size (leveler.analysis.nuisance): the
algebra of the joint linear solve under Gaussian priors."""

from __future__ import annotations

import numpy as np
import pytest

from leveler.analysis.nuisance import Projection, predictive_cost
from leveler.analysis.whittle import ENBW_BINS

ROOT = np.sqrt(ENBW_BINS / 2)


def _problem(seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((400, 2))
    c = rng.standard_normal(400)
    white = 0.7 * c + g @ np.array([0.3, -0.2]) + 0.01 * rng.standard_normal(400)
    return g, c, white


def test_without_knobs_it_is_the_candidate_alone() -> None:
    _, c, white = _problem()
    empty = Projection(np.zeros((0, 0)), np.zeros(0), np.zeros(0))
    beta, e = empty.residual(white, c)
    assert beta == pytest.approx(float(c @ white) / float(c @ c))
    np.testing.assert_allclose(e, white - beta * c)
    assert empty.cost(white) == pytest.approx(float(white @ white))


def test_loose_priors_free_the_knobs_and_tight_ones_pin_them() -> None:
    g, c, white = _problem()
    loose = Projection(g, ROOT / np.array([1e6, 1e6]), np.zeros(2))  # sigma 1e6: free
    beta, e = loose.residual(white, c)
    full, *_ = np.linalg.lstsq(np.column_stack([c, g]), white, rcond=None)
    assert beta == pytest.approx(full[0], rel=1e-6)  # the joint least squares
    assert float(e @ e) < 0.05  # only the 1 % noise is left
    tight = Projection(g, ROOT / np.array([1e-9, 1e-9]), np.zeros(2))  # sigma 1e-9: fixed
    beta_t, _ = tight.residual(white, c)
    assert beta_t == pytest.approx(float(c @ white) / float(c @ c), rel=1e-6)


def test_the_prior_is_on_the_offset_from_nominal_not_from_the_recalibrated_value() -> None:
    """A knob recalibrated to x = 2 sigma, with nothing in the data to move it: the
    prior alone takes the total offset x + d (1 + x) back to nominal (its row zero)."""
    sigma, x = 0.1, 0.2
    p = np.array([ROOT * (1 + x) / sigma])
    q = np.array([ROOT * x / sigma])
    nuis = Projection(np.zeros((1, 1)), p, q)  # the data says nothing about this knob
    e = nuis.residual(np.zeros(1))[1]
    assert e[-1] == pytest.approx(0.0, abs=1e-12)
    assert nuis.cost(np.zeros(1)) == pytest.approx(0.0, abs=1e-20)


def test_restricted_to_bins_equals_the_problem_on_those_bins() -> None:
    g, c, white = _problem(2)
    p, q = ROOT / np.array([0.05, 0.2]), ROOT * np.array([0.5, -1.0])
    keep = np.arange(400) < 150
    beta_r, e_r = Projection(g, p, q).restricted(keep).residual(white[keep], c[keep])
    beta_d, e_d = Projection(g[keep], p, q).residual(white[keep], c[keep])
    assert beta_r == pytest.approx(beta_d)
    np.testing.assert_allclose(e_r, e_d)
    # Bounds on the candidate's size hold, and the knobs are solved again at the bound.
    beta_b, e_b = Projection(g, p, q).residual(white, c, (-1.0, 0.1))
    assert beta_b == 0.1
    np.testing.assert_allclose(e_b, Projection(g, p, q).residual(white - 0.1 * c)[1])


def test_extended_columns_are_free_beside_the_knobs() -> None:
    """A start state added to tight knobs is solved as plain least squares would, the
    knobs still pinned; with no knobs at all it is the state alone."""
    g, c, white = _problem(3)
    state = np.random.default_rng(4).standard_normal(400)
    white = white + 2.5 * state
    tight = Projection(g, ROOT / np.array([1e-9, 1e-9]), np.zeros(2))
    beta, _ = tight.extended(state[:, None]).residual(white, c)
    full, *_ = np.linalg.lstsq(np.column_stack([c, state]), white, rcond=None)
    assert beta == pytest.approx(full[0], rel=1e-6)
    empty = Projection(np.zeros((0, 0)), np.zeros(0), np.zeros(0))
    alone = empty.extended(state[:, None])
    assert alone.knobs(white) == pytest.approx([float(state @ white) / float(state @ state)],
                                               rel=1e-6)


def test_held_out_cost_keeps_the_knobs_the_training_part_allows() -> None:
    """A free trend column (a lag's start state): on the training part the data has
    none. Solved on the held-out part alone it takes up a trend that appears only there,
    and the baseline is left with nothing to explain; given the training part it may not,
    and the trend stays in the held-out cost. Where both parts agree, the held-out cost
    is that of the knobs the training part fits (about one per number)."""
    rng = np.random.default_rng(5)
    n = 600
    ramp = np.linspace(-1.0, 1.0, 2 * n)[:, None]
    g_train, g_test = ramp[:n], ramp[n:]
    train = Projection(g_train, np.zeros(0), np.zeros(0), free=1)
    test = Projection(g_test, np.zeros(0), np.zeros(0), free=1)
    noise_train, noise_test = rng.standard_normal(n), rng.standard_normal(n)
    trend = 20.0 * (g_test[:, 0] - g_test[0, 0])  # only in the held-out part
    alone = test.cost(noise_test + trend)
    given = predictive_cost(train, test, noise_train, noise_test + trend)
    assert alone < 1.5 * n  # re-solved there, the ramp's trend is mostly gone
    assert given > 10 * n  # the training part pins the ramp: the trend is left
    agreeing = predictive_cost(train, test, noise_train + 3.0 * g_train[:, 0],
                               noise_test + 3.0 * g_test[:, 0])
    assert agreeing == pytest.approx(float(noise_test @ noise_test), rel=0.05)
    none = Projection(np.zeros((0, 0)), np.zeros(0), np.zeros(0))
    assert predictive_cost(none, none, noise_train, noise_test) == pytest.approx(
        float(noise_test @ noise_test))
