"""The stand's physics, discretized here: pendulum, resonant mode, thermal lags, noises.

Everything is continuous-time physics from PHYSICS.md, discretized exactly for inputs that
are piecewise linear in time (matrix exponential of an augmented system), so the generator
can step the piezo's slew ramps and the disturbances without a model-shaped shortcut.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter


@dataclass(frozen=True)
class Pendulum:
    """Inverted pendulum on a tilting platform, written for the absolute angle psi = theta + phi.

    J (theta'' + phi'') + c theta' + k theta - m g L (theta + phi) = 0 becomes
    J psi'' + c psi' + (k - m g L) psi = k phi + c phi', so a tilt phi that is linear within a
    step (slope r) enters as (phi, r) with no second derivative needed; the platform's own
    angular acceleration (the J phi'' term) is kept exactly.
    """

    inertia: float  # J [kg m^2]
    damping: float  # c [N m s/rad]
    k_flex: float  # k [N m/rad]
    mgl: float  # m g L_cm [N m/rad]
    # False drops the platform's angular acceleration (J phi''): then the state is
    # [theta, theta'] with J theta'' + c theta' + (k - m g L) theta = m g L phi. Only for
    # comparison: PHYSICS.md's full equation keeps it.
    platform_inertia: bool = True

    @classmethod
    def from_targets(cls, amplification: float, f0_hz: float, q: float,
                     inertia: float, platform_inertia: bool = True) -> Pendulum:
        """The pendulum with the given static amplification N, resonance f0 and quality Q."""
        w0 = 2 * math.pi * f0_hz
        kappa = inertia * w0 * w0  # k - m g L
        mgl = amplification * kappa
        return cls(inertia, inertia * w0 / q, kappa + mgl, mgl, platform_inertia)

    @property
    def kappa(self) -> float:
        return self.k_flex - self.mgl

    @property
    def amplification(self) -> float:
        return self.mgl / self.kappa

    @property
    def f0_hz(self) -> float:
        return math.sqrt(self.kappa / self.inertia) / (2 * math.pi)

    @property
    def q(self) -> float:
        return self.inertia * 2 * math.pi * self.f0_hz / self.damping

    def step(self, h: float) -> np.ndarray:
        """2x4: [psi, psi'](t+h) = S @ [psi, psi', phi(t), r] for phi linear with slope r
        (with platform_inertia False the state is [theta, theta'])."""
        j, c = self.inertia, self.damping
        m = np.zeros((4, 4))
        m[0, 1] = 1.0
        m[1, 0] = -self.kappa / j
        m[1, 1] = -c / j
        if self.platform_inertia:
            m[1, 2] = self.k_flex / j
            m[1, 3] = c / j
        else:
            m[1, 2] = self.mgl / j
        m[2, 3] = 1.0
        return expm(m * h)[:2, :]

    def deflection(self, state0: float, phi: float) -> float:
        """theta from the first state variable and the tilt."""
        return state0 - phi if self.platform_inertia else state0

    def equilibrium(self, phi: float) -> float:
        """The first state variable at rest under a constant tilt phi."""
        n = self.amplification
        return (1.0 + n) * phi if self.platform_inertia else n * phi


@dataclass(frozen=True)
class Mode:
    """A band-pass resonance driven by the tilt rate: m'' + (w/Q) m' + w^2 m = g (w/Q) phi'.

    Its response to tilt peaks at g (times the tilt) at f and vanishes at DC; the sensor sees
    it as g times the pendulum's static response there. Noise drives it too (`noise`).
    """

    f_hz: float
    q: float
    gain: float

    def _a(self) -> np.ndarray:
        w = 2 * math.pi * self.f_hz
        return np.array([[0.0, 1.0], [-w * w, -w / self.q]])

    def step(self, h: float) -> np.ndarray:
        """2x3: [m, m'](t+h) = S @ [m, m', r] for a constant tilt rate r."""
        w = 2 * math.pi * self.f_hz
        m = np.zeros((3, 3))
        m[:2, :2] = self._a()
        m[1, 2] = self.gain * w / self.q
        return expm(m * h)[:2, :]

    def noise(self, n: int, dt: float, rms: float, rng: np.random.Generator) -> np.ndarray:
        """n samples (spacing dt) of the mode rung by white force noise to `rms` (stationary)."""
        w = 2 * math.pi * self.f_hz
        a = self._a()
        intensity = 2 * w**3 * rms**2 / self.q  # var(m) = q_w Q / (2 w^3)
        # Van Loan: exact discrete transition and process covariance.
        big = np.zeros((4, 4))
        big[:2, :2] = -a
        big[:2, 2:] = np.diag([0.0, intensity])
        big[2:, 2:] = a.T
        e = expm(big * dt)
        phi = e[2:, 2:].T
        qd = phi @ e[:2, 2:]
        qd = 0.5 * (qd + qd.T)
        chol = np.linalg.cholesky(qd + 1e-30 * np.eye(2))
        p0 = np.diag([rms**2, (w * rms) ** 2])
        x = np.linalg.cholesky(p0) @ rng.standard_normal(2)
        out = np.empty(n)
        z = rng.standard_normal((n, 2)) @ chol.T
        p00, p01, p10, p11 = phi[0, 0], phi[0, 1], phi[1, 0], phi[1, 1]
        x0, x1 = float(x[0]), float(x[1])
        for i in range(n):
            out[i] = x0
            x0, x1 = p00 * x0 + p01 * x1 + z[i, 0], p10 * x0 + p11 * x1 + z[i, 1]
        return out


def lag(u: np.ndarray, dt: float, tau: float, y0: float) -> np.ndarray:
    """First-order lag y' = (u - y) / tau, exact for u linear between samples, from y(0) = y0."""
    a = math.exp(-dt / tau)
    b1 = 1.0 - tau / dt * (1.0 - a)
    b0 = (1.0 - a) - b1
    y = np.empty_like(u)
    y[0] = y0
    if len(u) > 1:
        y[1:], _ = lfilter([b1, b0], [1.0, -a], u[1:], zi=[a * y0 + b0 * u[0]])
    return y


def random_walk(n: int, step_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """A random walk from 0 with independent Gaussian steps of `step_sigma`."""
    steps = rng.standard_normal(n) * step_sigma
    steps[0] = 0.0
    return np.cumsum(steps)


def sawtooth(t: np.ndarray, period: float, fall_fraction: float) -> np.ndarray:
    """Unit peak-to-peak sawtooth, -0.5 at each period start, rising for (1 - fall) of it."""
    x = np.mod(t / period, 1.0)
    rise = 1.0 - fall_fraction
    return np.where(x < rise, x / rise, 1.0 - (x - rise) / fall_fraction) - 0.5


def jittered_sawtooth(t: np.ndarray, period: float, rise_fraction: float, jitter: float,
                      rng: np.random.Generator, t0: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit p-p asymmetric sawtooth whose every cycle has its own length (relative sigma
    `jitter`); the first cycle started at t0 <= t[0]. Returns (wave, cycle start times)."""
    span = t[-1] - t0
    n_cycles = int(span / period * 1.5) + 4
    lengths = period * np.clip(1.0 + jitter * rng.standard_normal(n_cycles), 0.5, 1.5)
    starts = t0 + np.concatenate(([0.0], np.cumsum(lengths)))
    idx = np.searchsorted(starts, t, side="right") - 1
    x = (t - starts[idx]) / lengths[idx]
    wave = np.where(x < rise_fraction, x / rise_fraction,
                    1.0 - (x - rise_fraction) / (1.0 - rise_fraction)) - 0.5
    return wave, starts[: idx[-1] + 1]
