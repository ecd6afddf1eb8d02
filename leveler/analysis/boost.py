"""More loop gain in the mHz band, bought from the margins the model's tolerances leave.

A single integrator gives loop gain falling as 1 / f from the crossover down: on the
default stand ~30x at 10 mHz, so a disturbance between a periodic disturbance's lines (or
of no line at all) is suppressed only that much there. A double integral (`ki2`,
leveler.loop.pid) makes it fall as 1 / f^2 below ki2 / (2 pi ki) Hz, but costs phase at
the crossover; the PID's own gains move that back. So the boost is a search: over the
integral and derivative gains around the running ones, a proportional gain and the
boost's corner, keep the controllers whose worst gain and phase margins over every
tolerance corner of the model (periodic.corners) meet the goals, and take the one with
the most in-loop suppression at its worst point in 1-10 mHz. Screened on frequency
responses; the best few are checked as every suggestion is (periodic.check: closed-loop
eigenvalues and margins on a dense grid).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np

from leveler.analysis.periodic import (
    MIN_GAIN_MARGIN_DB,
    MIN_PHASE_MARGIN_DEG,
    LoopCheck,
    check,
    corners,
    margin_rows,
    margins,
    notch_tf,
)
from leveler.analysis.suggest import _response, _toml_float, controller_tf, plant_tf
from leveler.loop.pid import ControllerConfig
from leveler.sim.params import PlantParams

KI_SCALES = (0.9, 1.0, 1.1, 1.2)
KD_SCALES = (0.7, 0.8, 0.9, 1.0)
KP_V_PER_M = (0.0, 1e5, 3e5, 6e5)
CORNERS_HZ = (0.04, 0.06, 0.08, 0.1, 0.12)  # the boost's corner, ki2 = 2 pi f ki
BAND_HZ = (1e-3, 1e-2)
MIN_GAIN = 2.0  # the boost must at least double the worst suppression in the band
CHECKED = 5  # of the screened, checked in full


@dataclass(frozen=True)
class Boost:
    """The boosted controller, its full check and the worst suppression in BAND_HZ
    (|1 + L|, the worst model) beside the current one's."""

    controller: ControllerConfig
    ours: LoopCheck
    theirs: LoopCheck
    suppression: float
    current_suppression: float
    corner_hz: float


def _screen(params: PlantParams, rate_hz: float,
            cands: list[ControllerConfig]) -> list[tuple[float, float, float, ControllerConfig]]:
    """(worst suppression in the band, worst gain margin, worst phase margin, controller)."""
    f = np.unique(np.concatenate([np.geomspace(1e-6, rate_hz / 2 * (1 - 1e-9), 3000),
                                  np.geomspace(*BAND_HZ, 200)]))
    band = (f >= BAND_HZ[0]) & (f <= BAND_HZ[1])
    plants = [_response(plant_tf(p, rate_hz), f) for _, p in corners(params)]
    out = []
    for c in cands:
        ctrl = _response(controller_tf(c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m,
                                       c.d_filter_tau_s, rate_hz, c.ki2_v_per_m_s2), f)
        n = notch_tf(c, rate_hz)
        if n is not None:
            ctrl = ctrl * _response(n, f)
        worst = [math.inf, math.inf, math.inf]
        for p in plants:
            loop = ctrl * p
            gm, pm = margins(loop)
            worst = [min(worst[0], float(np.min(np.abs(1 + loop)[band]))),
                     min(worst[1], gm), min(worst[2], pm)]
        out.append((worst[0], worst[1], worst[2], c))
    return out


def design(params: PlantParams, rate_hz: float, c: ControllerConfig) -> Boost | None:
    """The boosted PID on top of `c` (its notch and terms kept), or None when no candidate
    meets the goals on every model while at least doubling the worst suppression."""
    base = dataclasses.replace(c, periodic_period_s=0.0, periodic_gains_v_per_m_s=(),
                               periodic_phases_rad=())
    cands = [dataclasses.replace(base, kp_v_per_m=kp, ki_v_per_m_s=c.ki_v_per_m_s * a,
                                 kd_v_s_per_m=c.kd_v_s_per_m * b,
                                 ki2_v_per_m_s2=c.ki_v_per_m_s * a * 2 * math.pi * fc)
             for a, b, kp, fc in itertools.product(KI_SCALES, KD_SCALES, KP_V_PER_M,
                                                    CORNERS_HZ)]
    (now, *_), = _screen(params, rate_hz, [base])
    screened = [s for s in _screen(params, rate_hz, cands)
                if s[1] >= MIN_GAIN_MARGIN_DB and s[2] >= MIN_PHASE_MARGIN_DEG
                and s[0] >= MIN_GAIN * now]
    screened.sort(key=lambda s: -s[0])
    theirs = check(params, rate_hz, c)
    for sup, _, _, cand in screened[:CHECKED]:
        boosted = dataclasses.replace(cand, periodic_period_s=c.periodic_period_s,
                                      periodic_gains_v_per_m_s=c.periodic_gains_v_per_m_s,
                                      periodic_phases_rad=c.periodic_phases_rad)
        ours = check(params, rate_hz, boosted)
        if ours.ok:
            corner = cand.ki2_v_per_m_s2 / cand.ki_v_per_m_s / (2 * math.pi)
            return Boost(boosted, ours, theirs, sup, now, corner)
    return None


GAINS = ("kp_v_per_m", "ki_v_per_m_s", "kd_v_s_per_m", "ki2_v_per_m_s2")


def values(b: Boost) -> dict[str, float]:
    return {k: float(f"{getattr(b.controller, k):.4g}") for k in GAINS}


def report(b: Boost, c: ControllerConfig) -> str:
    """The boosted gains as config lines beside today's, and both loops' checks."""
    v = values(b)
    lines = [
        f"The model's tolerances leave room for more loop gain in {BAND_HZ[0] * 1e3:g}-"
        f"{BAND_HZ[1] * 1e3:g} mHz: worst in-loop suppression there {b.current_suppression:.3g}x "
        f"now, {b.suppression:.3g}x with a double integral (loop gain rising as 1/f^2 below "
        f"{b.corner_hz * 1e3:.3g} mHz) and the PID moved to keep the margins:",
        "[controller]",
        *(f"{k} = {_toml_float(v[k])}  # now {getattr(c, k):g}" for k in GAINS),
    ]
    return "\n".join(lines + margin_rows(b.ours, b.theirs))
