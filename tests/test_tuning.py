"""The default tuning (config/sim.toml) judged by python-control: stable with margins on the
nominal stand, still stable with margin on stands that differ from it, and the loop gain
issue 7's control goals need. The simulated proof is `make bench` (bench/control_quality.py).
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import control
import numpy as np
import pytest

from leveler.analysis.suggest import controller_tf, loop_margins, plant_tf
from leveler.settings import load_config
from leveler.sim.params import PlantParams

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def default():  # type: ignore[no-untyped-def]
    cfg, _ = load_config(REPO / "config" / "sim.toml")
    return cfg


def _gains(cfg) -> tuple[float, float, float, float]:  # type: ignore[no-untyped-def]
    c = cfg.controller
    return c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m, c.d_filter_tau_s


def test_nominal_margins_and_loop_gain(default) -> None:  # type: ignore[no-untyped-def]
    m = loop_margins(default.plant, default.loop.rate_hz, *_gains(default))
    assert m.stable
    assert m.gain_margin_db >= 6.0
    assert m.phase_margin_deg >= 40.0
    # Goals: 200x at 0.1 mHz and 10x up to 10 mHz in loop; 2x of the sensor floor out of
    # loop needs ~30x at the cooler's harmonics below 10 mHz.
    assert m.suppression_at[1e-4] >= 200
    assert m.suppression_at[1e-2] >= 30


def _vary(p: PlantParams, mgl: float, inertia: float, damping: float) -> PlantParams:
    pe = p.pendulum
    pe = dataclasses.replace(pe, mass_kg=pe.mass_kg * mgl, inertia_kgm2=pe.inertia_kgm2 * inertia,
                             damping_nms_per_rad=pe.damping_nms_per_rad * damping)
    return dataclasses.replace(p, pendulum=pe)


def _stability_margin(loop: control.TransferFunction, rate_hz: float) -> float:
    """min |1 + L| over frequency: the distance of the Nyquist curve from -1."""
    f = np.geomspace(1e-6, rate_hz / 2 * (1 - 1e-9), 20_000)
    return float(np.min(np.abs(1 + loop(np.exp(2j * np.pi * f / rate_hz)))))


def _worst_over_stands(cfg, gains: tuple[float, float, float, float]) -> float:  # type: ignore[no-untyped-def]
    """Smallest |1 + L| over the corners of the plant's uncertainty; 0 if one is unstable."""
    rate = cfg.loop.rate_hz
    worst = np.inf
    for mgl, inertia, damping in itertools.product((0.95, 1.0, 1.03), (0.8, 1.0, 1.25),
                                                   (0.5, 1.0, 2.0)):
        plant = _vary(cfg.plant, mgl, inertia, damping)
        loop = controller_tf(*gains, rate) * plant_tf(plant, rate)
        if not np.all(np.abs(control.feedback(loop, 1).poles()) < 1):
            return 0.0
        worst = min(worst, _stability_margin(loop, rate))
    return worst


def test_robust_to_a_stand_that_differs_from_the_model(default) -> None:  # type: ignore[no-untyped-def]
    """m g L_cm -5..+3 % (N from 6.3 to 13: the amplification rests on k - m g L_cm),
    inertia -20..+25 %, damping x0.5..x2: every corner stable, |1 + L| >= 0.4 (>= 4.4 dB of
    gain margin at any phase). The D term damps the resonance rather than cancelling it,
    which is why this holds; the integral-only tuning before it fails the same check."""
    assert _worst_over_stands(default, _gains(default)) >= 0.4
    assert _worst_over_stands(default, (0.0, 7.0e5, 0.0, 0.0)) < 0.2
