"""What temperature feedforward could buy against the sensor floor, on a model that names a
temperature path to the tilt.

Feedforward would add -tilt(T) / (tilt per volt) to the command: the temperature's tilt
through the fitted lag, taken out before the loop sees it. At best it removes that tilt
exactly, so the most it can buy is the difference between the model run as it is and the
same model with every temperature path to the tilt cut ([plant.thermal]'s coefficient and
a fitted [plant.effects.temperature_coupling]), both closed by the same loop over the same
disturbances. Where the loop already holds the temperature's tilt under the floor the
sensor's own noise and drift set, nothing is left to buy: the table then sits on what the
sensor gets wrong, which no feedforward from a thermometer can see. A real feedforward
does worse than this bound (the fitted gain and lag are uncertain, the thermometer is
noisy), so a bound near 1x is a clear no.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from leveler.settings import Config
from leveler.sim.params import PlantParams

WORTH = 1.2  # a bound under this (current / best, ASD) anywhere: not worth a thermometer path
ERROR = 0.1  # the relative gain error of a feedforward shown beside the perfect one
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
    """True tilt ASD [rad/rtHz] at `freqs_hz` with the loop as it is, with a perfect
    feedforward, and the sensor floor."""

    duration_s: float
    freqs_hz: np.ndarray
    current: np.ndarray
    best: np.ndarray
    off: np.ndarray  # with a feedforward ERROR off in gain
    floor: np.ndarray
    railed: float  # share of the run the piezo sat on a limit, as it is

    def gain(self, by: np.ndarray | None = None) -> tuple[float, float]:
        """(the most feedforward buys, current / best ASD, and where); with `by`, current /
        by at that same frequency."""
        i = int(np.argmax(self.current / self.best))
        ratio = self.current[i] / (self.best if by is None else by)[i]
        return float(ratio), float(self.freqs_hz[i])


def bound(model: Config, duration_s: float, seed: int = 1) -> Bound:
    """Simulate the model and its perfect-feedforward twin closed by the configured loop."""
    from leveler.analysis.periodic import floor_tilt
    from leveler.analysis.spectral import asd_at
    from leveler.virtual import run_virtual

    rate = model.loop.rate_hz
    freqs = np.array([f for f in np.geomspace(1e-5, 1e-1, 25) if f * duration_s >= 20])
    runs = [run_virtual(dataclasses.replace(model, plant=scaled_temperature(model.plant, k)),
                        duration_s, seed, engaged=True) for k in (1.0, 0.0, ERROR)]
    floor = floor_tilt(model, len(runs[0].tilt_rad), seed)
    cur, best, off, fl = (asd_at(x, rate, list(freqs)) for x in
                          (*(r.tilt_rad for r in runs), floor))
    lo, hi, _ = model.actuator_range_v()
    c = model.controller
    lo, hi = max(lo, c.output_min_v), min(hi, c.output_max_v)
    v = runs[0].applied_v
    railed = float(np.mean((v <= lo + RAIL_V) | (v >= hi - RAIL_V)))
    return Bound(duration_s, freqs, cur, best, off, fl, railed)


def report(paths: list[str], b: Bound) -> str:
    """The bound as a table by frequency, and the verdict."""
    lines = ["The model ties the tilt to the temperature: " + "; ".join(paths) + ".",
             f"True tilt on the model ({b.duration_s / 3600:g} h simulated, the same "
             "disturbances both ways) [nrad/rtHz]:",
             f"{'':<16}{'as it is':<12}{'perfect feedforward':<22}"
             f"{f'{ERROR:.0%} off in gain':<18}sensor floor"]
    for f, c, p, o, fl in zip(b.freqs_hz, b.current, b.best, b.off, b.floor, strict=True):
        lines.append(f"{f'{f * 1e3:.3g} mHz':<16}{c * 1e9:<12.3g}{p * 1e9:<22.3g}"
                     f"{o * 1e9:<18.3g}{fl * 1e9:.3g}")
    most, where = b.gain()
    if b.railed > MAX_RAILED:
        lines.append(
            f"The piezo sat on a limit for {b.railed:.1%} of the run: the temperature tilts the "
            "table further than the actuator reaches, so the loop cannot hold it, and a "
            "feedforward, which drives the same piezo, cannot either (the perfect one above "
            "is not reachable). This stand needs more stroke, or less coupling to the "
            "temperature.")
    elif most < WORTH:
        lines.append(
            f"Temperature feedforward is not worth it on this model: even a perfect one would "
            f"lower the true tilt by at most {most:.2f}x (at {where * 1e3:.3g} mHz). The loop "
            "already holds the temperature's tilt under the floor the sensor's own noise and "
            "drift set; that floor is what is left, and a thermometer cannot see it.")
    else:
        lines.append(
            f"A perfect temperature feedforward would lower the true tilt by up to {most:.2f}x "
            f"(at {where * 1e3:.3g} mHz), one {ERROR:.0%} off in gain by {b.gain(b.off)[0]:.2f}x "
            "there; lag errors and the thermometer's noise cost more. The daemon reads no "
            "temperature yet, so it is not offered here (issue 21).")
    return "\n".join(lines)
