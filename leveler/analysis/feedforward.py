"""Temperature feedforward against a model that names a temperature path to the tilt: the
paths it takes, and what it buys against the sensor floor.

The model says tilt = k x lag(T) for each path ([plant.thermal]'s coefficient and lag, a
fitted [plant.effects.temperature_coupling] with its one or two lags). The feedforward
(leveler.loop.feedforward) adds gain x lag(T) to the command with gain = -k / (tilt per
piezo volt), so the piezo takes each path's tilt out before the loop sees it.

What it buys is simulated, not argued: the model run as it is; with the suggested
feedforward reading the model's thermometer (its noise and resolution, every
`[thermometer] interval_s`); with every temperature path cut (a perfect feedforward: the
bound); and with the feedforward off in gain by the model's stated tolerance, all closed by
the same loop over the same disturbances. Where the loop already holds the temperature's
tilt under the floor the sensor's own noise and drift set, nothing is left to buy: the
table then sits on what the sensor gets wrong, which no thermometer can see.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from leveler.loop.feedforward import Feedforward, FeedforwardPath
from leveler.settings import Config, ThermometerConfig
from leveler.sim.params import PlantParams

WORTH = 1.2  # a bound under this (current / best, ASD) anywhere: not worth a thermometer path
ERROR = 0.1  # the gain error shown beside the perfect one when the model states none
RAIL_V = 1e-6  # within this of a limit, the piezo is railed
MAX_RAILED = 1e-3  # a run railed longer than this share is out of range, not short of a model


def temperature_paths(params: PlantParams) -> list[str]:
    """The model's paths from temperature to tilt, as the config names them."""
    paths = []
    if params.thermal.tilt_per_kelvin_rad_per_k:
        paths.append(f"[plant.thermal] {params.thermal.tilt_per_kelvin_rad_per_k:g} rad/K "
                     f"through {params.thermal.lag_s:g} s")
    fx = params.effects.temperature_coupling
    if fx is not None and fx.tilt_per_kelvin_rad_per_k:
        lags = f"{fx.lag_s:g} s" + (f" and {fx.lag2_s:g} s" if fx.lag2_s > 0 else "")
        paths.append(f"[plant.effects.temperature_coupling] {fx.tilt_per_kelvin_rad_per_k:g} "
                     f"rad/K through {lags}")
    return paths


def design(params: PlantParams) -> Feedforward | None:
    """The feedforward that cancels every temperature path of the model, or None if it
    has none: gain = -k / (tilt per piezo volt), through the path's own lags."""
    tilt_per_v = params.piezo.gain_m_per_v / params.platform.support_spacing_m
    paths = []
    th = params.thermal
    if th.tilt_per_kelvin_rad_per_k:
        paths.append(FeedforwardPath(-th.tilt_per_kelvin_rad_per_k / tilt_per_v, th.lag_s))
    fx = params.effects.temperature_coupling
    if fx is not None and fx.tilt_per_kelvin_rad_per_k:
        paths.append(FeedforwardPath(-fx.tilt_per_kelvin_rad_per_k / tilt_per_v, fx.lag_s,
                                     fx.lag2_s))
    return Feedforward(tuple(paths)) if paths else None


def values(ff: Feedforward) -> dict[str, list[float]]:
    """The feedforward as tune values ([controller] feedforward_*)."""
    return {"feedforward_gains_v_per_k": [p.gain_v_per_k for p in ff.paths],
            "feedforward_lags_s": [p.lag_s for p in ff.paths],
            "feedforward_lags2_s": [p.lag2_s for p in ff.paths]}


def toml_lines(ff: Feedforward) -> list[str]:
    """The [controller] lines that configure it (what --persist writes)."""
    return [f"{k} = [{', '.join(f'{x:.6g}' for x in v)}]" for k, v in values(ff).items()]


def gain_error(params: PlantParams) -> float:
    """The relative gain error a feedforward designed from the model carries: the stated
    tolerances of the thermal tilt and of the tilt per piezo volt, else ERROR."""
    u = params.uncertainty
    stated = math.hypot(u.thermal_tilt_rel, u.actuator_path_rel)
    return stated if stated > 0 else ERROR


def scaled_temperature(params: PlantParams, share: float) -> PlantParams:
    """The model with every temperature path to the tilt scaled by `share`: what a
    feedforward leaves that is right but for a relative error of `share` (0: perfect)."""
    fx = params.effects.temperature_coupling
    effects = params.effects if fx is None else params.effects.with_effect(
        dataclasses.replace(fx, tilt_per_kelvin_rad_per_k=fx.tilt_per_kelvin_rad_per_k * share))
    return dataclasses.replace(params, effects=effects, thermal=dataclasses.replace(
        params.thermal,
        tilt_per_kelvin_rad_per_k=params.thermal.tilt_per_kelvin_rad_per_k * share))


@dataclass(frozen=True)
class Bound:
    """True tilt ASD [rad/rtHz] at `freqs_hz` with the loop as it is, with the suggested
    feedforward (None: not simulated), with a perfect one, with one `error` off in gain,
    and the sensor floor."""

    duration_s: float
    freqs_hz: np.ndarray
    current: np.ndarray
    suggested: np.ndarray | None
    best: np.ndarray
    off: np.ndarray
    error: float
    floor: np.ndarray
    railed: float  # share of the run the piezo sat on a limit, as it is

    def gain(self, by: np.ndarray | None = None) -> tuple[float, float]:
        """(the most a perfect feedforward buys, current / best ASD, and where); with `by`,
        current / by at that same frequency."""
        i = int(np.argmax(self.current / self.best))
        ratio = self.current[i] / (self.best if by is None else by)[i]
        return float(ratio), float(self.freqs_hz[i])

    @property
    def worth_it(self) -> bool:
        return self.railed <= MAX_RAILED and self.gain()[0] >= WORTH


def with_feedforward(model: Config, ff: Feedforward, interval_s: float) -> Config:
    """The model's stand reading its simulated thermometer, `ff` in the loop."""
    return dataclasses.replace(
        model, thermometer=ThermometerConfig(backend="sim", interval_s=interval_s),
        controller=dataclasses.replace(model.controller, **{
            k: tuple(v) for k, v in values(ff).items()}))


def bound(model: Config, duration_s: float, seed: int = 1, ff: Feedforward | None = None,
          interval_s: float = 1.0) -> Bound:
    """Simulate the model, its perfect-feedforward twin, one off in gain and, given `ff`,
    the model with that feedforward, all closed by the configured loop."""
    from leveler.analysis.periodic import floor_tilt
    from leveler.analysis.spectral import asd_at
    from leveler.virtual import run_virtual

    rate = model.loop.rate_hz
    freqs = np.array([f for f in np.geomspace(1e-5, 1e-1, 25) if f * duration_s >= 20])
    error = gain_error(model.plant)
    configs = [dataclasses.replace(model, plant=scaled_temperature(model.plant, k))
               for k in (1.0, 0.0, error)]
    if ff is not None:
        configs.append(with_feedforward(model, ff, interval_s))
    runs = [run_virtual(c, duration_s, seed, engaged=True) for c in configs]
    floor = floor_tilt(model, len(runs[0].tilt_rad), seed)
    asds = [asd_at(x, rate, list(freqs)) for x in (*(r.tilt_rad for r in runs), floor)]
    lo, hi, _ = model.actuator_range_v()
    c = model.controller
    lo, hi = max(lo, c.output_min_v), min(hi, c.output_max_v)
    v = runs[0].applied_v
    railed = float(np.mean((v <= lo + RAIL_V) | (v >= hi - RAIL_V)))
    return Bound(duration_s, freqs, asds[0], asds[3] if ff is not None else None, asds[1],
                 asds[2], error, asds[-1], railed)


def report(paths: list[str], b: Bound, ff: Feedforward | None = None) -> str:
    """The runs as a table by frequency, and the verdict."""
    lines = ["The model ties the tilt to the temperature: " + "; ".join(paths) + ".",
             f"True tilt on the model ({b.duration_s / 3600:g} h simulated, the same "
             "disturbances every way) [nrad/rtHz]:"]
    cols = [("as it is", b.current)]
    if b.suggested is not None:
        cols.append(("suggested", b.suggested))
    cols += [("perfect", b.best), (f"{b.error:.0%} off in gain", b.off), ("sensor floor", b.floor)]
    lines.append(f"{'':<14}" + "".join(f"{name:<18}" for name, _ in cols).rstrip())
    for i, f in enumerate(b.freqs_hz):
        lines.append(f"{f'{f * 1e3:.3g} mHz':<14}"
                     + "".join(f"{a[i] * 1e9:<18.3g}" for _, a in cols).rstrip())
    most, where = b.gain()
    if b.railed > MAX_RAILED:
        lines.append(
            f"The piezo sat on a limit for {b.railed:.1%} of the run: the temperature tilts the "
            "table further than the actuator reaches, so the loop cannot hold it, and a "
            "feedforward, which drives the same piezo, cannot either (the perfect one above "
            "is not reachable). This stand needs more stroke, or less coupling to the "
            "temperature. No feedforward is suggested.")
    elif most < WORTH:
        lines.append(
            f"Temperature feedforward is not worth it on this model down to "
            f"{b.freqs_hz[0] * 1e3:.3g} mHz (what {b.duration_s / 3600:g} h resolve; a longer "
            f"--predict-hours looks lower): even a perfect one would lower the true tilt by "
            f"at most {most:.2f}x (at {where * 1e3:.3g} mHz). The loop "
            "already holds the temperature's tilt under the floor the sensor's own noise and "
            "drift set; that floor is what is left, and a thermometer cannot see it. No "
            "feedforward is suggested.")
    else:
        text = (f"A perfect temperature feedforward would lower the true tilt by up to "
                f"{most:.2f}x (at {where * 1e3:.3g} mHz), one {b.error:.0%} off in gain by "
                f"{b.gain(b.off)[0]:.2f}x there")
        if b.suggested is not None and ff is not None:
            text += (f"; the suggested one, through the model's thermometer, by "
                     f"{b.gain(b.suggested)[0]:.2f}x. Suggested feedforward "
                     f"({ff.describe()}):\n" + "\n".join(toml_lines(ff)))
        else:
            text += "."
        lines.append(text)
    return "\n".join(lines)
