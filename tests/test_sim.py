"""`leveler sim` end to end: the issue's acceptance run, determinism, and the report."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from figure_capture import legend_texts, saved_figures

from leveler.cli.main import main
from leveler.log.reader import read_log

REPO = Path(__file__).resolve().parents[1]
PAPER_OPEN_LOOP_M_RTHZ = 5.7e-6


def sim(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "leveler.cli", "sim", "--config", str(REPO / "config" / "sim.toml"),
         *args], capture_output=True, text=True, timeout=600, cwd=tmp_path)


@pytest.fixture(scope="module")
def day(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    tmp = tmp_path_factory.mktemp("day")
    out = tmp / "run.mcap"
    proc = sim(tmp, "--duration", "24h", "--seed", "1", "--out", str(out), "--json")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout), out


def test_day_json_has_the_promised_shape(day: tuple[dict[str, Any], Path]) -> None:
    result, _ = day
    assert result["samples"] == 864000
    assert result["sim_s"] == pytest.approx(86400.0)
    assert result["wall_s"] > 0
    asd = result["asd"]
    assert asd["freq_hz"] == [0.0001, 0.001, 0.01]
    for run in ("open_loop", "closed_loop"):
        for key in ("sensor_m_rthz", "tilt_rad_rthz"):
            assert len(asd[run][key]) == 3
            assert all(v > 0 for v in asd[run][key])


def test_day_open_loop_is_the_papers_and_the_loop_removes_20x(
        day: tuple[dict[str, Any], Path]) -> None:
    asd = day[0]["asd"]
    open_sensor = asd["open_loop"]["sensor_m_rthz"][0]
    assert PAPER_OPEN_LOOP_M_RTHZ / 2 <= open_sensor <= PAPER_OPEN_LOOP_M_RTHZ * 2
    tilt_open = asd["open_loop"]["tilt_rad_rthz"][0]
    tilt_closed = asd["closed_loop"]["tilt_rad_rthz"][0]
    assert tilt_open / tilt_closed >= 20
    assert asd["open_loop"]["sensor_m_rthz"][0] / asd["closed_loop"]["sensor_m_rthz"][0] >= 20


def test_day_log_holds_every_sample(day: tuple[dict[str, Any], Path]) -> None:
    result, out = day
    data = read_log(out)
    assert data.complete
    np.testing.assert_array_equal(data.samples["seq"], np.arange(result["samples"]))
    assert len(data.truth["tilt_rad"]) == result["samples"]
    assert data.metadata["leveler"]["seed"] == "1"


def test_same_seed_gives_an_identical_log(tmp_path: Path) -> None:
    logs = []
    for name in ("a", "b", "c"):
        seed = "4" if name != "c" else "5"
        out = tmp_path / f"{name}.mcap"
        proc = sim(tmp_path, "--duration", "20m", "--seed", seed, "--out", str(out), "--json")
        assert proc.returncode == 0, proc.stderr
        logs.append(read_log(out))
    a, b, c = logs
    for field in set(a.samples) - {"log_time_ns"}:  # wall-clock start differs by design
        np.testing.assert_array_equal(a.samples[field], b.samples[field], err_msg=field)
    for field in set(a.truth) - {"log_time_ns"}:
        np.testing.assert_array_equal(a.truth[field], b.truth[field], err_msg=field)
    assert not np.array_equal(a.samples["sensor_m"], c.samples["sensor_m"])


def test_short_run_reports_what_it_can(tmp_path: Path) -> None:
    proc = sim(tmp_path, "--duration", "2h")
    assert proc.returncode == 0, proc.stderr
    assert "0.1 mHz" in proc.stdout and "too short" in proc.stdout
    assert "10.0 mHz" in proc.stdout


def test_plot_shows_sensor_and_true_tilt_against_the_paper(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two log-log panels on one frequency axis, units on every axis, the paper's Fig. 15
    point on the sensor panel and the gains with units in the title."""
    figures = saved_figures(monkeypatch)
    png = tmp_path / "sim.png"
    assert main(["sim", "--config", str(REPO / "config" / "sim.toml"), "--duration", "2h",
                 "--seed", "3", "--json", "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    [fig] = figures
    sensor, tilt = fig.axes
    assert sensor.get_ylabel().endswith("[m/√Hz]") and tilt.get_ylabel().endswith("[rad/√Hz]")
    assert tilt.get_xlabel() == "Frequency [Hz]"
    assert sensor.get_shared_x_axes().joined(sensor, tilt)
    assert {ax.get_xscale() for ax in fig.axes} == {ax.get_yscale() for ax in fig.axes} == {"log"}
    paper = {line.get_label(): (line.get_xdata()[0], line.get_ydata()[0])
             for line in sensor.get_lines() if line.get_label().startswith("paper")}
    assert paper == {"paper, open 5.7 µm/√Hz": (1e-4, 5.7e-6),
                     "paper, closed 0.28 µm/√Hz": (1e-4, 2.8e-7)}
    assert sensor.get_xlim()[0] <= 1e-4  # the point is on the plot though 2 h do not reach it
    assert legend_texts(fig) == ["open loop", "closed loop", *paper, "open loop", "closed loop"]
    # Panel (b) is the truth, not the sensor again: the loop removes more of the reading
    # than of the tilt it stands for (out of loop, at 1 mHz: 56x, in loop: 590x).
    (so, sc), (to, tc) = ([np.interp(1e-3, *line.get_data()) for line in ax.get_lines()[:2]]
                          for ax in (sensor, tilt))
    assert to / tc > 10
    assert so / sc > 3 * (to / tc)
    title = fig.get_suptitle()
    for text in ("2 h", "seed 3", "V/m", "V/(m s)", "V s/m", "2.2×10$^{7}$"):
        assert text in title
