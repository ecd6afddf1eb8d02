"""PID controller: piezo volts from a displacement-sensor reading in metres.

Design choices, and why:

* The derivative acts on the (low-passed) measurement, not the error, so a setpoint step
  never kicks the piezo; setpoint changes are also ramped so the proportional term moves
  gently.
* The integral is stored in volts, not metre-seconds, so retuning ``ki`` (or any gain,
  through :meth:`PID.set_gains`) does not jump the output.
* Anti-windup is back-calculation plus a freeze. Back-calculation bleeds off whatever
  the integral holds beyond the rail; the freeze stops it ever growing toward a rail the
  output sits on, so however long the output saturates it leaves the rail within a few
  samples of the error reversing.
* It never reads a clock: the caller passes ``dt``, so simulation and hardware share one
  code path and tests are deterministic.
* Optional resonant terms (``PIDConfig.periodic``, leveler.loop.resonant) are the
  integral's counterpart for a periodic disturbance; their output is reported within
  ``i_v`` (both are the controller's internal models), so p + i + d stays the command.
* An optional double integral (``PIDGains.ki2``) adds ki2 x (the integral of the error) to
  the integral's own increments, so the integral state in volts holds both and every
  bumpless rule above holds for it: loop gain rising as 1 / f^2 below ki2 / (2 pi ki) Hz,
  for the mHz band a single integrator leaves. The error's integral it feeds on advances
  only while the command follows the sum (conditional integration).
* An optional notch (``PIDConfig.notch``, leveler.loop.notch) filters the reading before
  all three terms: the loop stops acting at one frequency (a mode the model lacks). The
  logged ``error_m`` is the setpoint minus the filtered reading, what the terms acted on.
* A feedforward (``ff_v`` of :meth:`PID.update`, leveler.loop.feedforward) is added to the
  sum before the limits, so the rails and anti-windup see the whole command; the bumpless
  rules keep it out of the integral, and :meth:`PID.absorb_feedforward` moves it in when
  the feedforward is switched off.
* :meth:`PID.update` runs at up to 1 kHz in Python next to a simulator, so it is plain
  float arithmetic on slotted attributes, allocating only the returned record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from leveler.loop.feedforward import Feedforward, FeedforwardPath
from leveler.loop.notch import Notch, NotchFilter
from leveler.loop.resonant import PeriodicTerms, Resonators
from leveler.typed_config import non_negative, positive

_INF = math.inf

# Back-calculation gain per sample when kp == 0 leaves no time scale to derive the tracking
# time from: track over about three samples, i.e. dt / (Tt + dt) with Tt = 3 dt.
_SAMPLE_TRACKING_GAIN = 1.0 / (3.0 + 1.0)
# Resonant terms start being fed this many periods after an engage (see `update`).
ENGAGE_SETTLE_PERIODS = 0.1


def _require_finite(name: str, value: float) -> None:
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")


def _require_non_negative(name: str, value: float) -> None:
    if not 0.0 <= value < _INF:
        raise ValueError(f"{name} must be finite and >= 0, got {value!r}")


def _require_rate(name: str, value: float) -> None:
    # inf is allowed: it is the documented "no limit" value.
    if not value > 0.0:
        raise ValueError(f"{name} must be > 0 (inf for no limit), got {value!r}")


@dataclass(frozen=True, slots=True)
class PIDGains:
    """Gains in SI units. Any sign is accepted, so a reverse-acting plant needs no wrapper."""

    kp: float  # V/m
    ki: float  # V/(m s)
    kd: float  # V s/m
    ki2: float = 0.0  # V/(m s^2): a double integral, loop gain as 1/f^2 below ki2/(2 pi ki)

    def __post_init__(self) -> None:
        _require_finite("kp", self.kp)
        _require_finite("ki", self.ki)
        _require_finite("kd", self.kd)
        _require_finite("ki2", self.ki2)


@dataclass(frozen=True, slots=True)
class PIDConfig:
    """Everything that shapes the controller; validated here so the hot path need not be."""

    gains: PIDGains
    output_min_v: float
    output_max_v: float
    setpoint_m: float = 0.0
    slew_v_per_s: float = math.inf  # output rate limit
    d_filter_tau_s: float = 0.0  # first-order low-pass on the derivative; 0 = none
    setpoint_ramp_m_per_s: float = math.inf  # setpoint changes ramp at this rate
    tracking_time_s: float = 0.0  # back-calculation time constant; 0 = derived from the gains
    periodic: PeriodicTerms | None = None  # resonant terms for a periodic disturbance
    notch: Notch | None = None  # on the reading, before the terms

    def __post_init__(self) -> None:
        _require_finite("output_min_v", self.output_min_v)
        _require_finite("output_max_v", self.output_max_v)
        if not self.output_min_v < self.output_max_v:
            raise ValueError(
                f"output_min_v must be < output_max_v, got {self.output_min_v!r} "
                f">= {self.output_max_v!r}"
            )
        _require_finite("setpoint_m", self.setpoint_m)
        _require_rate("slew_v_per_s", self.slew_v_per_s)
        _require_non_negative("d_filter_tau_s", self.d_filter_tau_s)
        _require_rate("setpoint_ramp_m_per_s", self.setpoint_ramp_m_per_s)
        _require_non_negative("tracking_time_s", self.tracking_time_s)



@dataclass(frozen=True, slots=True)
class ControllerConfig:
    """PID from sensor metres to actuator volts; error = setpoint - reading."""

    kp_v_per_m: float = 0.0
    ki_v_per_m_s: float = 7.0e5
    kd_v_s_per_m: float = 0.0
    ki2_v_per_m_s2: float = 0.0  # double integral; 0: none
    setpoint_m: float = 0.0
    output_min_v: float = 0.0
    output_max_v: float = 150.0
    slew_v_per_s: float = positive(10.0, allow_inf=True)
    d_filter_tau_s: float = non_negative(0.5)
    setpoint_ramp_m_per_s: float = positive(math.inf, allow_inf=True)
    tracking_time_s: float = non_negative(0.0)
    periodic_period_s: float = non_negative(0.0)  # 0: no resonant terms
    periodic_gains_v_per_m_s: tuple[float, ...] = ()  # harmonics 1, 2, ... of the period
    periodic_phases_rad: tuple[float, ...] = ()
    periodic_radius: float = field(default=1.0, metadata={"gt": 0.0, "le": 1.0})
    notch_frequency_hz: float = non_negative(0.0)  # 0: no notch on the reading
    notch_q: float = positive(2.0)
    notch_depth: float = field(default=0.0, metadata={"ge": 0.0, "lt": 1.0})
    # temperature feedforward (leveler.loop.feedforward), a path per gain; needs [thermometer]
    feedforward_gains_v_per_k: tuple[float, ...] = ()
    feedforward_lags_s: tuple[float, ...] = ()  # one per gain
    feedforward_lags2_s: tuple[float, ...] = ()  # a second lag in series per gain; () none

    def __post_init__(self) -> None:
        if not self.output_min_v < self.output_max_v:
            raise ValueError(
                f"output_min_v ({self.output_min_v}) must be below "
                f"output_max_v ({self.output_max_v})"
            )
        if len(self.periodic_gains_v_per_m_s) != len(self.periodic_phases_rad):
            raise ValueError(
                f"periodic_phases_rad needs one phase per gain of periodic_gains_v_per_m_s "
                f"({len(self.periodic_phases_rad)} vs {len(self.periodic_gains_v_per_m_s)})")
        if self.periodic_gains_v_per_m_s and not self.periodic_period_s > 0:
            raise ValueError("periodic_gains_v_per_m_s needs periodic_period_s > 0")
        n = len(self.feedforward_gains_v_per_k)
        for key in ("feedforward_lags_s", "feedforward_lags2_s"):
            got = len(getattr(self, key))
            if got != n and not (key == "feedforward_lags2_s" and got == 0):
                raise ValueError(f"{key} needs one lag [s] per gain of "
                                 f"feedforward_gains_v_per_k ({got} vs {n})")
        for key in ("feedforward_gains_v_per_k", "feedforward_lags_s", "feedforward_lags2_s"):
            for i, v in enumerate(getattr(self, key)):
                if not math.isfinite(v) or (v < 0 and key != "feedforward_gains_v_per_k"):
                    raise ValueError(f"{key}[{i}] must be finite"
                                     + ("" if key == "feedforward_gains_v_per_k" else " and >= 0")
                                     + f", got {v!r}")

    def periodic_terms(self) -> PeriodicTerms | None:
        if not (self.periodic_period_s > 0 and self.periodic_gains_v_per_m_s):
            return None
        return PeriodicTerms(self.periodic_period_s, tuple(self.periodic_gains_v_per_m_s),
                             tuple(self.periodic_phases_rad), self.periodic_radius)

    def notch(self) -> Notch | None:
        if not self.notch_frequency_hz > 0:
            return None
        return Notch(self.notch_frequency_hz, self.notch_q, self.notch_depth)

    def feedforward(self) -> Feedforward | None:
        gains = self.feedforward_gains_v_per_k
        if not any(gains):
            return None
        lags2 = self.feedforward_lags2_s or (0.0,) * len(gains)
        return Feedforward(tuple(FeedforwardPath(g, lag, lag2) for g, lag, lag2 in zip(
            gains, self.feedforward_lags_s, lags2, strict=True) if g))

    def pid_config(self) -> PIDConfig:
        return PIDConfig(
            gains=PIDGains(self.kp_v_per_m, self.ki_v_per_m_s, self.kd_v_s_per_m,
                           self.ki2_v_per_m_s2),
            output_min_v=self.output_min_v,
            output_max_v=self.output_max_v,
            setpoint_m=self.setpoint_m,
            slew_v_per_s=self.slew_v_per_s,
            d_filter_tau_s=self.d_filter_tau_s,
            setpoint_ramp_m_per_s=self.setpoint_ramp_m_per_s,
            tracking_time_s=self.tracking_time_s,
            periodic=self.periodic_terms(),
            notch=self.notch(),
        )


@dataclass(slots=True)
class PIDOutput:
    """One update's result; ``p_v + i_v + d_v`` and the feedforward given to the update are
    the command before clamping and slewing.

    Not frozen: a frozen dataclass sets each field through object.__setattr__, which was
    two thirds of an update's cost (bench/pid_speed.py). A fresh one is returned each time.
    """

    setpoint_m: float  # effective (ramped) setpoint
    error_m: float
    p_v: float
    i_v: float
    d_v: float
    command_v: float
    saturated: bool  # command_v differs from the sum (rail or slew limit)


def _auto_tracking_time(gains: PIDGains) -> float:
    """Åström and Hägglund's rule: sqrt(Ti Td) with derivative action, Ti without.

    0.0 tells ``update`` to track over a few samples instead (kp == 0 gives no Ti);
    inf disables tracking when there is no integral action to wind up.
    """
    if gains.ki == 0.0:
        return _INF
    if gains.kp == 0.0:
        return 0.0
    if gains.kd == 0.0:
        return abs(gains.kp / gains.ki)
    return math.sqrt(abs(gains.kd / gains.ki))


class PID:
    """Discrete PID with measurement derivative, setpoint ramp, slew limit and anti-windup."""

    __slots__ = (
        "_config",
        "_df",
        "_err",
        "_ff",
        "_hi",
        "_i",
        "_kd",
        "_ki",
        "_ki2",
        "_kp",
        "_lo",
        "_notch",
        "_out",
        "_prev",
        "_r",
        "_ramp",
        "_raw",
        "_res",
        "_res_wait_s",
        "_s1",
        "_slew",
        "_sp",
        "_target",
        "_tau",
        "_tt",
        "_u",
    )

    def __init__(self, config: PIDConfig, initial_output_v: float | None = None) -> None:
        """Start at ``initial_output_v`` (default 0 V), clamped into the output range.

        The first update preloads the integral so that it outputs exactly this value:
        taking over an actuator that already holds a voltage must not kick it.
        """
        out = 0.0 if initial_output_v is None else initial_output_v
        _require_finite("initial_output_v", out)
        self._apply(config)
        self._sp = config.setpoint_m
        self._out = min(max(out, self._lo), self._hi)
        self._u = self._out
        self._i = self._out
        self._err = 0.0
        self._df = 0.0
        self._prev: float | None = None  # None: the next update seeds the loop state
        self._r = 0.0  # the resonant terms' output in the last update
        self._res = None if config.periodic is None else Resonators(config.periodic)
        self._res_wait_s = 0.0  # until the resonant terms are fed (after an engage)
        self._notch: NotchFilter | None = None  # made at the first update, which knows dt
        self._raw = 0.0  # the last reading before the notch (while there is one)
        self._s1 = 0.0  # the error's integral [m s] the double integral feeds on
        self._ff = 0.0  # the feedforward in the last update [V]

    @property
    def config(self) -> PIDConfig:
        """The current configuration, including gain, limit, slew and setpoint changes."""
        return self._config

    @property
    def output_v(self) -> float:
        """The last command, always within the current output limits."""
        return self._out

    def _apply(self, config: PIDConfig) -> None:
        # Copy the configuration into plain attributes: update() reads them every sample.
        gains = config.gains
        self._config = config
        self._kp = gains.kp
        self._ki = gains.ki
        self._ki2 = gains.ki2
        self._kd = gains.kd
        self._lo = config.output_min_v
        self._hi = config.output_max_v
        self._slew = config.slew_v_per_s
        self._tau = config.d_filter_tau_s
        self._ramp = config.setpoint_ramp_m_per_s
        self._target = config.setpoint_m
        tt = config.tracking_time_s
        self._tt = tt if tt > 0.0 else _auto_tracking_time(gains)

    def update(self, measurement_m: float, dt_s: float, ff_v: float = 0.0) -> PIDOutput:
        """Advance one sample of ``dt_s`` seconds and return the new command; ``ff_v`` [V]
        is a feedforward added to the terms before the limits.

        Raises ValueError for a non-positive or non-finite ``dt_s`` or a non-finite
        measurement: the caller decides what a bad reading means, not the controller.
        Raises OverflowError, changing nothing, if the arithmetic leaves the floats.
        """
        if not 0.0 < dt_s < _INF:
            raise ValueError(f"dt_s must be finite and > 0, got {dt_s!r}")
        if not -_INF < measurement_m < _INF:
            raise ValueError(f"measurement_m must be finite, got {measurement_m!r}")
        notch = self._config.notch
        filt = None
        if notch is not None:
            filt = self._notch
            if filt is None or self._prev is None:
                filt = self._notch = NotchFilter(notch, dt_s)
                filt.seed(measurement_m)
            filtered = filt.state()  # undone if this sample is refused (OverflowError)
            raw = measurement_m
            measurement_m = filt.step(measurement_m, dt_s)

        sp = self._sp
        target = self._target
        if sp != target:
            step = self._ramp * dt_s
            if target - sp > step:
                sp += step
            elif sp - target > step:
                sp -= step
            else:
                sp = target
            self._sp = sp
        error = sp - measurement_m
        p = self._kp * error

        prev = self._prev
        if prev is None:
            # No derivative without a previous sample; preload the integral so that this
            # first output is exactly the one the controller was created with.
            df = 0.0
            self._i = self._out - p - ff_v
        else:
            # Backward-Euler first-order low-pass of d(measurement)/dt; exact difference
            # quotient when tau == 0.
            tau = self._tau
            df = (tau * self._df + (measurement_m - prev)) / (tau + dt_s)
        d = -self._kd * df
        i = self._i
        res = self._res
        if res is None:
            r = 0.0
            u = p + i + d + ff_v
        else:
            r = res.output_v()
            u = p + i + r + d + ff_v

        lo = self._lo
        hi = self._hi
        cmd = lo if u < lo else hi if u > hi else u
        last = self._out
        step = self._slew * dt_s
        if cmd > last + step:
            cmd = last + step
        elif cmd < last - step:
            cmd = last - step

        # Back-calculation discretised as dt / (Tt + dt) rather than dt / Tt, so a long
        # sample (dt >= Tt) pulls the integral back to the rail instead of overshooting.
        tt = self._tt
        k_track = dt_s / (tt + dt_s) if tt > 0.0 else _SAMPLE_TRACKING_GAIN
        delta = self._ki * error * dt_s + (cmd - u) * k_track
        ki2 = self._ki2
        if ki2:
            s1 = self._s1 + error * dt_s if cmd == u else self._s1
            delta += ki2 * s1 * dt_s
        if (delta > 0.0 and cmd >= hi) or (delta < 0.0 and cmd <= lo):
            delta = 0.0  # freeze: never integrate further into the rail we sit on
        i_next = i + delta
        if not -_INF < i_next + cmd < _INF:
            # Absurd inputs (a 1e300 reading times a large gain) overflow to inf - inf = NaN;
            # refuse before any state changes, so a NaN never reaches the actuator.
            if filt is not None:
                filt.restore(filtered)
            raise OverflowError(f"PID arithmetic overflowed (measurement {measurement_m!r} m, "
                                f"p {p!r} V, i {i!r} V, d {d!r} V)")
        self._i = i_next
        if filt is not None:
            self._raw = raw
        if ki2:
            self._s1 = s1
        if res is not None:
            # Fed while the command follows the sum (not railed or slew-limited), and not in
            # the engage transient, which is the PID's to take out: fed, it rings the terms
            # (a 430 nm engage left 1.9x the sensor floor at 8 mHz over the next 6 h).
            if self._res_wait_s > 0.0:
                self._res_wait_s -= dt_s
                res.advance(error, dt_s, feed=False)
            else:
                res.advance(error, dt_s, feed=cmd == u)
            self._r = r

        self._out = cmd
        self._u = u
        self._ff = ff_v
        self._err = error
        self._df = df
        self._prev = measurement_m
        return PIDOutput(sp, error, p, i if res is None else i + r, d, cmd, cmd != u)

    def set_gains(self, gains: PIDGains) -> None:
        """Change gains without a bump: the next output continues from the current one.

        The integral is re-solved so that the new p + i + d equals the last unclamped
        output at the last error and filtered derivative. This gives up the integral step
        taken in the last update, a one-sample loss the loop makes up at once.
        """
        config = replace(self._config, gains=gains)
        self._i = self._u - self._r - self._ff - gains.kp * self._err + gains.kd * self._df
        if not gains.ki2:
            self._s1 = 0.0  # switched on again, the double integral starts from rest
        self._apply(config)

    def set_periodic(self, terms: PeriodicTerms | None) -> None:
        """Switch resonant terms on, off or to new ones without a bump: the new terms start
        from rest and whatever the old ones were adding moves into the integral, so the
        next output continues from the current one."""
        if self._res is not None:
            self._i += self._res.output_v()
        self._r = 0.0
        self._res = None if terms is None else Resonators(terms)
        self._apply(replace(self._config, periodic=terms))

    def set_notch(self, notch: Notch | None) -> None:
        """Switch the notch on, off or to another one without a bump: the next update starts
        the new filter as if it had seen that reading forever (so it passes it unchanged);
        the integral is re-solved, as in `set_gains`, and the derivative continued, from
        the last reading unfiltered."""
        old = self._config.notch
        if notch == old:
            return
        self._apply(replace(self._config, notch=notch))
        self._notch = None
        if self._prev is None:  # not started: the first update seeds everything
            return
        raw = self._prev if old is None else self._raw
        err = self._sp - raw
        self._i = self._u - self._r - self._ff - self._kp * err + self._kd * self._df
        self._err = err
        self._prev = raw  # the derivative goes on from the reading the new filter passes

    def absorb_feedforward(self) -> None:
        """The feedforward goes away (switched off or replaced): what it added last moves
        into the integral, so the next output, without it, continues from the current one."""
        self._i += self._ff
        self._ff = 0.0

    def set_setpoint(self, setpoint_m: float) -> None:
        """Set the target; the effective setpoint ramps toward it in later updates."""
        self._apply(replace(self._config, setpoint_m=setpoint_m))

    def set_limits(self, output_min_v: float, output_max_v: float) -> None:
        """Change the output range; a narrowed range clamps the output at once.

        Limits win over the slew limit: they protect the hardware, the slew only smooths.
        """
        self._apply(replace(self._config, output_min_v=output_min_v, output_max_v=output_max_v))
        self._out = min(max(self._out, self._lo), self._hi)

    def set_slew(self, slew_v_per_s: float) -> None:
        """Change the output rate limit (V/s, inf for none)."""
        self._apply(replace(self._config, slew_v_per_s=slew_v_per_s))

    def engage(self, measurement_m: float, output_v: float) -> None:
        """Bumpless enable: take over an actuator that currently holds ``output_v``.

        The next update with the same measurement outputs ``output_v`` (clamped). The
        derivative is seeded from this measurement, so the loop does not see a jump from
        whatever it last measured while disengaged.
        """
        _require_finite("measurement_m", measurement_m)
        _require_finite("output_v", output_v)
        out = min(max(output_v, self._lo), self._hi)
        error = self._sp - measurement_m
        if self._config.periodic is not None:  # the disturbance's phase is unknown: from rest
            self._res = Resonators(self._config.periodic)
            self._r = 0.0
            self._res_wait_s = ENGAGE_SETTLE_PERIODS * self._config.periodic.period_s
        self._prev = measurement_m
        self._raw = measurement_m
        self._notch = None  # restarted from this reading by the next update
        self._s1 = 0.0
        self._df = 0.0
        self._ff = 0.0  # the caller's feedforward starts from zero at an engage
        self._err = error
        self._out = out
        self._u = out
        self._i = out - self._kp * error
