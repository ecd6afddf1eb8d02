"""`leveler import-csv` on files as real loggers write them: their own names, units and
delimiters, stray rows, a jittery clock and gaps. Every conversion must be exact, every row
moved, dropped or made up must be reported by line, and nothing made up may pass unmarked.
"""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np
import pytest

from leveler.cli.main import main
from leveler.log.reader import read_log

N = 300
DT = 0.5
MJD0 = 60500.25  # days
COUNT_M = 1.75e-9


def run(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    code = main(["import-csv", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def logger_rows(n: int = N, jitter_s: float = 0.0, seed: int = 0) -> dict[str, np.ndarray]:
    """A 2 Hz logger's columns: MJD in days, tilt in integer counts, piezo in V, degrees C."""
    rng = np.random.default_rng(seed)
    t_s = np.arange(n) * DT + rng.uniform(-jitter_s, jitter_s, n)
    return {"t_s": t_s, "MJD": MJD0 + t_s / 86400.0,
            "tilt_counts": rng.integers(-50_000, 50_000, n),
            "pzt_V": np.round(rng.uniform(0, 150, n), 4),
            "T_degC": np.round(21.5 + rng.normal(0, 0.05, n), 2)}


def format_rows(cols: dict[str, np.ndarray], sep: str = ";") -> list[str]:
    return [sep.join([f"{m:.11f}", str(c), repr(float(v)), f"{k:.2f}"])
            for m, c, v, k in zip(cols["MJD"], cols["tilt_counts"], cols["pzt_V"],
                                  cols["T_degC"], strict=True)]


HEADER = ["MJD", "tilt_counts", "pzt_V", "T_degC"]
MAPPING = ["--column", "t=MJD", "--column", "sensor=tilt_counts", "--column", "actuator=pzt_V",
           "--column", "temperature=T_degC", "--time-unit", "days",
           "--scale", f"sensor={COUNT_M}", "--offset", "temperature=273.15"]


def write(path: Path, rows: list[str], sep: str = ";", header: list[str] | None = None) -> None:
    lines = ["# logger T-7, plate 2", "# tilt: ADC counts of 1.75 nm", sep.join(header or HEADER)]
    path.write_text("\n".join(lines + rows) + "\n", encoding="utf-8")


@pytest.mark.parametrize("sep,name", [(";", "semicolon"), ("\t", "tab"), (" ", "space"),
                                      (",", "comma")])
def test_units_names_and_delimiters_convert_exactly(tmp_path: Path, sep: str, name: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    cols = logger_rows()
    csv, out = tmp_path / "t7.csv", tmp_path / "t7.mcap"
    write(csv, format_rows(cols, sep), sep)
    code, stdout, err = run(capsys, csv, "--out", out, *MAPPING)
    assert code == 0, err
    assert f"imported {N} rows" in stdout and "2 Hz" in stdout
    assert "time in days" in stdout and "sensor x 1.75e-09" in stdout
    log = read_log(out)
    s = log.samples
    # MJD to 1e-11 days (about 1 us) as written: the time base in seconds to a few us
    np.testing.assert_allclose(s["t_s"] - s["t_s"][0], cols["t_s"] - cols["t_s"][0], atol=5e-6)
    np.testing.assert_allclose(s["t_s"][0], MJD0 * 86400.0, rtol=1e-15)
    np.testing.assert_allclose(s["sensor_m"], cols["tilt_counts"] * COUNT_M, rtol=1e-15)
    np.testing.assert_allclose(s["applied_v"], cols["pzt_V"], rtol=1e-15)
    np.testing.assert_allclose(log.environment["temperature_k"], cols["T_degC"] + 273.15,
                               rtol=1e-15)
    assert "time in days" in log.metadata["leveler"]["conversion"]
    # the same file told the wrong delimiter fails on its header, naming it
    other = {"semicolon": "comma", "tab": "semicolon", "space": "tab", "comma": "tab"}[name]
    code, _, err = run(capsys, csv, "--out", tmp_path / "x.mcap", *MAPPING, "--delimiter",
                       other, "--force")
    assert code == 2 and "missing; the header found is" in err


def test_iso_times(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    start = datetime.datetime(2026, 3, 1, 23, 59, 50, tzinfo=datetime.UTC)
    rows = [f"{(start + datetime.timedelta(seconds=i * DT)).isoformat()},{i},{1e-9 * i}"
            for i in range(40)]
    rows[5] = rows[5].replace("+00:00", "")  # naive: read as UTC like the rest
    csv, out = tmp_path / "iso.csv", tmp_path / "iso.mcap"
    csv.write_text("time,actuator_V,sensor_m\n" + "\n".join(rows) + "\n")
    code, _, err = run(capsys, csv, "--out", out, "--column", "t=time", "--time-unit",
                            "iso")
    assert code == 0, err
    t = read_log(out).samples["t_s"]
    np.testing.assert_allclose(t, start.timestamp() + DT * np.arange(40), rtol=0, atol=1e-6)
    rows[7] = "2026-03-02 nonsense,7,7e-9"
    csv.write_text("time,actuator_V,sensor_m\n" + "\n".join(rows) + "\n")
    code, _, err = run(capsys, csv, "--out", out, "--column", "t=time", "--time-unit", "iso",
                       "--force")
    assert code == 2 and "line 9: time is not an ISO 8601 date-time" in err


def test_stray_rows_jitter_and_gaps_resampled_and_reported(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cols = logger_rows(jitter_s=0.004)
    rows = format_rows(cols)
    # rows index i is file line i + 4 (two comments and the header first)
    rows[100], rows[101] = rows[101], rows[100]  # a swapped pair: line 105 moved
    rows[200] = rows[199]  # an exact repeat on line 204, sample 200 lost: a 1-sample gap
    nan = rows[50].split(";")
    nan[1] = "NaN"
    rows[50] = ";".join(nan)  # line 54 bad: a 1-sample gap
    del rows[240:246]  # lines of samples 240-245 missing: a 7-interval gap
    rows.insert(150, ";".join(HEADER))  # a logger restart repeats the header on line 154
    csv, out = tmp_path / "stray.csv", tmp_path / "stray.mcap"
    write(csv, rows)

    code, _, err = run(capsys, csv, "--out", out, *MAPPING)  # neither skip nor resample
    assert code == 2 and "line 54: tilt_counts is 'NaN' (not finite)" in err
    assert "--resample sorts rows a little out of order in" in err  # the swapped pair
    code, _, err = run(capsys, csv, "--out", out, *MAPPING, "--skip-bad")
    assert code == 2 and "sampling is not uniform" in err and "--resample" in err
    assert not out.exists()

    code, stdout, err = run(capsys, csv, "--out", out, *MAPPING, "--skip-bad", "--resample")
    assert code == 0, err
    assert "line 54: tilt_counts is 'NaN'" in err
    assert "repeated header lines skipped (a logger restart?): 154" in err
    assert "rows out of order, sorted in: line 105" in err
    assert "rows repeating the one before, dropped: line 205" in err
    gaps = [line for line in err.splitlines() if line.startswith("gap after line")]
    assert len(gaps) == 3, err
    assert "gap after line 53:" in gaps[0] and "1 sample interpolated" in gaps[0]
    assert "6 samples interpolated" in gaps[2]
    assert "repeated headers skipped: 1" in stdout and "skipped bad rows: 1" in stdout

    log = read_log(out)
    s = log.samples
    assert len(s["t_s"]) == N  # the grid spans the file: every lost sample filled, none added
    np.testing.assert_allclose(np.diff(s["t_s"]), DT, rtol=2e-4)
    made = s["state"] == "interpolated"
    assert made.sum() == 1 + 1 + 6
    assert made[50] and made[200] and made[240:246].all() and not made[:50].any()
    # measured samples keep their values: the grid sits within the jitter of each row
    truth = cols["tilt_counts"] * COUNT_M
    kept = ~made
    kept[[99, 100, 101, 102]] = False  # the interpolation between jittered neighbours
    step = np.abs(np.diff(truth))
    steepest = np.maximum(np.r_[step, 0.0], np.r_[0.0, step])  # to either neighbour
    within = steepest * (2 * 0.004 + 1e-4) / DT  # the grid is within twice the jitter
    assert (np.abs(s["sensor_m"] - truth)[kept] <= within[kept] + 1e-18).all()
    assert np.abs(s["sensor_m"] - truth)[kept].max() > 0  # it did interpolate, not copy
    events = [e for e in log.events if e["kind"] == "gap"]
    # after the restart's header (line 154) each row sits one line further down
    assert [e["detail"]["after_line"] for e in events] == [53, 204, 244]
    assert events[2]["detail"]["samples_interpolated"] == 6
    assert "resampled" in log.metadata["leveler"]


def test_a_gap_too_long_fails_unless_allowed(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    cols = logger_rows()
    rows = format_rows(cols)
    del rows[100:190]  # 45 s without a sample, 91 intervals
    csv, out = tmp_path / "gap.csv", tmp_path / "gap.mcap"
    write(csv, rows)
    code, _, err = run(capsys, csv, "--out", out, *MAPPING, "--resample")
    assert code == 2
    assert "line 104: 45.5 s without a sample since line 103" in err and "--max-gap" in err
    assert not out.exists()
    code, _, err = run(capsys, csv, "--out", out, *MAPPING, "--resample", "--max-gap", "1min")
    assert code == 0, err
    assert (read_log(out).samples["state"] == "interpolated").sum() == 90


def test_a_row_far_out_of_order_is_a_stray_row(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A clock reset or a test line dated long ago is not sorted in."""
    rows = format_rows(logger_rows())
    stray = rows[10].split(";")
    rows.insert(200, ";".join([f"{MJD0:.11f}", *stray[1:]]))  # time of the first row
    csv, out = tmp_path / "reset.csv", tmp_path / "reset.mcap"
    write(csv, rows)
    code, _, err = run(capsys, csv, "--out", out, *MAPPING, "--resample")
    assert code == 2 and "line 204: MJD" in err and "more than 10 rows out of order" in err


@pytest.mark.parametrize("args,message", [
    (["--column", "pressure=x"], "unknown column role 'pressure'"),
    (["--column", "sensor"], "write ROLE=VALUE"),
    (["--scale", "sensor=abc"], "'abc' is not a number"),
    (["--scale", "sensor=0"], "must be a finite non-zero number"),
    (["--scale", "t=2"], "converted by --time-unit"),
    (["--scale", "sensor=1", "--scale", "sensor=2"], "given twice"),
    (["--max-gap", "5s"], "--max-gap needs --resample"),
    (["--column", "sensor=pzt_V", "--column", "actuator=pzt_V"], "named for two roles"),
])
def test_bad_options_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                               args: list[str], message: str) -> None:
    csv, out = tmp_path / "a.csv", tmp_path / "a.mcap"
    write(csv, format_rows(logger_rows()))
    code, _, err = run(capsys, csv, "--out", out, *args)
    assert code == 2 and message in err and "Traceback" not in err
    assert not out.exists()


def test_a_time_unit_that_looks_wrong_is_warned_of(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    cols = logger_rows()
    csv, out = tmp_path / "d.csv", tmp_path / "d.mcap"
    write(csv, format_rows(cols))
    mapping = [a for a in MAPPING if a not in ("--time-unit", "days")]
    code, stdout, err = run(capsys, csv, "--out", out, *mapping, "--resample")
    assert code == 0, err
    assert "is the time column in s?" in err and "172,800" not in stdout
