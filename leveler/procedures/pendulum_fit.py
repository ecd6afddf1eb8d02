"""The pendulum tiltmeter's response fitted to drive lines: its centre of mass from a recording.

From the piezo's command to the reading, the stand answers (docs/procedures.md)

    H(w) = A (w^2 + g) / (w0^2 - w^2 + i w w0 / Q) exp(-i w tau),   g = m g L / J,

A = sensor arm x tilt per volt (the reading well above the resonance is -A per volt: the
pendulum holds its absolute angle), w0 its resonance. A hanging pendulum (L < 0) has its zero
at w_z^2 = -g = m g d / J, where the tilt's pull and the platform's turning cancel; an inverted
one (L > 0) has none, and g shows in the static response g / w0^2 against the inertial limit.
tau is the command's lag behind its logged value (half a sample for a held DAC output, none for
a voltage sampled with the reading): fitted, under a prior of one sample interval.
So the signed centre-of-mass distance L = g J / (m g) needs only the stated mass and inertia,
and no gain: the zero's frequency is a ratio of lines in one record. A is fitted too, under the
prior the stated arm, sensor calibration and piezo geometry give (when they are stated), so its
pull checks them. The flexure is kept a spring (k > 0: a hanging pendulum's resonance above its
zero) and Q within LOG_Q_RANGE.

The fit is weighted least squares on the complex points, started from the best of a grid over
(g, w0, Q) with A solved exactly at each, so no starting guess from the config can hide the
zero; the covariance is scaled by the reduced chi-square when that is above 1.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from leveler.procedures.drive_lines import DriveLine
from leveler.sim.params import PlantParams

GRID_POINTS = 48
GRID_Q = (2.0, 10.0, 50.0, 300.0)
LOG_Q_RANGE = (-3.0, 16.0)  # Q from 0.05 to 9e6: a noisy sweep's Q may run off to either end


@dataclass(frozen=True, slots=True)
class PendulumFit:
    """What the drive lines say about the pendulum, with 1-sigma uncertainties."""

    lines: list[DriveLine]
    scale_m_per_v: float  # A
    scale_sigma: float
    scale_stated_m_per_v: float  # sensor arm x piezo gain / support spacing
    scale_stated_rel: float  # its stated 1-sigma, relative (0: not stated)
    g_per_s2: float  # m g L / J, signed
    g_sigma: float
    natural_frequency_hz: float
    natural_frequency_sigma: float
    delay_s: float  # tau
    delay_sigma_s: float
    q: float
    q_sigma: float
    com_length_m: float  # L, signed: > 0 above the pivot
    com_length_sigma_m: float
    mass_kg: float
    inertia_kgm2: float
    chi2: float
    dof: int
    predicted_m_per_v: list[complex]

    @property
    def kind(self) -> str:
        return "inverted" if self.com_length_m > 0 else "hanging"

    @property
    def zero_frequency_hz(self) -> float:
        """sqrt(m g d / J) / 2 pi of a hanging pendulum (NaN for an inverted one)."""
        return math.sqrt(-self.g_per_s2) / math.tau if self.g_per_s2 < 0 else math.nan

    @property
    def zero_frequency_sigma(self) -> float:
        if self.g_per_s2 >= 0:
            return math.nan
        return self.g_sigma / (2 * math.sqrt(-self.g_per_s2)) / math.tau

    @property
    def stiffness_nm_per_rad(self) -> float:
        """k = J (w0^2 + g): the flexure alone."""
        return self.inertia_kgm2 * ((math.tau * self.natural_frequency_hz) ** 2 + self.g_per_s2)

    @property
    def amplification(self) -> float:
        """The static theta / phi = g / w0^2."""
        return self.g_per_s2 / (math.tau * self.natural_frequency_hz) ** 2

    @property
    def scale_pull(self) -> float:
        """(A - stated) / stated sigma; NaN when the scale is not stated."""
        if self.scale_stated_rel <= 0:
            return math.nan
        return ((self.scale_m_per_v - self.scale_stated_m_per_v)
                / (self.scale_stated_rel * self.scale_stated_m_per_v))


def response(w: np.ndarray, a: float, g: float, w0: float, q: float,
             tau: float = 0.0) -> np.ndarray:
    """H(w) above, vectorised over any broadcastable arguments."""
    return a * (w * w + g) / (w0 * w0 - w * w + 1j * w * w0 / q) * np.exp(-1j * w * tau)


def _grid_start(w: np.ndarray, h: np.ndarray, sig: np.ndarray) -> tuple[float, float, float,
                                                                            float]:
    """(A, g, w0, Q) of the grid point with the least chi-square, A solved at each."""
    lo, hi = float(w.min()), float(w.max())
    mags = np.geomspace((lo / 10) ** 2, (hi * 10) ** 2, GRID_POINTS)
    gs = np.concatenate([-mags, mags])[:, None, None, None]
    w0s = np.geomspace(lo / 10, hi * 10, GRID_POINTS)[None, :, None, None]
    qs = np.asarray(GRID_Q)[None, None, :, None]
    shape = response(w[None, None, None, :], 1.0, gs, w0s, qs)
    wt = 1.0 / sig**2
    a = (np.sum(wt * (shape.conj() * h).real, axis=-1)
         / np.sum(wt * np.abs(shape) ** 2, axis=-1))
    chi2 = np.sum(wt * np.abs(a[..., None] * shape - h) ** 2, axis=-1)
    # a flexure pushes, never pulls: a hanging pendulum's resonance is above its zero
    chi2 = np.where(w0s[..., 0] ** 2 > 1.001 * np.maximum(-gs[..., 0], 0.0), chi2, np.inf)
    i, j, k = np.unravel_index(int(np.argmin(chi2)), chi2.shape)
    return float(a[i, j, k]), float(gs[i, 0, 0, 0]), float(w0s[0, j, 0, 0]), float(GRID_Q[k])


def fit_pendulum(lines: list[DriveLine], plant: PlantParams, dt_s: float) -> PendulumFit:
    """Fit the response to `lines` of a log sampled every `dt_s`; mass, inertia and the
    stated scale come from `plant`."""
    if len(lines) < 4:
        raise ValueError(f"{len(lines)} drive line{'s' if len(lines) != 1 else ''} found; the "
                         "pendulum's response needs at least 4 frequencies (a sweep across "
                         "its zero or resonance)")
    pe, u = plant.pendulum, plant.uncertainty
    w = np.array([math.tau * line.frequency_hz for line in lines])
    h = np.array([line.transfer_m_per_v for line in lines])
    sig = np.array([line.transfer_sigma_m_per_v for line in lines])
    stated = pe.sensor_arm_m * plant.piezo.gain_m_per_v / plant.platform.support_spacing_m
    stated_rel = math.sqrt(u.sensor_arm_rel**2 + u.sensor_gain_rel**2 + u.piezo_gain_rel**2
                           + u.support_spacing_rel**2)
    a0, g0, w00, q0 = _grid_start(w, h, sig)
    a0 = a0 if a0 != 0 else stated  # scales A; only its size matters
    ws = float(np.exp(np.mean(np.log(w))))  # scales the parameters to order one

    def unpack(x: np.ndarray) -> tuple[float, float, float, float, float]:
        """(A, g, w0, Q, tau); w0^2 = k / J + max(-g, 0) with k / J = e^x2 ws^2 > 0, so the
        flexure is a spring (a fit of a noisy sweep once put the resonance below the zero:
        k < 0, and 27 sigma off)."""
        g = x[1] * ws * ws
        w0 = math.sqrt(math.exp(min(x[2], 60.0)) * ws * ws + max(-g, 0.0))
        q = math.exp(min(max(x[3], LOG_Q_RANGE[0]), LOG_Q_RANGE[1]))  # no overflow on a
        return x[0] * abs(a0), g, w0, q, x[4] * dt_s                  # flat likelihood

    def residuals(x: np.ndarray) -> np.ndarray:
        d = (response(w, *unpack(x)) - h) / sig
        out = [d.real, d.imag, x[4:5]]  # the lag's prior: 0 +- one sample
        if stated_rel > 0:
            out.append(np.array([(unpack(x)[0] - stated) / (stated_rel * stated)]))
        return np.concatenate(out)

    x0 = np.array([a0 / abs(a0), g0 / ws**2, math.log((w00**2 - max(-g0, 0.0)) / ws**2),
                   math.log(q0), 0.0])
    fit = least_squares(residuals, x0, method="lm", x_scale="jac")
    chi2 = float(np.sum(fit.fun**2))
    dof = max(2 * len(lines) + (stated_rel > 0) - 4, 1)  # the lag's prior is paid by it
    jac = fit.jac
    cov = np.linalg.pinv(jac.T @ jac) * max(1.0, chi2 / dof)
    a, g, w0, q, tau = unpack(fit.x)
    sd = _propagated(unpack, fit.x, cov)  # of (A, g, w0, Q, tau)
    per_mass = pe.inertia_kgm2 / (pe.mass_kg * pe.gravity_m_per_s2)
    com = g * per_mass
    com_sigma = math.hypot(sd[1] * per_mass, com * math.hypot(u.inertia_rel, u.mass_rel))
    return PendulumFit(
        lines, a, sd[0], stated, stated_rel, g, sd[1], w0 / math.tau, sd[2] / math.tau, tau,
        sd[4], q, sd[3], com, com_sigma, pe.mass_kg, pe.inertia_kgm2, chi2, dof,
        [complex(v) for v in response(w, a, g, w0, q, tau)])


def _propagated(fn: Callable[[np.ndarray], tuple[float, ...]], x: np.ndarray,
                cov: np.ndarray) -> np.ndarray:
    """1-sigma of fn(x)'s outputs under x's covariance, by central differences."""
    jac = np.empty((len(fn(x)), len(x)))
    for i in range(len(x)):
        step = np.zeros_like(x)
        step[i] = 1e-6 * max(1.0, abs(x[i]))
        jac[:, i] = (np.asarray(fn(x + step)) - np.asarray(fn(x - step))) / (2 * step[i])
    return np.sqrt(np.maximum(np.diag(jac @ cov @ jac.T), 0.0))


__all__ = ["PendulumFit", "fit_pendulum", "response"]
