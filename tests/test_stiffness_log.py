"""`leveler analyze stiffness LOG`: a thrust stand's K0 and tilt coupling from its recording.

The recordings here come from leveler's own torsion-pendulum simulator (leveler.sim.torsion)
under a stepped tilt sweep with a square-wave thrust, a sensor that drifts and starts out of
equilibrium, written as a lab's CSV (uN, um, urad) and imported with import-csv;
tests/test_thrust_stand_example.py runs the same command on the independent generator's files.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from figure_capture import saved_figures

from leveler.cli.main import main
from leveler.log.reader import read_log
from leveler.procedures.stiffness import square_wave_thrust, unit_response
from leveler.sim.torsion import TorsionParams, sensor_noise, simulate

FS = 5.0
LEVELS_URAD = (0.0, 12.0, -12.0, 20.0, -20.0, 6.0, -6.0)
HOLD_S = 2400.0
IMPORT = ["--column", "t=time_s", "--column", "thrust=F_uN", "--column", "displacement=x_um",
          "--scale", "thrust=1e-6", "--scale", "displacement=1e-6"]


def stand_run(p: TorsionParams, seed: int, *, thrust_n: float = 1e-6,
              levels_urad: tuple[float, ...] = LEVELS_URAD) -> dict[str, np.ndarray]:
    """Stepped pitch (short ramps), a 0/F square wave of 400 s, drift, noise, a start swing."""
    rng = np.random.default_rng(seed)
    n = int(len(levels_urad) * HOLD_S * FS)
    t = np.arange(n) / FS
    target = np.repeat(np.asarray(levels_urad) * 1e-6, int(HOLD_S * FS))
    ramp = int(30 * FS)
    tilt = np.convolve(np.pad(target, (ramp, 0), mode="edge"), np.ones(ramp) / ramp,
                       mode="valid")[:n]
    thrust = square_wave_thrust(n, FS, 400.0, thrust_n)
    theta = simulate(p, 1 / FS, thrust, pitch_rad=tilt)
    swing = 3e-8 * np.exp(-t * p.natural_frequency_hz * math.pi / p.quality_factor) \
        * np.cos(math.tau * p.natural_frequency_hz * t)
    x = (p.arm_m * theta + swing + sensor_noise(rng, n, 1e-9, FS)
         + np.cumsum(rng.normal(0, 2e-11, n)) + 3e-9 * (t / t[-1]) ** 2)
    return {"time_s": t, "F_uN": thrust * 1e6, "x_um": x * 1e6,
            "tilt_urad": tilt * 1e6 + rng.normal(0, 0.02, n)}


def write_csv(path: Path, cols: dict[str, np.ndarray]) -> None:
    names = list(cols)
    rows = zip(*(cols[k].tolist() for k in names), strict=True)
    path.write_text(",".join(names) + ",humidity\n"
                    + "\n".join(",".join(f"{v:.12g}" for v in row) + ",40" for row in rows)
                    + "\n")


def imported(tmp_path: Path, capsys: pytest.CaptureFixture[str],
             cols: dict[str, np.ndarray]) -> Path:
    csv, log = tmp_path / "stand.csv", tmp_path / "stand.mcap"
    write_csv(csv, cols)
    tilt = ["--column", "tilt=tilt_urad", "--scale", "tilt=1e-6"]
    assert main(["import-csv", str(csv), "--out", str(log), *IMPORT, *tilt]) == 0
    assert "thrust stand: thrust, displacement, tilt" in capsys.readouterr().out
    return log


def analyze(capsys: pytest.CaptureFixture[str], log: Path, *args: str) -> dict:
    code = main(["analyze", "stiffness", str(log), "--arm-m", "0.25", "--json", *args])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


def test_a_recorded_force_is_joined_by_lines_between_samples() -> None:
    """The recording's thrust and tilt are samples of continuous signals: the response to them
    is the exact one for straight lines between samples (scipy's lsim interpolates so), where
    holding each sample half an interval late is 10 % off near a Q = 30 resonance."""
    from scipy.signal import lsim

    dt, f0, q = 0.5, 0.17, 30.0
    t = np.arange(4000) * dt
    u = np.sin(0.3 * t) + (t > 100)
    w0 = math.tau * f0
    _, want, _ = lsim(([w0**2], [1, w0 / q, w0**2]), u, t)
    scale = np.max(np.abs(want))
    assert np.max(np.abs(unit_response(u, dt, f0, q, hold="foh") - want)) < 1e-9 * scale
    assert np.max(np.abs(unit_response(u, dt, f0, q) - want)) > 0.05 * scale


def test_import_writes_the_stand_topic_without_leveler_samples(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cols = stand_run(TorsionParams(), seed=3, levels_urad=(0.0, 5.0))
    log = read_log(imported(tmp_path, capsys, cols))
    stand = log.thrust_stand
    assert len(log.samples["t_s"]) == 0 and len(stand["t_s"]) == len(cols["time_s"])
    np.testing.assert_allclose(stand["thrust_n"], cols["F_uN"] * 1e-6, rtol=1e-11)
    np.testing.assert_allclose(stand["displacement_m"], cols["x_um"] * 1e-6, rtol=1e-11,
                               atol=1e-20)
    np.testing.assert_allclose(stand["tilt_rad"], cols["tilt_urad"] * 1e-6, rtol=1e-11,
                               atol=1e-20)


@pytest.mark.parametrize("stiffness, seed", [(0.2, 11), (0.02, 12)])
def test_stiffness_and_coupling_recovered_within_their_uncertainty(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], stiffness: float,
        seed: int) -> None:
    p = TorsionParams(stiffness_nm_per_rad=stiffness)
    r = analyze(capsys, imported(tmp_path, capsys, stand_run(p, seed)))
    k0, sk = r["stiffness_nm_per_rad"], r["stiffness_sigma_nm_per_rad"]
    sens, ss = r["tilt_sensitivity_nm_per_rad"], r["tilt_sensitivity_sigma_nm_per_rad"]
    assert abs(k0 - stiffness) < 3 * sk and sk < 0.01 * stiffness
    assert abs(sens - p.tilt_sensitivity_nm_per_rad) < 3 * ss
    assert ss < 0.05 * p.tilt_sensitivity_nm_per_rad and r["coupling_significance"] > 10
    assert r["natural_frequency_hz"] == pytest.approx(p.natural_frequency_hz, rel=0.01)
    assert r["quality_factor"] == pytest.approx(p.quality_factor, rel=0.1)
    # every held tilt found, with the paper's r and regime
    found = sorted(round(pl["tilt_rad"] * 1e6) for pl in r["plateaus"])
    assert found == sorted(round(v) for v in LEVELS_URAD)
    for pl in r["plateaus"]:
        truth = p.coupling_ratio(1e-6, pl["tilt_rad"])
        assert pl["coupling_ratio"] == pytest.approx(truth, abs=0.03 + 0.05 * abs(truth))
        want = ("level (reference)" if abs(pl["tilt_rad"]) < 1e-7 else
                "softening" if pl["tilt_rad"] > 0 else
                "stiffening" if truth > -1 else "negative stiffness (unstable)")
        assert pl["regime"] == want
    budget = 0.25 * 1e-6 * p.arm_m / p.tilt_sensitivity_nm_per_rad
    assert r["tilt_budget_rad"] == pytest.approx(budget, rel=0.1)


def test_a_balanced_pendulum_shows_no_coupling(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    p = replace(TorsionParams(), com_y_m=0.0)
    log = imported(tmp_path, capsys, stand_run(p, seed=21))
    assert main(["analyze", "stiffness", str(log), "--arm-m", "0.25"]) == 0
    text = capsys.readouterr().out
    shown = re.search(r"only ([\d.]+) sigma from zero: no tilt coupling shown", text)
    assert shown and float(shown[1]) < 3 and "tilt budget" not in text


def test_report_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                         monkeypatch: pytest.MonkeyPatch) -> None:
    figures = saved_figures(monkeypatch)
    log = imported(tmp_path, capsys, stand_run(TorsionParams(), seed=5))
    assert main(["analyze", "stiffness", str(log), "--arm-m", "0.25", "--arm-sigma-m",
                 "0.00125", "--plot-dir", str(tmp_path / "plots")]) == 0
    text = capsys.readouterr().out
    # the stated arm-length sigma (0.5 %) enters K0's uncertainty as 2 x 0.5 %
    k0 = re.search(r"stiffness K0 = ([\d.]+) \+- ([\d.e-]+) N m/rad", text)
    assert k0 and 0.0099 < float(k0[2]) / float(k0[1]) < 0.011  # printed to 2 digits
    for needed in ("K0 = 0.2", "N m/rad", "uN m/urad", "sigma from zero: the stand feels",
                   "Per tilt plateau", "tilt budget", "negative stiffness", "softening",
                   "stiffening", "level (reference)", "f0 = 0.318"):
        assert needed in text, needed
    png = tmp_path / "plots" / "stiffness_log.png"
    assert png.stat().st_size > 20_000 and png.read_bytes()[:4] == b"\x89PNG"
    # The figure names its log; the time axis is labelled once, under the channels, and
    # the displacement above shares it without numbers of its own that no label explains.
    [fig] = figures
    assert fig.get_suptitle().startswith(f"{log.name}: thrust stand fit, K0 = ")
    assert " ± " in fig.get_suptitle()
    top, mid, bottom, twin = fig.axes
    assert not any(t.get_visible() and t.get_text() for t in top.get_xticklabels())
    assert mid.get_xlabel() == "Time from the first sample [h]"
    for ax in (top, mid, twin):
        assert ax.get_ylabel().endswith("]"), ax.get_ylabel()
    assert bottom.get_xlabel() == "Pitch tilt [urad]"


@pytest.fixture(scope="module")
def short_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One level, no tilt column: for what needs a stand's log but not a sweep."""
    tmp = tmp_path_factory.mktemp("short")
    write_csv(tmp / "stand.csv", {k: v for k, v in stand_run(
        TorsionParams(), seed=8, levels_urad=(0.0,)).items() if k != "tilt_urad"})
    log = tmp / "stand.mcap"
    assert main(["import-csv", str(tmp / "stand.csv"), "--out", str(log), *IMPORT]) == 0
    return log


def test_without_a_tilt_column_only_the_stiffness(short_log: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    log = short_log
    r = analyze(capsys, log)
    assert r["tilt_sensitivity_nm_per_rad"] is None and r["plateaus"] == []
    assert abs(r["stiffness_nm_per_rad"] - 0.2) < 3 * r["stiffness_sigma_nm_per_rad"]
    assert main(["analyze", "stiffness", str(log), "--arm-m", "0.25"]) == 0
    assert "--column tilt=NAME" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--arm-m", "0.25", "--seed", "3"], "--seed belong to the simulated sweep"),
    ([], "LOG needs --arm-m"),
    (["--arm-m", "0.25", "--drift", "cubic"], "--drift 'cubic': use poly:N"),
    (["--arm-m", "0.25", "--thrust-n", "1e-6", "2e-6"], "takes one F"),
    (["--arm-m", "-1"], "arm length must be positive"),
])
def test_bad_requests_are_named(short_log: Path, capsys: pytest.CaptureFixture[str],
                                args: list[str], message: str) -> None:
    assert main(["analyze", "stiffness", str(short_log), *args]) == 2
    assert message in capsys.readouterr().err


def test_a_leveler_log_without_stand_channels_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv, log = tmp_path / "lev.csv", tmp_path / "lev.mcap"
    csv.write_text("t_s,actuator_V,sensor_m\n" + "\n".join(f"{i / 2},50,{i * 1e-9}"
                                                          for i in range(300)) + "\n")
    assert main(["import-csv", str(csv), "--out", str(log)]) == 0
    capsys.readouterr()
    assert main(["analyze", "stiffness", str(log), "--arm-m", "0.25"]) == 2
    assert "no thrust-stand channels" in capsys.readouterr().err
    assert main(["analyze", "stiffness", "--arm-m", "0.25"]) == 2
    assert "only with a LOG" in capsys.readouterr().err
