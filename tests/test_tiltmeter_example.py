"""The worked example of docs/procedures.md, on a recording leveler did not make: a hanging
beam-balance tiltmeter from the independent generator (bench/independent/tiltmeter.py, written
from the physics alone: the lab's stated values 1-2 sigma off the truth, a day of stepped sine
sweep at 2 Hz, MJD in days, counts, degrees C, semicolons, stray rows, a jittery clock) is
imported, its centre of mass found, and the log replayed against the fitted model.
bench/com_score.py scores the same chain over seeds no test looks at."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from conftest import REPO

from leveler.cli.main import main

sys.path.insert(0, str(REPO / "bench"))  # bench/ is no package
from com_score import import_args, stand_config
from independent.tiltmeter import write_recording


@pytest.fixture(scope="module")
def example(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path, Path]:
    """Seed 1 with a quiet sensor (its zero's walk a tenth of the generator's nominal, which
    buries the lowest steps of the sweep under 0.8 um/rtHz at 1 mHz)."""
    out = tmp_path_factory.mktemp("tiltmeter")
    truth = write_recording(1, out, "sine", drift_scale=0.1)
    cfg = out / "stand.toml"
    cfg.write_text(stand_config(truth))
    return truth, out / "run.mcap", cfg


def test_the_loggers_file_imports_without_hand_edits(
        example: tuple[dict, Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    truth, log, _ = example
    assert main(import_args(truth, Path(truth["csv_path"]), log)) == 0
    out, err = capsys.readouterr()
    assert "time in days" in out and "2 Hz" in out
    for row in truth["stray_rows"]:  # each reported by the line the generator put it on
        kind, line = row["kind"], row["line"]
        if kind in ("nan_field", "empty_field"):
            assert f"line {line}: {row['column']} is" in err, row
        elif kind == "repeated_header":
            assert f"repeated header lines skipped (a logger restart?): {line}" in err
        elif kind == "duplicate":
            assert f"rows repeating the one before, dropped: line {line}" in err
        elif kind == "out_of_order":
            assert f"rows out of order, sorted in: line {row['swapped_with_line']}" in err
        elif kind == "gap":
            assert (f"gap after line {row['after_line']}: " in err
                    and f"{row['n_missing']} samples interpolated" in err), row


def test_centre_of_mass_within_ten_per_cent_and_covered(
        example: tuple[dict, Path, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    truth, log, cfg = example
    if not log.exists():
        assert main(import_args(truth, Path(truth["csv_path"]), log)) == 0
    fitted = tmp_path / "fitted.toml"
    capsys.readouterr()
    assert main(["calibrate-com", str(log), "--model", str(cfg), "--model-out", str(fitted),
                 "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    d, sigma, d_true = -r["com_length_m"], r["com_length_sigma_m"], truth["d_true_m"]
    assert r["kind"] == "hanging"
    assert abs(d / d_true - 1) < 0.10
    assert abs(d - d_true) < 2 * sigma
    assert r["zero_frequency_hz"] == pytest.approx(truth["f_z_hz"], rel=0.05)
    assert r["natural_frequency_hz"] == pytest.approx(truth["f_0_hz"], rel=0.03)
    assert len([x for x in r["lines"] if x["harmonic"] == 1]) == len(truth["drive"]["steps"])
    # the fitted model replays the drive: the 1-10 mHz band, where the sweep's lines are, is
    # explained once the zero's drift is set aside, and what is left is the sensor's noise
    assert main(["replay", str(log), "--model", str(fitted), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["bands"]["1-10 mHz"]["variance_explained_less_drift"] > 0.95
    assert rep["verdict"].startswith("The residual is what the model itself calls "
                                     "unpredictable")
    # against the lab's starting model (the centre of mass a guess) it is not
    assert main(["replay", str(log), "--model", str(cfg), "--json"]) == 0
    guess = json.loads(capsys.readouterr().out)
    assert not guess["bands"]["1-10 mHz"]["unpredictable"]
