"""The lattice scan that proposes ADC quantization: a coarse converter seen through a finer
one with a little analog noise between them (issue 17: the smallest-step estimate used to
see one count of the fine converter and never tried quantization)."""

from __future__ import annotations

import numpy as np
import pytest

from leveler.analysis.evidence import (
    find_lattice,
    lattice_deviance,
    modulation_hz,
    readings_on_levels,
)
from leveler.sim.effects import LEVEL_WINDOWS, LEVEL_Z

LSB_M = 20.0 / 2**16 / 2.0e5  # the default 16-bit, +-10 V ADC at 2e5 V/m: 1.53 nm


def reading(rng: np.random.Generator, step_m: float | None, analog_counts: float,
            n: int = 36_000) -> np.ndarray:
    """A slow wander with white sensor noise, through an optional coarse converter (its
    lattice offset at random), analog noise, and the fine ADC."""
    x = np.cumsum(rng.normal(0.0, 0.3e-9, n)) + rng.normal(0.0, 1.1e-9, n)
    if step_m is not None:
        off = rng.uniform(0.0, step_m)
        x = off + step_m * np.round((x - off) / step_m)
    x = x + rng.normal(0.0, analog_counts * LSB_M, n)
    return LSB_M * np.round(x / LSB_M)


@pytest.mark.parametrize("step_m", [4.6e-9, 1.0e-8, 2.5e-8])
def test_a_coarse_converter_behind_noise_and_a_fine_one_is_found(step_m: float) -> None:
    rng = np.random.default_rng(17)
    found = find_lattice([reading(rng, step_m, analog_counts=0.3)], LSB_M)
    assert found is not None
    # A starting guess: within 5 % (the fine converter rounds each change by up to
    # half a count, a third of the smallest step here); the fit refines it.
    assert found[0] == pytest.approx(step_m, rel=0.05)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_large_changes_of_a_few_steps_do_not_make_a_coarser_lattice(seed: int) -> None:
    """A square's edges the model does not predict, six steps each, line up on a lattice
    of six steps as well as on the converter's: a strong independent converter of 23.6 nm
    was taken for a 145 nm one, and quantization was never fitted. The converter's own
    steps line up far more strongly."""
    rng = np.random.default_rng(seed)
    step_m, n = 2.36e-8, 36_000
    x = np.cumsum(rng.normal(0.0, 0.3e-9, n)) + rng.normal(0.0, 8e-9, n)
    square = 6 * step_m * (np.arange(n) // 300 % 2)
    off = rng.uniform(0.0, step_m)
    x = off + step_m * np.round((x + square - off) / step_m) + rng.normal(0.0, 0.2 * LSB_M, n)
    found = find_lattice([LSB_M * np.round(x / LSB_M)], LSB_M)
    assert found is not None and found[0] == pytest.approx(step_m, rel=0.05)


def test_a_lattice_the_model_predicts_the_small_changes_of_is_found() -> None:
    """Changes the model predicts are left out (a modulation's, `_unpredicted`); where it
    predicts a few nanometres every sample (a closed loop hunting across a coarse
    converter's levels, replayed), no small trial step keeps any change, and the scan
    must go on to the steps that do: it stopped at the first, and a strong 23.6 nm
    converter was never fitted."""
    rng = np.random.default_rng(4)
    step_m, n = 2.36e-8, 36_000
    predicted = 2e-9 * (-1.0) ** np.arange(n)  # 4 nm changes every sample
    x = predicted + np.cumsum(rng.normal(0.0, 0.3e-9, n)) + rng.normal(0.0, 8e-9, n)
    x = step_m * np.round(x / step_m) + rng.normal(0.0, 0.2 * LSB_M, n)
    found = find_lattice([LSB_M * np.round(x / LSB_M)], LSB_M, [predicted])
    assert found is not None and found[0] == pytest.approx(step_m, rel=0.05)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_no_lattice_in_a_fine_converter_alone(seed: int) -> None:
    rng = np.random.default_rng(seed)
    assert find_lattice([reading(rng, None, analog_counts=0.3)], LSB_M) is None


def test_a_quiet_reading_on_the_fine_lattice_is_not_a_coarse_one() -> None:
    """Changes of one or two fine counts only: the scan starts at three counts, and its
    multiples of the count do not line up (their phases spread over the circle)."""
    rng = np.random.default_rng(5)
    y = LSB_M * np.round(rng.normal(0.0, 1.2 * LSB_M, 36_000) / LSB_M)
    assert find_lattice([y], LSB_M) is None


def test_the_held_out_score_of_a_lattice_is_a_deviance() -> None:
    """Quantization's held-out evidence is the readings' own lattice, scored like a
    deviance: large at the true step on data the fit never saw, about chi-squared with
    one degree of freedom (mean 1) where there is no lattice, and not large at a step a
    few per cent off either way or at twice the step (changes of one step then sit
    between its points)."""
    rng = np.random.default_rng(23)
    step = 2.5e-8
    y = reading(rng, step, analog_counts=0.2)
    halves = [y[:18_000], y[18_000:]]
    at_truth = lattice_deviance(halves, LSB_M, step)
    assert at_truth > 1000
    assert lattice_deviance(halves, LSB_M, 2 * step) < 0
    # A fast wander on the fine converter alone: changes of about a step, no lattice.
    nulls = [lattice_deviance([LSB_M * np.round(np.cumsum(
        np.random.default_rng(s).normal(0.0, step, 5_000)) / LSB_M)], LSB_M, step)
             for s in range(40)]
    assert abs(float(np.mean(nulls))) < 3.0
    assert max(nulls) < 31.0  # the penalty a three-parameter candidate pays


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_readings_through_a_converter_sit_on_its_levels(seed: int) -> None:
    """What rejects a lattice that only the changes show (`AdcQuantization.degenerate`):
    readings through a coarse converter with a little noise after it cluster on its
    levels, even at a step 4 % off; a fast wander through the fine converter alone, over
    as many steps, does not."""
    rng = np.random.default_rng(seed)
    step = 1.0e-8
    x = np.cumsum(rng.normal(0.0, 0.5 * step, 20_000))  # a few steps in 64 readings
    fine = LSB_M * np.round(x / LSB_M)
    coarse = step * np.round(x / step) + rng.normal(0.0, 0.3 * LSB_M, len(x))
    windows, z = readings_on_levels(LSB_M * np.round(coarse / LSB_M), 1.04 * step)
    assert windows >= LEVEL_WINDOWS and z > 2 * LEVEL_Z
    windows, z = readings_on_levels(fine, step)
    assert windows >= LEVEL_WINDOWS and z < LEVEL_Z / 2


def test_a_modulation_is_found_where_it_is_a_line_and_not_in_a_drift() -> None:
    """The modulation a periodic fit is checked against: a 163 s triangle over the first
    hour of three, with noise, to 0.1 %; a random walk (a drift, red) has no line."""
    rng = np.random.default_rng(4)
    dt = 0.1
    t = np.arange(0.0, 10_800.0, dt)
    tri = np.where(t < 3600.0, 5.5 * (2 * np.abs(2 * (t / 163.0 % 1) - 1) - 1), 0.0)
    f = modulation_hz(tri + rng.normal(0.0, 0.5, len(t)), dt)
    assert f is not None and f == pytest.approx(1 / 163.0, rel=1e-3)
    assert modulation_hz(np.cumsum(rng.normal(0.0, 0.01, len(t))), dt) is None
    assert modulation_hz(None, dt) is None


@pytest.mark.parametrize("n,period_s", [(36_001, 287.0), (50_000, 61.3), (9_000, 6.0)])
def test_the_modulations_refinement_is_the_direct_sums_pick(n: int, period_s: float) -> None:
    """The 101 trial frequencies between bins are one chirp-z transform: it must pick the
    trial that the plain sum of x exp(-2 pi i f t) over the record picks, for lines on and
    between bins (an error in its start or step would move the pick a trial or more)."""
    from leveler.analysis.whittle import hann

    rng = np.random.default_rng(n)
    dt = 0.1
    t = np.arange(n) * dt
    x = np.sign(np.sin(2 * np.pi * t / period_s + 0.3)) + 0.2 * rng.normal(size=n)
    found = modulation_hz(x, dt)
    x = x - np.mean(x)
    k = int(np.argmax(np.abs(np.fft.rfft(x * hann(n))[8:]) ** 2)) + 8
    trial = (k + np.linspace(-1.0, 1.0, 101)) / (n * dt)
    power = [abs(np.sum(x * np.exp(-2j * np.pi * f * t))) for f in trial]
    assert found == trial[int(np.argmax(power))]
    assert found == pytest.approx(1 / period_s, rel=2e-3)
