"""`leveler calibrate-com LOG`: a pendulum's centre of mass from a recorded drive of its table.

The recordings here come from leveler's own pendulum stepper (exact for the linear equation
with the platform's rotation) under a stepped sweep, with a random-walk drift far larger than
the drive's response and white noise; tests/test_tiltmeter_example.py runs the same command on
a recording from the independent generator.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from figure_capture import saved_figures

from leveler.cli.main import main
from leveler.procedures.drive_lines import drive_lines
from leveler.procedures.pendulum_fit import fit_pendulum
from leveler.sim.effects import play
from leveler.sim.params import PendulumParams, PlantParams
from leveler.sim.pendulum import PendulumModel

DT = 0.5
HANGING = PendulumParams(mass_kg=1.0, com_length_m=-2e-5, flexure_stiffness_nm_per_rad=4e-4,
                         inertia_kgm2=0.05, damping_nms_per_rad=2e-4, sensor_arm_m=0.1)
TILT_PER_V = PlantParams().piezo.gain_m_per_v / PlantParams().platform.support_spacing_m
SIM_TOML = Path(__file__).resolve().parents[1] / "config" / "sim.toml"


def sweep(pe: PendulumParams, freqs: np.ndarray, waveform: str, seed: int,
          amplitude_v: float = 20.0, dt: float = DT,
          min_step_s: float = 2400.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, command, reading) of a stepped sweep with pauses, drift and noise."""
    rng = np.random.default_rng(seed)
    parts = []
    for f in freqs:
        t = np.arange(int(max(15 / f, min_step_s) / dt)) * dt
        wave = np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
        parts += [50 + amplitude_v * (np.sign(wave) if waveform == "square" else wave),
                  np.full(int(rng.uniform(60, 300) / dt), 50.0)]
    u = np.concatenate(parts)
    model = PendulumModel(pe, dt)
    model.settle(pe, 0.0)
    model.omega = 1e-7  # out of equilibrium: it rings from the start
    y = np.array([model.step(TILT_PER_V * v) for v in u]) * pe.sensor_arm_m
    t = np.arange(len(u)) * dt
    y += np.cumsum(rng.normal(0, 3e-10, len(u))) + 2e-11 * t + rng.normal(0, 2e-10, len(u))
    return t, u, y


def recording(tmp_path: Path, capsys: pytest.CaptureFixture[str], pe: PendulumParams,
              waveform: str = "sine", seed: int = 1) -> tuple[Path, Path]:
    """The sweep as a CSV imported into a log, and a config stating the stand."""
    fz = math.sqrt(abs(pe.gravity_stiffness_nm_per_rad) / pe.inertia_kgm2) / math.tau
    t, u, y = sweep(pe, np.geomspace(fz / 4, fz * 4, 10), waveform, seed)
    csv = tmp_path / "rec.csv"
    csv.write_text("t_s,actuator_V,sensor_m\n" + "\n".join(
        f"{a!r},{b!r},{c!r}" for a, b, c in zip(t.tolist(), u.tolist(), y.tolist(), strict=True))
        + "\n")
    log = tmp_path / "rec.mcap"
    assert main(["import-csv", str(csv), "--out", str(log)]) == 0
    capsys.readouterr()
    cfg = tmp_path / "stand.toml"
    cfg.write_text(
        "[plant.pendulum]\n"
        f"mass_kg = {pe.mass_kg!r}\ncom_length_m = -1e-6\n"  # the lab's guess: what is sought
        f"flexure_stiffness_nm_per_rad = {pe.flexure_stiffness_nm_per_rad!r}\n"
        f"inertia_kgm2 = {pe.inertia_kgm2!r}\n"
        f"damping_nms_per_rad = {pe.damping_nms_per_rad!r}\n"
        f"sensor_arm_m = {pe.sensor_arm_m!r}\n"
        "[plant.uncertainty]\nmass_rel = 0.005\ninertia_rel = 0.03\nsensor_arm_rel = 0.02\n"
        "piezo_gain_rel = 0.03\nsupport_spacing_rel = 0.01\n")
    return log, cfg


def calibrate(capsys: pytest.CaptureFixture[str], *args: str | Path) -> dict:
    assert main(["calibrate-com", *map(str, args), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("waveform", ["sine", "square"])
def test_hanging_centre_of_mass_from_its_zero(tmp_path: Path, waveform: str,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    log, cfg = recording(tmp_path, capsys, HANGING, waveform)
    r = calibrate(capsys, log, "--model", cfg, "--plot", tmp_path / "bode.png")
    assert r["kind"] == "hanging"
    err = r["com_length_m"] - HANGING.com_length_m
    assert abs(err) < 0.05 * abs(HANGING.com_length_m)
    assert abs(err) < 3 * r["com_length_sigma_m"]  # an honest uncertainty covers it
    # the uncertainty is the stated inertia's and mass's (3 %, 0.5 %) and the fit's, no more
    assert r["com_length_sigma_m"] < 0.05 * abs(HANGING.com_length_m)
    assert r["zero_frequency_hz"] == pytest.approx(HANGING.zero_frequency_hz, rel=0.02)
    assert r["natural_frequency_hz"] == pytest.approx(HANGING.natural_frequency_hz, rel=0.03)
    assert r["scale_m_per_v"] == pytest.approx(HANGING.sensor_arm_m * TILT_PER_V, rel=0.02)
    fundamentals = [x for x in r["lines"] if x["harmonic"] == 1]
    assert len(fundamentals) == 10
    assert {x["waveform"] for x in fundamentals} == {waveform}
    if waveform == "square":  # the third harmonics are lines of their own, named so
        assert sum(x["harmonic"] == 3 for x in r["lines"]) >= 5
    assert (tmp_path / "bode.png").stat().st_size > 10_000
    assert main(["calibrate-com", str(log), "--model", str(cfg)]) == 0
    text = capsys.readouterr().out
    assert "centre of mass: L = -20" in text and "um below the pivot" in text
    assert "zero of the response" in text and "[nm/V]" in text


def test_bode_plot_draws_each_phase_on_the_fits_branch(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Below a hanging pendulum's zero the phase is near 180 deg: a line 8 deg past it is
    at 188 deg on the fitted curve's branch, not at -172 a turn away from it; the
    resonance is named like the zero, and every axis has its unit."""
    from leveler.cli.calibrate_com_log import plot
    from leveler.procedures.drive_lines import DriveLine
    from leveler.procedures.pendulum_fit import PendulumFit, response

    a, f0, q, f_zero = 2.5e-9, 5.1e-3, 19.0, 2.7e-3
    g = -(math.tau * f_zero) ** 2
    freqs = np.array([0.8, 1.0, 1.3, 1.8, 3.5, 4.9, 6.3, 7.8, 10.7]) * 1e-3
    h = response(math.tau * freqs, a, g, math.tau * f0, q)
    off = np.exp(1j * np.radians(np.where(np.arange(len(freqs)) % 2, 8.0, -8.0)))
    lines = [DriveLine(float(f), 0.0, 1.0, 6.0 + 0j, complex(6.0 * x * o), 1e-11)
             for f, x, o in zip(freqs, h, off, strict=True)]
    fit = PendulumFit(lines, a, 0.0, a, 0.0, g, 0.0, f0, 0.0, 0.0, 0.0, q, 0.0, -3e-7, 0.0,
                      4.3, 0.048, 1.0, len(freqs) - 4, list(h))
    figures = saved_figures(monkeypatch)
    plot(fit, str(tmp_path / "bode.png"), "rec.mcap: response to the drive lines")
    [fig] = figures
    mag, ph = fig.axes
    points, fitted = ph.get_lines()[:2]
    f, phase = (np.asarray(v, dtype=float) for v in points.get_data())
    model = np.interp(np.log(f), np.log(fitted.get_xdata()), fitted.get_ydata())
    assert np.abs(phase - model).max() == pytest.approx(8.0, abs=1.0)
    assert [t.get_text() for t in mag.texts] == ["zero 2.7 mHz", "resonance 5.1 mHz"]
    assert (mag.get_ylabel(), ph.get_ylabel(), ph.get_xlabel()) == (
        "|reading / command| [nm/V]", "phase [deg]", "Frequency [Hz]")


def test_inverted_pendulum_has_no_zero_and_its_distance_from_the_levels(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The default stand's inverted pendulum (N = 9) swept across its 0.71 Hz resonance at
    50 Hz: no zero, and the distance from the static level against the inertial limit.
    (Sampled at 10 Hz, a sweep to 3 Hz is a third of the sample rate, where a held command's
    steps are no longer the continuous drive the fitted response assumes.)"""
    pe = PlantParams().pendulum
    t, u, y = sweep(pe, np.geomspace(0.1, 3.0, 8), "sine", seed=3, amplitude_v=2.0, dt=0.02,
                    min_step_s=120.0)
    fit = fit_pendulum(drive_lines(t, u, y), PlantParams(), 0.02)
    assert fit.kind == "inverted"
    assert fit.com_length_m == pytest.approx(pe.com_length_m, rel=0.05)
    assert abs(fit.com_length_m - pe.com_length_m) < 3 * fit.com_length_sigma_m
    assert fit.amplification == pytest.approx(pe.amplification, rel=0.05)
    assert math.isnan(fit.zero_frequency_hz)


def test_no_drive_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(0)
    csv, log = tmp_path / "quiet.csv", tmp_path / "quiet.mcap"
    csv.write_text("t_s,actuator_V,sensor_m\n" + "\n".join(
        f"{i * DT!r},{50 + float(rng.normal(0, 0.01))!r},{float(rng.normal(0, 1e-9))!r}"
        for i in range(4000)) + "\n")
    assert main(["import-csv", str(csv), "--out", str(log)]) == 0
    capsys.readouterr()
    assert main(["calibrate-com", str(log)]) == 2
    assert "carries no config (imported?): give --model" in capsys.readouterr().err
    assert main(["calibrate-com", str(log), "--model", str(SIM_TOML)]) == 2
    err = capsys.readouterr().err
    assert "0 drive lines found" in err and "at least 4 frequencies" in err


def test_a_closed_loop_log_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """leveler's own closed-loop log: the command answers the reading, it drives nothing."""
    log = tmp_path / "closed.mcap"
    assert main(["sim", "--duration", "200s", "--out", str(log), "--seed", "1"]) == 0
    capsys.readouterr()
    assert main(["calibrate-com", str(log)]) == 2
    err = capsys.readouterr().err
    assert "0 drive lines found in the" in err and "s where the loop was open" in err


def test_a_line_found_only_where_the_loop_was_open() -> None:
    """A drive in the closed part is the controller's, not the lab's: left out."""
    t = np.arange(40_000) * DT
    u = 50 + 5 * np.sin(2 * np.pi * 0.01 * t) + 3 * np.sin(2 * np.pi * 0.0237 * t)
    open_ = t < t[-1] / 2
    u[~open_] = 50 + 3 * np.sin(2 * np.pi * 0.0237 * t[~open_])
    y = 1e-9 * u + np.random.default_rng(0).normal(0, 1e-12, len(t))
    lines = drive_lines(t, u, y, usable=open_)
    assert sorted(round(x.frequency_hz, 4) for x in lines) == [0.01, 0.0237]
    assert all(x.end_s < t[-1] / 2 + DT for x in lines)
    for x in lines:  # a flat 1 nm/V response, read back exactly
        assert abs(x.transfer_m_per_v - 1e-9) < 3 * x.transfer_sigma_m_per_v + 1e-13



def test_adjacent_steps_at_close_frequencies_are_two_lines() -> None:
    """3.03 then 3.51 mHz with no pause between (one envelope covers both): each is its own
    line with its own amplitude, and the response read at each is its own."""
    t = np.arange(20_000) * DT
    first = t < 5000
    u = 50 + np.where(first, 6 * np.sin(2 * np.pi * 3.03e-3 * t),
                      4 * np.sin(2 * np.pi * 3.51e-3 * t + 1.0))
    gain = np.where(first, 2e-9, 5e-9)  # a response that differs between the steps
    y = gain * (u - 50) + np.random.default_rng(1).normal(0, 1e-11, len(t))
    lines = drive_lines(t, u, y)
    assert [round(x.frequency_hz * 1e3, 2) for x in lines] == [3.03, 3.51]
    assert [round(abs(x.command_v), 1) for x in lines] == [6.0, 4.0]
    assert [x.transfer_m_per_v.real for x in lines] == pytest.approx([2e-9, 5e-9], rel=1e-3)


def _modulate_recorded(csv: Path, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                       capsys: pytest.CaptureFixture[str]) -> list[dict]:  # type: ignore[type-arg]
    """The waves `leveler modulate LOG --json` finds in a recording imported from a CSV of
    time, piezo voltage and reading, as another system would write it."""
    csv.write_text("t_s,actuator_V,sensor_m\n" + "\n".join(
        f"{a!r},{b!r},{c!r}" for a, b, c in zip(t.tolist(), u.tolist(), y.tolist(),
                                                 strict=True)) + "\n")
    log = csv.with_suffix(".mcap")
    assert main(["import-csv", str(csv), "--out", str(log)]) == 0
    capsys.readouterr()
    assert main(["modulate", str(log), "--model", str(SIM_TOML), "--json"]) == 0
    return json.loads(capsys.readouterr().out)["waves"]  # type: ignore[no-any-return]


def test_modulate_reads_a_recorded_square_wave(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """`leveler modulate LOG`: the default stand's inverted pendulum under 6 x 60 s of
    +-2 V, recorded at 10 Hz by another system: its step per volt is the model's (the
    recording is the model's own pendulum), and a log without a square wave is an error."""
    pe, dt = PlantParams().pendulum, 0.1
    t = np.arange(9000) * dt
    u = np.full(len(t), 75.0)
    on = (t >= 137.3) & (t < 137.3 + 6 * 60)
    u[on] += np.where(((t[on] - 137.3) % 60) < 30, 2.0, -2.0)
    model = PendulumModel(pe, dt)
    model.settle(pe, TILT_PER_V * 75)
    y = np.array([model.step(TILT_PER_V * v) for v in u]) * pe.sensor_arm_m
    y += np.random.default_rng(0).normal(0, 1e-9, len(t))
    csv = tmp_path / "m.csv"
    (wave,) = _modulate_recorded(csv, t, u, y, capsys)
    assert wave["wave"]["period_s"] == pytest.approx(60, rel=0.005)
    assert wave["wave"]["amplitude_v"] == pytest.approx(2, rel=0.02)
    assert wave["measured_over_model"] == pytest.approx(1, abs=0.01)
    assert wave["ip_m_per_v"] == pytest.approx(pe.sensor_arm_m * pe.amplification * TILT_PER_V,
                                               rel=0.01)
    log2 = tmp_path / "quiet.mcap"
    csv.write_text("t_s,actuator_V,sensor_m\n" + "\n".join(
        f"{a!r},75.0,{c!r}" for a, c in zip(t.tolist(), y.tolist(), strict=True)) + "\n")
    assert main(["import-csv", str(csv), "--out", str(log2)]) == 0
    capsys.readouterr()
    assert main(["modulate", str(log2), "--model", str(SIM_TOML)]) == 2
    assert "no square or triangle modulation of the piezo found" in capsys.readouterr().err
    assert main(["modulate", "--sim"]) == 2
    assert "--amplitude-v and --period needed" in capsys.readouterr().err


def test_modulate_reads_a_recorded_triangle_and_its_opening(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`leveler modulate LOG` on 5 x 150 s of a +-3 V triangle that starts at its low turn
    (another system's phase), recorded at 10 Hz (each reading before that cycle's write, a
    sample's lag otherwise: 0.016 V here) through a piezo whose stroke lags by a
    play of 0.4 V half-width on 25 % of it: the shape is found from the command, the step
    per volt is the model's (a play shifts each sweep, keeping its slope), and the opening
    is 2 x 0.25 x 0.4 = 0.2 V."""
    pe, dt = PlantParams().pendulum, 0.1
    t = np.arange(12000) * dt
    u = np.full(len(t), 75.0)
    on = (t >= 211.7) & (t < 211.7 + 5 * 150)
    ph = ((t[on] - 211.7) / 150) % 1.0
    u[on] += 3.0 * np.where(ph < 0.5, 4 * ph - 1, 3 - 4 * ph)
    stroke = u + 0.25 * (play(u, 0.4) - u)
    model = PendulumModel(pe, dt)
    model.settle(pe, TILT_PER_V * stroke[0])
    y = np.empty(len(t))
    for i, v in enumerate(stroke):  # read, then write: as the daemon logs a cycle
        y[i] = model.theta * pe.sensor_arm_m
        model.step(TILT_PER_V * v)
    y += np.random.default_rng(5).normal(0, 1e-9, len(t))
    (wave,) = _modulate_recorded(tmp_path / "t.csv", t, u, y, capsys)
    assert wave["wave"]["shape"] == "triangle"
    assert wave["wave"]["period_s"] == pytest.approx(150, rel=0.005)
    assert wave["wave"]["amplitude_v"] == pytest.approx(3, rel=0.02)
    assert wave["measured_over_model"] == pytest.approx(1, abs=0.01)
    assert wave["opening_v"] == pytest.approx(0.2, abs=0.01)
    assert wave["opening_z"] > 20
