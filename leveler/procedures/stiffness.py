"""Thrust stiffness and compliance of a tilted torsion pendulum (paper sec. 2.2, 3.1; Figs. 3-6).

What "stiffness" means here, and why it depends on tilt. The paper defines K = F L / theta
(eq. 4) and S = 1 / K (eq. 5), with theta the pendulum's angle from the rest position it has
with the base level and no thrust, the zero of the displacement sensor. A base tilt alpha adds
the theta-independent torque M g sin(alpha) l_cm, which moves the rest point by
M g sin(alpha) l_cm / K0. The pendulum's dynamics are unchanged (leveler.sim.torsion), but a
thrust-to-displacement transfer function identified from a run with the tilt present attributes
that gravity deflection to the thrust:

    S = theta / (F L) = (1 + r) / K0,   K = K0 / (1 + r),   r = M g sin(alpha) l_cm / (F L).

The procedure is the paper's: a unipolar square-wave thrust (0 / F) drives the simulated
pendulum at a fixed tilt; a second-order model H(s) = G w0^2 / (s^2 + s w0/Q + w0^2) from thrust
[N] to end displacement L theta [m] is fitted by output-error least squares. Its 0 Hz value G is
the least-squares gain with no offset term, since the sensor zero is the level rest point, and
gives S = G / L^2. For a 50 % duty square wave that G is (displacement at thrust on) / F, the
(1 + r) / K0 above, with r about 2 % small: least squares also weighs the ringing after each
edge, which the constant gravity deflection does not have.
Nothing puts r in by hand: it emerges from simulation plus identification, and the tests check
it against the formula. Fitting with a free offset instead returns K0 at every tilt (the
"incremental" stiffness, also reported): the tilt changes the calibration, not the pendulum.

Regimes (paper, after eq. 6): r > 0 softening (0 < K < K0), -1 < r < 0 stiffening (K > K0,
sharply as r -> -1), r < -1 negative stiffness: the reading moves against the thrust; the
paper calls it out of scope and we report it as unstable (as a thrust balance) rather than fit it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import curve_fit, least_squares
from scipy.signal import lfilter

from leveler.sim.torsion import TorsionParams, sensor_noise, simulate

SOFTENING = "softening"
STIFFENING = "stiffening"
NEGATIVE = "negative stiffness (unstable)"
LEVEL = "level (reference)"

# Identification run: 5 periods of a 400 s square wave sampled at 5 Hz. Half a period is 20x the
# 10 s decay time of the default pendulum, so the ringing after each edge biases the identified r
# by about 2 %; 2.5 Hz Nyquist is 8x the highest eigenfrequency studied (0.32 Hz).
RUN_FS_HZ = 5.0
RUN_PERIOD_S = 400.0
RUN_CYCLES = 5
# Displacement sensor noise at the arm end (a capacitive sensor of the kind the paper uses).
SENSOR_NOISE_M_PER_RTHZ = 1e-9
# Budget rule (paper sec. 3.1): gravity torque at the largest tilt below 1/4 of the thrust torque.
BUDGET_FRACTION = 0.25

_F0_GRID = 24
_Q_GRID = 6
_Q_BOUNDS = (0.6, 300.0)  # underdamped, as a thrust-stand pendulum is


@dataclass(frozen=True)
class TransferFit:
    """Identified H(s) = G w0^2 / (s^2 + s w0/Q + w0^2), thrust [N] -> end displacement [m]."""

    dc_gain_m_per_n: float  # G = H(0) with the sensor zero at the level rest point (the paper's)
    incremental_gain_m_per_n: float  # G with a free constant: the pendulum's own 1 / K0 L^-2
    offset_m: float  # that free constant: the gravity deflection L M g sin(alpha) l_cm / K0
    natural_frequency_hz: float
    quality_factor: float
    rms_residual_m: float  # of the fit with the free constant

    def magnitude_m_per_n(self, freq_hz: np.ndarray) -> np.ndarray:
        """|H(i 2 pi f)| with the paper's (level-zero) 0 Hz value."""
        w0, s = 2 * math.pi * self.natural_frequency_hz, 2j * math.pi * np.asarray(freq_hz)
        return np.abs(self.dc_gain_m_per_n * w0**2 / (s**2 + s * w0 / self.quality_factor
                                                       + w0**2))


def square_wave_thrust(n: int, fs_hz: float, period_s: float, amplitude_n: float) -> np.ndarray:
    """Unipolar 50 % duty square wave: off for the first half period, then F, and so on."""
    t = np.arange(n) / fs_hz
    return np.where((t % period_s) >= period_s / 2, amplitude_n, 0.0)


def thrust_run(p: TorsionParams, thrust_n: float, tilt_rad: float, rng: np.random.Generator,
               *, noise_m_per_rthz: float = SENSOR_NOISE_M_PER_RTHZ,
               fs_hz: float = RUN_FS_HZ) -> tuple[np.ndarray, np.ndarray]:
    """Square-wave thrust and the sensed end displacement L theta + noise, at a fixed pitch."""
    n = round(RUN_CYCLES * RUN_PERIOD_S * fs_hz)
    thrust = square_wave_thrust(n, fs_hz, RUN_PERIOD_S, thrust_n)
    theta = simulate(p, 1 / fs_hz, thrust, pitch_rad=tilt_rad)
    return thrust, p.arm_m * theta + sensor_noise(rng, n, noise_m_per_rthz, fs_hz)


def unit_response(thrust_n: np.ndarray, dt_s: float, f0_hz: float, q: float,
                  hold: str = "zoh") -> np.ndarray:
    """Exact response of w0^2 / (s^2 + s w0/Q + w0^2) from rest (underdamped, Q > 1/2) to
    the samples held constant over each interval (hold="zoh", as the simulator drives it) or
    joined by straight lines (hold="foh", a recording of a continuous force: a step between
    two samples lands, on average, where the ramp puts it, not half an interval late).

    Closed form from the poles p1,2 instead of cont2discrete: the fit evaluates this a few
    hundred times, and scipy's expm on a tiny matrix costs milliseconds when BLAS threads
    contend. With H(s)/s = 1/s + sum c_i / (s - p_i), c_i = w0^2 / (p_i (p_i - p_j)), the ZOH
    equivalent is (1 - 1/z) Z{H(s)/s} with Z{1/(s - p)} = 1 / (1 - e^(p dt) / z).
    """
    w0 = 2 * math.pi * f0_hz
    p1 = complex(-w0 / (2 * q), w0 * math.sqrt(1 - 1 / (4 * q * q)))
    p2 = p1.conjugate()
    if hold == "foh":
        return _foh_response(np.asarray(thrust_n, dtype=float), dt_s, p1, w0)
    c1 = w0**2 / (p1 * (p1 - p2))
    e1, e2 = np.exp(p1 * dt_s), np.exp(p2 * dt_s)
    # numerator of (1 - 1/z) [1/(1 - 1/z) + c1/(1 - e1/z) + c2/(1 - e2/z)] over (1-e1/z)(1-e2/z)
    b1 = -(e1 + e2) + c1 * (-1 - e2) + c1.conjugate() * (-1 - e1)
    b2 = e1 * e2 + c1 * e2 + c1.conjugate() * e1
    a = [1.0, -(e1 + e2).real, (e1 * e2).real]
    return np.asarray(lfilter([0.0, b1.real, b2.real], a, thrust_n))


def _foh_response(u: np.ndarray, dt_s: float, p1: complex, w0: float) -> np.ndarray:
    """Modal form: w0^2 / ((s - p1)(s - p2)) = 2 Re(r / (s - p1)), r = w0^2 / (p1 - p2); for
    u linear over a step, x' = p x + u gives x[k+1] = E x[k] + b0 u[k] + b1 u[k+1] with
    E = e^(p dt), b1 = (E - 1) / (p^2 dt) - 1 / p and b0 = (E - 1) / p - b1."""
    e = complex(np.exp(p1 * dt_s))
    b1 = (e - 1) / (p1 * p1 * dt_s) - 1 / p1
    b0 = (e - 1) / p1 - b1
    x = lfilter([b1, b0], [1.0, -e], u.astype(complex))
    return 2 * (w0**2 / (2j * p1.imag) * x).real


def _project(y: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares coefficients of y on the columns of basis, and the residual."""
    coef = np.linalg.lstsq(basis, y, rcond=None)[0]
    return coef, y - basis @ coef


def identify_transfer(thrust_n: np.ndarray, displacement_m: np.ndarray, fs_hz: float,
                      modulation_hz: float) -> TransferFit:
    """Least-squares second-order thrust -> displacement model; its 0 Hz value two ways.

    The dynamics (f0, Q) come from an output-error fit with a free constant, by variable
    projection: gain and constant are solved exactly for each (f0, Q), which are found on a
    coarse grid and refined by least_squares in log space. The 0 Hz value G is then the
    least-squares gain with the constant held at zero, the sensor zero (the paper's
    compliance); with the constant free it is the incremental gain. Fitting poles and gain
    together with no constant works while the gravity deflection is smaller than the thrust's
    (|r| < 1) but degenerates beyond it: the poles slide to the slowest allowed to mimic the
    constant. f0 is searched from 4x the modulation up, where the square wave has plateaus.
    """
    # In units of the data's spread: least_squares' tolerances are absolute, metres are tiny.
    scale = float(np.std(displacement_m)) or 1.0
    thrust = np.asarray(thrust_n, dtype=float)
    y = np.asarray(displacement_m, dtype=float) / scale
    dt = 1 / fs_hz
    log_f = (math.log(4 * modulation_hz), math.log(0.2 * fs_hz))
    log_q = (math.log(_Q_BOUNDS[0]), math.log(_Q_BOUNDS[1]))

    def basis(x: np.ndarray) -> np.ndarray:
        unit = unit_response(thrust, dt, math.exp(x[0]), math.exp(x[1]))
        return np.column_stack((unit, np.ones_like(unit)))

    def residual(x: np.ndarray) -> np.ndarray:
        return _project(y, basis(x))[1]

    grid = [np.array((lf, lq)) for lf in np.linspace(*log_f, _F0_GRID)
            for lq in np.linspace(*log_q, _Q_GRID)]
    start = min(grid, key=lambda x: float(np.sum(residual(x) ** 2)))
    best = least_squares(residual, start, bounds=tuple(zip(log_f, log_q, strict=True)),
                         x_scale=0.1)
    phi = basis(best.x)
    (gain, offset), res = _project(y, phi)
    (zero_offset_gain,), _ = _project(y, phi[:, :1])
    return TransferFit(dc_gain_m_per_n=float(zero_offset_gain) * scale,
                       incremental_gain_m_per_n=float(gain) * scale,
                       offset_m=float(offset) * scale,
                       natural_frequency_hz=math.exp(float(best.x[0])),
                       quality_factor=math.exp(float(best.x[1])),
                       rms_residual_m=float(np.sqrt(np.mean(res**2))) * scale)


def regime(r: float) -> str:
    """The paper's three cases for r = M g sin(alpha) l_cm / (F L)."""
    if r > 0:
        return SOFTENING
    if r == 0:
        return LEVEL
    return STIFFENING if r > -1 else NEGATIVE


@dataclass(frozen=True)
class TiltPoint:
    """One identification at one tilt."""

    tilt_rad: float
    fit: TransferFit
    compliance_rad_per_nm: float  # S = G / L^2
    stiffness_nm_per_rad: float  # K = 1 / S (inf when S = 0)
    incremental_stiffness_nm_per_rad: float  # from the fit with a free offset
    coupling_ratio: float  # r from the identified S: S / S(level) - 1
    model_coupling_ratio: float  # r from the simulator's parameters, for comparison
    regime: str


def sweep_tilts(max_tilt_rad: float, step_rad: float) -> np.ndarray:
    """Symmetric tilts -max..+max in steps of about step_rad, always including 0 (level)."""
    if not (step_rad > 0 and max_tilt_rad >= step_rad):
        raise ValueError(f"need 0 < tilt step <= max tilt, got {step_rad!r} and {max_tilt_rad!r}")
    half = round(max_tilt_rad / step_rad)
    return max_tilt_rad / half * np.arange(-half, half + 1)


def tilt_sweep(p: TorsionParams, thrust_n: float, tilts_rad: np.ndarray,
               seed: int = 0) -> list[TiltPoint]:
    """Identify S and K at each tilt; r and the regime relative to the level (0 rad) point."""
    tilts = np.asarray(tilts_rad, dtype=float)
    if not np.any(tilts == 0):
        raise ValueError("the tilt sweep must include 0 rad: r is measured against level")
    rng = np.random.default_rng(seed)
    rows = []
    for tilt in tilts:
        thrust, disp = thrust_run(p, thrust_n, float(tilt), rng)
        fit = identify_transfer(thrust, disp, RUN_FS_HZ, 1 / RUN_PERIOD_S)
        s = fit.dc_gain_m_per_n / p.arm_m**2
        rows.append((float(tilt), fit, s, p.arm_m**2 / fit.incremental_gain_m_per_n))
    s_level = next(s for tilt, _, s, _ in rows if tilt == 0)
    points = []
    for tilt, fit, s, k_incr in rows:
        r = s / s_level - 1 if tilt != 0 else 0.0
        points.append(TiltPoint(tilt, fit, s, 1 / s if s != 0 else math.inf, k_incr, r,
                                p.coupling_ratio(thrust_n, tilt), regime(r)))
    return points


@dataclass(frozen=True)
class LinearFit:
    """Compliance S = S0 + slope sin(alpha) (paper Fig. 6)."""

    intercept_rad_per_nm: float  # S0 = 1 / K0
    slope_rad_per_nm_per_rad: float  # dS / d sin(alpha) = M g l_cm / (F L K0)
    r_squared: float


def fit_compliance(points: list[TiltPoint]) -> LinearFit:
    x = np.sin([pt.tilt_rad for pt in points])
    s = np.array([pt.compliance_rad_per_nm for pt in points])
    slope, intercept = np.polyfit(x, s, 1)
    resid = s - (intercept + slope * x)
    return LinearFit(float(intercept), float(slope), _r_squared(s, resid))


@dataclass(frozen=True)
class TwoExpFit:
    """Stiffness K(alpha) = a exp(b alpha) + c exp(d alpha), alpha in urad (paper Fig. 5)."""

    a_nm_per_rad: float
    b_per_urad: float
    c_nm_per_rad: float
    d_per_urad: float
    r_squared: float
    max_rel_error: float

    def __call__(self, tilt_urad: np.ndarray) -> np.ndarray:
        return _two_exp(np.asarray(tilt_urad), self.a_nm_per_rad, self.b_per_urad,
                        self.c_nm_per_rad, self.d_per_urad)


def _two_exp(x: np.ndarray, a: float, b: float, c: float, d: float) -> np.ndarray:
    return a * np.exp(b * x) + c * np.exp(d * x)


def fit_stiffness(points: list[TiltPoint]) -> TwoExpFit:
    """Two-term exponential through the identified K; needs K > 0 at every point.

    The start is a single exponential from a log-linear fit, split into a faster and a slower
    term; curve_fit refines all four.
    """
    x = np.array([pt.tilt_rad * 1e6 for pt in points])
    k = np.array([pt.stiffness_nm_per_rad for pt in points])
    if not np.all(np.isfinite(k) & (k > 0)):
        raise ValueError("the two-term exponential fit needs K > 0 at every tilt: drop "
                         "negative-stiffness points or narrow the sweep")
    slope, log_a = np.polyfit(x, np.log(k), 1)
    a0 = math.exp(log_a) / 2
    p0 = (a0, 1.5 * slope, a0, 0.5 * slope)
    popt, _ = curve_fit(_two_exp, x, k, p0=p0, maxfev=20000)
    resid = k - _two_exp(x, *popt)
    return TwoExpFit(*(float(v) for v in popt), _r_squared(k, resid),
                     float(np.max(np.abs(resid / k))))


def _r_squared(y: np.ndarray, resid: np.ndarray) -> float:
    return float(1 - np.sum(resid**2) / np.sum((y - y.mean()) ** 2))


def tilt_sensitivity_nm_per_rad(lin: LinearFit, thrust_n: float, arm_m: float) -> float:
    """M g l_cm from the compliance line: slope = M g l_cm / (F L K0) and S0 = 1 / K0."""
    return lin.slope_rad_per_nm_per_rad * thrust_n * arm_m / lin.intercept_rad_per_nm


def tilt_budget_rad(sensitivity_nm_per_rad: float, thrust_n: float, arm_m: float,
                    fraction: float = BUDGET_FRACTION) -> float:
    """Largest |alpha| with M g sin(alpha) l_cm <= fraction * F L; pi/2 if no tilt breaks it."""
    if sensitivity_nm_per_rad == 0:
        return math.pi / 2
    return math.asin(min(1.0, fraction * thrust_n * arm_m / abs(sensitivity_nm_per_rad)))


def negative_stiffness_tilt_rad(sensitivity_nm_per_rad: float, thrust_n: float,
                                arm_m: float) -> float | None:
    """The tilt where r = -1 (stiffness diverges, then turns negative); None if unreachable."""
    x = thrust_n * arm_m / sensitivity_nm_per_rad if sensitivity_nm_per_rad else math.inf
    return -math.asin(x) if abs(x) <= 1 else None
