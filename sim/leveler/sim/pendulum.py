"""Pendulum tiltmeter dynamics, with the platform's own rotation:

    J (theta'' + phi'') + c theta' + k theta - m g L sin(theta + phi) = 0

theta is the pendulum's deflection relative to the platform (what the sensor on the
platform sees, divided by the arm), phi the platform tilt, L the signed height of the
centre of mass above the pivot (> 0 inverted, < 0 hanging). Linearised,

    theta / phi = (m g L - J s^2) / (J s^2 + c s + k - m g L)

(docs/procedures.md derives it). The J phi'' term is why a tilt step first swings the
reading the wrong way (the pendulum's inertia holds its absolute angle) and why a hanging
pendulum's response has its zero at m g d / J.

The platform tilt is held over each step (zero-order hold), so phi'' is a pair of impulses
at each change of phi: integrating the equation across one moves theta by -dphi and its
rate by +c dphi / J, and between changes the equation is the fixed-platform one. A piezo
change is a ramp at the amplifier's slew rate, not a jump: `ramp_terms` is what that adds
at the step's end (the plant and replay add it to the held step). Two forms
share that: the linear one (exact discretization, fast and exact for micro-radians) and
the full non-linear one (RK4), which the equilibrium and design tools need.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from leveler import jit
from leveler.sim.params import PendulumParams


def equilibrium_angle(p: PendulumParams, phi_rad: float) -> float:
    """Solve m g L sin(theta + phi) = k theta for the stable theta (rad).

    Within a quarter turn of the vertical, m g L sin(theta + phi) - k theta is strictly
    decreasing for a stable pendulum of either kind (k > m g L when inverted), so the root
    there is unique and bracketed."""
    mgl, k = p.gravity_stiffness_nm_per_rad, p.flexure_stiffness_nm_per_rad

    def torque(theta: float) -> float:
        return mgl * math.sin(theta + phi_rad) - k * theta

    from scipy.optimize import brentq  # the non-linear model only: not for a daemon's checks

    lim = math.pi if mgl > 0 else math.pi / 2 - abs(phi_rad)
    return float(brentq(torque, -lim, lim, xtol=1e-18, rtol=4 * np.finfo(float).eps))


def linear_matrices(p: PendulumParams) -> tuple[np.ndarray, np.ndarray]:
    """Continuous state space x = [theta, omega] on a platform held at phi: x' = A x + B phi."""
    j, c = p.inertia_kgm2, p.damping_nms_per_rad
    mgl, k = p.gravity_stiffness_nm_per_rad, p.flexure_stiffness_nm_per_rad
    a = np.array([[0.0, 1.0], [-(k - mgl) / j, -c / j]])
    b = np.array([[0.0], [mgl / j]])
    return a, b


def discrete_matrices(p: PendulumParams, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The linear pendulum stepped as `PendulumModel` steps it, as one linear system.

    State x_n = [theta_n, omega_n, phi_(n-1)], input phi_n: x_(n+1) = A x_n + B phi_n, and
    theta_n = x_n[0] is the reading at step n (before that step's tilt moves it)."""
    a2, b2 = _zoh(p, dt_s)
    jump = np.array([-1.0, p.damping_nms_per_rad / p.inertia_kgm2])  # per unit dphi
    a = np.zeros((3, 3))
    a[:2, :2] = a2
    a[:2, 2] = -a2 @ jump
    b = np.zeros(3)
    b[:2] = a2 @ jump + b2
    b[2] = 1.0
    return a, b


#: terms of the slew's series in its duration: the first left out is under 1e-8 of a
#: step's response where omega0 x tau < 1 (tau <= dt; at 10 Hz omega0 x dt is 0.44)
RAMP_TERMS = 10


@functools.lru_cache(maxsize=256)
def ramp_terms(p: PendulumParams, dt_s: float) -> np.ndarray:
    """What a tilt change dphi that the piezo slews over the first tau (<= dt) of a step
    adds to [theta, omega] at the step's end, beyond the same change made at its start:
    dphi * sum_m K[m - 1] tau^m over m = 1..RAMP_TERMS (the rows of the result).

    A held step moves theta by -dphi at once (the platform turns under the pendulum's
    inertia); a slewing amplifier turns it over tau, while gravity already pulls. With
    s' = A s + B phi - w phi'' (w = [0, 1]) and phi a ramp from the step's start, exactly:
    K[m - 1] = e^(A dt) ((-A)^(m+1) w - (-A)^(m-1) B) / ((m-1)! m (m+1)). Held at its
    mean instead (as the plant was), an 11.5 V square edge read 63 nm early at the next
    sample, every edge, against an independent simulator's continuous ramp."""
    a, b = linear_matrices(p)
    e = _zoh_exp(p, dt_s)[:2, :2]
    w = np.array([0.0, 1.0])
    power = np.eye(2)  # (-A)^(m-1)
    factorial = 1.0  # (m-1)!
    out = np.zeros((RAMP_TERMS, 2))
    for m in range(1, RAMP_TERMS + 1):
        ahead = power @ a @ a  # (-A)^(m+1), the sign of (-1)^2 dropped
        out[m - 1] = e @ (ahead @ w - power @ b[:, 0]) / (factorial * m * (m + 1))
        power = -power @ a
        factorial *= m
    return out


def free_step(p: PendulumParams, dt_s: float) -> np.ndarray:
    """e^(A dt): [theta, omega] over a step with the platform still."""
    return _zoh_exp(p, dt_s)[:2, :2].copy()


def ramp_gain(terms: np.ndarray, tau_s: np.ndarray) -> np.ndarray:
    """sum_m terms[m - 1] tau^m by Horner, in place on each column: shape (n, 2) for n
    taus (a replay of a day builds one per recalibration step)."""
    tau = np.asarray(tau_s, dtype=float)
    out = np.zeros((2, len(tau)))
    fast = jit.compiled(_horner)
    if fast is not None:
        fast(np.ascontiguousarray(terms, dtype=float), np.ascontiguousarray(tau), out)
        return out.T
    for acc, column in zip(out, terms.T, strict=True):
        for k in column[::-1]:
            acc += k
            acc *= tau
    return out.T


def _horner(terms: np.ndarray, tau: np.ndarray, out: np.ndarray) -> None:
    """`ramp_gain`'s Horner sums, one tau at a time, compiled by numba where it is
    installed: numpy's pass per term over a day's taus took 16 ms a replay (1.0 s of a
    null day's run), this 7 ms. The same operations in the same order, so the same to
    the bit; the two columns side by side, so neither waits on the other's last
    multiply."""
    for j in range(len(tau)):
        t, theta, omega = tau[j], 0.0, 0.0
        for m in range(terms.shape[0] - 1, -1, -1):
            theta += terms[m, 0]
            theta *= t
            omega += terms[m, 1]
            omega *= t
        out[0, j] = theta
        out[1, j] = omega


@functools.lru_cache(maxsize=256)
def late_terms(p: PendulumParams, dt_s: float, late_s: float) -> tuple[np.ndarray, np.ndarray]:
    """For a tilt change that starts `late_s` into a step (0 <= late_s < dt) instead of at
    its start: (what a jump there adds to [theta, omega] at the step's end, per unit dphi,
    beyond the same jump at the start; e^(-A late_s), which turns `ramp_terms`' sum for a
    ramp from the start into the same ramp from late_s). Exactly: the jump moves the state
    by [-1, c / J] at late_s, and phi is held from there to the end."""
    a, _ = linear_matrices(p)
    jump = np.array([-1.0, p.damping_nms_per_rad / p.inertia_kgm2])
    late, full = _zoh_exp(p, dt_s - late_s), _zoh_exp(p, dt_s)
    extra = (late[:2, :2] @ jump + late[:2, 2]) - (full[:2, :2] @ jump + full[:2, 2])
    return extra, expm(-a * late_s)


def delayed_slew(p: PendulumParams, dt_s: float, v: np.ndarray, tau_s: np.ndarray,
                 delay_s: float, ramp: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """A transport delay between the command and a slewing piezo, exactly: each step's
    change of `v` (its end values), ramped over `tau_s` (<= dt) from the step's start,
    starts `delay_s` later, a whole number of steps and a fraction of one; a ramp that no
    longer ends within its step finishes in the next. (the piezo's voltage at each step's
    end, how far its mean over the step sits below that, what the ramps add to theta and
    to omega at each step's end beyond jumps at the steps' starts, per volt: `ramp_terms`).
    `ramp`, `ramp_gain` of `tau_s` if the caller has it.

    Held at the mean of the two samples it straddles (as it was), a delay's change sat a
    fraction of a step early and its ramp ran from the step's start: fitted to an
    independent simulator's piezo, which switches within the step and then slews, delays
    came out 1.21-1.56 times the truth under a square modulation and 0.86-1.0 times it in
    a closed loop. The log starts settled: before it, the piezo held v[0]."""
    whole, late = divmod(max(delay_s, 0.0), dt_s)
    m, room = int(whole), dt_s - late
    terms = ramp_terms(p, dt_s)
    theta, omega = ramp if ramp is not None else tuple(ramp_gain(terms, tau_s).T)
    extra, back = late_terms(p, dt_s, late)
    fast = jit.compiled(_delayed_pass)
    if fast is not None:  # a fit replays a delayed day hundreds of times: 17 -> 4 ms
        n = len(v)
        out = np.empty((4, n))
        fast(np.ascontiguousarray(v, dtype=float), np.ascontiguousarray(tau_s, dtype=float),
             np.ascontiguousarray(theta), np.ascontiguousarray(omega),
             np.ascontiguousarray(terms), m, late, room, dt_s, extra, back, out)
        return out[0], out[1], (out[2], out[3])
    dv = np.diff(v, prepend=v[:1])
    # Per change, where it starts (before the shift by m whole steps): what of it falls
    # within its step, and the rest of the ramps that pass the step's end (few: a square's
    # edges), which finish from the next step's start.
    spill = np.flatnonzero(tau_s > room)
    first, dur = dv.copy(), tau_s.copy()
    first[spill] *= room / tau_s[spill]
    dur[spill] = room
    rest, rest_dur = dv[spill] - first[spill], tau_s[spill] - room
    if spill.size:
        theta, omega = theta.copy(), omega.copy()
        theta[spill], omega[spill] = ramp_gain(terms, dur[spill]).T
    gain_theta = (back[0, 0] * theta + back[0, 1] * omega + extra[0]) * first
    gain_omega = (back[1, 0] * theta + back[1, 1] * omega + extra[1]) * first
    lag = first * (late + 0.5 * dur) / dt_s
    end = v - dv + first  # v[k - 1] (the change before, whole) + first[k]
    after = spill + 1 < len(v)
    k, rest, rest_dur = spill[after] + 1, rest[after], rest_dur[after]
    tail = ramp_gain(terms, rest_dur)
    gain_theta[k] += rest * tail[:, 0]
    gain_omega[k] += rest * tail[:, 1]
    lag[k] += rest * (0.5 * rest_dur) / dt_s
    return (_later(end, m, v[0]), _later(lag, m, 0.0),
            (_later(gain_theta, m, 0.0), _later(gain_omega, m, 0.0)))


def _delayed_pass(v: np.ndarray, tau: np.ndarray, theta: np.ndarray, omega: np.ndarray,
                  terms: np.ndarray, m: int, late: float, room: float, dt: float,
                  extra: np.ndarray, back: np.ndarray, out: np.ndarray) -> None:
    """`delayed_slew`'s numpy passes, one change after another, compiled by numba where it
    is installed: the same operations in the same order, so the same to the bit. Rows of
    `out`: the end values, the lags, the injections into theta and into omega."""
    n = len(v)
    for j in range(min(m, n)):
        out[0, j], out[1, j], out[2, j], out[3, j] = v[0], 0.0, 0.0, 0.0
    carry_theta = carry_omega = carry_lag = 0.0  # a ramp's rest, for the next step
    for k in range(n):
        dv = v[k] - v[k - 1] if k > 0 else v[0] - v[0]
        t, first, d = tau[k], dv, tau[k]
        th, om = theta[k], omega[k]
        rest = rest_theta = rest_omega = rest_lag = 0.0
        if t > room:
            first = dv * (room / t)
            d = room
            rest, rd = dv - first, t - room
            th = om = rest_theta = rest_omega = 0.0
            for i in range(terms.shape[0] - 1, -1, -1):  # ramp_gain's Horner, both ramps
                th = (th + terms[i, 0]) * room
                om = (om + terms[i, 1]) * room
                rest_theta = (rest_theta + terms[i, 0]) * rd
                rest_omega = (rest_omega + terms[i, 1]) * rd
            rest_theta, rest_omega = rest * rest_theta, rest * rest_omega
            rest_lag = rest * (0.5 * rd) / dt
        j = k + m
        if j < n:
            out[0, j] = v[k] - dv + first
            out[1, j] = first * (late + 0.5 * d) / dt + carry_lag
            out[2, j] = (back[0, 0] * th + back[0, 1] * om + extra[0]) * first + carry_theta
            out[3, j] = (back[1, 0] * th + back[1, 1] * om + extra[1]) * first + carry_omega
        carry_theta, carry_omega, carry_lag = rest_theta, rest_omega, rest_lag


def _later(x: np.ndarray, m: int, before: float) -> np.ndarray:
    """x[j - m] at each j, `before` for j < m."""
    if m == 0:
        return x
    out = np.empty_like(x)
    out[:m] = before
    out[m:] = x[: max(len(x) - m, 0)]
    return out


def _zoh(p: PendulumParams, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretization of `linear_matrices` with phi held over dt."""
    e = _zoh_exp(p, dt_s)
    return e[:2, :2].copy(), e[:2, 2].copy()


@functools.lru_cache(maxsize=256)
def _zoh_exp(p: PendulumParams, dt_s: float) -> np.ndarray:
    """expm of the held-input system, remembered: a replay's fit of an effect builds a
    predictor per step with the pendulum unchanged."""
    a, b = linear_matrices(p)
    m = np.zeros((3, 3))
    m[:2, :2], m[:2, 2:] = a * dt_s, b * dt_s
    return expm(m)


def expm(m: np.ndarray) -> np.ndarray:
    """e^m of a small matrix with numpy alone: scaled to a 1-norm of at most 1/4, a Taylor
    series to 18th order (truncation below 1e-28), squared back. The daemon's stability
    check needs this discretization, and scipy.linalg would bring scipy into the real-time
    process for one 3x3 (tests hold it to scipy's expm)."""
    norm = float(np.abs(m).sum(axis=0).max())
    squarings = max(0, math.ceil(math.log2(norm / 0.25))) if norm > 0.25 else 0
    a = m / 2.0**squarings
    term = out = np.eye(m.shape[0])
    for k in range(1, 19):
        term = term @ a / k
        out = out + term
    for _ in range(squarings):
        out = out @ out
    return out


class PendulumModel:
    """Advances the pendulum by a fixed dt with the platform tilt held over the step."""

    __slots__ = ("_a11", "_a12", "_a21", "_a22", "_b1", "_b2", "_c", "_c_per_j", "_dt", "_j",
                 "_k", "_linear", "_mgl", "_phi", "_substeps", "omega", "theta")

    def __init__(self, p: PendulumParams, dt_s: float, substeps: int = 4) -> None:
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        self._linear = p.model == "linear"
        self._dt = dt_s
        self._substeps = substeps
        self._j, self._c = p.inertia_kgm2, p.damping_nms_per_rad
        self._c_per_j = self._c / self._j
        self._k, self._mgl = p.flexure_stiffness_nm_per_rad, p.gravity_stiffness_nm_per_rad
        e, eb = _zoh(p, dt_s)
        self._a11, self._a12, self._a21, self._a22 = (float(v) for v in e.ravel())
        self._b1, self._b2 = float(eb[0]), float(eb[1])
        self.theta = 0.0
        self.omega = 0.0
        self._phi = 0.0  # the platform tilt the last step held

    def settle(self, p: PendulumParams, phi_rad: float) -> None:
        """Start at rest at the static equilibrium for tilt phi."""
        if self._linear:
            self.theta = p.amplification * phi_rad
        else:
            self.theta = equilibrium_angle(p, phi_rad)
        self.omega = 0.0
        self._phi = phi_rad

    def step(self, phi_rad: float) -> float:
        """Advance one dt with the platform at phi_rad; returns the new theta."""
        dphi = phi_rad - self._phi
        self._phi = phi_rad
        th = self.theta - dphi  # the platform turned under the pendulum's inertia
        om = self.omega + self._c_per_j * dphi
        if self._linear:
            self.theta = self._a11 * th + self._a12 * om + self._b1 * phi_rad
            self.omega = self._a21 * th + self._a22 * om + self._b2 * phi_rad
            return self.theta
        return self._step_rk4(th, om, phi_rad)

    def _accel(self, th: float, om: float, phi: float) -> float:
        return (self._mgl * math.sin(th + phi) - self._k * th - self._c * om) / self._j

    def _step_rk4(self, th: float, om: float, phi: float) -> float:
        h = self._dt / self._substeps
        acc = self._accel
        for _ in range(self._substeps):
            k1t, k1o = om, acc(th, om, phi)
            k2t, k2o = om + 0.5 * h * k1o, acc(th + 0.5 * h * k1t, om + 0.5 * h * k1o, phi)
            k3t, k3o = om + 0.5 * h * k2o, acc(th + 0.5 * h * k2t, om + 0.5 * h * k2o, phi)
            k4t, k4o = om + h * k3o, acc(th + h * k3t, om + h * k3o, phi)
            th += h / 6.0 * (k1t + 2 * k2t + 2 * k3t + k4t)
            om += h / 6.0 * (k1o + 2 * k2o + 2 * k3o + k4o)
        self.theta, self.omega = th, om
        return th
