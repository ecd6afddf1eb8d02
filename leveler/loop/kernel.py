"""The virtual loop's common cycle as one function over arrays, compiled when numba is here.

A simulated day is 864,000 cycles of the same arithmetic: step the plant, read it through
the ADC, update the PID, command the piezo, record. Run as objects (drivers, `Loop`, `PID`,
`Plant`) that is ~100k cycles/s; `cycles` does exactly the same floating-point operations,
in the same order, on a state vector, so numba can compile it to ~100x that (issue 21).

It covers only the cycle where nothing happens: a reading that the screen passes, the loop
idle or engaged, no fault. Anything else (a railed or suspicious reading, the end of a
disturbance block, an overflowing PID) stops it *before* changing the state that cycle's
decision needs, and `leveler.virtual` lets the daemon's own code run that cycle. So the
objects stay the reference: tests hold `cycles` (compiled and interpreted) to them bit for
bit, and the real-time daemon never runs this module.

The PID's arithmetic is one function, `pid_step`, that `cycles` calls and so does
`replay`, which answers a log's own readings as its logged controller did (diagnose's
excitation, `leveler.analysis.predict`). The PID's state and constants map to the arrays
here (`export_pid`, `import_pid`, `pid_constants`); the plant's in `leveler.virtual`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from leveler import jit
from leveler.loop.pid import PID

# The float state: plant, pendulum, PID, loop.
(V_APPLIED, V_TARGET, V_EFFECTIVE, LAG_V, THETA, OMEGA, PHI, SP, OUTPUT, UNCLAMPED, INTEGRAL,
 ERR, DF, PREV, R_LAST, RES_WAIT_S, HELD_V, LAST_VALUE_M, LAST_GOOD_M) = range(19)
N_STATE = 19
# The integer state: plant step, index in the disturbance block, sample seq, clock tick,
# the screen's run counters, and the loop state (IDLE or ENGAGED).
(N, BLOCK_I, SEQ, TICK, SAME, SPIKES, ENGAGED) = range(7)
N_COUNT = 7
# Constants.
(K_TILT_PER_V, K_V_REF, K_V_MIN, K_V_MAX, K_MAX_DV, K_ARM, K_GAIN, K_OFFSET, K_ADC_MIN, K_LSB,
 K_TOP, K_LINEAR, K_A11, K_A12, K_A21, K_A22, K_B1, K_B2, K_C_PER_J, K_J, K_C, K_K, K_MGL,
 K_SUBSTEPS, K_PLANT_DT, K_OFFSET_TILT, K_KP, K_KI, K_KD, K_LO, K_HI, K_SLEW, K_TAU, K_RAMP,
 K_TARGET, K_TT, K_DT, K_PERIOD, K_STUCK_AFTER, K_MAX_STEP_M, K_SPIKE_MAX,
 K_SLEW_V_PER_S) = range(42)
# then the slew's terms to the end, Plant._ramp_k's pairs in its order (highest power first)
K_RAMP_TERMS = 42
N_CONST = K_RAMP_TERMS  # without them
# Rows of the float output, one column per cycle.
(T_S, SENSOR_M, SETPOINT_M, P_V, I_V, D_V, COMMAND_V, APPLIED_V, TILT_RAD, THERMAL_RAD,
 COOLER_RAD, PIEZO_RAD, PENDULUM_RAD, TEMPERATURE_K, DRIFT_M) = range(15)
N_OUT = 15
# Rows of the integer output.
RAW_COUNTS, SATURATED = range(2)
# Rows of the resonant terms' array: rotation, output projection, state (leveler.loop.resonant).
RES_C, RES_S, RES_COS_OUT, RES_SIN_OUT, RES_RE, RES_IM = range(6)
N_RES = 6
# Why `cycles` returned.
DONE = 0  # `limit` cycles run
BEFORE = 1  # the next cycle needs the objects from its start (a new block, an odd step)
AFTER_STEP = 2  # the clock and plant have stepped; the reading needs the daemon's screen

_SAMPLE_TRACKING_GAIN = 1.0 / (3.0 + 1.0)  # as leveler.loop.pid


def cycles(s: np.ndarray, c: np.ndarray, k: np.ndarray, thermal: np.ndarray,
           cooler: np.ndarray, effect: np.ndarray, noise: np.ndarray, drift: np.ndarray,
           temperature: np.ndarray, res: np.ndarray, open_v: np.ndarray, extra_v: np.ndarray,
           out: np.ndarray, out_i: np.ndarray, limit: int) -> tuple[int, int]:
    """Run up to `limit` cycles from state (s, c); returns (cycles completed, why it stopped).

    `res` holds the PID's resonant terms, one column each (rows RES_*: rotation, output
    projection, state), none when it has none. `open_v` and `extra_v`, when not empty,
    give cycle j's command while the loop is idle (a logged open-loop voltage, instead of
    the held one) and what is added to the PID's command while it is engaged (an
    excitation): a null log's schedule (`leveler.analysis.nullcal`). Each completed cycle
    fills column j of `out`/`out_i`. The statements mirror `SimulatedStand.read`,
    `Plant.step`/`measure`, `PendulumModel.step`, `Loop._screen`, `PID.update`,
    `Resonators`, `Plant.command` and `Plant.truth` one for one; change them together."""
    blen = len(noise)
    tilt_per_v, v_ref = k[K_TILT_PER_V], k[K_V_REF]
    v_min, v_max, max_dv = k[K_V_MIN], k[K_V_MAX], k[K_MAX_DV]
    offset_tilt = k[K_OFFSET_TILT]
    done = 0
    while done < limit:
        i = c[BLOCK_I]
        tick = c[TICK] + 1
        t_s = tick * k[K_PERIOD]
        if i + 1 >= blen or np.rint(t_s / k[K_PLANT_DT]) != c[N] + 1:
            return done, BEFORE
        # -- Plant.step: the piezo slews toward its target over the step
        before = s[V_APPLIED]
        dv = s[V_TARGET] - before
        if dv > max_dv:
            dv = max_dv
        elif dv < -max_dv:
            dv = -max_dv
        v = before + dv
        s[V_APPLIED] = v
        dv = v - before
        lag = dv * abs(dv) / (2.0 * max_dv)
        s[LAG_V] = lag
        dphi_u = tilt_per_v * (v - s[V_EFFECTIVE])
        s[V_EFFECTIVE] = v
        phi = (tilt_per_v * (v - v_ref) + thermal[i] + cooler[i] + effect[i]
               + offset_tilt)
        # -- PendulumModel.step
        dphi = phi - s[PHI]
        s[PHI] = phi
        th = s[THETA] - dphi
        om = s[OMEGA] + k[K_C_PER_J] * dphi
        if k[K_LINEAR] != 0.0:
            s[THETA] = k[K_A11] * th + k[K_A12] * om + k[K_B1] * phi
            s[OMEGA] = k[K_A21] * th + k[K_A22] * om + k[K_B2] * phi
        else:
            substeps = int(k[K_SUBSTEPS])
            h = k[K_PLANT_DT] / substeps
            jj, cc, kk, mgl = k[K_J], k[K_C], k[K_K], k[K_MGL]
            for _ in range(substeps):
                k1t = om
                k1o = (mgl * math.sin(th + phi) - kk * th - cc * om) / jj
                k2t = om + 0.5 * h * k1o
                k2o = (mgl * math.sin(th + 0.5 * h * k1t + phi) - kk * (th + 0.5 * h * k1t)
                       - cc * (om + 0.5 * h * k1o)) / jj
                k3t = om + 0.5 * h * k2o
                k3o = (mgl * math.sin(th + 0.5 * h * k2t + phi) - kk * (th + 0.5 * h * k2t)
                       - cc * (om + 0.5 * h * k2o)) / jj
                k4t = om + h * k3o
                k4o = (mgl * math.sin(th + h * k3t + phi) - kk * (th + h * k3t)
                       - cc * (om + h * k3o)) / jj
                th += h / 6.0 * (k1t + 2 * k2t + 2 * k3t + k4t)
                om += h / 6.0 * (k1o + 2 * k2o + 2 * k3o + k4o)
            s[THETA], s[OMEGA] = th, om
        # -- Plant.step: the ramp the piezo took
        ramp_s = abs(dv) / k[K_SLEW_V_PER_S]
        if ramp_s != 0.0:  # a held voltage adds nothing
            g_theta = 0.0
            g_omega = 0.0
            for m in range((len(k) - K_RAMP_TERMS) // 2):
                g_theta = (g_theta + k[K_RAMP_TERMS + 2 * m]) * ramp_s
                g_omega = (g_omega + k[K_RAMP_TERMS + 2 * m + 1]) * ramp_s
            s[THETA] += g_theta * dphi_u
            s[OMEGA] += g_omega * dphi_u
        c[N] += 1
        i += 1
        c[BLOCK_I] = i
        c[TICK] = tick
        # -- Plant.measure: one conversion
        x = k[K_ARM] * s[THETA] + 0.0 + drift[i] + noise[i]
        counts = math.floor((k[K_GAIN] * x + k[K_OFFSET] - k[K_ADC_MIN]) / k[K_LSB] + 0.5)
        if counts <= 0 or counts >= k[K_TOP]:
            return done, AFTER_STEP
        value = (counts * k[K_LSB] + k[K_ADC_MIN] - k[K_OFFSET]) / k[K_GAIN]
        # -- Loop._screen of an OK reading: anything it would flag goes to the loop
        same = c[SAME] + 1 if value == s[LAST_VALUE_M] else 0
        stuck_after = k[K_STUCK_AFTER]
        if stuck_after != 0.0 and same + 1 >= stuck_after:
            return done, AFTER_STEP
        max_step = k[K_MAX_STEP_M]
        if (max_step != 0.0 and abs(value - s[LAST_GOOD_M]) > max_step
                and c[SPIKES] < k[K_SPIKE_MAX]):
            return done, AFTER_STEP
        # -- PID.update (engaged) or the held voltage (idle)
        if c[ENGAGED] != 0:
            ok, p, integral, d, cmd, u = pid_step(s, k, res, value)
            if not ok:
                return done, AFTER_STEP  # the PID raises; the loop faults
            setpoint = s[SP]
            saturated = cmd != u
        else:
            p = integral = d = 0.0
            cmd = open_v[done] if len(open_v) != 0 else s[HELD_V]
            setpoint = k[K_TARGET]
            saturated = False
        c[SAME] = same
        c[SPIKES] = 0
        s[LAST_VALUE_M] = value
        s[LAST_GOOD_M] = value
        # -- Plant.command: clamp to the piezo's range; the next step slews toward it
        vt = cmd + extra_v[done] if c[ENGAGED] != 0 and len(extra_v) != 0 else cmd
        vt = vt if not v_min > vt else v_min
        vt = vt if not v_max < vt else v_max
        s[V_TARGET] = vt
        dv = vt - s[V_APPLIED]
        if dv > max_dv:
            dv = max_dv
        elif dv < -max_dv:
            dv = -max_dv
        applied = s[V_APPLIED] + dv
        s[HELD_V] = cmd
        # -- the records
        piezo = tilt_per_v * (s[V_EFFECTIVE] - v_ref)
        out[T_S, done] = t_s
        out[SENSOR_M, done] = value
        out[SETPOINT_M, done] = setpoint
        out[P_V, done] = p
        out[I_V, done] = integral
        out[D_V, done] = d
        out[COMMAND_V, done] = cmd
        out[APPLIED_V, done] = applied
        out[TILT_RAD, done] = piezo + thermal[i] + cooler[i] + effect[i] + offset_tilt
        out[THERMAL_RAD, done] = thermal[i]
        out[COOLER_RAD, done] = cooler[i]
        out[PIEZO_RAD, done] = piezo
        out[PENDULUM_RAD, done] = s[THETA]
        out[TEMPERATURE_K, done] = temperature[i]
        out[DRIFT_M, done] = drift[i]
        out_i[RAW_COUNTS, done] = counts
        out_i[SATURATED, done] = saturated
        c[SEQ] += 1
        done += 1
    return done, DONE


def pid_step(s: np.ndarray, k: np.ndarray, res: np.ndarray, value: float
             ) -> tuple[bool, float, float, float, float, float]:
    """`PID.update` of reading `value` on the state in `s` (rows SP to R_LAST) and `res`:
    (ok, p, i as reported, d, the command, the unclamped sum). Not ok: the PID would raise
    (its arithmetic overflowed), and nothing has changed. One copy of the arithmetic for
    every loop over arrays here: `cycles` and `replay`."""
    inf = math.inf
    dt = k[K_DT]
    sp = s[SP]
    target = k[K_TARGET]
    if sp != target:
        step = k[K_RAMP] * dt
        if target - sp > step:
            sp += step
        elif sp - target > step:
            sp -= step
        else:
            sp = target
    error = sp - value
    p = k[K_KP] * error
    tau = k[K_TAU]
    df = (tau * s[DF] + (value - s[PREV])) / (tau + dt)
    d = -k[K_KD] * df
    integral = s[INTEGRAL]
    nres = res.shape[1]
    r = 0.0
    if nres == 0:
        u = p + integral + d
    else:
        for j in range(nres):
            r += (res[RES_COS_OUT, j] * res[RES_RE, j]
                  - res[RES_SIN_OUT, j] * res[RES_IM, j])
        u = p + integral + r + d
    lo, hi = k[K_LO], k[K_HI]
    cmd = lo if u < lo else hi if u > hi else u
    last = s[OUTPUT]
    step = k[K_SLEW] * dt
    if cmd > last + step:
        cmd = last + step
    elif cmd < last - step:
        cmd = last - step
    tt = k[K_TT]
    k_track = dt / (tt + dt) if tt > 0.0 else _SAMPLE_TRACKING_GAIN
    delta = k[K_KI] * error * dt + (cmd - u) * k_track
    if (delta > 0.0 and cmd >= hi) or (delta < 0.0 and cmd <= lo):
        delta = 0.0
    i_next = integral + delta
    if not -inf < i_next + cmd < inf:
        return False, p, integral, d, cmd, u
    s[SP] = sp
    s[INTEGRAL] = i_next
    s[OUTPUT] = cmd
    s[UNCLAMPED] = u
    s[ERR] = error
    s[DF] = df
    s[PREV] = value
    if nres != 0:
        if s[RES_WAIT_S] > 0.0:
            s[RES_WAIT_S] -= dt
            x = 0.0
        else:
            x = error * dt if cmd == u else 0.0
        for j in range(nres):
            a, b = res[RES_RE, j], res[RES_IM, j]
            res[RES_RE, j] = res[RES_C, j] * a - res[RES_S, j] * b + x
            res[RES_IM, j] = res[RES_S, j] * a + res[RES_C, j] * b
        s[R_LAST] = r
        integral = integral + r  # reported within i_v, as PID.update does
    return True, p, integral, d, cmd, u


def replay(s: np.ndarray, k: np.ndarray, res: np.ndarray, y: np.ndarray, cmd: np.ndarray,
           limit: int) -> tuple[int, int]:
    """The PID's commands for the readings y[:limit], from the state in (s, res): a logged
    controller replayed on its own log (`leveler.analysis.predict.excitation_v`). Returns
    (samples done, DONE), or (j, BEFORE) where reading j would make the PID raise: the
    objects take that one."""
    for j in range(limit):
        ok, _, _, _, c_v, _ = pid_step(s, k, res, y[j])
        if not ok:
            return j, BEFORE
        cmd[j] = c_v
    return limit, DONE


def pid_unsupported(pid: PID) -> str:
    """Why `pid_step` cannot run this PID ('' when it can)."""
    if pid.config.notch is not None:
        return "a notch on the reading"
    if pid.config.gains.ki2:
        return "a double integral"
    return ""


# The PID's private state's one mapping to the arrays (the plant's is `leveler.virtual`'s).
def pid_constants(pid: PID, dt_s: float, k: np.ndarray) -> None:
    """The PID's constants, updated every `dt_s`, into `k`."""
    for i, v in ((K_KP, pid._kp), (K_KI, pid._ki), (K_KD, pid._kd), (K_LO, pid._lo),
                 (K_HI, pid._hi), (K_SLEW, pid._slew), (K_TAU, pid._tau),
                 (K_RAMP, pid._ramp), (K_TARGET, pid._target), (K_TT, pid._tt),
                 (K_DT, dt_s)):
        k[i] = v


def export_pid(pid: PID, dt_s: float, s: np.ndarray) -> np.ndarray:
    """The PID's state into s[SP:HELD_V]; returns its resonant terms as `res`."""
    s[SP:HELD_V] = (pid._sp, pid._out, pid._u, pid._i, pid._err, pid._df,
                    math.nan if pid._prev is None else pid._prev, pid._r, pid._res_wait_s)
    res = pid._res
    if res is None:
        return np.zeros((N_RES, 0))
    rot_c, rot_s = res.rotation(dt_s)
    return np.array([rot_c, rot_s, res._cos_out, res._sin_out, res._re, res._im],
                    dtype=float).reshape(N_RES, -1)


def import_pid(pid: PID, s: np.ndarray, res: np.ndarray) -> None:
    """`export_pid` undone: the state the kernel left, back to the PID."""
    (pid._sp, pid._out, pid._u, pid._i, pid._err, pid._df, pid._prev, pid._r,
     pid._res_wait_s) = s[SP:HELD_V].tolist()
    if pid._res is not None:
        pid._res._re = res[RES_RE].tolist()
        pid._res._im = res[RES_IM].tolist()


def compiled() -> Callable[..., tuple[int, int]] | None:
    """`cycles` compiled by numba (`leveler.jit`), or None when numba is not installed
    (`pip install lab-leveler[fast]`)."""
    return jit.compiled(cycles, pid_step)


def compiled_replay() -> Callable[..., tuple[int, int]] | None:
    """`replay` compiled, as `compiled`."""
    return jit.compiled(replay, pid_step)
