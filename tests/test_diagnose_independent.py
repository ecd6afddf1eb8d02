"""`leveler diagnose` on logs it did not make: the independent generator (bench/independent,
written from the physics alone, with calibration offsets within 1-2 sigma, noise levels
off by 10-25 % and a start out of equilibrium in every log). Tuning seeds (101-126) only: the
untouched seeds are for `make bench-diagnose --untouched`. The full scoreboard is
bench/diagnose_score.py; these are the cases a change of this code must keep."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import REPO

from leveler.analysis.diagnose import Diagnosis, diagnose, make_blocks
from leveler.analysis.evidence import Evidence
from leveler.analysis.nuisance import Nuisance
from leveler.analysis.predict import Predictor, excitation_v, load_measured

sys.path.insert(0, str(REPO / "bench"))  # bench/ is no package
from independent.generator import generate


def _diagnose(tmp_path: Path, family: str | None, severity: str,
              seed: int = 101) -> tuple[Diagnosis, Any]:
    log = tmp_path / f"{family}-{severity}.mcap"
    truth = generate(family, severity, seed, log, hours=3.0, modulated=True,
                     nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    d = diagnose(load_measured(log))
    print(truth["params"], [str(f.effect) for f in d.effects])
    return d, truth["params"]


def _delay_alone_is_named(tmp_path: Path, severity: str, seed: int = 101) -> None:
    """The delay is the only effect named, its fit within 30 % of the truth."""
    d, truth = _diagnose(tmp_path, "actuator_delay", severity, seed)
    assert [f.effect.name for f in d.effects] == ["actuator_delay"]
    assert d.effects[0].effect.delay_s == pytest.approx(truth["delay_s"], rel=0.3)  # type: ignore[attr-defined]


@pytest.mark.slow  # 60 s; make test-slow
def test_a_delay_is_not_taken_for_a_mode_at_the_pendulum(tmp_path: Path) -> None:
    """A 44 ms delay shifts the phase at the pendulum's resonance; a mode of gain -0.97
    at 0.885 Hz (the pendulum's band) did the same and made it "ambiguous"."""
    _delay_alone_is_named(tmp_path, "strong")


@pytest.mark.slow  # 15 s
def test_a_weak_delay_under_a_square_fitted_short_is_still_a_delay(tmp_path: Path) -> None:
    """A 14.3 ms delay under a square modulation fits at 9.2 ms before the knobs are
    refitted with it (the first recalibration took part of it into the pendulum's
    frequency and Q): under a tenth of the 100 ms sample it was thrown out as sampling and
    hold, and nothing was named."""
    _delay_alone_is_named(tmp_path, "weak", seed=119)


@pytest.mark.slow  # 15 s
def test_a_weak_delay_under_a_triangle_passes_the_size_gate_of_an_exact_form(
        tmp_path: Path) -> None:
    """A 13.6 ms delay under a triangle modulation fits at 14.6 ms and holds out at 288,
    but moves the reading by 0.13 of the sensor noise: the size gate for the fitted bins
    (a fifth of it, for forms that approximate the physics) threw it out."""
    _delay_alone_is_named(tmp_path, "weak", seed=104)


@pytest.mark.slow  # 15 s
def test_a_mode_whose_whole_log_refit_rings_elsewhere_is_confirmed_as_held_out(
        tmp_path: Path) -> None:
    """A 1.66 Hz mode of Q 6.8 held out at 1.66 Hz, Q 9.8; refitted on the whole log it
    went to 1.36 Hz, Q 2.3 with its gain negative, and the log was "unexplained". A refit
    outside the mode's half-power band has moved off it (`ExtraResonance.moved_off`)."""
    d, truth = _diagnose(tmp_path, "extra_resonance", "strong", seed=106)
    assert [f.effect.name for f in d.effects] == ["extra_resonance"]
    mode = d.effects[0].effect
    assert mode.frequency_hz == pytest.approx(truth["frequency_hz"], rel=0.01)  # type: ignore[attr-defined]
    assert mode.gain > 0  # type: ignore[attr-defined]


@pytest.mark.slow  # 35 s; scored by bench-diagnose, its period by test_retrack's sawtooths
def test_a_jittered_sawtooth_is_named_and_the_gap_shrinks(tmp_path: Path) -> None:
    """A 184 s asymmetric sawtooth with 3.4 % period jitter, fitted as a sine: its
    refinement with the knobs had moved it to 187 s at a quarter of its size (gap 111 ->
    54 nm); a refinement is kept only where it does better on all bins."""
    d, truth = _diagnose(tmp_path, "periodic_disturbance", "strong")
    assert d.effects and d.effects[0].effect.name == "periodic_disturbance"
    assert d.effects[0].effect.period_s == pytest.approx(truth["period_s"], rel=0.05)  # type: ignore[attr-defined]
    assert d.gap_before["rms_m"] > 10 * d.gap_after["rms_m"]
    _cancel_on_the_log(tmp_path / "periodic_disturbance-strong.mcap", d)


def _cancel_on_the_log(log: Path, d: Diagnosis) -> None:
    """Resonant terms designed from the fitted model (what `tune --suggest --model` does)
    keep their margins over its tolerances, and the replay what-if of this log with them
    added brings the reading at the fitted fundamental down: the design holds on a
    disturbance of another form (asymmetric, jittered) than the model's."""
    import dataclasses

    from leveler.analysis import periodic
    from leveler.analysis.diagnose import warmup_samples
    from leveler.analysis.replay import what_if
    from leveler.analysis.spectral import asd_at

    meas = load_measured(log)
    assert d.params is not None and meas.controller is not None
    plant = dataclasses.replace(d.params, effects=d.model)
    named = periodic.named_disturbance(plant)
    assert named is not None and named.source.startswith("[plant.effects")
    rate = 1.0 / meas.dt_s
    terms = periodic.design(plant, rate, meas.controller, named.period_s)
    with_terms = dataclasses.replace(
        meas.controller, periodic_period_s=terms.period_s,
        periodic_gains_v_per_m_s=terms.gains_v_per_m_s, periodic_phases_rad=terms.phases_rad)
    # On this recalibrated stand (sensor path +9.8 %, Q +24 %) the PID alone has 4.8 dB
    # and 33 deg at its worst tolerance corner: the terms must not make that worse.
    ours, theirs = (periodic.check(plant, rate, c) for c in (with_terms, meas.controller))
    assert periodic.refusal(ours, theirs) == ""
    assert ours.gain_margin_db >= theirs.gain_margin_db - 0.1
    assert ours.phase_margin_deg >= theirs.phase_margin_deg - 1.0
    pred = Predictor(plant, meas, ringing=True)
    span = slice(warmup_samples(meas, pred), len(meas.y_m))
    f1 = [1.0 / terms.period_s]
    logged = asd_at(meas.y_m[span], rate, f1)
    replayed = asd_at(what_if(meas, pred, with_terms)[span], rate, f1)
    assert replayed[0] < logged[0] / 2, (logged, replayed)


@pytest.mark.slow  # 24 s; the bench-diagnose scoreboard scores this family
def test_a_coupling_within_the_thermal_path_is_still_a_coupling(tmp_path: Path) -> None:
    """A 2.6 urad/K coupling through 592 s and 1,978 s lags, a quarter of the thermal
    path's own: with its start state fitted by plain least squares on the raw residual
    its fits turned sign and a sensor drift was named; solved with the knobs, it is a
    coupling."""
    d, _ = _diagnose(tmp_path, "temperature_coupling", "weak")
    assert [f.effect.name for f in d.effects] == ["temperature_coupling"]


def test_a_refinement_that_agrees_with_what_held_out_is_kept(tmp_path: Path) -> None:  # 25 s
    """A medium coupling of -5.4 urad/K through 853 s and 355 s lags (tuning seed 104),
    against the thermal path's own +10: held out at -5.7 through 941 s and 316 s, the
    whole log's refit on one noise spectrum ran to -14.1, its refinement with the knobs
    came back to -5.4 but cost more on that refit's whitening, and nothing was named.
    The refinement agrees with both fits that held out: it is kept."""
    d, truth = _diagnose(tmp_path, "temperature_coupling", "medium", seed=104)
    assert [f.effect.name for f in d.effects] == ["temperature_coupling"]
    coupling = d.effects[0].effect
    assert coupling.tilt_per_kelvin_rad_per_k == pytest.approx(  # type: ignore[attr-defined]
        truth["tilt_per_kelvin_rad_per_k"], rel=0.25)
    assert d.gap_before["rms_m"] > 10 * d.gap_after["rms_m"]


def test_a_whole_log_refit_along_a_ridge_does_not_undo_what_held_out(tmp_path: Path) -> None:
    """A strong coupling of 13.8 urad/K through 398 s and 1,648 s lags (tuning seed 105),
    held out at 17 urad/K through about 2,000 s and 300 s on both parts. The whole log's
    refit, on one noise spectrum, ran along the size-lag ridge to 49 urad/K through
    7,768 s (1,683 better there, under 1 % of the held-out evidence): "the whole log's
    fit disagrees", nothing named, 182 nm left. With the families fitted in two
    processes (their rounding) the refinement no longer came back; now the refit is
    not taken and the coupling is named with the size that held out."""  # 40 s
    log = tmp_path / "coupling.mcap"
    truth = generate("temperature_coupling", "strong", 105, log, hours=3.0, modulated=True,
                     nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    d = diagnose(load_measured(log), jobs=2)
    assert [f.effect.name for f in d.effects] == ["temperature_coupling"]
    assert d.effects[0].effect.tilt_per_kelvin_rad_per_k == pytest.approx(  # type: ignore[attr-defined]
        truth["params"]["tilt_per_kelvin_rad_per_k"], rel=0.3)
    assert d.gap_before["rms_m"] > 30 * d.gap_after["rms_m"]


@pytest.mark.slow  # 45 s; make test-slow
def test_a_whole_log_refit_toward_a_trend_does_not_undo_what_held_out(tmp_path: Path) -> None:
    """A strong coupling of 16.2 urad/K through 585 s and 881 s lags (tuning seed 108),
    held out at 15.7 through 868 s and 585 s. The whole log's refit ran to 126 urad/K
    through 10,080 s and 122 s in this 10,800 s log, the lagged temperature become a
    trend; "the whole log's fit disagrees", and a drift that is not there was named
    (98 -> 51 nm). A lag that grows past half the log is a move toward a trend: not
    taken, and the coupling is named."""
    d, truth = _diagnose(tmp_path, "temperature_coupling", "strong", seed=108)
    assert [f.effect.name for f in d.effects] == ["temperature_coupling"]
    assert d.effects[0].effect.tilt_per_kelvin_rad_per_k == pytest.approx(  # type: ignore[attr-defined]
        truth["tilt_per_kelvin_rad_per_k"], rel=0.3)
    assert d.gap_before["rms_m"] > 10 * d.gap_after["rms_m"]


def test_a_gain_error_beyond_half_with_the_paths_held_is_named(tmp_path: Path) -> None:
    """A +31 % sensor gain error (tuning seed 103, strong) on a stand whose calibration
    was drawn high (sensor path +9.6 %, actuator +5.8 %): both paths are disputed and held
    at nominal, so the error takes the whole loop, +52 %. Its fit ran to the old +50 %
    bound, was rejected there, and a hysteresis was named (59.6 -> 59.1 nm). A sensor
    reading up to double is a gain error: named, and the held-out residual power comes
    down to the noise in every band it filled."""  # 25 s
    d, truth = _diagnose(tmp_path, "sensor_gain_error", "strong", seed=103)
    assert [f.effect.name for f in d.effects] == ["sensor_gain_error"]
    assert d.effects[0].effect.gain_error > truth["gain_error"]  # type: ignore[attr-defined]
    for band in ("1-10 mHz", "10-100 mHz"):
        g = d.gap_normalised[band]
        assert g is not None and g["before"] > 100 and g["after"] < 2.0


@pytest.mark.slow  # 60 s; make test-slow
def test_a_gain_error_taken_before_a_coupling_is_dropped_as_a_calibration(
        tmp_path: Path) -> None:
    """A strong coupling (12 urad/K through 599 s and 2,176 s lags) pulls the first
    recalibration's sensor path beyond its tolerance, so the path is held and a "sensor
    gain error" is named before the coupling. With the coupling in the model the path
    recalibrates within its tolerance: the gain error was a calibration."""
    d, _ = _diagnose(tmp_path, "temperature_coupling", "strong")
    assert [f.effect.name for f in d.effects] == ["temperature_coupling"]
    assert any(c.name == "sensor_gain_error" and c.note.startswith("dropped")
               for c in d.candidates)
    assert d.params is not None and d.model.sensor_gain_error is None


@pytest.mark.slow  # 20 s; make test-slow
def test_an_effect_the_whole_log_does_not_confirm_is_not_taken(tmp_path: Path) -> None:
    """A medium Bouc-Wen piezo under a square (tuning seed 106): a 'mode' held out with
    evidence 1,210 at gain -0.0035, and the whole log's fit made it -0.011, three times
    larger. What held out is not what the whole log says: not confirmed, not named.
    (Until stop 52 this was a null log's drift, seed 102006, held out at 1.5 pm/s and
    0.24 pm/s on the whole log; with the recalibration stepped by its scale that drift
    no longer holds out, and nothing is named there either.)"""
    log = tmp_path / "hysteresis.mcap"
    generate("actuator_hysteresis", "medium", 106, log, hours=3.0, modulated=True,
             nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    d = diagnose(load_measured(log))
    assert "extra_resonance" not in [f.effect.name for f in d.effects]
    assert any(c.name == "extra_resonance"
               and c.note.startswith("the whole log's fit disagrees") for c in d.candidates)


@pytest.mark.slow  # 23 s; the bench-diagnose scoreboard scores this family
@pytest.mark.xfail(strict=True, reason=(
    "lost with e3ee301 (found by bisection: the model follows the piezo's slew ramp, "
    "which removed a 63 nm error after every square edge); every play fitted on this log "
    "now runs to its 5 V bound (held-out evidence -439) and nothing is named, with "
    "hysteresis reported 'hardly testable here' under the square"))
def test_a_hysteresis_under_a_square_modulation_shows_in_the_closed_loops_reversals(
        tmp_path: Path) -> None:
    """A strong Bouc-Wen piezo (a = 0.147) under a square modulation (tuning seed 107): over
    the square every play is a gain, and the plays fitted there were rejected as one.
    Scored beyond a free actuator gain per part of the log, a sub-volt play is found
    where the closed loop reverses, with the small-signal share of the truth's loop."""
    log = tmp_path / "hysteresis.mcap"
    truth = generate("actuator_hysteresis", "strong", 107, log, hours=3.0, modulated=True,
                     nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    assert truth["modulation"]["shape"] == "square"
    d = diagnose(load_measured(log))
    assert [f.effect.name for f in d.effects] == ["actuator_hysteresis"]
    play = d.effects[0].effect
    assert play.width_v < 1.0  # type: ignore[attr-defined]
    assert 0.5 < play.fraction / truth["params"]["a"] < 1.5  # type: ignore[attr-defined]


@pytest.mark.slow  # 23 s; make test-slow
def test_a_hysteresis_a_square_cannot_show_is_reported_as_such_not_misnamed(
        tmp_path: Path) -> None:
    """The same strong Bouc-Wen piezo under a square (tuning seed 107), which diagnose does
    not name (above): nothing else is named in its place, and the report says why a
    hysteresis is hardly testable here and which modulation would test it."""
    log = tmp_path / "hysteresis.mcap"
    generate("actuator_hysteresis", "strong", 107, log, hours=3.0, modulated=True,
             nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    d = diagnose(load_measured(log))
    assert [f.effect.name for f in d.effects] in ([], ["actuator_hysteresis"])
    if not d.effects:
        assert "--shape triangle" in d.unseen["actuator_hysteresis"]


def test_a_modulated_null_log_names_nothing(tmp_path: Path) -> None:
    d, _ = _diagnose(tmp_path, None, "strong")
    assert d.effects == [] and not d.ambiguous


def test_a_mode_rung_by_its_own_noise_is_named_from_its_bump(tmp_path: Path) -> None:
    """A 2.19 Hz mode, Q 23, rung mostly by its own noise (2.9 nm rms): no replay predicts
    a sample of it, and it was "unexplained structure". Scored as a bump in the spectrum
    it is named, with its frequency and rms (its Q comes out high: see
    leveler.analysis.bump), and the held-out power above 1 Hz over the noise spectrum
    comes down to about 1."""
    d, truth = _diagnose(tmp_path, "extra_resonance", "strong", seed=102)
    assert [f.effect.name for f in d.effects] == ["extra_resonance"]
    fx = d.effects[0].effect
    assert fx.frequency_hz == pytest.approx(truth["frequency_hz"], rel=0.02)  # type: ignore[attr-defined]
    assert fx.noise_rms_m == pytest.approx(truth["noise_rms_m"], rel=0.3)  # type: ignore[attr-defined]
    band = d.gap_normalised["1 Hz-Nyquist"]
    assert band is not None and band["before"] > 2.0 and band["after"] < 1.3


@pytest.mark.slow  # 30 s more on the worker that runs this file; make test-slow
def test_with_no_search_the_unexplained_structure_names_the_bump(tmp_path: Path) -> None:
    log = tmp_path / "mode.mcap"
    truth = generate("extra_resonance", "strong", 102, log, hours=3.0, modulated=True,
                     nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    rest = diagnose(load_measured(log), max_effects=0)
    assert rest.leftover is not None and rest.leftover.bump is not None
    assert rest.leftover.bump.f0_hz == pytest.approx(truth["params"]["frequency_hz"], rel=0.02)
    assert "bump at 2.1" in rest.leftover.describe()


def test_a_foreign_controllers_modulation_is_found(tmp_path: Path) -> None:
    """The generator's own PID is not leveler's: replayed, its closed loop leaves volts of
    "excitation", which on seed 9005's logs hid the open-loop square's line (84x the
    median around it, where 100x is asked) and with it the rule that a periodic
    disturbance on the modulation's harmonic is the actuator's response (a 252 s sine
    took a sensor drift's place beside a 249 s square). The modulation, its line and the
    span that resolves it, is read where the loop was open."""
    log = tmp_path / "null.mcap"
    truth = generate(None, "medium", 101, log, hours=3.0, modulated=True,
                     nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    meas = load_measured(log)
    pred = Predictor(meas.config.plant, meas)
    ev = Evidence(meas, pred, make_blocks(meas, pred, [slice(3000, 30000)]),
                  Nuisance(pred, None, meas))
    mod = truth["modulation"]
    assert ev.modulation_hz() == pytest.approx(1.0 / mod["period_s"], rel=0.005)
    assert ev.modulation_span_s() == pytest.approx(mod["end_t_s"] - mod["start_t_s"], rel=0.1)
    exc = excitation_v(meas)
    assert exc is not None and np.ptp(exc[np.asarray(meas.engaged, dtype=bool)]) > 0.1


def test_a_knob_a_refit_flings_beyond_its_tolerance_goes_back_to_the_first_fit(
        tmp_path: Path) -> None:
    """An extra 1.9 Hz mode the model lacks disputes both paths (held at nominal);
    refitted without them, the resonance frequency ran from the first fit's 2.1 sigma (the
    truth's 1.9) to 7.1 and was held too, and the mode went unnamed against a baseline
    62 nm off. A knob the first fit put well within its tolerance, and found independent
    of the disputed ones, goes back where it put it (named now, 48 -> 3.8 nm:
    bench/diagnose_score.py). Knobs tied to a disputed one stay held, as the paths and the
    thermal tilt are (test_recalibrate's `far_beyond`: a gain error beside its actuator
    path)."""
    from leveler.analysis.diagnose import (
        APART,
        KEEP_PULL,
        _recalibrated,
        make_whitener,
        warmup_samples,
    )
    from leveler.analysis.predict import actuator_excited
    from leveler.analysis.recalibrate import recalibrate

    log = tmp_path / "mode.mcap"
    generate("extra_resonance", "strong", 104, log, hours=3.0, modulated=True,
             nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    meas = load_measured(log)
    plant = meas.config.plant
    pred = Predictor(plant, meas)
    whole = slice(warmup_samples(meas, pred), None)
    excited = actuator_excited(meas, pred, whole)
    first = recalibrate(meas, plant, make_whitener(meas, pred, whole), excited)
    assert first is not None and set(first.disputed) == {"sensor_path", "actuator_path"}
    assert abs(first.pull("natural_frequency")) <= KEEP_PULL
    assert all(abs(first.correlation["natural_frequency", d]) < APART for d in first.disputed)
    assert abs(first.correlation["sensor_path", "actuator_path"]) > APART
    refit = recalibrate(meas, plant, make_whitener(meas, pred, whole), excited,
                        omit=tuple(first.disputed))
    assert refit is not None and refit.disputed == ["natural_frequency"]  # flung
    _, recal, _ = _recalibrated(meas, plant, whole, excited)
    assert recal is not None and set(recal.held) == {"sensor_path", "actuator_path"}
    assert recal.offset["natural_frequency"] == first.offset["natural_frequency"]
    f0 = recal.params.pendulum.natural_frequency_hz / plant.pendulum.natural_frequency_hz
    assert f0 == pytest.approx(1 + first.offset["natural_frequency"], rel=1e-9)
