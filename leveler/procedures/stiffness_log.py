"""Stiffness and tilt coupling of a torsion pendulum from a recording (paper sec. 2.2, 3.1, 3.3).

`leveler.procedures.stiffness` runs the paper's procedure on the simulator, one tilt at a time.
A recording is not so tidy: the tilt drifts or steps while the thrust runs, the sensor's zero
walks, and the record starts wherever the pendulum was. So the whole record is fitted at once
with the equation of motion, J theta'' + lambda theta' + K0 theta = F L + M g sin(alpha) l_cm:
both torques go through the same pendulum, and the displacement at the arm end, L theta, is

    y = G u_F + B u_a + ringing + drift,   u = w0^2 / (s^2 + s w0/Q + w0^2) applied to F, sin(a)

with G = L^2 / K0 [m/N] and B = L M g l_cm / K0 [m/rad], the ringing the pendulum's free motion
from an unknown start (two columns), and the sensor's slow zero drift a Legendre polynomial.
(f0, Q) come by variable projection as in `identify_transfer` (grid, then least squares in log
space); G, B and the rest by linear least squares. The recorded forces are taken as joined by
straight lines between samples or as held, whichever fits the record better. Then

    K0 = L^2 / G,   M g l_cm = B L / G,

the second a ratio in which the displacement sensor's gain cancels, as in the paper's
dual-frequency calibration (sec. 3.3): a pitch line and a thrust line in one record are that
case of this fit, taken in the time domain. The paper's stiffness at a tilt follows as
K = K0 / (1 + r), r = M g sin(alpha) l_cm / (F L), with F the thrust being measured.

Uncertainties: a delete-one-block jackknife over contiguous blocks (the noise is coloured and
the drift is not a polynomial: the scatter between blocks is what the data say), with (f0, Q)
held; then the stated calibrations in quadrature: the arm length (K0 goes as L^2, M g l_cm as
L), the thrust scale (both), the tiltmeter's gain (M g l_cm).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import median_filter
from scipy.optimize import least_squares

from leveler.procedures.drive_lines import free_ringing
from leveler.procedures.stiffness import (
    BUDGET_FRACTION,
    LEVEL,
    negative_stiffness_tilt_rad,
    regime,
    tilt_budget_rad,
    unit_response,
)

JACKKNIFE_BLOCKS = 20
HOLDS = ("foh", "zoh")  # forces joined by lines between samples, or held (stiffness.unit_response)
MIN_SAMPLES = 200
_F0_GRID = 28
_Q_GRID = 7
_Q_BOUNDS = (0.6, 1e4)
# A plateau: the tilt within this many of its own sample-to-sample noise of the plateau's
# median, or PLATEAU_MIN_RAD, whichever is larger, for at least one thrust period.
PLATEAU_NOISE_FACTOR = 6.0
PLATEAU_MIN_RAD = 0.25e-6


@dataclass(frozen=True)
class Recording:
    """A thrust stand's channels on a uniform time base, SI."""

    t_s: np.ndarray
    thrust_n: np.ndarray
    displacement_m: np.ndarray
    tilt_rad: np.ndarray | None  # None: the recording has no tilt column

    @property
    def dt_s(self) -> float:
        return float(self.t_s[1] - self.t_s[0])


@dataclass(frozen=True)
class Plateau:
    """A stretch of steady tilt, with r measured on it against the fitted line."""

    start_s: float  # from the record's first sample
    end_s: float
    tilt_rad: float
    coupling_ratio: float  # r measured: the plateau's gravity deflection over G F
    model_coupling_ratio: float  # r from the fitted M g l_cm
    stiffness_nm_per_rad: float  # K = K0 / (1 + r measured) (inf at r = -1)
    regime: str  # of the fitted line's r; level within PLATEAU_MIN_RAD of 0


@dataclass(frozen=True)
class StandFit:
    """What a recording says about the stand; sigmas are 1-sigma, calibrations included."""

    arm_m: float
    thrust_n: float  # F in r = M g sin(a) l_cm / (F L)
    natural_frequency_hz: float
    quality_factor: float
    stiffness_nm_per_rad: float  # K0
    stiffness_sigma_nm_per_rad: float
    tilt_sensitivity_nm_per_rad: float | None  # M g l_cm; None without a tilt column
    tilt_sensitivity_sigma_nm_per_rad: float | None
    drift_order: int
    hold: str  # "foh" or "zoh": how the fit took the forces between samples
    rms_residual_m: float
    duration_s: float
    tilt_range_rad: tuple[float, float] | None
    plateaus: list[Plateau] = field(default_factory=list)

    @property
    def coupling_significance(self) -> float | None:
        """|M g l_cm| / sigma: how clearly the record shows a tilt coupling at all."""
        if self.tilt_sensitivity_nm_per_rad is None or not self.tilt_sensitivity_sigma_nm_per_rad:
            return None
        return abs(self.tilt_sensitivity_nm_per_rad) / self.tilt_sensitivity_sigma_nm_per_rad

    def coupling_ratio(self, tilt_rad: float) -> float:
        return (self.tilt_sensitivity_nm_per_rad or 0.0) * math.sin(tilt_rad) / (
            self.thrust_n * self.arm_m)

    @property
    def tilt_budget_rad(self) -> float | None:
        """Largest |tilt| with the gravity torque <= 1/4 of F L (paper sec. 3.1)."""
        if self.tilt_sensitivity_nm_per_rad is None:
            return None
        return tilt_budget_rad(self.tilt_sensitivity_nm_per_rad, self.thrust_n, self.arm_m,
                               BUDGET_FRACTION)

    @property
    def negative_stiffness_tilt_rad(self) -> float | None:
        if self.tilt_sensitivity_nm_per_rad is None:
            return None
        return negative_stiffness_tilt_rad(self.tilt_sensitivity_nm_per_rad, self.thrust_n,
                                           self.arm_m)


def thrust_step_n(thrust_n: np.ndarray) -> float:
    """F: the thrust's step, its 98th minus 2nd percentile (the F of a 0/F square wave)."""
    lo, hi = np.percentile(thrust_n, [2, 98])
    return float(hi - lo)


def _legendre(n: int, order: int) -> list[np.ndarray]:
    x = np.linspace(-1.0, 1.0, n)
    return [np.polynomial.legendre.legval(x, np.eye(order + 1)[j]) for j in range(order + 1)]


class _Design:
    """The columns for one (f0, Q): responses, ringing, drift; scaled for a stable solve.

    The drift columns do not depend on (f0, Q), so the search projects them out once
    (an orthonormal basis of their span) and solves only for the few that do.
    """

    def __init__(self, rec: Recording, drift_order: int, hold: str) -> None:
        self.rec, self.hold = rec, hold
        self.inputs = [rec.thrust_n] + ([] if rec.tilt_rad is None else [np.sin(rec.tilt_rad)])
        self.drift = _legendre(len(rec.t_s), drift_order) if drift_order >= 0 else []
        self.y_scale = float(np.std(rec.displacement_m)) or 1.0
        self.y = rec.displacement_m / self.y_scale
        self.basis = np.linalg.qr(np.column_stack(self.drift))[0] if self.drift else None
        self.y_off_drift = self._off_drift(self.y)

    def _off_drift(self, x: np.ndarray) -> np.ndarray:
        return x if self.basis is None else x - self.basis @ (self.basis.T @ x)

    def _varying(self, f0_hz: float, q: float) -> list[np.ndarray]:
        return ([unit_response(u, self.rec.dt_s, f0_hz, q, self.hold) for u in self.inputs]
                + free_ringing(self.rec.t_s, f0_hz, q))

    def matrix(self, f0_hz: float, q: float) -> tuple[np.ndarray, np.ndarray]:
        """The columns, each divided by its scale, and those scales."""
        x = np.column_stack(self._varying(f0_hz, q) + self.drift)
        scale = np.sqrt(np.mean(x**2, axis=0))
        scale[scale == 0] = 1.0
        return x / scale, scale

    def residual(self, logx: np.ndarray) -> np.ndarray:
        """What the best fit at (f0, Q) = exp(logx) leaves of the data."""
        x = self._off_drift(np.column_stack(self._varying(math.exp(logx[0]),
                                                          math.exp(logx[1]))))
        x /= np.sqrt(np.mean(x**2, axis=0)) + 1e-300
        coef = np.linalg.lstsq(x, self.y_off_drift, rcond=None)[0]
        return self.y_off_drift - x @ coef


def _dynamics(design: _Design, fs_hz: float, duration_s: float) -> tuple[float, float, float]:
    """(f0, Q) by a grid over log f0 and log Q, then least squares from the best point; and
    the residual's sum of squares there."""
    log_f = (math.log(max(4.0 / duration_s, 1e-4)), math.log(0.4 * fs_hz))
    log_q = (math.log(_Q_BOUNDS[0]), math.log(_Q_BOUNDS[1]))
    grid = [np.array((lf, lq)) for lf in np.linspace(*log_f, _F0_GRID)
            for lq in np.linspace(*log_q, _Q_GRID)]
    start = min(grid, key=lambda x: float(np.sum(design.residual(x) ** 2)))
    best = least_squares(design.residual, start, bounds=tuple(zip(log_f, log_q, strict=True)),
                         x_scale=0.1)
    return math.exp(float(best.x[0])), math.exp(float(best.x[1])), 2 * float(best.cost)


def _jackknife(x: np.ndarray, y: np.ndarray, blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """The full least-squares solution, and its delete-one-block replicates (rows)."""
    edges = np.linspace(0, len(y), blocks + 1).astype(int)
    xtx, xty = x.T @ x, x.T @ y
    full = np.linalg.solve(xtx, xty)
    reps = []
    for a, b in itertools.pairwise(edges):
        xb, yb = x[a:b], y[a:b]
        reps.append(np.linalg.lstsq(xtx - xb.T @ xb, xty - xb.T @ yb, rcond=None)[0])
    return full, np.array(reps)


def _jack_sigma(reps: np.ndarray) -> float:
    n = len(reps)
    return float(math.sqrt((n - 1) / n * np.sum((reps - reps.mean()) ** 2))) if n > 1 else 0.0


def find_plateaus(t_s: np.ndarray, tilt_rad: np.ndarray, min_length_s: float) -> list[slice]:
    """Stretches where the tilt stays near one value for at least min_length_s."""
    noise = float(np.median(np.abs(np.diff(tilt_rad)))) / 0.6745 / math.sqrt(2)
    tol = max(PLATEAU_NOISE_FACTOR * noise, PLATEAU_MIN_RAD)
    dt = float(t_s[1] - t_s[0])
    need = max(int(min_length_s / dt), 2)
    # the median over a window of need/4 samples: the noise averaged, a ramp kept
    smooth = median_filter(tilt_rad, size=2 * max(need // 8, 1) + 1, mode="nearest")
    out, a, total = [], 0, 0.0
    for i, value in enumerate(smooth):
        if i > a and abs(value - total / (i - a)) > tol:
            if i - a >= need:
                out.append(slice(a, i))
            a, total = i, 0.0
        total += value
    if len(smooth) - a >= need:
        out.append(slice(a, len(smooth)))
    return out


def fit_recording(rec: Recording, arm_m: float, *, drift_order: int = 2,
                  thrust_n: float | None = None, arm_sigma_m: float = 0.0,
                  thrust_sigma_rel: float = 0.0, tilt_sigma_rel: float = 0.0) -> StandFit:
    """K0 and M g l_cm from one recording (module docstring); raises ValueError saying why
    the record cannot tell."""
    n = len(rec.t_s)
    if n < MIN_SAMPLES:
        raise ValueError(f"only {n} samples; the fit needs at least {MIN_SAMPLES}")
    if not arm_m > 0:
        raise ValueError(f"the arm length must be positive, got {arm_m!r} m")
    step = thrust_step_n(rec.thrust_n)
    if not step > 0:
        raise ValueError("the thrust never changes: a stiffness needs thrust or calibration "
                         "steps in the record")
    force = step if thrust_n is None else thrust_n
    if not force > 0:
        raise ValueError(f"the thrust F must be positive, got {force!r} N")
    fs = 1.0 / rec.dt_s
    duration = float(rec.t_s[-1] - rec.t_s[0])
    # How the logged samples stand for the forces between them: a continuous force's are
    # best joined by lines, a DAQ's output (and leveler's simulator) holds each; the data say.
    fits = []
    for hold in HOLDS:
        design = _Design(rec, drift_order, hold)
        fits.append((_dynamics(design, fs, duration), design))
    (f0, q, _), design = min(fits, key=lambda fit: fit[0][2])
    x, scale = design.matrix(f0, q)
    full, reps = _jackknife(x, design.y, min(JACKKNIFE_BLOCKS, n // 50))
    coef = full / scale * design.y_scale
    rep_coef = reps / scale * design.y_scale
    resid = design.y - x @ full
    g, g_reps = coef[0], rep_coef[:, 0]
    if not g > 0:
        raise ValueError(f"the displacement moves against the thrust (G = {g:.3g} m/N): check "
                         "the signs of the thrust and displacement columns")
    k0, k0_reps = arm_m**2 / g, arm_m**2 / g_reps
    k0_sigma = math.hypot(_jack_sigma(k0_reps),
                          k0 * math.hypot(2 * arm_sigma_m / arm_m, thrust_sigma_rel))
    sens = sens_sigma = None
    plateaus: list[Plateau] = []
    tilt_range = None
    if rec.tilt_rad is not None:
        b, b_reps = coef[1], rep_coef[:, 1]
        sens = b * arm_m / g
        sens_sigma = math.hypot(_jack_sigma(b_reps * arm_m / g_reps),
                                abs(sens) * math.sqrt((arm_sigma_m / arm_m) ** 2
                                                      + thrust_sigma_rel**2 + tilt_sigma_rel**2))
        tilt_range = (float(rec.tilt_rad.min()), float(rec.tilt_rad.max()))
        # the gravity deflection the data show on each plateau: what the fit does not put
        # elsewhere (thrust response, ringing, drift), as r = that / (G F)
        gravity = resid * design.y_scale + b * x[:, 1] * scale[1]
        # a plateau lasts at least 10 min (an eighth of a short record)
        for sl in find_plateaus(rec.t_s, rec.tilt_rad, min(duration / 8, 600.0)):
            tilt = float(np.median(rec.tilt_rad[sl]))
            r = float(np.mean(gravity[sl])) / (g * force)
            r_fit = sens * math.sin(tilt) / (force * arm_m)
            plateaus.append(Plateau(float(rec.t_s[sl.start] - rec.t_s[0]),
                                    float(rec.t_s[sl.stop - 1] - rec.t_s[0]),
                                    tilt, r, r_fit, k0 / (1 + r) if r != -1 else math.inf,
                                    LEVEL if abs(tilt) < PLATEAU_MIN_RAD else regime(r_fit)))
    return StandFit(arm_m=arm_m, thrust_n=force, natural_frequency_hz=f0, quality_factor=q,
                    stiffness_nm_per_rad=k0, stiffness_sigma_nm_per_rad=k0_sigma,
                    tilt_sensitivity_nm_per_rad=sens, tilt_sensitivity_sigma_nm_per_rad=sens_sigma,
                    drift_order=drift_order, hold=design.hold,
                    rms_residual_m=float(np.sqrt(np.mean(resid**2))) * design.y_scale,
                    duration_s=duration, tilt_range_rad=tilt_range, plateaus=plateaus)
