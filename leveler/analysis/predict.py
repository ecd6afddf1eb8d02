"""Open-loop prediction of a logged run: the plant model driven by what the log recorded.

The model is fed the *logged* actuator voltage (valid in closed loop too: whatever the
controller did, that is what moved the piezo) and, when the log has one, the measured
temperature; it predicts what the sensor should have read. Everything is vectorized over
the whole log with the same discretization the simulated plant steps with (exact ZOH of
the linear pendulum), so a log from the simulator replays against its own model down to
the noise.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from scipy.signal import lfilter, ss2tf

from leveler import jit
from leveler.errors import LogError
from leveler.log.reader import read_log
from leveler.loop import kernel as kn
from leveler.loop.pid import PID, ControllerConfig
from leveler.settings import Config, load_config
from leveler.sim.effects import Effect, EffectsParams, Signals
from leveler.sim.params import CoolerParams, PlantParams
from leveler.sim.pendulum import (
    delayed_slew,
    discrete_matrices,
    free_step,
    linear_matrices,
    ramp_gain,
    ramp_terms,
)
from leveler.sim.plant import slew_lag_v
from leveler.typed_config import ConfigError, build

_MAX_BAD_FRACTION = 0.05
T = TypeVar("T")


@dataclass
class Measured:
    """The series of one log that replay needs, on a uniform time grid."""

    path: str
    sig: Signals
    u_v: np.ndarray  # voltage applied to the actuator over each step
    y_m: np.ndarray  # sensor reading
    config: Config  # the model (and controller) the log was recorded with, or --model
    model_source: str  # where `config` came from
    model_text: str  # its TOML text ("" for built-in defaults)
    bad_samples: int  # readings that were faulted or NaN, filled by interpolation
    gains: tuple[float, float, float]  # kp, ki, kd of the logged controller
    controller: ControllerConfig | None = None  # as logged (None: not a leveler log)
    engaged: np.ndarray | None = None  # per sample: was the loop closed?
    incomplete: str = ""  # why the log is incomplete, as read_log says ("" if it is not)
    live: bool = False  # still being written: read as a stream (read_log)

    @property
    def dt_s(self) -> float:
        return self.sig.dt_s

    @property
    def t_s(self) -> np.ndarray:
        return self.sig.t_s


def _fill(x: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """Linear interpolation over bad samples (faults must not become data, nor holes)."""
    if not bad.any():
        return x
    idx = np.arange(len(x))
    out = x.copy()
    out[bad] = np.interp(idx[bad], idx[~bad], x[~bad])
    return out


def _config_from_text(text: str, where: str) -> Config:
    try:
        return build(Config, tomllib.loads(text))
    except (ConfigError, tomllib.TOMLDecodeError) as exc:
        raise LogError(f"{where}: the config stored in the log is not valid: {exc}") from None


def load_measured(path: str | Path, model: str | Path | None = None,
                  progress: Callable[[float], None] | None = None) -> Measured:
    """Read a log (and the model to replay it against); clear errors for unusable logs.
    Ticks a late real-time loop skipped are put back: the reading interpolated, the
    voltage held, counted with the faulted samples. `progress`: told the fraction of the
    log read (read_log)."""
    path = str(path)
    data = read_log(path, progress)
    s = data.samples
    n = len(s.get("t_s", ()))
    if n < 1000:
        early = f" (the log is incomplete: {data.stop_reason})" if not data.complete else ""
        if not n and len(data.thrust_stand.get("t_s", ())):
            early = (": it holds a thrust stand's channels only (leveler analyze stiffness "
                     "LOG; leveler asd LOG --channel displacement_m)")
        raise LogError(f"{path}: {n} samples; replay needs at least 1000{early}")
    seq = s["seq"]
    gaps = np.flatnonzero(np.diff(seq) != 1)
    if len(gaps):
        raise LogError(f"{path}: samples missing after seq {int(seq[gaps[0]])} "
                       "(replay needs a contiguous log)")
    t = s["t_s"].astype(float)
    dt = float(np.median(np.diff(t)))
    # A real-time loop that wakes more than a period late skips the deadlines it missed
    # (loop.clock): its samples sit on the period's grid with ticks left out.
    k = np.rint((t - t[0]) / dt).astype(np.int64) if dt > 0 else np.zeros(n, np.int64)
    if not dt > 0 or np.any(np.diff(k) < 1) or np.max(np.abs(t - t[0] - k * dt)) > 0.01 * dt:
        raise LogError(f"{path}: samples are not uniformly spaced (median {dt:g} s)")
    at = np.searchsorted(k, np.arange(k[-1] + 1), side="right") - 1  # the sample in force
    skipped = np.ones(len(at), bool)
    skipped[k] = False
    y = np.where(skipped, np.nan, s["sensor_m"].astype(float)[at])  # no reading: filled
    bad = ~np.isfinite(y) | (s["status"][at] != 0)
    u = s["applied_v"].astype(float)[at]  # the piezo held its voltage through a skipped tick
    bad_u = ~np.isfinite(u)
    nbad = int(np.count_nonzero(bad | bad_u))
    if nbad > _MAX_BAD_FRACTION * len(at):
        raise LogError(f"{path}: {nbad} of {len(at)} samples faulted or missing; too many to "
                       "replay")
    y, u = _fill(y, bad), _fill(u, bad_u)
    t = t[0] + np.arange(len(at)) * dt
    temp = data.per_sample("temperature_k")  # the thermometer's, else the simulation's truth
    if temp is None and len(data.truth.get("temperature_k", ())) == n:
        temp = data.truth["temperature_k"].astype(float)
    if temp is not None:
        temp = temp[at]
        temp = _fill(temp, ~np.isfinite(temp)) if np.isfinite(temp).any() else None
    logged_text = data.metadata.get("leveler", {}).get("config", "")
    if model is not None:
        cfg, text = load_config(model)
        source = str(model)
    elif logged_text:
        cfg, text, source = _config_from_text(logged_text, path), logged_text, "the log's config"
    else:
        cfg, text, source = Config(), "", "built-in defaults (the log carries no config)"
    logged = _config_from_text(logged_text, path) if logged_text else cfg
    c = logged.controller
    return Measured(path, Signals(t, dt, temp), u, y, cfg, source, text, nbad,
                    (c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m),
                    c if logged_text else None, s["state"][at] == "engaged", data.stop_reason,
                    data.live)


#: the last logs `excitation_v` was asked about and its answers, the latest last: a
#: diagnosis asks four times about the same log, and each answer replays the controller
#: sample by sample (1.3 s a day); a null calibration's worker asks about the log and its
#: own simulated one in turn
_EXCITATIONS: list[tuple[Measured, np.ndarray | None]] = []
_EXCITATIONS_KEPT = 2


def excitation_v(meas: Measured) -> np.ndarray | None:
    """The part of the actuator voltage that is not the logged controller's answer to the
    logged readings (a modulation, a hand on the knob); None if the log does not say
    what the controller was.

    Without it (and without a measured input such as the temperature) a closed loop says
    nothing about the actuator: "the piezo did not move" and "the table moved the other
    way" look the same, so diagnose does not look for actuator effects then.
    """
    for i, (seen, exc) in enumerate(_EXCITATIONS):
        if seen is meas:
            _EXCITATIONS.append(_EXCITATIONS.pop(i))
            return exc
    exc = _excitation_v(meas)
    if exc is not None:
        exc.flags.writeable = False  # shared by every caller: none may change it
    _EXCITATIONS.append((meas, exc))
    del _EXCITATIONS[:-_EXCITATIONS_KEPT]
    return exc


#: an open-loop part shorter than this [s] holds no modulation worth reading
MIN_OPEN_S = 300.0


def modulation_v(meas: Measured) -> np.ndarray | None:
    """`excitation_v` where the loop was open, held at its nearest open value elsewhere,
    if the log has an open part (MIN_OPEN_S: a modulation with the loop open); else all
    of it. In a closed loop, the excitation is the difference between the log's
    controller and its replay: rounding for leveler's own, but volts and wandering for
    one leveler did not write (an independent simulator's integrator: 7.7 V), which
    hides the modulation's line and would pass for a drive of its own."""
    exc = excitation_v(meas)
    if exc is None or meas.engaged is None:
        return exc
    is_open = ~np.asarray(meas.engaged, dtype=bool)
    if np.count_nonzero(is_open) * meas.dt_s < MIN_OPEN_S or is_open.all():
        return exc  # a sample or two before the loop engaged are no modulation
    idx = np.where(is_open, np.arange(len(exc)), -1)
    idx = np.maximum.accumulate(idx)  # the last open sample at or before each one
    idx[idx < 0] = int(np.flatnonzero(is_open)[0])  # before the first: the first
    return exc[idx]


def _excitation_v(meas: Measured, kernel: str = "auto") -> np.ndarray | None:
    """`excitation_v` worked out: the logged controller replayed on the logged readings.
    `kernel`: who replays the closed loop's samples after each engage ("auto": compiled
    where numba is installed, "python": interpreted, "off": the `PID` object alone); the
    same answer to the bit whoever does (a day's replay: 0.52 s as objects, 0.064 s
    compiled)."""
    if kernel not in ("auto", "python", "off"):
        raise ValueError(f"kernel must be auto, python or off, not {kernel!r}")
    if meas.controller is None or meas.engaged is None:
        return _unexplained_by_feedback(meas)
    pid = PID(meas.controller.pid_config())
    fn = (None if kernel == "off" or kn.pid_unsupported(pid)
          else kn.replay if kernel == "python" else kn.compiled_replay())
    y_m, u_v = meas.y_m, meas.u_v
    on = np.asarray(meas.engaged, dtype=bool)
    n, dt = len(u_v), meas.dt_s
    out = np.empty(n)
    ends = np.append(np.flatnonzero(np.diff(on.astype(np.int8))) + 1, n)
    y, u = y_m.tolist(), u_v.tolist()
    held = u[0]
    start = 0
    for end in ends.tolist():
        if not on[start]:  # open loop: every move of the voltage is excitation (a modulation)
            out[start:end] = u_v[start:end] - u_v[start]
            held = u[end - 1]
            start = end
            continue
        pid.engage(y[start], held)
        i = start
        while i < end:
            if fn is not None and i > start:  # the objects engage, the kernel goes on
                i += _replayed(pid, fn, y_m, u_v, out, i, end, dt)
                if i == end:
                    break
            out[i] = u[i] - pid.update(y[i], dt).command_v  # raises where it must
            i += 1
        start = end
    return out


def _replayed(pid: PID, fn: Callable[..., tuple[int, int]], y_m: np.ndarray, u_v: np.ndarray,
              out: np.ndarray, i: int, end: int, dt_s: float) -> int:
    """Samples i to `end` of a closed loop replayed by `fn` (`kernel.replay`) from `pid`'s
    state, their excitation into `out`; returns how many it did (all, unless the PID
    would raise at the next), `pid` left where they leave it."""
    s = np.zeros(kn.N_STATE)
    k = np.zeros(kn.N_CONST)
    kn.pid_constants(pid, dt_s, k)
    res = kn.export_pid(pid, dt_s, s)
    cmd = np.empty(end - i)
    m, _ = fn(s, k, res, y_m[i:end], cmd, end - i)
    kn.import_pid(pid, s, res)
    out[i:i + m] = u_v[i:i + m] - cmd[:m]
    return m


def slewed(u_v: np.ndarray, max_dv: float) -> tuple[np.ndarray, np.ndarray]:
    """(the piezo's voltage at the end of each step, how far its mean over the step sits
    below that) for logged commands `u_v`, the amplifier slewing max_dv per step, as the
    simulated plant does. A leveler log holds what was applied (within the slew); a log of
    other origin may ask for more in one step, and then the piezo is still on its way."""
    du = np.diff(u_v, prepend=u_v[:1])
    big = np.flatnonzero(np.abs(du) > max_dv)
    if not big.size:
        return u_v, slew_lag_v(du, max_dv)
    # Between steps too large for one sample the piezo has caught up and follows the
    # command: only the few samples after each are stepped one by one (a day of square
    # modulation: ~600 of 864,000).
    v = np.array(u_v, dtype=float)
    n, k = len(u_v), int(big[0])
    while k < n:
        prev = v[k - 1]
        while k < n and abs(u_v[k] - prev) > max_dv:
            prev += math.copysign(max_dv, u_v[k] - prev)
            v[k] = prev
            k += 1
        nxt = np.searchsorted(big, k + 1)  # the sample at k is reached within its step
        if nxt == big.size:
            break
        k = int(big[nxt])
    return v, slew_lag_v(np.diff(v, prepend=v[:1]), max_dv)


#: how many set-ups `_memo` keeps, the least recently used dropped first (each holds a
#: few series as long as the log: a day's slewing is 28 MB)
_MEMO_SIZE = 8
_MEMO: dict[tuple[Any, ...], tuple[tuple[np.ndarray, ...], Any]] = {}


def _memo(arrays: tuple[np.ndarray, ...], values: tuple[Any, ...], make: Callable[[], T]) -> T:
    """`make()`, kept for the same `arrays` (the very objects, held so their ids stay
    theirs) and `values`, and handed out read-only: a recalibration builds a `Predictor`
    per knob it turns, and most of one's set-up (the slewing, the cooler's waveform, the
    lagged temperature, the thermal lag's start) depends on none of them; rebuilt, it was
    a fifth of a modulated null day's diagnosis."""
    key = (tuple(id(a) for a in arrays), values)
    hit = _MEMO.pop(key, None)
    if hit is not None and all(a is b for a, b in zip(hit[0], arrays, strict=True)):
        _MEMO[key] = hit  # the most recently used goes last, the least first out
        return hit[1]
    out = make()
    for x in out if isinstance(out, tuple) else (out,):
        if not any(x is a for a in arrays):  # `slewed` may hand back the log's own
            x.flags.writeable = False
    if len(_MEMO) >= _MEMO_SIZE:
        del _MEMO[next(iter(_MEMO))]
    _MEMO[key] = (arrays, out)
    return out


def _slewing(params: PlantParams, meas: Measured
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`slewed`'s two series, what each step's slew adds per unit dphi to the
    pendulum's [theta, omega] at its end (`ramp_gain`), and how long the piezo ramps in
    each step."""
    pz, dt = params.piezo, meas.dt_s
    v, lag_v = slewed(meas.u_v, pz.slew_v_per_s * dt)
    tau_s = np.minimum(np.abs(np.diff(v, prepend=v[:1])) / pz.slew_v_per_s, dt)
    ramp = ramp_gain(ramp_terms(params.pendulum, dt), tau_s)
    return v, lag_v, ramp[:, 0].copy(), ramp[:, 1].copy(), tau_s


def _cooler_shape(co: CoolerParams, sig: Signals) -> np.ndarray:
    """The cooler's waveform, -0.5 to 0.5 (its peak to peak scales it)."""
    frac = np.mod((sig.t_s + co.phase_s) / co.period_s, 1.0)
    rise = 1.0 - co.fall_fraction
    return np.where(frac < rise, frac / rise, (1.0 - frac) / co.fall_fraction) - 0.5


def _lagged(temp_k: np.ndarray, lag_s: float, dt_s: float) -> np.ndarray:
    """The temperature through the table's first-order thermal lag, settled at the start."""
    a = math.exp(-dt_s / lag_s)
    return lfilter([1 - a], [1, -a], temp_k, zi=np.array([a * temp_k[0]]))[0]


def pendulum_filter(params: PlantParams, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """theta/phi of the discretized linear pendulum (`PendulumModel`'s steps) as lfilter
    coefficients."""
    a, b = discrete_matrices(params.pendulum, dt_s)
    num, den = ss2tf(a, b[:, None], np.array([[1.0, 0.0, 0.0]]), np.array([[0.0]]))
    return np.ravel(num), np.ravel(den)


@dataclass
class Prediction:
    """Model output for one log: before and after the sensor stage, and the piezo tilt."""

    x_m: np.ndarray  # true displacement at the sensor the model expects
    y_m: np.ndarray  # what the sensor should read
    phi_u_rad: np.ndarray  # platform tilt the piezo made


class Predictor:
    """The model of one `PlantParams` applied to one log's inputs.

    Caches the base prediction so a candidate effect of a late stage costs one filter and
    an FFT, not a whole replay: that is what makes fitting a 24 h log take seconds.
    """

    def __init__(self, params: PlantParams, meas: Measured, ringing: bool = False) -> None:
        self.params = params
        self.meas = meas
        pe, pz = params.pendulum, params.piezo
        self.arm_m = pe.sensor_arm_m
        self.static_m_per_rad = pe.sensor_arm_m * pe.amplification
        self._kv = pz.gain_m_per_v / params.platform.support_spacing_m
        self._ref = pz.ref_v
        self._v, self._lag_v, self._ramp_theta, self._ramp_omega, self._tau_s = _memo(
            (meas.u_v,), (pe, pz.slew_v_per_s, meas.dt_s), lambda: _slewing(params, meas))
        self._b, self._a = pendulum_filter(params, meas.dt_s)
        # e^(A dt), whose characteristic polynomial is pendulum_filter's denominator
        self._e = free_step(pe, meas.dt_s)
        self._amp = pe.amplification
        self.nominal_tilt = self._nominal_tilt()
        self._transient = self.thermal_transient()
        # replay fits the pendulum's start; diagnose skips the first minutes instead (with the
        # swing free in every fit, a tuning case's actuator delay was taken for hysteresis)
        self._ringing = self.ringing() if ringing else []
        own = self.start_shapes(EffectsParams())
        self._own_states = _StartStates(own) if own else None
        self.effects = params.effects
        self._base: Prediction | None = None

    @property
    def base(self) -> Prediction:
        """The prediction of the base effects, made when first asked for: a recalibration
        builds a `Predictor` per knob only for its response to the modulation."""
        if self._base is None:
            self._base = self.predict(self.effects)
        return self._base

    def rebase(self, effects: EffectsParams) -> None:
        """Make `effects` the base that candidates are added to."""
        self.effects = effects
        self._base = None

    def _nominal_tilt(self) -> np.ndarray:
        """Disturbance tilt the nominal model can predict: thermal (if the temperature was
        logged) and the cooler; the table's offset is unknown and left to the fit."""
        p, sig = self.params, self.meas.sig
        co, th = p.cooler, p.thermal
        tilt = co.peak_to_peak_rad * _memo(
            (sig.t_s,), (co.phase_s, co.period_s, co.fall_fraction),
            lambda: _cooler_shape(co, sig))
        temp = sig.temperature_k
        if temp is not None and th.tilt_per_kelvin_rad_per_k != 0:
            if th.lag_s > 0:
                temp = _memo((temp,), (th.lag_s, sig.dt_s),
                             lambda: _lagged(temp, th.lag_s, sig.dt_s))
            tilt = tilt + th.tilt_per_kelvin_rad_per_k * (temp - th.mean_k)
        return tilt

    def actuator_tilt(self, v: np.ndarray) -> np.ndarray:
        """Platform tilt [rad] that a change of the piezo voltage by `v` makes."""
        return self._kv * v

    def pend(self, phi: np.ndarray) -> np.ndarray:
        """Sensor displacement [m] for platform tilt phi, starting settled at phi[0]."""
        return self.arm_m * (self._amp * phi[0] + lfilter(self._b, self._a, phi - phi[0]))

    def pend_slewed(self, phi: np.ndarray, phi_end: np.ndarray,
                    inject: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """`pend` of `phi` plus what the piezo's slewing adds, its tilt at each step's end
        `phi_end` (`leveler.sim.pendulum.ramp_terms`): each step's change injects into
        [theta, omega] at the step's end, and the held pendulum carries it on. Both run
        through the pendulum's one denominator in one filter (every replay does this).
        `inject`, the injections themselves (per step, in radians: a delayed piezo's,
        `leveler.sim.pendulum.delayed_slew`), replaces the slews from each step's start.

        A fit replays a day hundreds of times: after the numerator's convolution, the
        injections and the denominator's recursion are one pass compiled by numba where
        it is installed (`_slewed_pass`: a day's call 11 -> 6.4 ms), else numpy's passes in place;
        the same operations in the same order either way, so the same to the bit."""
        d = phi - phi[0]
        w = np.convolve(d, self._b)[: len(d)]
        (_, e12), (_, e22) = self._e
        offset = self._amp * phi[0]
        if inject is None:
            dphi = np.empty(len(phi_end))
            dphi[0] = phi_end[0] - phi_end[0]
            np.subtract(phi_end[1:], phi_end[:-1], out=dphi[1:])
            g_theta, g_omega = self._ramp_theta * dphi, self._ramp_omega * dphi
        else:
            g_theta, g_omega = inject
        fast = jit.compiled(_slewed_pass)
        if fast is not None and self._a[0] == 1.0 and len(self._a) >= 2:
            return fast(w, g_theta, g_omega, e12, e22,
                        np.ascontiguousarray(self._a, dtype=float), float(offset),
                        self.arm_m)
        w[1:] += g_theta[:-1]
        turn = g_omega[:-2] * e12
        turn -= e22 * g_theta[:-2]
        w[2:] += turn
        x = lfilter([1.0], self._a, w)
        x += offset
        x *= self.arm_m
        return x

    def thermal_transient(self) -> np.ndarray | None:
        """Shape of the thermal lag's unknown initial state (a nuisance the fit removes)."""
        th = self.params.thermal
        if self.meas.sig.temperature_k is None or th.lag_s <= 0:
            return None
        t_s = self.meas.t_s
        return _memo((t_s,), (self.params.pendulum, th.lag_s, self.meas.dt_s),
                     lambda: self.pend(np.exp(-(t_s - t_s[0]) / th.lag_s)))

    def ringing(self) -> list[np.ndarray]:
        """Shapes of the pendulum's free motion from an unknown start (its two modes, e.g.
        e^(-t/tau) cos and sin of its resonance): a log may begin with the pendulum swinging,
        and a lightly damped one (Q of thousands) rings for hours; a replay that started it
        at rest would lay its own ringing over every later comparison."""
        a, _ = linear_matrices(self.params.pendulum)
        lam = np.linalg.eigvals(a)
        t = self.meas.t_s - self.meas.t_s[0]
        if abs(lam[0].imag) > 0:
            ring = np.exp(complex(lam[0]) * t)
            modes = [ring.real, ring.imag]
        else:
            modes = [np.exp(float(lam[0].real) * t), np.exp(float(lam[1].real) * t)]
        return [self.arm_m * m for m in modes]

    def predict(self, effects: EffectsParams) -> Prediction:
        sig, u = self.meas.sig, self._v
        delay = effects.actuator_delay
        for fx in effects.of("actuator"):
            if fx is not delay:  # a rate-independent piezo: the same delayed or not
                u = fx.apply(u, sig)
        lag_v, inject = self._lag_v, None
        if delay is not None and delay.delay_s > 0:
            u, lag_v, (theta, omega) = delayed_slew(
                self.params.pendulum, sig.dt_s, u, self._tau_s, delay.delay_s,
                (self._ramp_theta, self._ramp_omega))
            inject = self._kv * theta, self._kv * omega
        phi_end = self._kv * (u - self._ref)  # where the piezo is at each step's end
        phi_u = phi_end - self._kv * lag_v  # its mean over the step
        phi = phi_end + self.nominal_tilt
        for fx in effects.of("tilt"):
            phi = phi + fx.tilt(sig)  # type: ignore[attr-defined]
        x = self.pend_slewed(phi, phi_end, inject)
        for fx in effects.of("response"):
            x = x + fx.response(phi_u, self.static_m_per_rad, sig)  # type: ignore[attr-defined]
        shapes = self.start_shapes(effects)
        if shapes:
            x = x + self._start_state(self._sensor(x, effects), shapes)
        return Prediction(x, self._sensor(x, effects), phi_u)

    def start_shapes(self, effects: EffectsParams) -> list[np.ndarray]:
        """Displacements [m] that the unknown states at the log's start add, per unit state:
        the pendulum's swing (`ringing`), the table's thermal lag, and `effects`' lags."""
        shapes = list(self._ringing) + ([] if self._transient is None else [self._transient])
        return shapes + [s for fx in effects.of("tilt") for s in self.state_shapes(fx)]

    def state_shapes(self, fx: Effect) -> list[np.ndarray]:
        """Displacements [m] per unit of one effect's own start states (a coupling's lags
        that had not settled): a candidate's, for a fit to solve with the nuisances."""
        if fx.stage != "tilt":
            return []
        return [self.pend(s) for s in fx.start_shapes(self.meas.sig)]

    def _start_state(self, y_pred: np.ndarray, shapes: list[np.ndarray]) -> np.ndarray:
        """The lags' unknown states at the log's start (the table's thermal lag, an
        effect's), fitted by least squares (with an offset) to what the whole prediction,
        sensor effects included, leaves: they decay within a few lags, and fitted once here
        they cannot pass for a drift later on. A log that starts out of equilibrium would
        otherwise hand a temperature coupling a transient it cannot follow."""
        own = self._own_states
        if own is None or len(own.shapes) != len(shapes) or not all(
                a is b for a, b in zip(own.shapes, shapes, strict=False)):
            return _StartStates(shapes).fit(self.meas.y_m - y_pred)
        return own.fit(self.meas.y_m - y_pred)

    def _sensor(self, x: np.ndarray, effects: EffectsParams) -> np.ndarray:
        """The sensor stage, fed the displacement aligned with the readings: the table's
        offset is unknown to the model, and a non-linear stage (a coarse lattice) needs
        the absolute value, not just the changes."""
        fx_sensor = effects.of("sensor")
        if fx_sensor:
            x = x + float(np.median(self.meas.y_m - x))
        for fx in fx_sensor:
            x = fx.apply(x, self.meas.sig)
        return x

    def with_candidate(self, fx: Effect) -> np.ndarray:
        """Predicted reading of the base effects plus (or with this one replaced by) `fx`.

        Tilt and response effects add linearly to the cached base, a lag of their own
        settled at the first sample (its unknown start is the fit's: `state_shapes`);
        actuator effects are non-linear (hysteresis) and replay in full.
        """
        merged = self.effects.with_effect(fx)
        if fx.stage == "actuator" or getattr(self.effects, fx.name) is not None:
            return self.predict(merged).y_m
        x = self.base.x_m
        if fx.stage == "tilt":
            x = x + self.pend(fx.tilt(self.meas.sig))  # type: ignore[attr-defined]
        elif fx.stage == "response":
            x = x + fx.response(self.base.phi_u_rad, self.static_m_per_rad,  # type: ignore[attr-defined]
                                self.meas.sig)
        return self._sensor(x, merged)

    def physical_change(self, fx: Effect) -> np.ndarray:
        """How much adding `fx` changes the displacement (or, for a sensor effect, the
        reading): its size, undistorted by a coarse quantizer downstream."""
        if fx.stage == "sensor":
            return self.with_candidate(fx) - self.base.y_m
        return self.predict(self.effects.with_effect(fx)).x_m - self.base.x_m


class _StartStates:
    """The least-squares fit of an offset plus `shapes` to a residual, less the offset.

    By the normal equations of the centred, unit-scaled shapes, refined once against the
    residual (that refinement is what keeps it at a direct solve's precision): every
    replay of a candidate fits these states, and a direct solve of the tall system took
    30 ms of a 40 ms replay of a day (a hysteresis fit replays it hundreds of times). The
    scaled shapes and their Gram matrix depend on the shapes alone, so a `Predictor`
    keeps those of its own shapes (the ringing, the thermal lag's) for every replay."""

    def __init__(self, shapes: list[np.ndarray]) -> None:
        self.shapes = shapes
        cols = np.array(shapes, dtype=float)  # one row a shape
        self.means = cols.mean(axis=1)
        cols -= self.means[:, None]
        self.norms = np.linalg.norm(cols, axis=1)
        self.norms[self.norms == 0] = 1.0
        cols /= self.norms[:, None]
        self.cols = cols
        self.gram = cols @ cols.T

    def fit(self, r: np.ndarray) -> np.ndarray:
        cols, gram = self.cols, self.gram
        rc = r - float(np.mean(r))
        coef = np.linalg.lstsq(gram, cols @ rc, rcond=None)[0]
        fit = coef @ cols
        coef += np.linalg.lstsq(gram, cols @ (rc - fit), rcond=None)[0]
        return coef @ cols + float(np.dot(coef / self.norms, self.means))


def _slewed_pass(w: np.ndarray, g_theta: np.ndarray, g_omega: np.ndarray, e12: float,
                 e22: float, a: np.ndarray, offset: float, arm: float) -> np.ndarray:
    """`Predictor.pend_slewed` after its convolution, one sample after another: each
    step's injections, then scipy's lfilter([1], a) with a[0] = 1 (direct form II
    transposed, its zero numerator terms included), then the offset and the arm, each
    in numpy's order."""
    n, m = len(w), len(a) - 1
    out = np.empty(n)
    z = np.zeros(m)
    for i in range(n):
        x = w[i]
        if i >= 1:
            x = x + g_theta[i - 1]
        if i >= 2:
            x = x + (g_omega[i - 2] * e12 - e22 * g_theta[i - 2])
        y = z[0] + 1.0 * x
        for k in range(1, m):
            z[k - 1] = (z[k] + x * 0.0) - y * a[k]
        z[m - 1] = x * 0.0 - y * a[m]
        out[i] = (y + offset) * arm
    return out


def _unexplained_by_feedback(meas: Measured) -> np.ndarray:
    """For a log without its controller (imported data): the voltage changes a PID in
    velocity form (du = kp de + ki e dt + kd d2e / dt) fitted to the readings cannot
    explain, summed up. Open-loop data keeps all its changes; a closed loop's are
    explained and leave ~0."""
    y, u = meas.y_m, meas.u_v
    du = np.diff(u)[1:]
    a = np.column_stack([y[2:], np.diff(y)[1:], np.diff(y, 2)])
    a = a / np.maximum(np.std(a, axis=0), 1e-300)
    coef, *_ = np.linalg.lstsq(a, du, rcond=None)
    return np.concatenate([[0.0, 0.0], np.cumsum(du - a @ coef)])


def actuator_excited(meas: Measured, pred: Predictor, span: slice) -> bool:
    """Did anything but feedback move the actuator enough to be seen at the sensor? In a
    closed loop the controller's replay differs from the log by rounding (1e-10 V), and
    a line of that, at a disturbance the loop answered, is no modulation."""
    exc = excitation_v(meas)
    if exc is None:  # not a leveler log: the voltage may well be a modulation
        return True
    p = pred.params
    kv = p.piezo.gain_m_per_v / p.platform.support_spacing_m
    seen = pred.pend(kv * exc)[span]
    return float(np.std(seen)) > 3 * sensor_noise_m(p, meas.dt_s)


def sensor_noise_m(params: PlantParams, dt_s: float) -> float:
    """The model's white sensor noise per sample, ADC rounding included: the floor a replay
    residual cannot go below, and the yardstick for "big enough to matter"."""
    se = params.sensor
    return math.hypot(se.noise_m_per_rthz * math.sqrt(0.5 / dt_s), se.lsb_m / math.sqrt(12))
