"""Would these PID gains make the loop on the plant model unstable? numpy alone, for the daemon.

The daemon asks before it applies gains (`tune`, a reload, engaging on start). python-control
(leveler.analysis.suggest) answers the same question and much more, but brings scipy and
matplotlib into the real-time process, about a second of start-up and tens of MiB. Here the
closed loop of `leveler.loop.pid.PID` on the discretized plant is one state-space matrix, and
its eigenvalues are the closed-loop poles; tests/test_stability.py holds them to
python-control's `feedback(controller * plant).poles()` over random gains and stands.
"""

from __future__ import annotations

import math

import numpy as np

from leveler.loop.notch import Notch
from leveler.loop.resonant import PeriodicTerms
from leveler.sim.params import PlantParams
from leveler.sim.pendulum import discrete_matrices


def closed_loop_matrix(params: PlantParams, rate_hz: float, kp: float, ki: float, kd: float,
                       d_filter_tau_s: float, terms: PeriodicTerms | None = None,
                       notch: Notch | None = None, ki2: float = 0.0) -> np.ndarray:
    """x_(n+1) = M x_n for the plant's state, then the notch's two (with one), then the
    integrator's and the derivative filter's (each only with its gain non-zero, as
    suggest.controller_tf leaves them out), then two per resonant term.

    Plant: x' = A x + b u [V], reading y = x[0] [m] (strictly proper). The notch
    (leveler.loop.notch, direct form II transposed) makes what the terms see, yf = b0 y + z1,
    with z1' = b1 y + z2 - a1 yf, z2' = b2 y - a2 yf; without one yf = y. Controller on
    e = -yf: P: kp e; I: ki dt s with s' = s + e (with a double integral, I is the integral
    in volts, i' = i + ki dt e + ki2 dt s1', where the error's integral s1' = s1 + dt e
    is one more state); D: kd (z - 1) / ((tau + dt) z - tau) on
    e, i.e. g e + g (alpha - 1) w with w' = alpha w + e, g = kd / (tau + dt),
    alpha = tau / (tau + dt); resonant term h (leveler.loop.resonant):
    (re, im)' = r rot(w_h dt) (re, im) + (dt e, 0), adding k_h (cos(phase_h) re -
    sin(phase_h) im) to u (linear: the rail freeze ignored).
    """
    pe, dt = params.pendulum, 1.0 / rate_hz
    a, b = discrete_matrices(pe, dt)
    bv = b * (params.piezo.gain_m_per_v / params.platform.support_spacing_m * pe.sensor_arm_m)
    g = kd / (d_filter_tau_s + dt) if kd else 0.0
    alpha = d_filter_tau_s / (d_filter_tau_s + dt)
    blocks: list[tuple[float, float, float]] = []  # (gain into u, pole, fed by e times)
    if ki2:
        blocks.append((0.0, 1.0, dt))  # s1, the error's integral
        blocks.append((1.0, 1.0, ki * dt + ki2 * dt * dt))  # the integral in volts
    elif ki:
        blocks.append((ki * dt, 1.0, 1.0))
    if kd:
        blocks.append((g * (alpha - 1.0), alpha, 1.0))
    harmonics = [] if terms is None else list(enumerate(
        zip(terms.gains_v_per_m_s, terms.phases_rad, strict=True), 1))
    nf = 0 if notch is None else 2
    n = 3 + nf + len(blocks) + 2 * len(harmonics)
    m = np.zeros((n, n))
    m[:3, :3] = a
    y = np.zeros(n)  # the reading as a row over the state
    y[0] = 1.0
    yf = y.copy()  # what the controller's terms see
    if notch is not None:
        (b0, b1, b2), (a1, a2) = notch.coefficients(dt)
        yf = b0 * y
        yf[3] = 1.0
        m[3] = b1 * y - a1 * yf
        m[3, 4] += 1.0
        m[4] = b2 * y - a2 * yf
    m[:3] -= np.outer(bv, (kp + g) * yf)
    first = 3 + nf
    for j, (gain, pole, feed) in enumerate(blocks, start=first):
        m[:3, j] += bv * gain  # the block's state drives u
        m[j] -= feed * yf      # fed by e = -yf
        m[j, j] += pole
    if ki2:
        m[first + 1, first] += ki2 * dt  # the integral takes ki2 dt s1 each sample
    for i, (h, (k, phase)) in enumerate(harmonics):
        assert terms is not None
        j = first + len(blocks) + 2 * i
        theta = 2.0 * math.pi * h / terms.period_s * dt
        m[:3, j] += bv * k * math.cos(phase)
        m[:3, j + 1] -= bv * k * math.sin(phase)
        m[j] -= dt * yf
        m[j:j + 2, j:j + 2] += terms.radius * np.array([[math.cos(theta), -math.sin(theta)],
                                                        [math.sin(theta), math.cos(theta)]])
    return m


def predicted_instability(params: PlantParams, rate_hz: float, kp: float, ki: float,
                          kd: float, d_filter_tau_s: float,
                          terms: PeriodicTerms | None = None,
                          notch: Notch | None = None, ki2: float = 0.0) -> str | None:
    """Why the plant model says these gains make an unstable loop, or None if they do not.

    Only the closed-loop poles (microseconds): `tune` and a reload ask this before they
    apply new gains, so a dropped derivative or a typo cannot set the stand ringing."""
    if not (kp or ki or kd or ki2 or terms):  # no feedback: the open plant, as configured
        return None
    poles = np.linalg.eigvals(closed_loop_matrix(params, rate_hz, kp, ki, kd, d_filter_tau_s,
                                                 terms, notch, ki2))
    worst = poles[np.argmax(np.abs(poles))]
    if abs(worst) < 1.0:
        return None
    f_hz = abs(np.angle(worst)) * rate_hz / (2 * np.pi)
    return (f"the plant model predicts an unstable loop at {rate_hz:g} Hz: a closed-loop pole "
            f"at |z| = {abs(worst):.4g} ({f_hz:.3g} Hz) with kp {kp:g} V/m, ki {ki:g} V/(m s), "
            f"kd {kd:g} V s/m, d_filter_tau_s {d_filter_tau_s:g} s"
            + (f", ki2 {ki2:g} V/(m s^2)" if ki2 else "")
            + ("" if terms is None else
               f", and {len(terms.gains_v_per_m_s)} resonant terms at the harmonics of "
               f"{terms.period_s:g} s")
            + ("" if notch is None else
               f", and a notch at {notch.frequency_hz:g} Hz (Q {notch.q:g}, depth "
               f"{notch.depth:g})"))
