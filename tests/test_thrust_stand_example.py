"""The thrust-stand example of docs/procedures.md, on recordings leveler did not make: the
independent generator (bench/independent/thrust_stand.py, written from the physics alone: a
torsion pendulum drawn per seed, the lab's own column names, units and delimiter, thrust and
tiltmeter calibrations off within their tolerances, a drifting sensor, a record that starts
ringing) writes a stepped tilt sweep and the same sweep with the pendulum balanced (l_cm = 0);
each is imported as its preamble says and analysed with the lab's stated arm and tolerances.
bench/stiffness_score.py scores the same chain over seeds no test looks at."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from conftest import REPO

from leveler.cli.main import main

sys.path.insert(0, str(REPO / "bench"))  # bench/ is no package
from independent.thrust_stand import write_recording
from stiffness_score import analyze_args, import_args

SEED = 1


def analysed(tmp: Path, scenario: str, capsys: pytest.CaptureFixture[str]) -> tuple[dict, dict]:
    truth = write_recording(SEED, tmp, scenario=scenario)
    csv, log = tmp / f"thrust_stand_{SEED}_{scenario}.csv", tmp / f"{scenario}.mcap"
    assert main(import_args(truth, csv, log)) == 0
    out = capsys.readouterr().out
    assert "thrust stand: thrust, displacement, tilt" in out
    assert main(analyze_args(truth, log)) == 0
    return truth, json.loads(capsys.readouterr().out)


def test_a_stepped_sweep_gives_k0_and_the_coupling_within_their_sigma(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    truth, r = analysed(tmp_path, "stepped", capsys)
    p = truth["pendulum"]
    k0, mgl = p["K0_N_m_per_rad"], p["Mgl_cm_N_m_per_rad"]
    assert abs(r["stiffness_nm_per_rad"] - k0) < 2 * r["stiffness_sigma_nm_per_rad"]
    assert abs(r["stiffness_nm_per_rad"] / k0 - 1) < 0.05
    sens, sigma = r["tilt_sensitivity_nm_per_rad"], r["tilt_sensitivity_sigma_nm_per_rad"]
    assert abs(sens - mgl) < 2 * sigma and abs(sens / mgl - 1) < 0.05
    assert r["coupling_significance"] > 10
    assert r["natural_frequency_hz"] == pytest.approx(p["f0_hz"], rel=0.01)
    # every plateau the generator held, found, with its r on the truth's
    held = truth["plateaus"]
    assert len(r["plateaus"]) == len(held)
    for got in r["plateaus"]:
        want = min(held, key=lambda h: abs(h["alpha_rad"] - got["tilt_rad"]))
        assert got["coupling_ratio"] == pytest.approx(want["r"], abs=0.05 + 0.05 * abs(want["r"]))


@pytest.mark.slow  # 11 s; make test-slow (the stepped sweep stays in make test)
def test_a_balanced_pendulum_is_not_called_coupled(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    truth, r = analysed(tmp_path, "null", capsys)
    assert truth["pendulum"]["l_cm_m"] == 0
    assert r["coupling_significance"] < 3
    assert abs(r["tilt_sensitivity_nm_per_rad"]) < 3 * r["tilt_sensitivity_sigma_nm_per_rad"]
    k0 = truth["pendulum"]["K0_N_m_per_rad"]
    assert abs(r["stiffness_nm_per_rad"] - k0) < 2 * r["stiffness_sigma_nm_per_rad"]
