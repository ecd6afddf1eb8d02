"""Gain suggestions: the model against the simulator and the PID, and the design's promises."""

from __future__ import annotations

import tomllib
from pathlib import Path

import control
import numpy as np
import pytest
from figure_capture import legend_texts, saved_figures

from leveler.analysis.suggest import (
    MIN_GAIN_MARGIN_DB,
    SUPPRESSION_HZ,
    Suggestion,
    controller_tf,
    loop_margins,
    plant_tf,
    plot,
    report,
    suggest,
)
from leveler.loop.pid import PID, PIDConfig, PIDGains
from leveler.sim.params import PendulumParams, PlantParams
from leveler.sim.plant import Plant
from leveler.typed_config import build

RATE_HZ = 10.0
DEFAULT_KI = 7.0e5  # config/sim.toml: a pure integrator
Loop = tuple[PlantParams, Suggestion]


def quiet_plant() -> PlantParams:
    """The default stand without disturbances, noise or drift, behind a 32-bit ADC, and
    with a piezo amplifier that slews 1e7 times faster: its ramp within a step
    (`slew_lag_v`, quadratic in the change) is the one part of the plant no transfer
    function holds, 5 % of a 1 V step's first sample at 100 V/s."""
    return build(PlantParams, {
        "platform": {"initial_tilt_rad": 0.0},
        "piezo": {"slew_v_per_s": 1.0e9},
        "thermal": {"random_walk_k_per_sqrt_s": 0.0, "daily_amplitude_k": 0.0},
        "cooler": {"peak_to_peak_rad": 0.0},
        "sensor": {"noise_m_per_rthz": 0.0, "drift_m_per_sqrt_s": 0.0, "adc_bits": 32},
    })


@pytest.mark.parametrize("pendulum", [PendulumParams(),
                                      PendulumParams(flexure_stiffness_nm_per_rad=0.13)])
def test_plant_dc_gain_and_resonance(pendulum: PendulumParams) -> None:
    params = PlantParams(pendulum=pendulum)
    p = plant_tf(params, RATE_HZ)
    expected = (params.piezo.gain_m_per_v / params.platform.support_spacing_m
                * pendulum.amplification * pendulum.sensor_arm_m)
    assert float(p.dcgain()) == pytest.approx(expected, rel=1e-6)
    f = np.linspace(0.05, 4.9, 100_000)
    mag = np.abs(p(np.exp(2j * np.pi * f / RATE_HZ)))
    assert f[mag.argmax()] == pytest.approx(pendulum.natural_frequency_hz, rel=2e-3)


def test_plant_step_matches_the_simulator() -> None:
    """One volt more from n = 0: the first reading to see it is y[1], as in the model."""
    params = quiet_plant()
    plant = Plant(params, 1.0 / RATE_HZ)
    v = params.piezo.ref_v + 1.0
    sim = []
    for _ in range(200):
        sim.append(plant.measure()[1])
        plant.command(v)
        plant.step()
    model = control.step_response(plant_tf(params, RATE_HZ), T=np.arange(200) / RATE_HZ)
    y, want = np.asarray(sim) - sim[0], np.squeeze(model.outputs)
    np.testing.assert_allclose(y, want, rtol=0, atol=2 * params.sensor.lsb_m)
    # the test could tell a missing or extra sample
    assert np.abs(y[1:] - want[:-1]).max() > 20 * params.sensor.lsb_m
    assert np.abs(y[:-1] - want[1:]).max() > 20 * params.sensor.lsb_m


def test_closed_loop_model_matches_pid_and_simulator() -> None:
    """A setpoint step through leveler.loop.pid.PID and the Plant against the transfer functions.

    PID differentiates the measurement, so for a setpoint r the model is
    y = P (kp + I) / (1 + P (kp + I + D)) r: all three terms of controller_tf are pinned.
    """
    params = quiet_plant()
    kp, ki, kd, tau, r, n = 3.0e4, 9.0e5, 2.0e4, 0.5, 1.0e-7, 400
    assert loop_margins(params, RATE_HZ, kp, ki, kd, tau).stable
    pid = PID(PIDConfig(PIDGains(kp, ki, kd), 0.0, 150.0, d_filter_tau_s=tau))
    plant = Plant(params, 1.0 / RATE_HZ)
    pid.engage(plant.measure()[1], params.piezo.ref_v)
    pid.set_setpoint(r)
    sim = []
    for _ in range(n):
        y = plant.measure()[1]
        sim.append(y)
        plant.command(pid.update(y, 1.0 / RATE_HZ).command_v)
        plant.step()
    p = plant_tf(params, RATE_HZ)
    cl = (control.feedback(p, controller_tf(kp, ki, kd, tau, RATE_HZ))
          * controller_tf(kp, ki, 0.0, 0.0, RATE_HZ))
    model = r * np.squeeze(control.step_response(cl, T=np.arange(n) / RATE_HZ).outputs)
    np.testing.assert_allclose(sim, model, rtol=0, atol=1e-6 * r)
    assert sim[-1] > 0.9 * r  # it did follow the step


@pytest.fixture(scope="module")
def default_loop() -> Loop:
    params = PlantParams()
    return params, loop_margins(params, RATE_HZ, 0.0, DEFAULT_KI, 0.0, 0.5)


def test_the_default_integrator_crosses_near_10_mhz(default_loop: Loop) -> None:
    _, current = default_loop
    assert current.stable
    assert current.crossover_hz == pytest.approx(0.01, rel=0.05)


@pytest.mark.parametrize("pm", [45.0, 60.0, 89.0])
def test_suggest_meets_margins_and_beats_the_default(default_loop: Loop, pm: float) -> None:
    params, current = default_loop
    s = suggest(params, RATE_HZ, phase_margin_deg=pm)
    assert s.phase_margin_deg >= pm
    assert s.gain_margin_db >= MIN_GAIN_MARGIN_DB
    assert s.resonance_loop_gain <= 0.5
    assert s.stable
    # Independently of loop_margins: the closed-loop poles of C P.
    loop = controller_tf(s.kp_v_per_m, s.ki_v_per_m_s, 0.0, 0.0, RATE_HZ) * plant_tf(
        params, RATE_HZ)
    assert np.abs(control.feedback(loop, 1).poles()).max() < 1.0
    for f in SUPPRESSION_HZ:
        assert s.suppression_at[f] > 1.4 * current.suppression_at[f]


def test_a_phase_margin_above_the_integrators_is_met_with_a_pi_zero() -> None:
    s = suggest(PlantParams(), RATE_HZ, phase_margin_deg=90.5)
    assert s.kp_v_per_m > 0
    assert s.phase_margin_deg == pytest.approx(90.5, abs=3.0)
    assert s.resonance_loop_gain <= 0.5


def test_a_given_bandwidth_is_the_crossover() -> None:
    s = suggest(PlantParams(), RATE_HZ, bandwidth_hz=0.012)
    assert s.crossover_hz == pytest.approx(0.012, rel=0.02)
    assert s.stable


@pytest.mark.parametrize("bandwidth_hz", [1.0, 0.05])
def test_an_impossible_bandwidth_names_the_resonance(bandwidth_hz: float) -> None:
    with pytest.raises(ValueError, match=r"resonance at 0\.712 Hz.*highest .* is 0\.017"):
        suggest(PlantParams(), RATE_HZ, bandwidth_hz=bandwidth_hz)


def test_report_config_lines_are_the_gains(default_loop: Loop) -> None:
    params, current = default_loop
    s = suggest(params, RATE_HZ)
    text = report(s, current)
    block = text.split("[controller]\n", 1)[1].split("\n\n", 1)[0]
    assert tomllib.loads(block) == {"kp_v_per_m": s.kp_v_per_m, "ki_v_per_m_s": s.ki_v_per_m_s,
                                    "kd_v_s_per_m": s.kd_v_s_per_m}
    assert "current" in text and "10 mHz" in text


def test_plot_writes_a_png(tmp_path: Path, default_loop: Loop,
                           monkeypatch: pytest.MonkeyPatch) -> None:
    figures = saved_figures(monkeypatch)
    params, current = default_loop
    out = plot(params, RATE_HZ, current, tmp_path / "loop.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # What it is in the title, a unit on every axis (L is V/V), the gains in 7×10⁵ form,
    # the suppression frequencies named, the crossover a point that crosses no name.
    [fig] = figures
    mag, phase, nyq = fig.axes
    assert fig.get_suptitle().startswith("Loop gain L = controller [V/m] × plant [m/V]")
    for ax in (mag, phase, nyq):
        assert ax.get_ylabel().endswith("]"), ax.get_ylabel()
    assert phase.get_xlabel() == "Frequency [Hz]" and nyq.get_xlabel() == "Re L [V/V]"
    assert "ki 7×10$^{5}$ V/(m s)" in mag.get_title()
    assert [t.get_text() for t in mag.texts] == ["0.1 mHz", "1 mHz", "10 mHz"]
    assert any(t.startswith("crossover ") for t in legend_texts(fig))
    vertical = [ln for ln in mag.get_lines() if len(set(ln.get_xdata())) == 1
                and len(ln.get_xdata()) == 2]
    assert [ln.get_xdata()[0] for ln in vertical] == list(SUPPRESSION_HZ)
