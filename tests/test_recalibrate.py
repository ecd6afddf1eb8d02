"""Baseline recalibration (issue 17, parts 1-2): an in-tolerance calibration offset is a
recalibration with its pull, not a missing effect; a sensor path beyond tolerance is held
at nominal and the sensor gain error found among the candidates; degenerate fits are no
evidence."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO

from leveler.analysis.diagnose import _recalibrated, diagnose, warmup_samples
from leveler.analysis.predict import Predictor, load_measured
from leveler.analysis.synthetic import make_measured
from leveler.cli.main import main
from leveler.settings import Config, load_config
from leveler.sim.effects import (
    ActuatorDelay,
    ActuatorHysteresis,
    AdcQuantization,
    ExtraResonance,
    PeriodicDisturbance,
    SensorGainError,
    Signals,
    TemperatureCoupling,
)
from leveler.sim.params import PlantParams
from leveler.typed_config import ConfigError, build

# The truth's offsets: each within about 1.5 sigma of config/sim.toml's tolerances.
PIEZO, ARM, F0 = 1.045, 0.965, 1.02


def _offset(cfg: Config) -> Config:
    p = cfg.plant
    pe = p.pendulum
    return dataclasses.replace(cfg, plant=dataclasses.replace(
        p, piezo=dataclasses.replace(p.piezo, gain_m_per_v=p.piezo.gain_m_per_v * PIEZO),
        pendulum=dataclasses.replace(pe, sensor_arm_m=pe.sensor_arm_m * ARM,
                                     inertia_kgm2=pe.inertia_kgm2 / F0**2)))


@pytest.fixture(scope="module")
def offset_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Modulated 3 h logs of a stand with in-tolerance offsets, with and without a sensor
    gain error far beyond its tolerance; each log carries the nominal model."""
    cfg, text = load_config(REPO / "config" / "sim.toml")
    out = {}
    for name, fx in (("offsets", None), ("gain", SensorGainError(gain_error=0.25))):
        path = tmp_path_factory.mktemp(name) / f"{name}.mcap"
        make_measured(path, _offset(cfg), text, fx, duration_s=3 * 3600, seed=11,
                      dither_v=4.0, dither_period_s=120.0)
        out[name] = path
    return out


def test_in_tolerance_offsets_are_a_recalibration_not_a_missing_effect(
        offset_logs: dict[str, Path]) -> None:
    d = diagnose(load_measured(offset_logs["offsets"]))
    assert d.effects == [], [f.effect for f in d.effects]  # it was "actuator hysteresis"
    assert d.recalibration is not None
    off = d.recalibration.offset
    # What the log shows is pinned: the product of the two paths (the modulation's
    # response), the sensor path times the cooler's level (its lines; the truth's cooler
    # is nominal) and the resonance. How each product splits is the priors' to say, so
    # the single paths are only asked to lie within their posterior 2 sigma.
    assert abs((1 + off["sensor_path"]) * (1 + off["actuator_path"]) - ARM * PIEZO) < 0.01
    assert abs((1 + off["sensor_path"]) * (1 + off["cooler_amplitude"]) - ARM) < 0.01
    post = d.recalibration.sigma_post
    assert abs(off["sensor_path"] - (ARM - 1)) < 2 * post["sensor_path"]
    assert abs(off["actuator_path"] - (PIEZO - 1)) < 2 * post["actuator_path"]
    assert abs(off["natural_frequency"] - (F0 - 1)) < 0.002
    assert all(abs(d.recalibration.pull(k.name)) < 2 for k in d.recalibration.knobs)
    assert d.recalibration.disputed == []


def test_a_found_converter_leaves_the_knobs_where_they_were(
        offset_logs: dict[str, Path]) -> None:
    """A converter in the model (found, or stated) puts a staircase between the knobs and
    the reading, whose finite differences are steps, not slopes: the knobs ran to -9 and
    +12 sigma on an independent log, all were held at nominal and its gap stayed at 105
    of 111 nm. The knobs are fitted on the model without it (`replayable`), and the
    model they give keeps it."""
    meas = load_measured(offset_logs["offsets"])
    plant = meas.config.plant
    coarse = dataclasses.replace(plant, effects=plant.effects.with_effect(
        AdcQuantization(step_m=2e-8, replay_noise_m=2e-9)))
    whole = slice(warmup_samples(meas, Predictor(plant, meas)), None)
    without = _recalibrated(meas, plant, whole, True)[1]
    pred, with_it, _ = _recalibrated(meas, coarse, whole, True)
    assert without is not None and with_it is not None
    assert with_it.disputed == [] and with_it.held == ()
    for k in without.knobs:
        assert abs(with_it.pull(k.name) - without.pull(k.name)) < 0.1, k.name
    assert pred.effects.adc_quantization == coarse.effects.adc_quantization


def test_the_report_gives_each_recalibrated_value_with_its_pull(
        offset_logs: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    report = offset_logs["offsets"].parent / "report"
    assert main(["diagnose", str(offset_logs["offsets"]), "--json", "--report",
                 str(report)]) == 0
    out = json.loads(capsys.readouterr().out)
    text = (report / "summary.md").read_text()  # was empty when nothing was found
    assert "recalibrated within the model's stated tolerances:" in text
    assert "pendulum resonance frequency: +2.0" in text and "pull +1.0 sigma" in text
    assert "no missing effect found" in text
    assert out["model_out"] is None
    assert not offset_logs["offsets"].with_suffix(".fitted.toml").exists()
    assert set(out["recalibration"]) == {"sensor_path", "actuator_path", "natural_frequency",
                                         "q", "thermal_tilt", "cooler_amplitude"}
    assert out["recalibration"]["natural_frequency"]["sigma_rel"] == 0.02


@pytest.mark.slow  # 23 s; make test-slow
def test_a_sensor_path_far_beyond_its_tolerance_is_the_sensor_gain_error(
        offset_logs: dict[str, Path], tmp_path: Path) -> None:
    model_out = tmp_path / "fitted.toml"
    assert main(["diagnose", str(offset_logs["gain"]), "--model-out", str(model_out)]) == 0
    fitted, _ = load_config(model_out)
    g = fitted.plant.effects.sensor_gain_error
    assert g is not None and g.gain_error > 0.15
    nominal, _ = load_config(REPO / "config" / "sim.toml")
    # The reading's whole scale, the effect times what is left recalibrated in tolerance
    # (written in place, like the resonance), is what the log pins in products: with the
    # actuator path (the modulation's response; truth 1.25 x 0.965 x 1.045) and with the
    # cooler's level (its lines; truth 1.25 x 0.965 x 1).
    arm = fitted.plant.pendulum.sensor_arm_m / nominal.plant.pendulum.sensor_arm_m
    piezo = fitted.plant.piezo.gain_m_per_v / nominal.plant.piezo.gain_m_per_v
    cooler = fitted.plant.cooler.peak_to_peak_rad / nominal.plant.cooler.peak_to_peak_rad
    assert abs(arm - 1) < 2 * nominal.plant.uncertainty.sensor_path_rel  # within tolerance
    assert abs((1 + g.gain_error) * arm * piezo - 1.25 * ARM * PIEZO) < 0.02
    assert abs((1 + g.gain_error) * arm * cooler - 1.25 * ARM) < 0.02
    assert fitted.plant.pendulum.inertia_kgm2 != nominal.plant.pendulum.inertia_kgm2


def test_a_model_that_states_no_tolerance_is_not_recalibrated(tmp_path: Path) -> None:
    cfg, text = load_config(REPO / "config" / "sim.toml")
    bare = dataclasses.replace(cfg, plant=dataclasses.replace(
        cfg.plant, uncertainty=type(cfg.plant.uncertainty)()))
    log = tmp_path / "bare.mcap"
    cut = text[:text.index("[plant.uncertainty]")]
    make_measured(log, bare, cut, None, duration_s=3600, seed=2)
    d = diagnose(load_measured(log))
    assert d.recalibration is None and d.effects == []


def test_tolerances_are_checked_like_every_other_key() -> None:
    with pytest.raises(ConfigError, match=r"plant\.uncertainty\.piezo_gain_rel"):
        build(Config, {"plant": {"uncertainty": {"piezo_gain_rel": -0.01}}})
    with pytest.raises(ConfigError, match=r"plant\.uncertainty\.sensor_gain"):
        build(Config, {"plant": {"uncertainty": {"sensor_gain": 0.01}}})  # unit suffix missing
    u = build(PlantParams, {"uncertainty": {"sensor_arm_rel": 0.03, "sensor_gain_rel": 0.04,
                                            "piezo_gain_rel": 0.03,
                                            "support_spacing_rel": 0.04}}).uncertainty
    assert u.sensor_path_rel == pytest.approx(0.05) and u.actuator_path_rel == pytest.approx(0.05)


class _Spread:
    """What a degenerate-fit check reads: the command, a triangle `spread_v` peak to peak."""

    def __init__(self, spread_v: float) -> None:
        self.spread_v = spread_v

    def command_spread_v(self) -> float:
        return self.spread_v

    def command_blocks_v(self) -> list[np.ndarray]:
        t = self.sig.t_s
        return [75.0 + self.spread_v / 2 * (2 * np.abs(2 * (t / 60.0 % 1) - 1) - 1)]

    def block_gains(self, fx: object) -> list[float]:
        return [1.0]

    @property
    def sig(self) -> Signals:  # a 600 s log
        return Signals(np.arange(0.0, 600.0, 0.1), 0.1, None)

    def modulation_hz(self) -> float:
        return 1.0 / 60.0

    def modulation_span_s(self) -> float:  # ten cycles: lines resolved to 1/600 Hz
        return 600.0

    def cooler_hz(self) -> float:
        return 1.0 / 300.0

    pull_limit = 3.0

    def sensor_path_pull(self, gain_error: float) -> float:  # recalibrated +1 %, sigma 4.1 %
        return (1.01 * (1 + gain_error) - 1) / 0.041

    def natural_frequency_hz(self) -> float:
        return 0.73


class _SquareThenLoop(_Spread):
    """A 3.3 V square modulation block, then a closed-loop block whose command rises
    25 V (half a day's thermal cycle) with 0.2 V of noise; the fit's evidence in the
    blocks `gains`."""

    def __init__(self, gains: list[float]) -> None:
        super().__init__(31.0)
        self.gains = gains

    def command_blocks_v(self) -> list[np.ndarray]:
        t = np.arange(0.0, 3600.0, 0.1)
        square = 75.0 + 3.3 * np.sign(np.sin(2 * np.pi * t / 200.0))
        loop = (75.0 - 12.5 * np.cos(np.pi * t / 3600.0)
                + np.random.default_rng(3).normal(0.0, 0.2, t.size))
        return [square, loop]

    def block_gains(self, fx: object) -> list[float]:
        return self.gains


def test_a_play_is_judged_where_its_evidence_lies() -> None:
    """Over a square modulation every play is a gain (it turns at each reversal in phase
    with it, or never): a fit whose evidence all lies there is a gain that differs between
    the parts of the log (a day's null log of the independent generator, evidence 1,348).
    On the loop's noisy command a narrow play turns on every reversal: a loop."""
    assert "a gain, not hysteresis" in ActuatorHysteresis(
        width_v=0.1, fraction=-0.012).degenerate(_SquareThenLoop([2544.0, 0.0]))  # type: ignore[arg-type]
    # A 3.4 V play needs reversals of 6.8 V, which neither block has: it never turns.
    assert "turns 0 times" in ActuatorHysteresis(
        width_v=3.4, fraction=-0.012).degenerate(_SquareThenLoop([2544.0, 0.0]))  # type: ignore[arg-type]
    assert ActuatorHysteresis(width_v=0.1, fraction=0.1).degenerate(
        _SquareThenLoop([0.0, 300.0])) == ""  # type: ignore[arg-type]


def test_degenerate_fits_are_no_evidence() -> None:
    """A play wider than the command's reversals never turns (a gain or a lag); a fit
    pinned at a bound wanted something the form does not have."""
    ev = _Spread(8.0)
    assert ActuatorHysteresis(width_v=0.5, fraction=0.3).degenerate(ev) == ""  # type: ignore[arg-type]
    assert "not below the command's spread" in ActuatorHysteresis(
        width_v=16.5, fraction=0.3).degenerate(ev)  # type: ignore[arg-type]
    # A play that needs a reversal of 2 x 4.5 V never turns on an 8 V triangle: what it
    # adds is a ramp and an offset; at 2 V it turns at every reversal and is a loop.
    assert "turns 0 times" in ActuatorHysteresis(
        width_v=4.5, fraction=0.3).degenerate(ev)  # type: ignore[arg-type]
    assert ActuatorHysteresis(width_v=2.0, fraction=0.3).degenerate(ev) == ""  # type: ignore[arg-type]
    # A loop's command that drifts 25 V through a day's half cycle with 0.2 V of noise:
    # a 1 V play turns once, at the start, and shows no loop.
    drift = _SquareThenLoop([0.0, 1.0])
    drift.command_blocks_v = lambda: _SquareThenLoop.command_blocks_v(drift)[1:]  # type: ignore[method-assign]
    assert "turns 1 times" in ActuatorHysteresis(width_v=1.0, fraction=0.05).degenerate(drift)  # type: ignore[arg-type]
    assert "fraction = 1 sits at its bound" in ActuatorHysteresis(
        width_v=0.5, fraction=1.0).degenerate(ev)  # type: ignore[arg-type]
    # A loop the wrong way round (the stroke leading its command), with one play or two:
    # no piezo runs it.
    assert "the wrong way round" in ActuatorHysteresis(
        width_v=0.5, fraction=-0.3).degenerate(ev)  # type: ignore[arg-type]
    assert "the wrong way round" in ActuatorHysteresis(
        width_v=0.5, fraction=-0.05, width2_v=2.0, weight2=0.5).degenerate(ev)  # type: ignore[arg-type]
    assert "sits at its bound" in SensorGainError(gain_error=-0.5).degenerate(ev)  # type: ignore[arg-type]
    assert SensorGainError(gain_error=0.2).degenerate(ev) == ""  # type: ignore[arg-type]
    # Reading half or double is the range, symmetric in the ratio: +60 % is no bound.
    assert SensorGainError(gain_error=0.6).degenerate(ev) == ""  # type: ignore[arg-type]
    assert "sits at its bound" in SensorGainError(gain_error=1.0).degenerate(ev)  # type: ignore[arg-type]
    # A periodic tilt on a harmonic of the modulation is the actuator's response to it.
    assert "the actuator's response" in PeriodicDisturbance(period_s=60.0 / 7).degenerate(ev)  # type: ignore[arg-type]
    assert PeriodicDisturbance(period_s=60.0 / 7 * 1.02).degenerate(ev) == ""  # type: ignore[arg-type]
    # ... within the modulation's resolution of it, too: 1.2 % off is 1/720 Hz off the
    # 7th harmonic, and ten cycles tell lines apart only 1/600 Hz apart.
    near = PeriodicDisturbance(period_s=60.0 / 7 * 1.012).degenerate(ev)  # type: ignore[arg-type]
    assert "the actuator's response" in near
    assert PeriodicDisturbance(period_s=97.0).degenerate(ev) == ""  # type: ignore[arg-type]
    # ... and one on a harmonic of the modelled cooler is that cooler's own waveform.
    assert "modelled cooler" in PeriodicDisturbance(period_s=150.2).degenerate(ev)  # type: ignore[arg-type]
    # A gain error that leaves the sensor path within the accepted pull is a calibration.
    assert "a calibration, not an effect" in SensorGainError(gain_error=-0.05).degenerate(ev)  # type: ignore[arg-type]
    assert SensorGainError(gain_error=-0.15).degenerate(ev) == ""  # type: ignore[arg-type]
    # A delay under a twentieth of a sample is sampling and hold.
    assert "sampling and hold" in ActuatorDelay(delay_s=0.003).degenerate(ev)  # type: ignore[arg-type]
    assert ActuatorDelay(delay_s=0.04).degenerate(ev) == ""  # type: ignore[arg-type]
    # A mode whose band reaches near the pendulum's resonance (0.73 Hz) is its f0 or Q.
    near = ExtraResonance(frequency_hz=0.885, q=8.6, gain=-0.97).degenerate(ev)  # type: ignore[arg-type]
    assert "its frequency or Q, not a mode" in near
    assert ExtraResonance(frequency_hz=0.9, q=40.0, gain=-0.5).degenerate(ev) == ""  # type: ignore[arg-type]
    assert ExtraResonance(frequency_hz=1.6, q=8.6, gain=0.2).degenerate(ev) == ""  # type: ignore[arg-type]
    # A lag over 3x the log is a trend (and its start state a free straight line).
    assert TemperatureCoupling(lag_s=1500.0).degenerate(ev) == ""  # type: ignore[arg-type]
    for lags in ({"lag_s": 2000.0}, {"lag_s": 300.0, "lag2_s": 2000.0}):
        assert "a trend, not a coupling" in TemperatureCoupling(**lags).degenerate(ev)  # type: ignore[arg-type]


def test_an_open_loop_modulation_is_all_excitation() -> None:
    """While the loop is open every move of the voltage is excitation (it used to count only
    the sample-to-sample increments, so a modulated open-loop part looked unexcited)."""
    import numpy as np

    from leveler.analysis.predict import Measured, excitation_v
    from leveler.sim.effects import Signals

    cfg, _ = load_config(REPO / "config" / "sim.toml")
    n = 2000
    t = np.arange(n) * 0.1
    square = 75.0 + 5.0 * np.sign(np.sin(2 * np.pi * t / 60.0) + 1e-9)
    engaged = t >= 150.0
    u = np.where(engaged, square[1499], square)
    c = cfg.controller
    meas = Measured("x", Signals(t, 0.1), u, np.zeros(n), cfg, "", "", 0,
                    (c.kp_v_per_m, c.ki_v_per_m_s, c.kd_v_s_per_m), c, engaged)
    exc = excitation_v(meas)
    assert exc is not None
    assert np.ptp(exc[:1500]) == pytest.approx(10.0)  # the whole swing, not 10 V spikes
    assert np.count_nonzero(np.abs(exc[:1500]) > 1.0) > 500  # every low half, not 5 edges
    assert np.max(np.abs(exc[1500:])) < 1e-9  # closed, readings at 0: the PID holds


def test_a_cooler_stronger_than_told_is_its_level_not_a_periodic_disturbance(
        tmp_path: Path) -> None:
    """A disturbance's level drifts from day to day: the cooler 25 % stronger than the
    model says, with nothing else missing, named "periodic disturbance" at the cooler's
    own period in a third of the independent generator's null logs (this log, told the
    level exactly: a 299.95 s sine). Its level is now a knob within
    `cooler_amplitude_rel`, refitted with every candidate."""
    cfg, text = load_config(REPO / "config" / "sim.toml")
    co = cfg.plant.cooler
    strong = dataclasses.replace(cfg, plant=dataclasses.replace(
        cfg.plant, cooler=dataclasses.replace(co, peak_to_peak_rad=1.25 * co.peak_to_peak_rad)))
    log = tmp_path / "strong.mcap"
    make_measured(log, strong, text, None, duration_s=3 * 3600, seed=13)
    d = diagnose(load_measured(log))
    assert d.effects == [], [f.effect for f in d.effects]
    assert d.recalibration is not None
    assert abs(d.recalibration.offset["cooler_amplitude"] - 0.25) < 0.05  # 0.229 measured
