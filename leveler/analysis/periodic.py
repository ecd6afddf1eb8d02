"""Resonant terms against a named periodic disturbance, designed through the plant model.

The loop L0 = C0 P (the configured PID, `suggest.controller_tf`, and the plant,
`suggest.plant_tf`) leaves a periodic disturbance's lines suppressed by |1 + L0| only. A
resonant term R_h at each harmonic h of the period (leveler.loop.resonant) makes the
suppression infinite at the line. Added to C0, it closes a loop of its own through the
process sensitivity G = P / (1 + L0): near the line, R_h ~ (k_h / 2) e^(j(phase_h - theta_h))
/ s (theta_h = w_h dt, the term's one sample of delay), so with

    phase_h = theta_h - arg G(w_h),    k_h = 2 beta / |G(w_h)|

R_h G ~ beta / s: an integrator of its own, whose closed-loop pole sits at -beta beside the
line (it settles in ~1 / beta; `beta_rel` is beta in units of the fundamental, 2 pi / T).
That is the design; the check does not trust it: stability from the closed loop's
state-space eigenvalues (high-order transfer functions lose the poles near z = 1 to
rounding), and the gain and phase margins of the summed frequency response, for the
nominal model and every corner of its stated tolerances (+-2 sigma of the sensor and
actuator paths, the resonance frequency and Q; `recalibrate.knobs`).

Harmonics: those where the PID alone still has loop gain to build on, |1 + L0| >= 10
(above that a term only trades the line for shoulders beside it), at most 30.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import control
import numpy as np

from leveler.analysis.recalibrate import Knob, knobs
from leveler.analysis.suggest import (
    MIN_GAIN_MARGIN_DB,
    _response,
    _toml_float,
    controller_tf,
    plant_tf,
)
from leveler.loop.pid import ControllerConfig
from leveler.loop.resonant import PeriodicTerms
from leveler.settings import Config
from leveler.sim.disturbance import Disturbances
from leveler.sim.effects import PeriodicDisturbance
from leveler.sim.params import PlantParams

MIN_PHASE_MARGIN_DEG = 40.0
MIN_LOOP_GAIN = 10.0  # |1 + L0| at a harmonic worth a term
MAX_HARMONICS = 30
BETA_REL = 0.3  # each term's settling rate, in units of the fundamental (rad/s)
CORNER_SIGMAS = 2.0
MODE_SIGMAS = {"frequency_hz": 0.025, "gain": 0.15}  # 1 sigma, relative
_DYNAMIC_KNOBS = ("sensor_path", "actuator_path", "natural_frequency", "q")


@dataclass(frozen=True)
class Disturbance:
    """The periodic disturbance a model names: where it came from and its period."""

    source: str  # "[plant.effects.periodic_disturbance]" or "[plant.cooler]"
    period_s: float
    peak_to_peak_rad: float


@dataclass(frozen=True)
class LoopCheck:
    """Stability and margins of a loop, the worst over the model's tolerance corners."""

    stable: bool
    gain_margin_db: float
    phase_margin_deg: float
    max_sensitivity: float  # max |1 / (1 + L)|: 1 / the smallest distance to -1
    corners: int  # models checked: the nominal one and every tolerance corner
    worst_corner: str
    mode_corners: bool = False  # the corners include a mode's frequency and gain

    @property
    def ok(self) -> bool:
        return (self.stable and self.gain_margin_db >= MIN_GAIN_MARGIN_DB
                and self.phase_margin_deg >= MIN_PHASE_MARGIN_DEG)


MARGIN_SLACK_DB = 0.5  # what the terms may cost the current loop's worst gain margin
MARGIN_SLACK_DEG = 3.0  # and its worst phase margin


def refusal(ours: LoopCheck, theirs: LoopCheck) -> str:
    """Why the loop with the terms (`ours`) must not replace the current one (`theirs`),
    or '' when it may: unstable on some model, or under the goals (6 dB, 40 deg) and
    worse than the current loop by more than a little. A current loop that itself misses
    the goals on the fitted model (a stand recalibrated 2 sigma off the nominal one) is the
    PID's to fix; terms that do not lower its margins are still a gain."""
    if not ours.stable:
        return f"unstable on a model ({ours.worst_corner})"
    low_gm = min(MIN_GAIN_MARGIN_DB, theirs.gain_margin_db - MARGIN_SLACK_DB)
    low_pm = min(MIN_PHASE_MARGIN_DEG, theirs.phase_margin_deg - MARGIN_SLACK_DEG)
    if ours.gain_margin_db < low_gm or ours.phase_margin_deg < low_pm:
        return (f"worst margins {ours.gain_margin_db:.1f} dB, {ours.phase_margin_deg:.1f} deg "
                f"({ours.worst_corner}), under {low_gm:.1f} dB, {low_pm:.1f} deg")
    return ""


def named_disturbance(params: PlantParams) -> Disturbance | None:
    """The model's periodic disturbance: a fitted effect first (what diagnose named), else
    the configured cooler; None when there is neither."""
    for fx in params.effects.of("tilt"):
        if isinstance(fx, PeriodicDisturbance) and fx.peak_to_peak_rad != 0:
            return Disturbance("[plant.effects.periodic_disturbance]", fx.period_s,
                               abs(fx.peak_to_peak_rad))
    co = params.cooler
    if co.peak_to_peak_rad > 0:
        return Disturbance("[plant.cooler]", co.period_s, co.peak_to_peak_rad)
    return None


def _resonator_tf(k: float, phase: float, theta: float, radius: float,
                  dt: float) -> control.TransferFunction:
    """One term from error to volts: k dt (cos(phase) z - r cos(phase - theta)) /
    (z^2 - 2 r cos(theta) z + r^2) (leveler.loop.resonant's recursion)."""
    return control.tf([k * dt * math.cos(phase), -k * dt * radius * math.cos(phase - theta)],
                      [1.0, -2.0 * radius * math.cos(theta), radius * radius], dt)


def notch_tf(c: ControllerConfig, rate_hz: float) -> control.TransferFunction | None:
    """The notch on the reading (leveler.loop.notch), in series with every part, or None."""
    notch = c.notch()
    if notch is None:
        return None
    b, a = notch.coefficients(1.0 / rate_hz)
    return control.tf(list(b), [1.0, *a], 1.0 / rate_hz)


def controller_parts(c: ControllerConfig, rate_hz: float) -> list[control.TransferFunction]:
    """The controller as a sum of small transfer functions: the PID, then each term (a
    notch, `notch_tf`, multiplies them all)."""
    parts = [controller_tf(c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m, c.d_filter_tau_s,
                           rate_hz, c.ki2_v_per_m_s2)]
    terms = c.periodic_terms()
    if terms is not None:
        dt = 1.0 / rate_hz
        for h, (k, ph) in enumerate(zip(terms.gains_v_per_m_s, terms.phases_rad,
                                        strict=True), 1):
            theta = 2 * math.pi * h / terms.period_s * dt
            parts.append(_resonator_tf(k, ph, theta, terms.radius, dt))
    return parts


def design(params: PlantParams, rate_hz: float, c: ControllerConfig, period_s: float, *,
           harmonics: int | None = None, beta_rel: float = BETA_REL,
           radius: float = 1.0) -> PeriodicTerms:
    """Gains and phases of resonant terms at the harmonics of `period_s` on top of the
    PID in `c` (module doc). ValueError when not even the fundamental has loop gain."""
    if not period_s > 0:
        raise ValueError(f"period_s must be > 0, got {period_s}")
    if c.ki2_v_per_m_s2:
        # measured: on the boosted default loop (|1 + L0| = 4,079 at 3.3 mHz) every beta
        # tried left a closed-loop pole at 0 Hz outside the unit circle
        raise ValueError("resonant terms are designed on a single-integral loop; this one "
                         "has a double integral (ki2_v_per_m_s2), whose loop gain already "
                         "takes the lines out in the mHz band")
    dt = 1.0 / rate_hz
    plant = plant_tf(params, rate_hz)
    pid = controller_parts(c, rate_hz)[0]
    notch = notch_tf(c, rate_hz)
    if notch is not None:
        plant = notch * plant  # the terms see the notched reading, as the PID does
    w1 = 2 * math.pi / period_s
    gains: list[float] = []
    phases: list[float] = []
    limit = MAX_HARMONICS if harmonics is None else harmonics
    for h in range(1, limit + 1):
        f = h / period_s
        if f >= rate_hz / 4:
            break
        p, l0 = complex(_response(plant, f)), complex(_response(pid, f) * _response(plant, f))
        if harmonics is None and abs(1 + l0) < MIN_LOOP_GAIN:
            break
        g = p / (1 + l0)
        gains.append(float(f"{2 * beta_rel * w1 / abs(g):.4g}"))
        phases.append(float(f"{2 * math.pi * f * dt - np.angle(g):.6g}"))
    if not gains:
        raise ValueError(
            f"the loop has too little gain at 1/{period_s:g} s = {1e3 / period_s:.3g} mHz "
            f"(|1 + L| < {MIN_LOOP_GAIN:g}) for a resonant term to build on")
    return PeriodicTerms(period_s, tuple(gains), tuple(phases), radius)


def _mode_knobs(params: PlantParams) -> list[Knob]:
    """A mode the piezo rings (`ExtraResonance` with a gain): its frequency and gain, at
    MODE_SIGMAS (a fit's report has the uncertainties; the model file does not)."""
    fx = params.effects.extra_resonance
    if fx is None or not fx.gain:
        return []

    def vary(key: str) -> Callable[[PlantParams, float], PlantParams]:
        def apply(p: PlantParams, d: float) -> PlantParams:
            mode = p.effects.extra_resonance
            assert mode is not None
            moved = dataclasses.replace(mode, **{key: getattr(mode, key) * (1 + d)})
            return dataclasses.replace(p, effects=p.effects.with_effect(moved))
        return apply

    return [Knob(f"mode_{key}", f"the mode's {key}", MODE_SIGMAS[key], vary(key))
            for key in ("frequency_hz", "gain")]


def _vary(params: PlantParams, corner: dict[str, float]) -> PlantParams:
    by_name = {k.name: k for k in (*knobs(params, temperature_logged=False, excited=True),
                                   *_mode_knobs(params))}
    for name, d in corner.items():
        params = by_name[name].apply(params, d)
    return params


def corners(params: PlantParams) -> list[tuple[str, PlantParams]]:
    """The nominal model and each +-CORNER_SIGMAS corner of its dynamic tolerances (and of
    a mode it names that the piezo rings)."""
    ks = [k for k in knobs(params, temperature_logged=False, excited=True)
          if k.name in _DYNAMIC_KNOBS] + _mode_knobs(params)
    out = [("nominal", params)]
    for signs in itertools.product((-1, 1), repeat=len(ks)):
        corner = {k.name: s * CORNER_SIGMAS * k.sigma for k, s in zip(ks, signs, strict=True)}
        label = ", ".join(f"{n} {d * 100:+.3g} %" for n, d in corner.items())
        out.append((label, _vary(params, corner)))
    return out


def _one(params: PlantParams, rate_hz: float, c: ControllerConfig,
         f_hz: np.ndarray) -> tuple[bool, float, float, float]:
    plant = plant_tf(params, rate_hz)
    parts = controller_parts(c, rate_hz)
    ctrl = control.ss(parts[0])
    for part in parts[1:]:
        ctrl = control.parallel(ctrl, control.ss(part))
    notch = notch_tf(c, rate_hz)
    if notch is not None:
        ctrl = control.series(control.ss(notch), ctrl)
    closed = control.feedback(control.series(ctrl, control.ss(plant)), 1)
    stable = bool(np.all(np.abs(np.linalg.eigvals(closed.A)) < 1.0))
    loop = sum(_response(p, f_hz) for p in parts) * _response(plant, f_hz)
    if notch is not None:
        loop = loop * _response(notch, f_hz)
    gm_db, pm = margins(loop)
    return stable, gm_db, pm, float(np.max(1 / np.abs(1 + loop)))


def margins(loop: np.ndarray) -> tuple[float, float]:
    """(gain margin [dB], phase margin [deg]) of a loop's response on a dense grid: at each
    crossing of the negative real axis, how far |L| is from 1 either way (a gain that may
    rise or, where |L| > 1, fall before the loop goes unstable); at each crossing of |L| = 1,
    how far the phase is from -180 deg. inf where there is no crossing. The grid must be
    dense (check's is): crossings are read between neighbouring points."""
    mag = np.abs(loop)
    gm = math.inf
    axis = np.nonzero((np.sign(loop.imag[:-1]) != np.sign(loop.imag[1:]))
                      & (loop.real[:-1] + loop.real[1:] < 0))[0]
    for i in axis:
        w = loop.imag[i] / (loop.imag[i] - loop.imag[i + 1])
        m = mag[i] + w * (mag[i + 1] - mag[i])
        gm = min(gm, abs(20 * math.log10(m)))
    pm = math.inf
    for i in np.nonzero(np.sign(mag[:-1] - 1) != np.sign(mag[1:] - 1))[0]:
        w = (mag[i] - 1) / (mag[i] - mag[i + 1])
        z = loop[i] + w * (loop[i + 1] - loop[i])
        pm = min(pm, 180.0 - abs(math.degrees(np.angle(z))))
    return gm, pm


def check(params: PlantParams, rate_hz: float, c: ControllerConfig, *,
          nominal_only: bool = False) -> LoopCheck:
    """The loop `c` makes on the model and on every tolerance corner (module doc); with
    `nominal_only` on the model alone (a cheap first look for a search)."""
    terms = c.periodic_terms()
    lines = [] if terms is None else [h / terms.period_s
                                      for h in range(1, len(terms.gains_v_per_m_s) + 1)]
    notch, mode = c.notch(), params.effects.extra_resonance
    sharp = [x.frequency_hz for x in (notch, mode) if x is not None]
    top = rate_hz / 2 * (1 - 1e-9)
    # dense around each line, never on one (|L| is infinite there), and over a notch or mode
    f_hz = np.unique(np.concatenate([
        np.geomspace(1e-6, top, 6000),
        *[np.linspace(f * 0.9, f * 1.1, 200) for f in lines],
        *[np.linspace(f * 0.7, min(f * 1.3, top), 600) for f in sharp]]))
    models = [("nominal", params)] if nominal_only else corners(params)
    results = [(label, _one(p, rate_hz, c, f_hz)) for label, p in models]
    unstable = [label for label, r in results if not r[0]]
    worst_label = unstable[0] if unstable else max(results, key=lambda lr: lr[1][3])[0]
    return LoopCheck(not unstable, min(r[1] for _, r in results),
                     min(r[2] for _, r in results), max(r[3] for _, r in results),
                     len(results), worst_label, bool(_mode_knobs(params)) and not nominal_only)


def models_line(x: LoopCheck) -> str:
    """What the checked models were, the worst of them and the goals, for a report."""
    mode = (f"; the mode's frequency +-{CORNER_SIGMAS * MODE_SIGMAS['frequency_hz']:.0%} and "
            f"gain +-{CORNER_SIGMAS * MODE_SIGMAS['gain']:.0%}" if x.mode_corners else "")
    return (f"models: the model itself and each +-{CORNER_SIGMAS:g} sigma corner of its stated "
            f"tolerances (sensor and actuator paths, pendulum resonance frequency and Q{mode}); "
            f"worst: {x.worst_corner}; goals: >= {MIN_GAIN_MARGIN_DB:g} dB, "
            f">= {MIN_PHASE_MARGIN_DEG:g} deg")


def floor_tilt(cfg: Config, n: int, seed: int) -> np.ndarray:
    """(sensor white noise + zero drift) / G0 [rad], drawn as a run with this seed draws
    them: what a perfect loop leaves on the table (it nulls its reading, so the platform
    is tilted by exactly what the sensor gets wrong; G0 = sensor arm x amplification)."""
    dist = Disturbances(cfg.plant, 1.0 / cfg.loop.rate_hz, seed)
    noise: list[np.ndarray] = []
    while sum(len(b) for b in noise) < n:
        b = dist.next_block()
        noise.append(b.arrays["noise_m"] + b.arrays["drift_m"])
    g0 = cfg.plant.pendulum.sensor_arm_m * cfg.plant.pendulum.amplification
    return np.concatenate(noise)[:n] / g0


@dataclass(frozen=True)
class Predicted:
    """The true tilt a simulated run of the model leaves, as ASD [rad/rtHz] at `freqs_hz`
    for the current and the suggested controller and the sensor floor; `lines` of them are
    the disturbance's harmonics, the rest a log-spaced grid."""

    duration_s: float
    freqs_hz: np.ndarray
    lines: int
    current: np.ndarray
    suggested: np.ndarray
    floor: np.ndarray

    def worst_over_floor(self, which: str, lo_hz: float, hi_hz: float) -> tuple[float, float]:
        """(max ASD / floor, where) over [lo_hz, hi_hz]."""
        ratio = getattr(self, which) / self.floor
        band = (self.freqs_hz >= lo_hz) & (self.freqs_hz <= hi_hz)
        i = int(np.argmax(np.where(band, ratio, -np.inf)))
        return float(ratio[i]), float(self.freqs_hz[i])


def lines_hz(period_s: float) -> list[float]:
    """A periodic disturbance's first lines that `predict` shows (up to 100 mHz)."""
    return [h / period_s for h in range(1, 6) if h / period_s <= 0.1]


def predict(model: Config, current: ControllerConfig, suggested: ControllerConfig,
            lines: list[float], duration_s: float, seed: int = 1) -> Predicted:
    """Both controllers closing the loop on the model's simulated stand over the same
    disturbance realization (leveler.virtual, so its own loop, limits and ADC): the
    true tilt's ASD at `lines` [Hz] (a disturbance's, a mode's) and across 0.1-100 mHz,
    where the record resolves them, beside the sensor floor."""
    from leveler.analysis.spectral import asd_at
    from leveler.virtual import run_virtual

    rate = model.loop.rate_hz
    grid = [f for f in np.geomspace(1e-4, 1e-1, 31) if f * duration_s >= 20]
    freqs = np.array(lines + grid)
    runs = [run_virtual(dataclasses.replace(model, controller=c), duration_s, seed,
                        engaged=True) for c in (current, suggested)]
    floor = floor_tilt(model, len(runs[0].tilt_rad), seed)
    cur, sug, fl = (asd_at(x, rate, list(freqs)) for x in
                    (runs[0].tilt_rad, runs[1].tilt_rad, floor))
    return Predicted(duration_s, freqs, len(lines), cur, sug, fl)


def _hz(f: float) -> str:
    return f"{f * 1e3:.3g} mHz"


def _toml_list(xs: tuple[float, ...]) -> str:
    return "[" + ", ".join(_toml_float(x) for x in xs) + "]"


def terms_toml(terms: PeriodicTerms) -> list[str]:
    """The terms as the [controller] lines a config holds."""
    return ["[controller]", f"periodic_period_s = {_toml_float(terms.period_s)}",
            f"periodic_gains_v_per_m_s = {_toml_list(terms.gains_v_per_m_s)}",
            f"periodic_phases_rad = {_toml_list(terms.phases_rad)}"]


def margin_rows(ours: LoopCheck, theirs: LoopCheck) -> list[str]:
    """The suggested loop's checks beside the current one's, as report lines."""
    rows = [
        ("closed loop", *(("stable" if x.stable else "UNSTABLE") + f" ({x.corners} models)"
                          for x in (ours, theirs))),
        ("gain margin, worst", *(f"{x.gain_margin_db:.1f} dB" for x in (ours, theirs))),
        ("phase margin, worst", *(f"{x.phase_margin_deg:.1f} deg" for x in (ours, theirs))),
        ("peak |1 / (1 + L)|, worst", *(f"{x.max_sensitivity:.2f}" for x in (ours, theirs))),
    ]
    return (["", f"{'':<34}{'suggested':<22}current"]
            + [f"{a:<34}{b:<22}{c}" for a, b, c in rows] + [models_line(ours)])


def predicted_rows(pred: Predicted, labels: list[str]) -> list[str]:
    """What the model predicts for the true tilt, as report lines: `labels` name the
    prediction's first (line) frequencies, then the worst over the floor per band."""
    lines = ["", f"Predicted true tilt on the model ({pred.duration_s / 3600:g} h simulated, "
             "the same disturbances both ways) [nrad/rtHz]:",
             f"{'':<34}{'suggested':<22}{'current':<22}sensor floor"]
    for j, label in enumerate(labels):
        lines.append(f"{label:<34}{pred.suggested[j] * 1e9:<22.3g}"
                     f"{pred.current[j] * 1e9:<22.3g}{pred.floor[j] * 1e9:.3g}")
    grid = pred.freqs_hz[pred.lines:]
    for lo, hi, band in ((1e-4, 1e-2, "0.1-10 mHz"), (1e-2, 1e-1, "10-100 mHz")):
        if not np.any((grid >= lo) & (grid <= hi)):
            continue
        cells = []
        for which in ("suggested", "current"):
            r, f = pred.worst_over_floor(which, lo, hi)
            cells.append(f"{r:.2f}x at {_hz(f)}")
        lines.append(f"{'worst over the floor, ' + band:<34}{cells[0]:<22}{cells[1]}")
    return lines


def report(d: Disturbance, terms: PeriodicTerms, c: ControllerConfig, ours: LoopCheck,
           theirs: LoopCheck, pred: Predicted | None) -> str:
    """The suggestion as config lines, its margins beside the current loop's, and what the
    model predicts it does to the true tilt."""
    n = len(terms.gains_v_per_m_s)
    lines = [
        f"The model names a periodic disturbance: {d.source}, period {d.period_s:g} s, "
        f"{d.peak_to_peak_rad * 1e9:.3g} nrad peak to peak.",
        f"Suggested: resonant terms at harmonics 1-{n} ({_hz(1 / d.period_s)} to "
        f"{_hz(n / d.period_s)}) added to the PID (kp {c.kp_v_per_m:g} V/m, "
        f"ki {c.ki_v_per_m_s:g} V/(m s), kd {c.kd_v_s_per_m:g} V s/m):",
        *terms_toml(terms),
    ]
    lines += margin_rows(ours, theirs)
    if pred is not None:
        lines += predicted_rows(pred, [f"ASD at {_hz(f)} (line {j + 1})"
                                       for j, f in enumerate(pred.freqs_hz[:pred.lines])])
    return "\n".join(lines)
