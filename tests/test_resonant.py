"""Resonant (internal-model) terms against a periodic disturbance: the running terms
(leveler.loop.resonant, in the PID) against their transfer function, switching them
bumplessly, the daemon's numpy stability check and the design's margins against
python-control, the designed terms stable and within margins over the model's tolerances,
and the cooler's lines gone from the simulated stand's tilt."""

from __future__ import annotations

import copy
import dataclasses
import math

import control
import numpy as np
import pytest

from leveler.analysis import periodic
from leveler.analysis.stability import closed_loop_matrix, predicted_instability
from leveler.analysis.suggest import _response, plant_tf
from leveler.daemon.protocol import ProtocolError, tune_args
from leveler.loop.pid import PID, ControllerConfig
from leveler.loop.resonant import PeriodicTerms, Resonators
from leveler.settings import load_config
from leveler.sim.effects import EffectsParams, PeriodicDisturbance
from leveler.virtual import run_virtual

from conftest import REPO  # isort: skip

CFG = load_config(REPO / "config" / "sim.toml")[0]
RATE = CFG.loop.rate_hz


@pytest.fixture(scope="module")
def designed() -> ControllerConfig:
    d = periodic.named_disturbance(CFG.plant)
    assert d is not None and d.source == "[plant.cooler]" and d.period_s == 300.0
    terms = periodic.design(CFG.plant, RATE, CFG.controller, d.period_s)
    return dataclasses.replace(CFG.controller, periodic_period_s=terms.period_s,
                               periodic_gains_v_per_m_s=terms.gains_v_per_m_s,
                               periodic_phases_rad=terms.phases_rad)


def test_the_running_terms_are_their_transfer_function() -> None:
    terms = PeriodicTerms(300.0, (2e6, 1e6, 5e5), (0.3, -1.2, 2.0), radius=0.999)
    res = Resonators(terms)
    e = np.random.default_rng(1).standard_normal(3000) * 1e-9
    out = []
    for x in e:
        out.append(res.output_v())
        res.advance(float(x), 1 / RATE)
    c = dataclasses.replace(CFG.controller, kp_v_per_m=0.0, ki_v_per_m_s=0.0, kd_v_s_per_m=0.0,
                            periodic_period_s=300.0, periodic_gains_v_per_m_s=(2e6, 1e6, 5e5),
                            periodic_phases_rad=(0.3, -1.2, 2.0), periodic_radius=0.999)
    # term by term: their sum as one transfer function loses its poles near z = 1 to rounding
    ref = sum(control.forced_response(tf, U=e).outputs
              for tf in periodic.controller_parts(c, RATE)[1:])
    assert np.max(np.abs(np.asarray(out) - ref)) < 1e-9 * np.max(np.abs(ref))
    assert np.max(np.abs(ref)) > 0


def test_switching_terms_on_and_off_is_bumpless(designed: ControllerConfig) -> None:
    """The update after a switch gives what it would have without the switch (on: the new
    terms start at rest), or moves by far less than the terms were adding (off: their
    output moves into the integral)."""
    pid = PID(CFG.controller.pid_config(), initial_output_v=75.0)
    pid.engage(1e-9, 75.0)
    rng = np.random.default_rng(2)
    for x in rng.standard_normal(200) * 2e-9:
        pid.update(float(x), 1 / RATE)
    twin = copy.deepcopy(pid)
    pid.set_periodic(designed.periodic_terms())
    assert pid.update(1e-9, 1 / RATE).command_v == twin.update(1e-9, 1 / RATE).command_v
    for x in rng.standard_normal(3000) * 2e-9:
        pid.update(float(x), 1 / RATE)
    assert pid._res is not None
    adding = pid._res.output_v()
    assert abs(adding) > 1e-3  # the terms took part
    twin = copy.deepcopy(pid)
    pid.set_periodic(None)
    jump = pid.update(1e-9, 1 / RATE).command_v - twin.update(1e-9, 1 / RATE).command_v
    assert abs(jump) < 0.05 * abs(adding), (jump, adding)


def test_the_daemons_check_finds_python_controls_poles(designed: ControllerConfig) -> None:
    """The numpy closed-loop matrix with resonant terms has python-control's poles (its
    state-space feedback: a transfer function of this order loses them to rounding), and a
    term with its phase turned half a turn is called unstable."""
    c = designed
    terms = c.periodic_terms()
    m = closed_loop_matrix(CFG.plant, RATE, c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m,
                           c.d_filter_tau_s, terms)
    parts = periodic.controller_parts(c, RATE)
    ctrl = control.ss(parts[0])
    for part in parts[1:]:
        ctrl = control.parallel(ctrl, control.ss(part))
    closed = control.feedback(control.series(ctrl, control.ss(plant_tf(CFG.plant, RATE))), 1)
    ours = np.sort_complex(np.linalg.eigvals(m))
    ref = np.sort_complex(np.linalg.eigvals(closed.A))
    assert len(ours) == len(ref)
    assert abs(np.max(np.abs(ours)) - np.max(np.abs(ref))) < 1e-9
    assert np.max(np.abs(ours)) < 1
    assert predicted_instability(CFG.plant, RATE, c.kp_v_per_m, c.ki_v_per_m_s,
                                 c.kd_v_s_per_m, c.d_filter_tau_s, terms) is None
    flipped = dataclasses.replace(terms, phases_rad=tuple(p + math.pi for p in terms.phases_rad))
    why = predicted_instability(CFG.plant, RATE, c.kp_v_per_m, c.ki_v_per_m_s,
                                c.kd_v_s_per_m, c.d_filter_tau_s, flipped)
    assert why is not None and "resonant terms at the harmonics of 300 s" in why


def test_margins_are_python_controls() -> None:
    """periodic.margins reads the same crossings python-control's stability_margins does."""
    f = np.geomspace(1e-6, RATE / 2 * (1 - 1e-9), 6000)
    c = CFG.controller
    for kd in (c.kd_v_s_per_m, 0.0):
        cc = dataclasses.replace(c, kd_v_s_per_m=kd, ki_v_per_m_s=c.ki_v_per_m_s if kd else 7e5)
        loop = (_response(periodic.controller_parts(cc, RATE)[0], f)
                * _response(plant_tf(CFG.plant, RATE), f))
        gm, pm = periodic.margins(loop)
        ref_gm, ref_pm, *_ = control.stability_margins(
            control.FrequencyResponseData(loop, 2 * np.pi * f))
        assert gm == pytest.approx(20 * math.log10(ref_gm), abs=0.05)
        assert pm == pytest.approx(ref_pm, abs=0.2)


def test_designed_terms_keep_the_margins_over_the_tolerances(designed: ControllerConfig) -> None:
    check = periodic.check(CFG.plant, RATE, designed)
    assert check.corners == 17  # nominal + 2^4 corners of the dynamic tolerances
    assert check.stable and check.ok, check
    assert check.gain_margin_db >= 6.0 and check.phase_margin_deg >= 40.0
    # Too fast a term (settling within a tenth of a period at every harmonic) is caught.
    greedy = periodic.design(CFG.plant, RATE, CFG.controller, 300.0, beta_rel=20.0)
    c = dataclasses.replace(designed, periodic_gains_v_per_m_s=greedy.gains_v_per_m_s,
                            periodic_phases_rad=greedy.phases_rad)
    greedy_check = periodic.check(CFG.plant, RATE, c)
    assert not greedy_check.ok
    assert periodic.refusal(greedy_check, periodic.check(CFG.plant, RATE, CFG.controller))
    assert periodic.refusal(check, periodic.check(CFG.plant, RATE, CFG.controller)) == ""


def test_a_model_names_its_periodic_disturbance() -> None:
    none = dataclasses.replace(CFG.plant, cooler=dataclasses.replace(CFG.plant.cooler,
                                                                     peak_to_peak_rad=0.0))
    assert periodic.named_disturbance(none) is None
    fitted = dataclasses.replace(none, effects=EffectsParams().with_effect(
        PeriodicDisturbance(period_s=187.0, peak_to_peak_rad=-2e-8)))
    d = periodic.named_disturbance(fitted)
    assert d is not None and d.period_s == 187.0 and d.peak_to_peak_rad == 2e-8
    assert d.source == "[plant.effects.periodic_disturbance]"
    with pytest.raises(ValueError, match="too little gain"):
        periodic.design(CFG.plant, RATE, CFG.controller, 1.0)


def test_the_cooler_lines_leave_the_tilt(designed: ControllerConfig) -> None:
    """6 h of the default stand: at the cooler's first three lines the true tilt stands
    well above the floor the sensor's noise and drift set, and with the terms on it is
    down to within 30 % of it; between the lines it does not rise by 20 %."""
    from leveler.analysis.spectral import asd_at

    with_terms = dataclasses.replace(CFG, controller=designed)
    runs = [run_virtual(c, 6 * 3600.0, 5, engaged=True) for c in (CFG, with_terms)]
    freqs = [h / 300.0 for h in (1, 2, 3)] + [4.5e-3, 8.3e-3]
    floor = asd_at(periodic.floor_tilt(CFG, len(runs[0].tilt_rad), 5), RATE, freqs)
    before, after = (asd_at(r.tilt_rad, RATE, freqs) / floor for r in runs)
    assert np.all(before[:3] > 1.5) and np.all(after[:3] < 1.3), (before, after)
    assert np.all(after[3:] < before[3:] * 1.2), (before, after)


def test_tune_carries_the_terms_and_refuses_bad_ones() -> None:
    values, _ = tune_args({"verb": "tune", "periodic_period_s": 300,
                           "periodic_gains_v_per_m_s": [1e6, 2], "periodic_phases_rad": [0, 1.5]})
    assert values == {"periodic_period_s": 300.0, "periodic_gains_v_per_m_s": (1e6, 2.0),
                      "periodic_phases_rad": (0.0, 1.5)}
    for bad in ({"periodic_gains_v_per_m_s": 1e6}, {"periodic_phases_rad": [True]},
                {"periodic_gains_v_per_m_s": [None]}, {"periodic_period_s": -1},
                {"periodic_gains_v_per_m_s": [1.0] * 65}, {"periodic_radius": "0.9"}):
        with pytest.raises(ProtocolError, match=next(iter(bad))):
            tune_args({"verb": "tune", **bad})
    with pytest.raises(ValueError, match="one phase per gain"):
        dataclasses.replace(CFG.controller, periodic_period_s=300.0,
                            periodic_gains_v_per_m_s=(1.0,), periodic_phases_rad=())
