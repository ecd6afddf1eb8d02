"""Baseline recalibration: fit the model's calibrated numbers to the log, within their
stated tolerances, before any missing effect is looked for.

A lab states its numbers with 1-sigma tolerances (`[plant.uncertainty]`); a healthy stand
differs from its nominal model by offsets within them, and a detector that compares the
log with the nominal model names those offsets as effects (a gain error of 3 % becomes a
"hysteresis"). So the uncertain numbers are fitted first, as a maximum a posteriori
estimate under Gaussian priors, on the whitened residual (`leveler.analysis.whittle`).
Each is reported with its pull, offset / sigma: a pull beyond PULL_LIMIT says the log
disputes the stated calibration; `leveler.analysis.diagnose` then holds that number at
nominal and lets the effect families compete for what pulled it.

The knobs are the combinations a replay can tell apart: the sensor path (reading per unit
tilt: arm x amplification x sensor gain), the actuator path (tilt per piezo volt: piezo
gain / support spacing), the pendulum's resonance frequency and Q (at a fixed static
amplification), the thermal tilt coefficient when the temperature was logged, and the
cooler's amplitude (a disturbance's level, which drifts from day to day).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from leveler.analysis.predict import Measured, Predictor, excitation_v
from leveler.analysis.steps import stepped_least_squares
from leveler.analysis.whittle import ENBW_BINS, Whitener
from leveler.sim.effects import Effect
from leveler.sim.params import PlantParams

#: a pull beyond this many sigma is a calibration the log disputes
PULL_LIMIT = 3.0
#: a bin this far above the noise spectrum is a line (chance: once in 160,000 bins)
LINE_Z = 12.0


def _sensor(p: PlantParams, d: float) -> PlantParams:
    pe = p.pendulum
    return dataclasses.replace(p, pendulum=dataclasses.replace(
        pe, sensor_arm_m=pe.sensor_arm_m * (1 + d)))


def _actuator(p: PlantParams, d: float) -> PlantParams:
    pz = p.piezo
    return dataclasses.replace(p, piezo=dataclasses.replace(
        pz, gain_m_per_v=pz.gain_m_per_v * (1 + d)))


def _frequency(p: PlantParams, d: float) -> PlantParams:
    """f0 * (1 + d) at the same static amplification and Q: the inertia changes, and the
    damping with it."""
    pe = p.pendulum
    inertia = pe.inertia_kgm2 / (1 + d) ** 2
    return dataclasses.replace(p, pendulum=dataclasses.replace(
        pe, inertia_kgm2=inertia, damping_nms_per_rad=pe.damping_nms_per_rad / (1 + d)))


def _q(p: PlantParams, d: float) -> PlantParams:
    pe = p.pendulum
    return dataclasses.replace(p, pendulum=dataclasses.replace(
        pe, damping_nms_per_rad=pe.damping_nms_per_rad / (1 + d)))


def _thermal(p: PlantParams, d: float) -> PlantParams:
    th = p.thermal
    return dataclasses.replace(p, thermal=dataclasses.replace(
        th, tilt_per_kelvin_rad_per_k=th.tilt_per_kelvin_rad_per_k * (1 + d)))


def _cooler(p: PlantParams, d: float) -> PlantParams:
    co = p.cooler
    return dataclasses.replace(p, cooler=dataclasses.replace(
        co, peak_to_peak_rad=co.peak_to_peak_rad * (1 + d)))


@dataclass(frozen=True)
class Knob:
    name: str
    title: str
    sigma: float  # relative 1-sigma
    apply: Callable[[PlantParams, float], PlantParams]


TITLES = {
    "sensor_path": "sensor path (arm x amplification x gain)",
    "actuator_path": "actuator path (piezo gain / support spacing)",
    "natural_frequency": "pendulum resonance frequency",
    "q": "pendulum Q",
    "thermal_tilt": "thermal tilt coefficient",
    "cooler_amplitude": "cooler amplitude",
}


def knobs(params: PlantParams, temperature_logged: bool, excited: bool,
          omit: tuple[str, ...] = ()) -> list[Knob]:
    """The uncertain numbers this model states, as knobs a replay can turn. The two path
    gains only when something other than feedback moved the actuator (`excited`): in a
    closed loop alone the voltage carries the disturbance it cancels, and a gain applied to
    it shrinks that unpredicted disturbance with it, which fits better without being true."""
    u = params.uncertainty
    all_knobs = [
        Knob("sensor_path", TITLES["sensor_path"], u.sensor_path_rel, _sensor),
        Knob("actuator_path", TITLES["actuator_path"], u.actuator_path_rel, _actuator),
        Knob("natural_frequency", TITLES["natural_frequency"], u.natural_frequency_rel,
             _frequency),
        Knob("q", TITLES["q"], u.q_rel, _q),
        Knob("thermal_tilt", TITLES["thermal_tilt"],
             u.thermal_tilt_rel if temperature_logged else 0.0, _thermal),
        Knob("cooler_amplitude", TITLES["cooler_amplitude"],
             u.cooler_amplitude_rel if params.cooler.peak_to_peak_rad > 0 else 0.0, _cooler),
    ]
    paths = ("sensor_path", "actuator_path")
    return [k for k in all_knobs if k.sigma > 0 and (excited or k.name not in paths)
            and k.name not in omit]


@dataclass
class Recalibration:
    """The recalibrated model and what moved: relative offsets, their prior and posterior
    1-sigma, and pulls (offset / prior sigma)."""

    params: PlantParams
    knobs: list[Knob]
    offset: dict[str, float]
    sigma_post: dict[str, float]
    deviance: float  # twice the log-likelihood gain over the nominal model
    held: tuple[str, ...] = ()  # knobs a first fit put beyond PULL_LIMIT, now at nominal
    # posterior correlation of each pair of fitted knobs: which a disputed one may have moved
    correlation: dict[tuple[str, str], float] = field(default_factory=dict)

    def pull(self, name: str) -> float:
        k = next(k for k in self.knobs if k.name == name)
        return self.offset[name] / k.sigma

    @property
    def disputed(self) -> list[str]:
        return [k.name for k in self.knobs if abs(self.pull(k.name)) > PULL_LIMIT]

    def releasing(self, knob: Knob, offset: float, sigma_post: float) -> Recalibration:
        """This fit with a held knob put back at `offset` (from nominal, where holding
        left it) and counted among the fitted ones again."""
        return dataclasses.replace(
            self, params=knob.apply(self.params, offset), knobs=[*self.knobs, knob],
            offset={**self.offset, knob.name: offset},
            sigma_post={**self.sigma_post, knob.name: sigma_post},
            held=tuple(n for n in self.held if n != knob.name))

    def as_dict(self) -> dict[str, dict[str, float]]:
        return {k.name: {"offset_rel": self.offset[k.name], "sigma_rel": k.sigma,
                         "posterior_sigma_rel": self.sigma_post[k.name],
                         "pull": self.pull(k.name)} for k in self.knobs}

    def describe(self) -> list[str]:
        return [f"{k.title}: {self.offset[k.name] * 100:+.2f} % "
                f"(+-{self.sigma_post[k.name] * 100:.2g} %; tolerance {k.sigma * 100:.3g} %, "
                f"pull {self.pull(k.name):+.1f} sigma)" for k in self.knobs] + [
            f"{TITLES[name]}: beyond its tolerance, held at nominal and left to the effect "
            "candidates" for name in self.held]


def apply(params: PlantParams, ks: list[Knob], x: np.ndarray) -> PlantParams:
    for k, d in zip(ks, x, strict=True):
        params = k.apply(params, float(d))
    return params


def replayable(params: PlantParams) -> PlantParams:
    """`params` without the effects a replay cannot weigh (`Effect.own_score_only`: a
    coarse converter). A knob moves the reading through a found converter's staircase,
    and the fit's finite differences see steps, not slopes: with an 11 nm converter
    found, the knobs ran to -9 and +12 sigma, all were held at nominal, and the gap
    stayed at 105 of its 111 nm. Left out, the converter is noise of a step/sqrt(12) to
    them, which is what the knobs saw before it was found."""
    unweighable = [fx.name for fx in params.effects if fx.own_score_only]
    if not unweighable:
        return params
    return dataclasses.replace(params, effects=params.effects.without(*unweighable))


def with_unreplayable(params: PlantParams, source: PlantParams) -> PlantParams:
    """`params` with `source`'s effects that `replayable` leaves out put back."""
    effects = params.effects
    for fx in source.effects:
        if fx.own_score_only:
            effects = effects.with_effect(fx)
    return dataclasses.replace(params, effects=effects)


def recalibrate(meas: Measured, params: PlantParams, w: Whitener,
                excited: bool, omit: tuple[str, ...] = (),
                refine: Effect | None = None) -> Recalibration | None:
    """MAP of the model's uncertain numbers on the span `w` whitens (its noise spectrum
    fitted to the nominal residual), lines left out, the knobs in `omit` held at nominal;
    None if the model states no tolerance (nothing to recalibrate).

    `refine`, an effect of `params` just found, is refitted jointly (flat prior): fitted
    on a model whose resonance an unmodelled effect had pulled, a sawtooth's drop comes
    out 5 ms late, and recalibrating with it held there keeps the resonance wrong
    (Q 14 % off), the two errors holding each other in place."""
    ks = knobs(params, meas.sig.temperature_k is not None, excited, omit)
    if not ks:
        return None
    full, params = params, replayable(params)
    fkeys = refine.free if refine is not None else ()
    fscale = np.array([refine.scale(k) for k in fkeys]) if refine is not None else np.zeros(0)
    f0 = np.array([float(getattr(refine, k)) for k in fkeys])
    nk = len(ks)

    def effect_at(v: np.ndarray) -> PlantParams:
        if refine is None:
            return params
        fx = refine.replace(**{k: float(x) for k, x in zip(fkeys, f0 + v * fscale,
                                                            strict=True)})
        return dataclasses.replace(params, effects=params.effects.with_effect(fx))

    sigma = np.array([k.sigma for k in ks])
    root = math.sqrt(2.0 / ENBW_BINS)  # whitened cost -> -2 log-likelihood
    nominal = Predictor(params, meas)
    base = nominal.base.y_m
    # Bins where the nominal residual stands far above its noise spectrum are lines: an
    # unmodelled periodic disturbance that the loop cancelled sits in the residual scaled
    # by the sensor path, and would pull that path towards zero. Lines are the candidates'
    # business, except those of the excitation (a square or triangle modulation is a comb
    # of lines too): where a 1-sigma knob moves the response to it, a bin tells the knob.
    # The cooler's own lines stay out too: an unmodelled disturbance near its period leaks
    # into them. Its level is refitted with every candidate, on all bins
    # (`leveler.analysis.nuisance`), where that disturbance has a name to compete for them.
    exc = excitation_v(meas)
    told = np.zeros(len(w.f_hz), dtype=bool)
    if exc is not None:
        def response(p: Predictor) -> np.ndarray:
            return p.pend(p.actuator_tilt(exc))

        r0 = response(nominal)
        for i in range(len(ks)):
            one = np.where(np.arange(len(ks)) == i, sigma, 0.0)
            told |= w.zscores(response(Predictor(apply(params, ks, one), meas)) - r0) > 1.0
    quiet = np.tile((w.zscores(meas.y_m - base) < LINE_Z) | told, 2)

    def residuals(z: np.ndarray) -> np.ndarray:
        pred = Predictor(apply(effect_at(z[nk:]), ks, z[:nk] * sigma), meas)
        return np.concatenate([root * w.whiten(meas.y_m - pred.base.y_m)[quiet], z[:nk]])

    # Relative offsets above -90 %: a model cannot be recalibrated to nothing.
    lo = np.concatenate([-0.9 / sigma, [(refine.bounds(k)[0] - v) / d for k, v, d in
                                        zip(fkeys, f0, fscale, strict=True)]])
    hi = np.concatenate([np.full(nk, np.inf), [(refine.bounds(k)[1] - v) / d for k, v, d in
                                               zip(fkeys, f0, fscale, strict=True)]])
    z0 = np.clip(np.zeros(len(lo)), lo + 1e-9, hi - 1e-9)
    # The trust region scaled by the Jacobian's columns: in sigma units a day pins the
    # resonance frequency 2,500 times tighter than the sensor path, and an unscaled region
    # zig-zagged down that valley (a null day: 59 Jacobians, 54 s; scaled, 16 and 13 s,
    # the same cost to 1e-6 and every knob within 0.004 sigma).
    r0 = residuals(z0)  # the nominal's, which the search also starts from: made once
    # Stepped by scipy's 1.5e-8 fallback at the start, a refined coupling's two lag
    # columns came out 150 and 290 times too long (rounding): `stepped_least_squares`.
    res = stepped_least_squares(
        lambda z: r0.copy() if np.array_equal(z, z0) else residuals(z), z0, (lo, hi),
        30 * (len(lo) + 1), x_scale="jac")
    deviance = float(r0 @ r0 - res.fun @ res.fun)
    corr: dict[tuple[str, str], float] = {}
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac)
        sd = np.sqrt(np.abs(np.diag(cov)))
        post = sd[:nk] * sigma
        for i, a in enumerate(ks):
            for j, b in enumerate(ks):
                if i != j and sd[i] > 0 and sd[j] > 0:
                    corr[a.name, b.name] = float(cov[i, j] / (sd[i] * sd[j]))
    except np.linalg.LinAlgError:
        post = np.full(nk, math.inf)
    x = res.x[:nk] * sigma
    return Recalibration(with_unreplayable(apply(effect_at(res.x[nk:]), ks, x), full), ks,
                         {k.name: float(v) for k, v in zip(ks, x, strict=True)},
                         {k.name: float(v) for k, v in zip(ks, post, strict=True)}, deviance,
                         omit, corr)
