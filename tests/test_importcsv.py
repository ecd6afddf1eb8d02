"""`leveler import-csv`: other systems' CSV recordings become leveler logs, or fail loudly.

Bad input must never leave a log behind (a half-imported or gappy time base would corrupt
replay and every spectrum computed from it), and every refusal must name the line.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path

import numpy as np
import pytest

from leveler import __version__
from leveler.cli.main import main
from leveler.log import import_csv as importcsv
from leveler.log.reader import read_log
from leveler.log.writer import LogWriter

N = 200
DT = 0.1


def columns(n: int = N, seed: int = 0) -> dict[str, np.ndarray]:
    """Values that exercise float round-tripping: random mantissas, tiny and large scales."""
    rng = np.random.default_rng(seed)
    return {
        "t_s": 12.5 + np.arange(n) * DT,
        "actuator_V": rng.uniform(-30.0, 150.0, n),
        "sensor_m": rng.normal(0.0, 3e-6, n),
        "temperature_K": 293.15 + rng.normal(0.0, 0.02, n),
    }


def write_csv(path: Path, cols: dict[str, np.ndarray], header: list[str] | None = None,
              preamble: str = "") -> list[str]:
    """Write `cols` (header names may differ in case/order); returns the file's lines."""
    names = header or list(cols)
    keys = {k.lower(): k for k in cols}
    data = [cols[keys[n.strip().lower()]] for n in names]
    lines = [*preamble.splitlines(), ",".join(names)]
    lines += [",".join(repr(float(x)) for x in row) for row in zip(*data, strict=True)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return lines


def run(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    code = main(["import-csv", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def assert_nothing_written(out: Path) -> None:
    assert not out.exists()
    assert not out.with_name(out.name + ".partial").exists()


def test_round_trip_with_temperature(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cols = columns()
    csv, out = tmp_path / "stand.csv", tmp_path / "stand.mcap"
    write_csv(csv, cols, preamble="# exported by another stand\n\n# units: SI")
    code, stdout, err = run(capsys, csv, "--out", out)
    assert code == 0, err
    assert f"imported {N} rows" in stdout
    assert "temperature: yes" in stdout and "10 Hz" in stdout
    assert "skipped bad rows: 0" in stdout
    log = read_log(out)
    assert log.complete
    s = log.samples
    np.testing.assert_array_equal(s["seq"], np.arange(N))
    for got, want in [(s["t_s"], cols["t_s"]), (s["sensor_m"], cols["sensor_m"]),
                      (s["applied_v"], cols["actuator_V"]),
                      (s["command_v"], cols["actuator_V"]),
                      (s["error_m"], -cols["sensor_m"]),
                      (log.environment["temperature_k"], cols["temperature_K"]),
                      (log.environment["t_s"], cols["t_s"])]:
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    assert (s["state"] == "imported").all()
    np.testing.assert_array_equal(s["log_time_ns"], np.rint(cols["t_s"] * 1e9).astype(np.int64))
    np.testing.assert_array_equal(log.environment["seq"], np.arange(N))
    meta = log.metadata["leveler"]
    assert meta["source"] == "import-csv"
    assert meta["csv"] == str(csv.resolve())
    assert meta["rows"] == str(N)
    assert meta["version"] == __version__
    assert meta["columns"] == "t_s,actuator_V,sensor_m,temperature_K"
    assert [e["kind"] for e in log.events] == ["start", "stop"]
    assert log.events[0]["detail"] == {"csv": str(csv.resolve())}
    assert not out.with_name(out.name + ".partial").exists()


def test_without_temperature_has_no_environment(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    cols = columns()
    del cols["temperature_K"]
    csv, out = tmp_path / "a.csv", tmp_path / "a.mcap"
    write_csv(csv, cols)
    code, stdout, err = run(capsys, csv, "--out", out)
    assert code == 0, err
    assert "temperature: no" in stdout
    log = read_log(out)
    assert log.environment == {}
    assert len(log.samples["seq"]) == N


def test_header_order_case_and_extra_columns(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    cols = columns()
    cols["Humidity"] = np.full(N, 40.0)
    csv, out = tmp_path / "shuffled.csv", tmp_path / "shuffled.mcap"
    write_csv(csv, cols, header=[" SENSOR_M", "Humidity", "Temperature_k ", "T_S", "actuator_v"])
    code, stdout, err = run(capsys, csv, "--out", out)
    assert code == 0, err
    assert "ignored columns: Humidity" in stdout
    log = read_log(out)
    np.testing.assert_allclose(log.samples["sensor_m"], cols["sensor_m"], rtol=1e-12, atol=0)
    np.testing.assert_allclose(log.samples["applied_v"], cols["actuator_V"], rtol=1e-12)
    np.testing.assert_allclose(log.samples["t_s"], cols["t_s"], rtol=1e-12)
    np.testing.assert_allclose(log.environment["temperature_k"], cols["temperature_K"],
                               rtol=1e-12)


def bad_file(tmp_path: Path) -> tuple[Path, dict[int, str]]:
    """A file with one bad row of each kind; returns it and {line number: expected reason}."""
    csv = tmp_path / "bad.csv"
    lines = write_csv(csv, columns())  # line 1 is the header, row i is on line i + 2
    bad = {
        5: ("12.8,1.0", "2 fields"),
        9: ("13.2,abc,1e-6,293.0", "actuator_V is not a number"),
        14: ("13.7,1.0,nan,293.0", "sensor_m is 'nan'"),
        20: ("14.3,1.0,1e-6,inf", "temperature_K is 'inf'"),
        31: ("13.0,1.0,1e-6,293.0", "not after"),
    }
    for lineno, (text, _) in bad.items():
        lines[lineno - 1] = text
    csv.write_text("\n".join(lines) + "\n")
    return csv, {k: v for k, (_, v) in bad.items()}


def test_bad_rows_fail_naming_each_line(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    csv, bad = bad_file(tmp_path)
    out = tmp_path / "bad.mcap"
    code, stdout, err = run(capsys, csv, "--out", out)
    assert code == 2 and stdout == ""
    assert err.startswith("leveler import-csv: error:")
    assert "Traceback" not in err
    assert f"{len(bad)} bad rows" in err
    for lineno, reason in bad.items():
        line = next(x for x in err.splitlines() if x.strip().startswith(f"line {lineno}:"))
        assert reason in line
    assert_nothing_written(out)


def test_skipped_rows_that_leave_gaps_still_fail(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """--skip-bad drops rows, but rows that held samples leave holes in the time base."""
    csv, _ = bad_file(tmp_path)
    out = tmp_path / "skip.mcap"
    code, _, err = run(capsys, csv, "--out", out, "--skip-bad")
    assert code == 2
    assert "not uniform" in err and "skipped bad rows leave gaps" in err
    assert_nothing_written(out)


def test_skip_bad_without_gaps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bad rows inserted between good ones (e.g. a logger's glitch lines) leave no gap."""
    cols = columns()
    csv, out = tmp_path / "glitch.csv", tmp_path / "glitch.mcap"
    lines = write_csv(csv, cols)
    inserted = {10: "13.3,oops,1,1", 40: "", 60: "ERROR sensor timeout", 90: "1.0,2.0,3.0,4.0"}
    for at in sorted(inserted):  # ascending: each lands on its line number
        lines.insert(at - 1, inserted[at])
    csv.write_text("\n".join(lines) + "\n")
    code, stdout, err = run(capsys, csv, "--out", out, "--skip-bad")
    assert code == 0, err
    bad_lines = [10, 60, 90]  # line 40 is blank: skipped, not bad
    for lineno in bad_lines:
        assert f"line {lineno}:" in err
    assert "line 40:" not in err
    assert f"skipped {len(bad_lines)} bad rows" in err
    assert f"imported {N} rows" in stdout and "skipped bad rows: 3" in stdout
    log = read_log(out)
    assert len(log.samples["seq"]) == N
    np.testing.assert_allclose(log.samples["sensor_m"], cols["sensor_m"], rtol=1e-12, atol=0)
    assert log.metadata["leveler"]["rows"] == str(N)


def test_time_not_increasing_is_named_by_line(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    cols = columns()
    cols["t_s"][50] = cols["t_s"][49]  # row 50 is on line 52
    csv, out = tmp_path / "t.csv", tmp_path / "t.mcap"
    write_csv(csv, cols)
    code, _, err = run(capsys, csv, "--out", out)
    assert code == 2
    assert re.search(r"line 52: t_s \S+ is not after \S+ \(line 51\)", err), err
    assert "1 bad row " in err
    assert_nothing_written(out)


def test_non_uniform_sampling(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cols = columns()
    cols["t_s"][120:] += 0.05  # a half-interval jump: interval ending at row 120 (line 122)
    csv, out = tmp_path / "gap.csv", tmp_path / "gap.mcap"
    write_csv(csv, cols)
    code, _, err = run(capsys, csv, "--out", out)
    assert code == 2
    assert "line 122: sampling is not uniform" in err
    assert "median interval 0.1 s" in err
    assert_nothing_written(out)


def test_small_jitter_is_accepted(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cols = columns()
    cols["t_s"] += np.random.default_rng(3).uniform(-0.0004, 0.0004, N)  # < 1% of 0.1 s
    csv, out = tmp_path / "jitter.csv", tmp_path / "jitter.mcap"
    write_csv(csv, cols)
    code, _, err = run(capsys, csv, "--out", out)
    assert code == 0, err


def test_missing_required_column_is_named(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    cols = columns()
    del cols["actuator_V"]
    csv, out = tmp_path / "m.csv", tmp_path / "m.mcap"
    write_csv(csv, cols)
    code, _, err = run(capsys, csv, "--out", out)
    assert code == 2
    assert "actuator_V missing" in err
    assert "'t_s,sensor_m,temperature_K'" in err  # the header it found
    assert_nothing_written(out)


def test_refuses_to_overwrite_without_force(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    csv, out = tmp_path / "o.csv", tmp_path / "o.mcap"
    write_csv(csv, columns())
    out.write_bytes(b"precious")
    code, _, err = run(capsys, csv, "--out", out)
    assert code == 2 and "already exists" in err and "--force" in err
    assert out.read_bytes() == b"precious"
    code, _, err = run(capsys, csv, "--out", out, "--force")
    assert code == 0, err
    assert len(read_log(out).samples["seq"]) == N


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "no header line"),
        (b"# only a comment\n\n", "no header line"),
        (b"t_s,actuator_V,sensor_m\n", "no data rows"),
        (b"t_s,actuator_V,sensor_m\n0,1,2\n0.1,1,2\n", "only 2 good data rows"),
        (b"t_s,actuator_V,sensor_m\n0,1,2\n0.1,1,\xff\n", "line 3: not UTF-8"),
    ],
)
def test_unusable_files_give_clear_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                          content: bytes, message: str) -> None:
    csv, out = tmp_path / "x.csv", tmp_path / "x.mcap"
    csv.write_bytes(content)
    code, _, err = run(capsys, csv, "--out", out)
    assert code == 2
    assert message in err and "Traceback" not in err
    assert_nothing_written(out)


def test_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(capsys, tmp_path / "nope.csv", "--out", tmp_path / "x.mcap")
    assert code == 2 and "no such file" in err


def test_negative_times_and_crlf(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """t_s as recorded (may start below 0); MCAP log times count from the first row then."""
    cols = columns()
    cols["t_s"] -= 100.0
    csv, out = tmp_path / "neg.csv", tmp_path / "neg.mcap"
    lines = write_csv(csv, cols)
    csv.write_bytes(("\ufeff" + "\r\n".join(lines) + "\r\n").encode())  # spreadsheet style
    code, _, err = run(capsys, csv, "--out", out)
    assert code == 0, err
    s = read_log(out).samples
    np.testing.assert_allclose(s["t_s"], cols["t_s"], rtol=1e-12)
    assert s["log_time_ns"][0] == 0
    assert (np.diff(s["log_time_ns"]) > 0).all()


def test_many_rows_are_all_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """More rows than the pacing interval: nothing may be dropped on the way to the file."""
    n = 25_000
    cols = columns(n)
    csv, out = tmp_path / "many.csv", tmp_path / "many.mcap"
    write_csv(csv, cols)
    code, stdout, err = run(capsys, csv, "--out", out)
    assert code == 0, err
    assert f"imported {n} rows" in stdout
    log = read_log(out)
    np.testing.assert_array_equal(log.samples["seq"], np.arange(n))
    np.testing.assert_array_equal(log.environment["seq"], np.arange(n))
    np.testing.assert_allclose(log.samples["sensor_m"], cols["sensor_m"], rtol=1e-12, atol=0)


def test_dropped_records_fail_and_leave_nothing(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str],
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """If the writer ever dropped records (no pacing, tiny backlog), the import must fail."""
    monkeypatch.setattr(importcsv, "_DRAIN_EVERY", 10**9)
    monkeypatch.setattr(importcsv, "LogWriter", functools.partial(LogWriter, max_backlog=10))
    csv, out = tmp_path / "d.csv", tmp_path / "d.mcap"
    write_csv(csv, columns(5000))
    code, _, err = run(capsys, csv, "--out", out)
    assert code == 2 and "records dropped" in err
    assert_nothing_written(out)


def test_help_states_the_format(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["import-csv", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for needed in ("temperature_K", "t_s", "actuator_V", "sensor_m", "--skip-bad", "--force",
                   "docs/log-format.md", "#"):
        assert needed in text
