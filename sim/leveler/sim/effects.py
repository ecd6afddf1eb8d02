"""Named model effects: physically meaningful additions to the plant, one small class each.

An effect is a `[plant.effects.<name>]` table of a config file. The same class serves three
users, which is what keeps them consistent:

- the simulated plant steps it sample by sample (`stepper`, or `tilt` for disturbances,
  which are generated ahead in blocks);
- replay applies it to whole logged series at once (`apply`, `tilt`, `response`);
- diagnose fits it (`free` parameters with their `scale` and `bounds`) starting from the
  guesses its `guesses` classmethod reads off the evidence in a residual.

Stages, in the order a signal meets them: ``actuator`` (volts the amplifier was told ->
volts that move the piezo; a delay moves their timing instead, which the plant and replay
step with the pendulum), ``tilt`` (extra platform tilt [rad]), ``response`` (extra
displacement at the sensor caused by the piezo tilt [m]) and ``sensor`` (true
displacement -> reading [m]). To add an effect: write its class here and list it in
`EFFECTS` and as a field of `EffectsParams`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Literal, Protocol

import numpy as np

# scipy is imported where an effect computes, not here: the effects are also the plant's
# config ([plant.effects]), which a daemon on hardware reads without simulating anything,
# and importing scipy.signal costs it 0.5 s and tens of MiB (issue 21)
from leveler import jit
from leveler.typed_config import non_negative, positive

Stage = Literal["actuator", "tilt", "response", "sensor"]


@dataclass(frozen=True, slots=True)
class Signals:
    """What an effect may depend on: sample times, the step and (if logged) temperature."""

    t_s: np.ndarray
    dt_s: float
    temperature_k: np.ndarray | None = None


class Evidence(Protocol):
    """What `guesses` reads off a replay residual. leveler.analysis.evidence provides it; a
    Protocol here, so that the plant model imports nothing of the analysis."""

    @property
    def sig(self) -> Signals: ...
    @property
    def pull_limit(self) -> float: ...
    def fmin_hz(self) -> float: ...
    def bin_hz(self) -> float: ...
    def peaks(self, fmin_hz: float, fmax_hz: float, most: int = 3) -> list[float]: ...
    def bumps(self, fmin_hz: float, fmax_hz: float, most: int = 2) -> list[float]: ...
    def best_linear(self, starts: Sequence[Effect], amp_key: str | None,
                    keep: int) -> list[Effect]: ...
    def best_phase(self, template: Effect, phase_key: str, period_s: float,
                   amp_key: str, steps: int = 12) -> list[Effect]: ...
    def command_spread_v(self) -> float: ...
    def command_blocks_v(self) -> list[np.ndarray]: ...
    def block_gains(self, fx: Effect) -> list[float]: ...
    def lattice(self) -> tuple[float, float] | None: ...
    def lattice_deviance(self, step_m: float) -> float: ...
    def readings_on_levels(self, step_m: float) -> list[tuple[int, float]]: ...
    def line_deviance(self, fx: Effect, f0_hz: float, harmonics: int) -> float: ...
    def modulation_hz(self) -> float | None: ...
    def modulation_span_s(self) -> float: ...
    def cooler_hz(self) -> float | None: ...
    def sensor_path_pull(self, gain_error: float) -> float | None: ...
    def noise_std_m(self) -> float: ...
    def natural_frequency_hz(self) -> float: ...


class Effect:
    """Base of all effects: class-level description used by the simulator and diagnose."""

    name: ClassVar[str]
    stage: ClassVar[Stage]
    title: ClassVar[str]  # a physicist's words for the report
    free: ClassVar[tuple[str, ...]]  # parameters diagnose fits
    magnitude: ClassVar[str]  # the free parameter that says how big the effect is
    linear: ClassVar[bool] = True  # is the effect on the reading proportional to magnitude?
    needs_temperature: ClassVar[bool] = False
    # Only identifiable if the actuator was driven by more than feedback on the residual
    # (a modulation) or the disturbance it fights is modeled (a logged temperature).
    needs_excitation: ClassVar[bool] = False
    # Its own held-out evidence (`held_out_deviance`) replaces the replay's, and the size
    # gate with it: the replay cannot weigh the effect at all.
    own_score_only: ClassVar[bool] = False
    # Scored beyond a free actuator gain in each part of the log (the loop open under a
    # modulation, the loop closed), its baseline too: only what no such gain explains is
    # its evidence (`leveler.analysis.diagnose`).
    beyond_part_gains: ClassVar[bool] = False
    # Its form is the physics itself, no approximation of it (a transport delay shifts the
    # command in time), so the size gate in the fitted bins asks half as much of it.
    exact_form: ClassVar[bool] = False

    def values(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}  # type: ignore[arg-type]

    def replace(self, **kw: Any) -> Effect:
        return type(self)(**(self.values() | kw))

    def scale(self, key: str) -> float:
        """Typical size of a free parameter: what a fit step of 1 means."""
        return abs(getattr(self, key)) or 1.0

    def bounds(self, key: str) -> tuple[float, float]:
        return (-math.inf, math.inf)

    def describe(self) -> str:
        return self.title

    def canonical(self) -> Effect:
        """The one form of equivalent parameter sets that reports use."""
        return self

    def size(self) -> float:
        """How big the effect is, signed: what two fits of it must agree on."""
        return float(getattr(self, self.magnitude))

    def difference(self, other: Effect, key: str) -> float:
        """How far apart two fits of this effect are in one parameter."""
        return float(getattr(self, key)) - float(getattr(other, key))

    def band_hz(self) -> tuple[float, float]:
        """Where in frequency the effect mostly shows (for the report's headline band)."""
        return (1e-3, 1e-2)

    def fit_bands_hz(self) -> tuple[float, ...]:
        """Upper frequencies of coarse-to-fine fitting stages, () for a smooth cost."""
        return ()

    # Stage hooks; each effect implements the ones of its stage.
    def apply(self, x: np.ndarray, sig: Signals) -> np.ndarray:
        raise TypeError(f"{self.name} is not an actuator or sensor effect")

    def stepper(self, dt_s: float) -> Callable[[float, float], float]:
        """Per-sample form for the simulator: f(value, t_s) -> value."""
        raise TypeError(f"{self.name} is not an actuator or sensor effect")

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        """Starting points for a fit, read off the evidence; [] if nothing points here."""
        return []

    def variants(self) -> list[Effect]:
        """Other forms worth fitting that a fitted one implies (other waveform shapes)."""
        return []

    def start_shapes(self, sig: Signals) -> list[np.ndarray]:
        """Tilt shapes of the effect's unknown state at the log's start (a lag that had not
        settled): a replay fits their sizes, as it does the thermal lag's."""
        return []

    def held_out_deviance(self, ev: Evidence) -> float | None:
        """The effect's own evidence on held-out data (None: none but the replay's
        likelihood), on the same scale (2 ln of a likelihood ratio). With
        `own_score_only` it replaces the replay's, else the better of the two counts."""
        return None

    def moved_off(self, refit: Effect, ev: Evidence) -> str:
        """Why `refit`, this fit refitted on more of the log, has left this effect for
        another's shape along a ridge of its parameters ("" if it has not)."""
        return ""

    def degenerate(self, ev: Evidence) -> str:
        """Why this fit is no evidence for its effect ("" if it is): a parameter pinned at
        its bound means the data wanted more than the form allows, i.e. something else."""
        for key in self.free:
            lo, hi = self.bounds(key)
            v, tol = float(getattr(self, key)), 1e-3 * self.scale(key)
            if v <= lo + tol or v >= hi - tol:
                return f"{key} = {v:.4g} sits at its bound"
        return ""


# -- tilt: extra platform tilt ---------------------------------------------------------------


def _cycle_integral(shape: str, frac: np.ndarray) -> np.ndarray:
    """Integral over [0, frac] of a unit peak-to-peak, zero-mean shape (frac in cycles):
    zero again at the end of each cycle, so it is periodic."""
    if shape == "sawtooth":  # x - 1/2
        return 0.5 * frac * (frac - 1.0)
    if shape == "triangle":  # 1/2 - |2x - 1|
        return np.where(frac <= 0.5, frac * (frac - 0.5), -(frac - 1.0) * (frac - 0.5))
    return (1.0 - np.cos(2.0 * np.pi * frac)) / (4.0 * np.pi)  # sin(2 pi x) / 2


def waveform(shape: str, cycles: np.ndarray, hold_cycles: float) -> np.ndarray:
    """The shape's mean over each sample's hold [cycles, cycles + hold_cycles]: what a
    sampled plant sees of a continuous tilt. A point sample would put a sawtooth's drop on
    whole samples, which makes its cost a staircase in the period and phase that no
    gradient can climb. When the samples are a hold apart (as a replayed log's are, to
    1 % of a step), each hold ends where the next starts and the integral is taken once
    per sample, not twice."""
    def integral(x: np.ndarray) -> np.ndarray:
        if shape == "sine":  # periodic as it stands: no wrap needed
            return (1.0 - np.cos(2.0 * np.pi * x)) / (4.0 * np.pi)
        # x - floor(x), not np.mod: the same wrap at a third of the cost (a fit evaluates
        # this on every sample of a day-long log hundreds of times); it may give 1.0 for a
        # tiny negative x, where each shape's integral is 0 as at 0.0
        return _cycle_integral(shape, x - np.floor(x))

    n = len(cycles)
    if n > 1 and abs(cycles[-1] - cycles[0] - (n - 1) * hold_cycles) < 0.01 * n * hold_cycles:
        return np.diff(integral(np.append(cycles, cycles[-1] + hold_cycles))) / hold_cycles
    return (integral(cycles + hold_cycles) - integral(cycles)) / hold_cycles


#: A periodic disturbance within this fraction of a modulation harmonic (up to the
#: MODULATION_HARMONICS-th) is taken for the actuator's response to the modulation.
LOCKED_REL = 0.005
MODULATION_HARMONICS = 30
#: a periodic disturbance's held-out lines are its first this many harmonics
LINE_HARMONICS = 5


@dataclass(frozen=True, slots=True)
class PeriodicDisturbance(Effect):
    """A periodic tilt: a cooler, an air handler, a pump cycling (sawtooth: slow rise, drop)."""

    name: ClassVar[str] = "periodic_disturbance"
    stage: ClassVar[Stage] = "tilt"
    title: ClassVar[str] = "periodic disturbance"
    free: ClassVar[tuple[str, ...]] = ("period_s", "peak_to_peak_rad", "phase_s")
    magnitude: ClassVar[str] = "peak_to_peak_rad"

    shape: Literal["sawtooth", "triangle", "sine"] = "sawtooth"
    period_s: float = positive(300.0)
    peak_to_peak_rad: float = 0.0  # negative: the waveform upside down (a falling sawtooth)
    phase_s: float = 0.0  # time at which a period starts (the sawtooth's bottom)

    def tilt(self, sig: Signals, state: dict[str, Any] | None = None) -> np.ndarray:
        cycles = (sig.t_s - self.phase_s) / self.period_s
        return self.peak_to_peak_rad * waveform(self.shape, cycles, sig.dt_s / self.period_s)

    def scale(self, key: str) -> float:
        if key == "phase_s":
            return self.period_s / 20
        if key == "period_s":
            return self.period_s / 100
        return abs(self.peak_to_peak_rad) or 1e-9

    def bounds(self, key: str) -> tuple[float, float]:
        # Within 25% of where the line was seen: beyond, the fit is chasing something else.
        if key == "period_s":
            return (0.8 * self.period_s, 1.25 * self.period_s)
        return (-math.inf, math.inf)

    def canonical(self) -> Effect:
        """A sine or triangle upside down is the same one half a period later: report it
        with a positive peak to peak (a sawtooth's sign means rising or falling)."""
        if self.shape != "sawtooth" and self.peak_to_peak_rad < 0:
            return self.replace(peak_to_peak_rad=-self.peak_to_peak_rad,
                                phase_s=(self.phase_s + self.period_s / 2) % self.period_s)
        return self.replace(phase_s=self.phase_s % self.period_s)

    def difference(self, other: Effect, key: str) -> float:
        d = float(getattr(self, key)) - float(getattr(other, key))
        if key == "phase_s":  # a phase is defined modulo the period
            d = (d + self.period_s / 2) % self.period_s - self.period_s / 2
        return d

    def degenerate(self, ev: Evidence) -> str:
        """A period on a harmonic of the log's modulation is the actuator's response to it
        (a hysteresis or a delay the form cannot hold), not a disturbance: a 0.3 nrad one on
        the 7th harmonic of a triangle modulation had stood out of the noise. "On" is
        within the modulation's resolution, one cycle over the span it ran: a 252 s sine
        beside a 249 s square of 14 cycles took a sensor drift's place, its evidence the
        square's response. One on a harmonic of the modelled cooler is that cooler's
        waveform, not the model's sawtooth: a 299 s one followed a strong hysteresis,
        its evidence the lines of a cooler of another form."""
        return self.locked(ev) or Effect.degenerate(self, ev)

    def locked(self, ev: Evidence) -> str:
        """Why its period is a harmonic of the modulation's or the modelled cooler's
        (see `degenerate`); "" if it is neither."""
        f = 1.0 / self.period_s
        span = ev.modulation_span_s()
        for f0, what, why, resolution in (
                (ev.modulation_hz(), "the modulation's", "the actuator's response to it",
                 1.0 / span if span > 0 else 0.0),
                (ev.cooler_hz(), "the modelled cooler's", "its waveform, not another one",
                 0.0)):
            if f0 is None:
                continue
            n = round(f / f0)
            if (1 <= n <= MODULATION_HARMONICS
                    and abs(f - n * f0) <= max(LOCKED_REL * f, resolution)):
                return f"its period {self.period_s:.4g} s is {what} ({1 / f0:.4g} s) / {n}: {why}"
        return ""

    def held_out_deviance(self, ev: Evidence) -> float | None:
        """Its lines on the held-out part whatever their phase (`line_deviance`): a cycle
        whose period wanders by a few per cent (a thermostat's) has lost its phase by
        then, not its lines (a 128 s sawtooth with 2.9 % jitter: training evidence
        1,669, held-out 15 in phase). Its first LINE_HARMONICS lines: they hold most of
        a sawtooth's power, and a wandering period smears the rest."""
        return ev.line_deviance(self, 1.0 / self.period_s, LINE_HARMONICS)

    def describe(self) -> str:
        return (f"periodic disturbance, period {self.period_s:.4g} s, {self.shape}, "
                f"{abs(self.peak_to_peak_rad) * 1e6:.3g} urad peak to peak")

    def band_hz(self) -> tuple[float, float]:
        return (0.5 / self.period_s, 5.0 / self.period_s)

    def fit_bands_hz(self) -> tuple[float, ...]:
        """A sawtooth's or triangle's harmonics make its cost a needle in the period: fit
        the first 2, 10, 50 and 250 harmonics first (see diagnose's `fit_effect`)."""
        if self.shape == "sine":
            return ()
        return tuple(k / self.period_s for k in (2.5, 10.5, 50.5, 250.5))

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        """A sine on each line of the residual, but those on a harmonic of the modulation
        or the cooler (`locked`): their fits stay there and are rejected, and the four fits
        (the sine, two sawtooths, a triangle) were a fifth of a square-modulated null day's
        diagnosis."""
        out: list[Effect] = []
        for f_hz in ev.peaks(ev.fmin_hz(), 0.1):
            sine = cls(shape="sine", period_s=1.0 / f_hz)
            if not sine.locked(ev):
                out += ev.best_phase(sine, "phase_s", 1.0 / f_hz, "peak_to_peak_rad")
        return out

    def variants(self) -> list[Effect]:
        """From a fitted sine, the sawtooth and the triangle with the same fundamental:
        fitting those directly from a grid fails, their harmonics make the cost rugged."""
        if self.shape != "sine":
            return []
        # Fundamentals: sawtooth -(pp/pi) sin(w(t - phase)), triangle -(4 pp/pi^2)
        # cos(w(t - phase)), sine (pp/2) sin(w(t - phase)). A sawtooth upside down is not
        # the same sawtooth shifted, so both senses are tried.
        p, pp, ph = self.period_s, self.peak_to_peak_rad, self.phase_s
        tri_pp, tri_ph = (math.pi**2 / 8) * pp, ph - p / 4
        if tri_pp < 0:
            tri_pp, tri_ph = -tri_pp, tri_ph + p / 2
        saw = -math.pi * pp / 2
        return [self.replace(shape="sawtooth", peak_to_peak_rad=saw, phase_s=ph % p),
                self.replace(shape="sawtooth", peak_to_peak_rad=-saw, phase_s=(ph + p / 2) % p),
                self.replace(shape="triangle", peak_to_peak_rad=tri_pp, phase_s=tri_ph % p)]


#: a temperature coupling's lag beyond this many times the log is a trend
MAX_LAG_SPANS = 3.0


@dataclass(frozen=True, slots=True)
class TemperatureCoupling(Effect):
    """Tilt following the temperature through a lag: the other axis, a bending table top.

    `lag2_s` > 0 adds a second lag in series: heat that reaches the bending part through
    a slow body (a granite top, a frame) first, whose response a single lag cannot hold
    (it starts flat, then rises)."""

    name: ClassVar[str] = "temperature_coupling"
    stage: ClassVar[Stage] = "tilt"
    title: ClassVar[str] = "temperature coupling"
    magnitude: ClassVar[str] = "tilt_per_kelvin_rad_per_k"
    needs_temperature: ClassVar[bool] = True

    tilt_per_kelvin_rad_per_k: float = 0.0
    lag_s: float = non_negative(600.0)
    reference_k: float = positive(295.15)
    lag2_s: float = non_negative(0.0)

    @property
    def free(self) -> tuple[str, ...]:  # type: ignore[override]
        keys = ("tilt_per_kelvin_rad_per_k", "lag_s")
        return (*keys, "lag2_s") if self.lag2_s > 0 else keys

    def tilt(self, sig: Signals, state: dict[str, Any] | None = None) -> np.ndarray:
        """First-order lags of the temperature, each exact for a signal held over each
        sample; `state` carries the filter across the simulator's blocks."""
        temp = sig.temperature_k
        if temp is None:
            raise ValueError("temperature_coupling needs a temperature series")
        lags = [t for t in (self.lag_s, self.lag2_s) if t > 0]
        if not lags:
            return self.tilt_per_kelvin_rad_per_k * (temp - self.reference_k)
        b, a = np.array([1.0]), np.array([1.0])
        for lag in lags:
            k = math.exp(-sig.dt_s / lag)
            b, a = np.convolve(b, [1 - k]), np.convolve(a, [1, -k])
        from scipy.signal import lfilter, lfilter_zi

        zi = None if state is None else state.get("zi")
        if zi is None:
            zi = lfilter_zi(b, a) * temp[0]  # settled at the first temperature
        lagged, zi = lfilter(b, a, temp, zi=zi)
        if state is not None:
            state["zi"] = zi
        return self.tilt_per_kelvin_rad_per_k * (lagged - self.reference_k)

    def start_shapes(self, sig: Signals) -> list[np.ndarray]:
        """A lag's state decays as exp(-t / lag). Two in series span exp(-t / lag) and
        the divided difference of the two decays, which stays a second shape (t exp(-t /
        lag)) as the lags meet, where the two plain decays would become one."""
        t = sig.t_s - sig.t_s[0]
        lags = [lag for lag in (self.lag_s, self.lag2_s) if lag > 0]
        if not lags:
            return []
        first = np.exp(-t / lags[0])
        if len(lags) == 1:
            return [first]
        r1, r2 = 1 / lags[0], 1 / lags[1]
        if math.isclose(r1, r2, rel_tol=1e-6):
            return [first, t * first]
        return [first, (first - np.exp(-t * r2)) / (r2 - r1)]

    def scale(self, key: str) -> float:
        if key in ("lag_s", "lag2_s"):
            return max(getattr(self, key), 60.0) / 10
        return abs(self.tilt_per_kelvin_rad_per_k) or 1e-7

    def bounds(self, key: str) -> tuple[float, float]:
        return (1.0, 1e6) if key in ("lag_s", "lag2_s") else (-math.inf, math.inf)

    def degenerate(self, ev: Evidence) -> str:
        """A lag much longer than the log turns the temperature's wander into a trend, and
        the lag's start state into a free straight line (beyond 3x the log, straight to
        within 3 % of its fall): a sensor drift or the table's own walk can wear it (a
        4 pm/s drift was named a coupling through a 1e6 s lag). Up to 3x it is still a
        lag: two in series of 600 s and 2,200 s fit as one of 12,100 s in a 3 h log."""
        span_s = float(ev.sig.t_s[-1] - ev.sig.t_s[0])
        longest = max(self.lag_s, self.lag2_s)
        if longest > MAX_LAG_SPANS * span_s:
            return (f"a lag of {longest:.4g} s is over {MAX_LAG_SPANS:g}x the log "
                    f"({span_s:.4g} s): a trend, not a coupling")
        return Effect.degenerate(self, ev)

    def moved_off(self, refit: Effect, ev: Evidence) -> str:
        """A lag that grows from within half the log to beyond it is the lag's start state
        and the temperature's slow wander becoming a trend: a strong two-lag coupling
        (16.2 urad/K through 585 s and 881 s) held out at 15.7 through 868 s and 585 s,
        refitted on the whole log at 126 urad/K through 10,080 s and 122 s (the log is
        10,800 s), was rejected, and a drift that is not there was named in its place."""
        assert isinstance(refit, TemperatureCoupling)
        half_s = 0.5 * float(ev.sig.t_s[-1] - ev.sig.t_s[0])
        was, now = max(self.lag_s, self.lag2_s), max(refit.lag_s, refit.lag2_s)
        if was <= half_s < now:
            return (f"its lag went from {was:.4g} s to {now:.4g} s, beyond half the log: "
                    "toward a trend")
        return ""

    def canonical(self) -> Effect:
        """Two lags in series commute: the longer is reported first."""
        if self.lag2_s > self.lag_s:
            return self.replace(lag_s=self.lag2_s, lag2_s=self.lag_s)
        return self

    def describe(self) -> str:
        lags = (f"lags of {self.lag_s:.4g} s and {self.lag2_s:.4g} s in series"
                if self.lag2_s > 0 else f"a {self.lag_s:.4g} s lag")
        return (f"temperature coupling, {self.tilt_per_kelvin_rad_per_k * 1e6:.3g} urad/K "
                f"through {lags}")

    def band_hz(self) -> tuple[float, float]:
        return (1e-4, 1e-3)

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        """The best single lag and the best pair: which fits is the held-out part's call,
        the pair paying for its extra parameter."""
        if ev.sig.temperature_k is None:
            return []
        ref = float(np.mean(ev.sig.temperature_k))
        lags = (120.0, 600.0, 1800.0, 5400.0)
        single = [cls(lag_s=lag, reference_k=ref) for lag in lags]
        pairs = [cls(lag_s=b, lag2_s=a, reference_k=ref)
                 for i, a in enumerate(lags) for b in lags[i + 1:]]
        return (ev.best_linear(single, "tilt_per_kelvin_rad_per_k", keep=1)
                + ev.best_linear(pairs, "tilt_per_kelvin_rad_per_k", keep=1))


# -- actuator: volts commanded -> volts that move the piezo ----------------------------------


#: a delay under this share of a sample is sampling and hold, not a delay: an independent
#: simulator's null log read as 3.2 ms at 10 Hz; its weak delays under a square modulation
#: (9.4-14.3 ms) fit at 6-9 ms, part of them in the first recalibration's pendulum
#: frequency and Q, and a tenth of a sample (10 ms) threw them out before any test
MIN_DELAY_SAMPLES = 0.05


_NOT_ON_THE_VOLTAGE = ("an actuator delay is no stage on the voltage: it moves the piezo's "
                       "slewing ramps, which the pendulum follows, so the plant and replay "
                       "step it with the pendulum (leveler.sim.pendulum.delayed_slew)")


@dataclass(frozen=True, slots=True)
class ActuatorDelay(Effect):
    """A transport delay between the logged command and the piezo moving (amplifier, bus).

    It moves the timing of the piezo's slewing ramps, within a step and across steps, so
    the plant and replay both step it with the pendulum (`leveler.sim.pendulum.
    delayed_slew`), not as a stage on the voltage."""

    name: ClassVar[str] = "actuator_delay"
    stage: ClassVar[Stage] = "actuator"
    title: ClassVar[str] = "actuator delay"
    free: ClassVar[tuple[str, ...]] = ("delay_s",)
    magnitude: ClassVar[str] = "delay_s"
    needs_excitation: ClassVar[bool] = True
    linear: ClassVar[bool] = False
    exact_form: ClassVar[bool] = True

    delay_s: float = non_negative(0.0)

    def scale(self, key: str) -> float:
        return max(self.delay_s, 0.05)

    def bounds(self, key: str) -> tuple[float, float]:
        return (0.0, 30.0)

    def apply(self, x: np.ndarray, sig: Signals) -> np.ndarray:
        raise TypeError(_NOT_ON_THE_VOLTAGE)

    def stepper(self, dt_s: float) -> Callable[[float, float], float]:
        raise TypeError(_NOT_ON_THE_VOLTAGE)

    def degenerate(self, ev: Evidence) -> str:
        """A delay under a twentieth of a sample (MIN_DELAY_SAMPLES) is how the DAQ times
        its read and write within a sample, and how the model holds a slewing command
        between samples, not a part of the stand."""
        if self.delay_s < MIN_DELAY_SAMPLES * ev.sig.dt_s:
            return (f"a delay of {self.delay_s * 1e3:.3g} ms is under "
                    f"{MIN_DELAY_SAMPLES:g} of a {ev.sig.dt_s * 1e3:.3g} ms sample: "
                    "sampling and hold, not a delay")
        return Effect.degenerate(self, ev)

    def describe(self) -> str:
        return f"actuator delay, {self.delay_s * 1e3:.4g} ms"

    def band_hz(self) -> tuple[float, float]:
        return (0.1, 1.0)

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        dt = ev.sig.dt_s
        return ev.best_linear([cls(delay_s=d) for d in (dt, 3 * dt, 10 * dt)], None, keep=1)


#: samples per block of `play`'s scan
PLAY_BLOCK = 64


def play(u: np.ndarray, width_v: float) -> np.ndarray:
    """Backlash (play) operator of half-width `width_v`: the output follows the input only
    once it has moved `width_v` the other way; starts centred on the first input.

    A hysteresis fit replays a log hundreds of times, each through a play or two: a day's
    play takes 4 ms as numba's compiled loop over the samples (`_play_sequential`), 12-24
    ms as numpy's blocked scan (`_play_blocks`, where numba is not installed). Both give
    the definition's result to the bit."""
    fn = jit.compiled(_play_sequential) or _play_blocks
    return fn(np.ascontiguousarray(u, dtype=float), float(width_v))  # type: ignore[no-any-return]


def _play_sequential(u: np.ndarray, width_v: float) -> np.ndarray:
    """`play` by its definition, one sample after another (for numba to compile)."""
    out = np.empty(len(u))
    y = u[0]
    for i in range(len(u)):
        y = min(max(y, u[i] - width_v), u[i] + width_v)
        out[i] = y
    return out


def _play_blocks(u: np.ndarray, width_v: float) -> np.ndarray:
    """`play` in numpy, without a loop over the samples.

    Each sample clamps the output into [u - w, u + w], and clamps compose into clamps
    (min and max only, so in any order the result is the same to the bit). The log is cut
    into blocks of PLAY_BLOCK samples: each block's clamps are composed into one (a pass
    per position in the block, vectorized across blocks), a prefix scan over the blocks
    gives the output entering each, and a last pass per position runs it through. About 3
    clamps a sample, where a prefix scan over the samples takes 2 log2 n (40 for a day).
    """
    n = len(u)
    m = -(-n // PLAY_BLOCK)
    padded = np.empty(m * PLAY_BLOCK)
    padded[:n] = u
    padded[n:] = u[-1]  # after the last sample: changes nothing before it
    at = padded.reshape(m, PLAY_BLOCK).T.copy()  # at[j]: sample j of every block
    lo, hi = at - width_v, at + width_v
    block_lo, block_hi = lo[0].copy(), hi[0].copy()
    for j in range(1, PLAY_BLOCK):
        np.minimum(np.maximum(block_lo, lo[j], out=block_lo), hi[j], out=block_lo)
        np.minimum(np.maximum(block_hi, lo[j], out=block_hi), hi[j], out=block_hi)
    d = 1
    while d < m:  # block b's clamp after the ones of blocks b - d + 1 .. b - 1 before it
        new_lo = np.minimum(np.maximum(block_lo[:-d], block_lo[d:]), block_hi[d:])
        new_hi = np.minimum(np.maximum(block_hi[:-d], block_lo[d:]), block_hi[d:])
        block_lo[d:], block_hi[d:] = new_lo, new_hi
        d *= 2
    y = np.empty(m)  # the output entering each block
    y[0] = u[0]
    y[1:] = np.minimum(np.maximum(u[0], block_lo[:-1]), block_hi[:-1])
    for j in range(PLAY_BLOCK):
        np.minimum(np.maximum(y, lo[j], out=y), hi[j], out=y)
        at[j] = y
    return at.T.reshape(-1)[:n]


def turns(played: np.ndarray) -> int:
    """How often a play's output changes direction: each turn is a reversal of the
    input by more than twice the width, one half of a hysteresis loop."""
    step = np.diff(played)
    sign = np.sign(step[step != 0])
    return int(np.count_nonzero(sign[1:] != sign[:-1]))


#: a hysteresis whose addition to the stroke is more than this share a gain is a gain
GAIN_LIKE = 0.9
#: a hysteresis shows its loop in at least this many turns of its play (two loops)
MIN_TURNS = 4
#: a second play weighs at most this many times the first
MAX_WEIGHT2 = 20.0


@dataclass(frozen=True, slots=True)
class ActuatorHysteresis(Effect):
    """Piezo hysteresis as a Prandtl-Ishlinskii model of one or two play operators:
    stroke ~ u + fraction * ((play(u, width_v) - u) + weight2 * (play(u, width2_v) - u)).

    A second play (`width2_v` > 0, its weight relative to the first's, so the loop stays
    linear in `fraction`) holds a loop that a single one cannot: a saturating, Bouc-Wen-like
    loop is steep at each turn and flattens, a sum of plays of widths spread apart."""

    name: ClassVar[str] = "actuator_hysteresis"
    stage: ClassVar[Stage] = "actuator"
    title: ClassVar[str] = "actuator hysteresis"
    magnitude: ClassVar[str] = "fraction"
    needs_excitation: ClassVar[bool] = True
    # Under a square modulation a piezo's hysteresis is a smaller gain than the closed
    # loop's long sweeps see, which a sensor gain error or a calibration does as well; its
    # own mark is the turn of direction, where the closed loop's small reversals (the
    # cooler's) meet a stroke that lags. An independent strong Bouc-Wen log: a play held
    # out +2,700 as a 4 V "gain" with its fraction negative (a loop the wrong way round),
    # and 674 with 0.08-0.46 V and +0.165 (the truth's a = 0.21) beyond a gain per part.
    beyond_part_gains: ClassVar[bool] = True

    model: Literal["prandtl_ishlinskii"] = "prandtl_ishlinskii"
    width_v: float = positive(1.0)
    fraction: float = field(default=0.0, metadata={"ge": -1.0, "le": 1.0})
    width2_v: float = non_negative(0.0)
    weight2: float = field(default=0.0, metadata={"ge": 0.0, "le": MAX_WEIGHT2})

    @property
    def free(self) -> tuple[str, ...]:  # type: ignore[override]
        one = ("width_v", "fraction")
        return (*one, "width2_v", "weight2") if self.width2_v > 0 else one

    def _plays(self) -> list[tuple[float, float]]:
        """(width, weight relative to the first) of each play."""
        plays = [(self.width_v, 1.0)]
        return [*plays, (self.width2_v, self.weight2)] if self.width2_v > 0 else plays

    def added(self, x: np.ndarray) -> np.ndarray:
        """What the plays add to the stroke per unit `fraction`."""
        return sum((k * (play(x, w) - x) for w, k in self._plays()), np.zeros_like(x))

    def apply(self, x: np.ndarray, sig: Signals) -> np.ndarray:
        return x + self.fraction * self.added(x)

    def stepper(self, dt_s: float) -> Callable[[float, float], float]:
        plays, state = self._plays(), []
        a = self.fraction

        def step(v: float, t_s: float) -> float:
            if not state:
                state.extend(v for _ in plays)
            out = v
            for i, (w, k) in enumerate(plays):
                p = min(max(state[i], v - w), v + w)
                state[i] = p
                out += a * k * (p - v)
            return out

        return step

    def scale(self, key: str) -> float:
        if key in ("width_v", "width2_v"):
            return max(getattr(self, key), 1e-3) / 4
        return 0.25 if key == "weight2" else 0.05

    def bounds(self, key: str) -> tuple[float, float]:
        if key in ("width_v", "width2_v"):
            return (1e-4, 1e3)
        return (0.0, MAX_WEIGHT2) if key == "weight2" else (-1.0, 1.0)

    def canonical(self) -> Effect:
        """The narrower play first (its weight then the other's relative to it)."""
        if 0 < self.width2_v < self.width_v and self.weight2 > 0:
            return self.replace(width_v=self.width2_v, width2_v=self.width_v,
                                fraction=self.fraction * self.weight2,
                                weight2=1.0 / self.weight2)
        return self

    def variants(self) -> list[Effect]:
        """From one play, two: a second play four times wider or narrower, at half its
        weight to start."""
        if self.width2_v > 0:
            return []
        return [self.replace(width2_v=self.width_v * k, weight2=0.5) for k in (4.0, 0.25)]

    def degenerate(self, ev: Evidence) -> str:
        """A play wider than the command's reversals never turns: a gain or a lag, not a
        loop. One that turns too rarely does nearly the same: where the fit finds its
        evidence (the blocks weighted by what it gains in each), what it adds to the stroke
        must not be mostly a straight line in the command (a gain and an offset). Over a
        square modulation every play is a gain: a day's null log of the independent
        generator had a 3.4 V play named with evidence 1,348, all of it from the square's
        blocks, where it asked for a gain 1.2 % below the closed loop's (the piezo's steps
        ring a pendulum whose response to fast steps the model has slightly wrong).
        And it must turn at all: an independent generator's closed-loop null log, the
        loop starting out of equilibrium, had a 2.25 V play that never turned in 3 h (a
        ramp through its dead band, then a constant) named for that start's transient.
        And its loop must run the way a piezo's does, the stroke lagging the command
        (fraction > 0: below on the way up, above on the way down; the other way round
        the actuator would give energy back every cycle). On tuning seeds 101-106 every
        hysteresis named with a negative fraction was false (three, each a second effect,
        after a sawtooth or a converter) and every true one was positive; the own
        generator's converter of seed 58200 had a -0.48 play of 7.5 mV named after it."""
        spread = ev.command_spread_v()
        commands = ev.command_blocks_v()
        for w, _ in self._plays():
            if w >= spread:
                return (f"play width {w:.3g} V is not below the command's spread "
                        f"({spread:.3g} V): a gain or a lag, not hysteresis")
            turned = sum(turns(play(u, w)) for u in commands)
            if turned < MIN_TURNS:
                return (f"a play of {w:.3g} V turns {turned} times in the log (a loop "
                        f"needs {MIN_TURNS}): a ramp and a step, not hysteresis")
        shares = []
        for u in commands:
            added = self.added(u)
            a = np.column_stack([u, np.ones_like(u)])
            coef, *_ = np.linalg.lstsq(a, added, rcond=None)
            var = float(np.var(added))
            shares.append(1.0 - float(np.var(added - a @ coef)) / var if var > 0 else 1.0)
        gains = ev.block_gains(self)
        weights = gains if sum(gains) > 0 else [1.0] * len(shares)
        share = float(np.average(shares, weights=weights))
        if share > GAIN_LIKE:
            return (f"where the fit finds its evidence, {share:.0%} of what the play adds is "
                    "a gain and an offset of the command: a gain, not hysteresis")
        if self.fraction < 0:
            return (f"fraction {self.fraction:.3g} < 0: a stroke that leads its command, a "
                    "loop the wrong way round, which a piezo cannot run")
        return Effect.degenerate(self, ev)

    def describe(self) -> str:
        lags = f"{abs(self.fraction) * 100:.3g}% of the stroke lags by up to {self.width_v:.3g} V"
        if self.width2_v > 0:
            lags += (f" and {abs(self.fraction * self.weight2) * 100:.3g}% by up to "
                     f"{self.width2_v:.3g} V")
        return f"actuator hysteresis (Prandtl-Ishlinskii), {lags}"

    def band_hz(self) -> tuple[float, float]:
        return (1e-2, 1e-1)

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        """Two starts a decade apart, each scanned over a factor of 8 either way by the fit,
        among widths whose play turns often enough to be a loop at all (`degenerate`). One
        start picked by a plain least-squares cost is the widest, a gain in all but name:
        it fitted best in strong independent Bouc-Wen logs, never turned over their square
        modulation, and the closed loop's sub-volt reversals, where the loop shows, were
        never tried."""
        spread = ev.command_spread_v()
        if spread <= 0:
            return []
        blocks = ev.command_blocks_v()
        return [cls(width_v=w, fraction=0.1) for w in (spread * k for k in (0.01, 0.1))
                if sum(turns(play(u, w)) for u in blocks) >= MIN_TURNS]


# -- response: extra displacement at the sensor driven by the piezo tilt ---------------------


#: a mode within this share of the pendulum's resonance frequency is the pendulum's own
NEAR_PENDULUM = 0.2
#: a mode rung by noise spreads its power over at least this many bins of its spectrum
MIN_BAND_BINS = 4
#: and is no broader than this Q says
MIN_NOISE_Q = 5.0


@dataclass(frozen=True, slots=True)
class ExtraResonance(Effect):
    """A mode the model lacks (table top, mount, the piezo stack) rung by the actuator:
    a band-pass of the piezo tilt, `gain` times the pendulum's static response at its peak,
    and by its own noise (the floor, air): the same band-pass driven by white noise, with
    `noise_rms_m` rms at the sensor. Replay predicts the first; the second is a bump in
    the residual's spectrum (`leveler.analysis.bump`), fitted alone ("rung by noise")."""

    name: ClassVar[str] = "extra_resonance"
    stage: ClassVar[Stage] = "response"
    title: ClassVar[str] = "extra resonance"
    magnitude: ClassVar[str] = "gain"
    needs_excitation: ClassVar[bool] = True

    frequency_hz: float = positive(1.0)
    q: float = positive(10.0)
    gain: float = 0.0
    noise_rms_m: float = non_negative(0.0)

    @property
    def free(self) -> tuple[str, ...]:  # type: ignore[override]
        if self.rung_by_noise:
            return ("frequency_hz", "q", "noise_rms_m")
        return ("frequency_hz", "q", "gain")

    @property
    def rung_by_noise(self) -> bool:
        """Only its noise: nothing for replay to predict."""
        return self.gain == 0 and self.noise_rms_m > 0

    def size(self) -> float:
        return self.noise_rms_m if self.rung_by_noise else self.gain

    def discrete(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """ZOH-discretized band-pass (unit gain at resonance) as lfilter coefficients."""
        from scipy.signal import cont2discrete

        w = 2 * math.pi * self.frequency_hz
        num, den = [w / self.q, 0.0], [1.0, w / self.q, w * w]
        b, a, _ = cont2discrete((num, den), dt_s, method="zoh")
        return np.ravel(b), np.ravel(a)

    def response(self, phi_u: np.ndarray, static_m_per_rad: float, sig: Signals) -> np.ndarray:
        from scipy.signal import lfilter

        b, a = self.discrete(sig.dt_s)
        return self.gain * static_m_per_rad * lfilter(b, a, phi_u - phi_u[0])

    def scale(self, key: str) -> float:
        if key == "frequency_hz":
            return self.frequency_hz / 200
        if key == "q":
            return self.q / 5
        return abs(self.gain) or 0.01

    def bounds(self, key: str) -> tuple[float, float]:
        if key == "frequency_hz":  # near the line it was seen at; not a drift (< 20 mHz)
            return (max(0.8 * self.frequency_hz, 0.02), 1.25 * self.frequency_hz)
        # A mode larger than the pendulum's whole static response would be the pendulum.
        # Rung by noise, a band over a fifth of its frequency is a hump that the noise
        # spectrum's own shape (the loop's, the pendulum's) may hold as well: a closed-loop
        # null log of the independent generator had a 1.44 Hz hump of Q 3.2.
        if key == "q":
            return (MIN_NOISE_Q if self.rung_by_noise else 2.0, 1e4)
        return (-1.0, 1.0)

    def degenerate(self, ev: Evidence) -> str:
        """Near the pendulum's own resonance a mode is its frequency or Q off, where no
        fit starts (`guesses`) and none may reach with its half-power band: a 44 ms
        delay's phase was fitted as a 0.885 Hz mode of Q 8.6 (band from 0.83 Hz; the
        pendulum's 0.73 Hz) and gain -0.97, the pendulum cancelled."""
        f0 = ev.natural_frequency_hz()
        if abs(self.frequency_hz / f0 - 1) - 0.5 / self.q <= NEAR_PENDULUM:
            return (f"at {self.frequency_hz:.3g} Hz, Q {self.q:.3g}, its band reaches within "
                    f"{NEAR_PENDULUM:.0%} of the pendulum's resonance ({f0:.3g} Hz): its "
                    "frequency or Q, not a mode")
        width = self.frequency_hz / self.q
        if self.rung_by_noise and width < MIN_BAND_BINS * ev.bin_hz():
            return (f"its band, {width * 1e3:.3g} mHz, is under {MIN_BAND_BINS} bins: a line "
                    "(something periodic), not a mode rung by noise")
        return Effect.degenerate(self, ev)

    def moved_off(self, refit: Effect, ev: Evidence) -> str:
        """A refit whose frequency leaves this fit's half-power band rings elsewhere: a
        broad shape of the response, not the mode that held out. Tuning seed 106's strong
        1.66 Hz mode (Q 6.8) held out at 1.66 Hz, Q 9.8 (1.70 Hz on the held-out part
        alone), and refitted on the whole log went to 1.36 Hz, Q 2.3 with its gain
        turned negative: "the whole log's fit disagrees", and nothing was named."""
        assert isinstance(refit, ExtraResonance)
        half_hz = 0.5 * self.frequency_hz / self.q
        if abs(refit.frequency_hz - self.frequency_hz) > half_hz:
            return (f"its frequency went from {self.frequency_hz:.4g} Hz to "
                    f"{refit.frequency_hz:.4g} Hz, beyond the mode's half-power band "
                    f"(+-{half_hz:.3g} Hz): another shape")
        return ""

    def describe(self) -> str:
        head = f"extra resonance at {self.frequency_hz:.4g} Hz, Q {self.q:.3g}"
        parts = ([f"{abs(self.gain) * 100:.3g}% of the static response at its peak"]
                 if self.gain else [])
        if self.noise_rms_m:
            parts.append(f"rung by its own noise, {self.noise_rms_m * 1e9:.3g} nm rms")
        return ", ".join([head, *parts])

    def band_hz(self) -> tuple[float, float]:
        return (self.frequency_hz / 1.5, self.frequency_hz * 1.5)

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        nyquist = 0.5 / ev.sig.dt_s
        f0 = ev.natural_frequency_hz()
        starts = [cls(frequency_hz=f, q=q) for f in ev.peaks(0.02, 0.9 * nyquist)
                  if abs(f / f0 - 1) > NEAR_PENDULUM for q in (5.0, 30.0)]
        return ev.best_linear(starts, "gain", keep=2)

    @classmethod
    def noise_guesses(cls, ev: Evidence) -> list[float]:
        """Where a mode rung by its own noise may be: lines and bumps of the residual's
        spectrum away from the pendulum's resonance, a fifth of an octave apart."""
        nyquist = 0.5 / ev.sig.dt_s
        f0 = ev.natural_frequency_hz()
        out: list[float] = []
        for f in ev.bumps(0.02, 0.9 * nyquist) + ev.peaks(0.02, 0.9 * nyquist):
            if abs(f / f0 - 1) > NEAR_PENDULUM and all(abs(math.log(f / g)) > 0.2 for g in out):
                out.append(f)
        return out


# -- sensor: true displacement -> reading -------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SensorGainError(Effect):
    """The sensor reads (1 + gain_error) times the true displacement (calibration error)."""

    name: ClassVar[str] = "sensor_gain_error"
    stage: ClassVar[Stage] = "sensor"
    title: ClassVar[str] = "sensor gain error"
    free: ClassVar[tuple[str, ...]] = ("gain_error",)
    magnitude: ClassVar[str] = "gain_error"
    needs_excitation: ClassVar[bool] = True

    gain_error: float = field(default=0.0, metadata={"gt": -1.0})

    def apply(self, x: np.ndarray, sig: Signals) -> np.ndarray:
        return (1.0 + self.gain_error) * x

    def stepper(self, dt_s: float) -> Callable[[float, float], float]:
        g = 1.0 + self.gain_error
        return lambda v, t_s: g * v

    def scale(self, key: str) -> float:
        return 0.01

    def bounds(self, key: str) -> tuple[float, float]:
        # A sensor reading half or double (a range setting): symmetric in the ratio.
        # Beyond that it is a different sensor, not a calibration error. The upper bound
        # was +0.5: a +31 % error on a stand whose paths were drawn 6-10 % high (its whole
        # loop +52 %, both paths held at nominal) ran to it and was rejected there.
        return (-0.5, 1.0)

    def degenerate(self, ev: Evidence) -> str:
        """The sensor path with this error on top of its recalibration, still within the
        pull the recalibration accepts, is a calibration, not an effect: a null log read
        as "sensor gain error, -2.6 %" against a stated 4.1 % tolerance."""
        pull = ev.sensor_path_pull(self.gain_error)
        if pull is not None and abs(pull) <= ev.pull_limit:
            return (f"the sensor path then reads {pull:+.2g} sigma of its stated tolerance "
                    "from nominal: a calibration, not an effect")
        return Effect.degenerate(self, ev)

    def describe(self) -> str:
        return f"sensor gain error, reads {self.gain_error * 100:+.3g}%"

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        return ev.best_linear([cls(gain_error=0.01)], "gain_error", keep=1)


@dataclass(frozen=True, slots=True)
class SensorDrift(Effect):
    """A steady drift of the sensor zero (electronics warming, a creeping target)."""

    name: ClassVar[str] = "sensor_drift"
    stage: ClassVar[Stage] = "sensor"
    title: ClassVar[str] = "sensor drift"
    free: ClassVar[tuple[str, ...]] = ("rate_m_per_s",)
    magnitude: ClassVar[str] = "rate_m_per_s"
    # Without the temperature the table's own thermal tilt is unpredicted, and a trend in
    # the residual is as likely tilt as sensor: only sought when the tilt is modeled.
    needs_temperature: ClassVar[bool] = True

    rate_m_per_s: float = 0.0

    def apply(self, x: np.ndarray, sig: Signals) -> np.ndarray:
        return x + self.rate_m_per_s * sig.t_s

    def stepper(self, dt_s: float) -> Callable[[float, float], float]:
        r = self.rate_m_per_s
        return lambda v, t_s: v + r * t_s

    def scale(self, key: str) -> float:
        return abs(self.rate_m_per_s) or 1e-13

    def describe(self) -> str:
        return f"sensor drift, {self.rate_m_per_s * 3600e9:+.3g} nm/h"

    def band_hz(self) -> tuple[float, float]:
        return (1e-4, 1e-3)

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        return ev.best_linear([cls(rate_m_per_s=1e-12)], "rate_m_per_s", keep=1)


#: replay noise (in steps) from which the expected reading is smooth enough to tabulate
SMOOTH_NOISE_STEPS = 0.01
#: points of that table over a step (its interpolation error: under 2e-5 of a step)
SMOOTH_GRID = 4097


#: replay noise (in steps) from which the expected reading is summed as a Fourier series
FOURIER_NOISE_STEPS = 0.25


def _expected_excess(v: np.ndarray, s: float) -> np.ndarray:
    """The expected reading's excess over the nearest level, in steps, for a signal `v`
    steps from it with Gaussian noise of `s` steps at the quantizer's input.

    Rounding takes off a sawtooth, sum_k (-1)^(k+1) sin(2 pi k x) / (pi k), and the noise
    damps its k-th harmonic by exp(-2 pi^2 k^2 s^2): from a quarter step on, four terms
    are exact to 1e-13. Summed level by level instead, the cost grows with the noise: a
    recalibration that ran it to thousands of steps (a converter the fit no longer
    needed) took 0.8 s a call at 1,000 steps, and a diagnosis over half an hour."""
    if s >= FOURIER_NOISE_STEPS:
        e = v.copy()
        for k in range(1, 5):
            e -= ((-1) ** (k + 1) * math.exp(-2 * math.pi**2 * k * k * s * s) / (math.pi * k)
                  * np.sin(2 * math.pi * k * v))
        return e
    from scipy.special import ndtr

    e = np.zeros_like(v)
    for j in range(int(6 * s) + 2):  # P(reading above / below the nearest level by j+1)
        e += ndtr((v - j - 0.5) / s) - ndtr((-v - j - 0.5) / s)
    return e


#: a block with this many stretches of readings that cross two converter steps shows its
#: levels there: their mean Rayleigh statistic beats this (about 1 where readings fall
#: anywhere; `leveler.analysis.evidence.readings_on_levels`)
LEVEL_WINDOWS = 20
LEVEL_Z = 10.0


@dataclass(frozen=True, slots=True)
class AdcQuantization(Effect):
    """Readings on a coarser lattice than the model's ADC: fewer effective bits, a lower
    sensor gain, a DAQ range set too wide.

    The simulator rounds the noisy signal to the lattice. Replay cannot know the noise, so
    it predicts the *expected* reading: the lattice smoothed by Gaussian noise of
    `replay_noise_m` at the quantizer's input, which is what a noisy signal hovering at a
    step edge reads on average.
    """

    name: ClassVar[str] = "adc_quantization"
    stage: ClassVar[Stage] = "sensor"
    title: ClassVar[str] = "ADC quantization"
    free: ClassVar[tuple[str, ...]] = ("step_m", "offset_m", "replay_noise_m")
    magnitude: ClassVar[str] = "step_m"
    linear: ClassVar[bool] = False
    own_score_only: ClassVar[bool] = True

    step_m: float = positive(1e-8)
    offset_m: float = 0.0  # where the lattice sits: readings are offset_m + k step_m
    replay_noise_m: float = non_negative(1e-9)

    def apply(self, x: np.ndarray, sig: Signals) -> np.ndarray:
        u = (x - self.offset_m) / self.step_m
        m = np.floor(u + 0.5)
        v = u - m  # in [-0.5, 0.5)
        s = max(self.replay_noise_m / self.step_m, 1e-6)
        if s < SMOOTH_NOISE_STEPS:
            return self.offset_m + self.step_m * (m + _expected_excess(v, s))
        # The excess is a smooth function of v alone: tabulated on a uniform grid, then
        # interpolated (a recalibration with a coarse converter replays it thousands of
        # times: 35 ms a call for 3 h at 10 Hz, 5 ms so).
        table = _expected_excess(np.linspace(-0.5, 0.5, SMOOTH_GRID), s)
        at = (v + 0.5) * (SMOOTH_GRID - 1)
        i = np.minimum(at.astype(np.intp), SMOOTH_GRID - 2)
        e = table[i] + (at - i) * (table[i + 1] - table[i])
        return self.offset_m + self.step_m * (m + e)

    def stepper(self, dt_s: float) -> Callable[[float, float], float]:
        s, o = self.step_m, self.offset_m
        return lambda v, t_s: o + s * math.floor((v - o) / s + 0.5)

    def scale(self, key: str) -> float:
        if key == "replay_noise_m":
            return max(self.replay_noise_m, 0.01 * self.step_m) / 4
        return self.step_m / 50

    def bounds(self, key: str) -> tuple[float, float]:
        if key == "step_m":
            return (1e-15, math.inf)
        return (0.0, math.inf) if key == "replay_noise_m" else (-math.inf, math.inf)

    def describe(self) -> str:
        return f"ADC quantization, step {self.step_m * 1e9:.4g} nm"

    def band_hz(self) -> tuple[float, float]:
        return (1e-3, 1e-2)

    def held_out_deviance(self, ev: Evidence) -> float | None:
        """How well the held-out readings line up on this step, not how well a replay
        predicts them: which side of a step a reading falls on is decided by a model
        error of a fraction of the step, and a fit that aligned the lattice on the
        training part misplaces it once the model's error has wandered by a step (a
        26 nm converter: training evidence 9,556, held-out 243, then -6,236)."""
        return ev.lattice_deviance(self.step_m)

    def degenerate(self, ev: Evidence) -> str:
        """Where the readings cross its steps, a converter's levels show in the readings
        themselves, not only in their changes. A modulation's steps and the ringing after
        them repeat with the same sizes every cycle, and the changes a model a little wrong
        leaves unpredicted line up on some step: a modulated null log's "65 nm converter"
        held out at 40, its readings in windows that cross two steps or more on its levels
        no more than chance allows (Rayleigh's statistic 5.6 at best; 2.6 for another
        null's 42 nm), where true converters' sit on theirs (14-41)."""
        for windows, z in ev.readings_on_levels(self.step_m):
            if windows >= LEVEL_WINDOWS and z < LEVEL_Z:
                return (f"in {windows} stretches where the readings cross its steps they do "
                        f"not sit on its levels (Rayleigh's statistic {z:.2g}): repeated "
                        "steps, not a converter")
        return Effect.degenerate(self, ev)

    @classmethod
    def guesses(cls, ev: Evidence) -> list[Effect]:
        lattice = ev.lattice()
        if lattice is None:
            return []
        step, offset = lattice
        # The readings give the lattice, but where the model's displacement sits on it is
        # only known to within a step (the loop hovers at a step edge): scan it, since a
        # fit cannot cross the flat stretches between edges. The model's own ADC rounds
        # the levels, so the step is scanned a little too.
        starts = [cls(step_m=step * k, offset_m=offset + step * j / 16,
                      replay_noise_m=ev.noise_std_m())
                  for k in (0.97, 1.0, 1.03) for j in range(-8, 8)]
        return ev.best_linear(starts, None, keep=1)


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (PeriodicDisturbance, TemperatureCoupling, ActuatorDelay, ActuatorHysteresis,
                ExtraResonance, SensorGainError, SensorDrift, AdcQuantization)
}
_ORDER = list(EFFECTS)


@dataclass(frozen=True, slots=True)
class EffectsParams:
    """`[plant.effects]`: each table present adds that effect to the plant."""

    periodic_disturbance: PeriodicDisturbance | None = None
    temperature_coupling: TemperatureCoupling | None = None
    actuator_delay: ActuatorDelay | None = None
    actuator_hysteresis: ActuatorHysteresis | None = None
    extra_resonance: ExtraResonance | None = None
    sensor_gain_error: SensorGainError | None = None
    sensor_drift: SensorDrift | None = None
    adc_quantization: AdcQuantization | None = None

    def __iter__(self) -> Iterator[Effect]:
        """The effects present, in signal order."""
        for name in _ORDER:
            fx = getattr(self, name)
            if fx is not None:
                yield fx

    def of(self, stage: Stage) -> list[Effect]:
        return [fx for fx in self if fx.stage == stage]

    def with_effect(self, fx: Effect) -> EffectsParams:
        return EffectsParams(**{n: getattr(self, n) for n in _ORDER} | {fx.name: fx})

    def without(self, *names: str) -> EffectsParams:
        return EffectsParams(**{n: getattr(self, n) for n in _ORDER if n not in names})
