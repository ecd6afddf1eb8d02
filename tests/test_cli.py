"""The `leveler` command line: help everywhere, asd on real logs, recover, clear errors."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from figure_capture import legend_texts, saved_figures

from leveler.cli.main import build_parser, main
from leveler.log.reader import read_log

REPO = Path(__file__).resolve().parents[1]
COMMANDS = ["run", "sim", "asd", "recover"]


def leveler(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "leveler.cli", *args], capture_output=True,
                          text=True, timeout=300, cwd=cwd)


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert f"usage: leveler {command}" in out
    assert len(out) > 300  # says what it does, not only the usage line


def test_version_and_a_bare_leveler(capsys: pytest.CaptureFixture[str]) -> None:
    """`leveler --version` names the version; a bare `leveler` shows the help, not an error."""
    from leveler import __version__

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith(f"leveler {__version__} (Python 3.")
    assert main([]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("usage: leveler") and "import-csv" in out and err == ""


SOCKET_VERBS_DO_NOT_IMPORT = ("numpy", "scipy", "control", "mcap", "matplotlib")


def test_the_socket_verbs_start_without_the_numeric_stack(tmp_path: Path) -> None:
    """`leveler status` (and every verb that only talks to the daemon) imports no numpy,
    scipy, python-control or mcap: polled at 3 a.m. or in a loop, it answers in ~0.1 s, not
    the ~0.4 s those imports cost. Judged in a fresh interpreter, to the error it gives with
    no daemon, so the status path itself runs."""
    probe = (
        "import sys\n"
        "from leveler.cli.main import main\n"
        f"rc = main(['status', '--socket', {str(tmp_path / 'none.sock')!r}])\n"
        f"heavy = {{m.split('.')[0] for m in sys.modules}} & {set(SOCKET_VERBS_DO_NOT_IMPORT)!r}\n"
        "print(rc, sorted(heavy))\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=60)
    rc, heavy = out.stdout.split(" ", 1)
    assert rc == "2" and "no leveler daemon is running" in out.stderr, out.stderr
    assert heavy.strip() == "[]", heavy


def test_top_level_help_lists_the_commands() -> None:
    text = build_parser().format_help()
    for command in COMMANDS:
        assert command in text


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("logs")
    closed = tmp / "closed.mcap"
    proc = leveler("sim", "--config", str(REPO / "config" / "sim.toml"), "--duration", "3h",
                   "--seed", "2", "--out", str(closed), cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    # an "open loop" log: the same plant with the loop never engaged
    cfg, n = re.subn(r"(?m)^(ki_v_per_m_s|kd_v_s_per_m) = .*$", r"\1 = 0.0",
                     (REPO / "config" / "sim.toml").read_text())
    assert n == 2
    (tmp / "open.toml").write_text(cfg)
    opened = tmp / "open.mcap"
    proc = leveler("sim", "--config", str(tmp / "open.toml"), "--duration", "3h", "--seed", "2",
                   "--out", str(opened), cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    return closed, opened


def test_asd_compares_two_logs_and_plots(logs: tuple[Path, Path], tmp_path: Path) -> None:
    closed, opened = logs
    png = tmp_path / "asd.png"
    proc = leveler("asd", str(opened), "--channel", "tilt_rad", "--compare", str(closed),
                   "--plot", str(png), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "ASD of tilt_rad [rad/sqrt(Hz)]" in proc.stdout  # the unit from the log's schema
    header = next(ln for ln in proc.stdout.splitlines() if ln.strip().startswith("frequency"))
    assert header.split()[1:] == ["open.mcap", "closed.mcap", "2nd/1st"]  # names, not paths
    row = next(ln for ln in proc.stdout.splitlines() if ln.strip().startswith("0.001 Hz"))
    ratio = float(row.split()[-1].rstrip("x"))
    assert ratio < 0.5  # closed loop well below open loop at 1 mHz
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_asd_legend_tells_a_log_from_itself(logs: tuple[Path, Path], tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """The same file twice (or two alike names) still gives two legend entries one can tell
    apart, file names not paths, and the axes say what is drawn in which unit."""
    from leveler.cli.asd import _short_labels

    closed = logs[0]
    figures = saved_figures(monkeypatch)
    assert main(["asd", str(closed), "--compare", str(closed), "--plot",
                 str(tmp_path / "asd.png")]) == 0
    [fig] = figures
    assert legend_texts(fig) == ["closed.mcap", "closed.mcap (compare)"]
    [ax] = fig.axes
    assert ax.get_xlabel() == "Frequency [Hz]" and ax.get_ylabel() == "ASD of sensor_m [m/√Hz]"
    assert "closed.mcap (compare)" in capsys.readouterr().out  # the table's column too
    assert _short_labels(["a/x/run.mcap", "b/y/run.mcap"]) == ["x/run.mcap", "y/run.mcap"]
    assert _short_labels(["run.mcap", "./run.mcap"]) == ["run.mcap", "run.mcap (compare)"]


def test_asd_units_come_from_each_fields_schema(logs: tuple[Path, Path]) -> None:
    units = read_log(logs[0]).units
    assert (units["sensor_m"], units["applied_v"], units["t_s"], units["temperature_k"]) == (
        "m", "V", "s", "K")
    assert "seq" not in units and "state" not in units  # no unit, none made up


def test_asd_json_is_a_spectrum(logs: tuple[Path, Path], tmp_path: Path) -> None:
    proc = leveler("asd", str(logs[0]), "--json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    spec = json.loads(proc.stdout)[str(logs[0])]
    assert len(spec["freq_hz"]) == len(spec["asd"]) > 50
    assert spec["freq_hz"] == sorted(spec["freq_hz"])


def test_asd_unknown_channel_lists_the_real_ones(logs: tuple[Path, Path], tmp_path: Path) -> None:
    proc = leveler("asd", str(logs[0]), "--channel", "tilt", cwd=tmp_path)
    assert proc.returncode == 2
    assert "no channel 'tilt'" in proc.stderr and "tilt_rad" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_asd_on_a_file_that_is_not_mcap(tmp_path: Path) -> None:
    bogus = tmp_path / "notes.mcap"
    bogus.write_text("not a log\n")
    proc = leveler("asd", str(bogus), cwd=tmp_path)
    assert proc.returncode == 2
    assert "not an MCAP file" in proc.stderr and "Traceback" not in proc.stderr


def test_recover_a_truncated_log(logs: tuple[Path, Path], tmp_path: Path) -> None:
    data = logs[0].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    damaged = read_log(cut)
    assert not damaged.complete
    out = tmp_path / "fixed.mcap"
    proc = leveler("recover", str(cut), "--out", str(out), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    fixed = read_log(out)
    assert fixed.complete
    assert len(fixed.samples["seq"]) == len(damaged.samples["seq"]) > 1000


def _sim_log_with_faults(tmp: Path, name: str, faults: str) -> Path:
    """A 1 h `leveler sim` log whose sensor fails as `faults` ([[sim.faults]] tables) say:
    held bad readings, logged as null like a daemon's."""
    cfg = (REPO / "config" / "sim.toml").read_text()
    assert "[sim]\nseed = 1\n" in cfg
    (tmp / f"{name}.toml").write_text(cfg.replace("[sim]\nseed = 1\n",
                                                  f"[sim]\nseed = 1\n{faults}\n"))
    out = tmp / f"{name}.mcap"
    proc = leveler("sim", "--config", str(tmp / f"{name}.toml"), "--duration", "1h",
                   "--out", str(out), cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    return out


def test_asd_bridges_a_few_held_bad_readings_and_refuses_long_gaps(tmp_path: Path) -> None:
    """A daemon log with one glitch (sensor_m null while the voltage was held) is analysed
    with a note; one whose sensor was out for a minute is refused, saying why."""
    glitch = _sim_log_with_faults(tmp_path, "glitch", (
        '[[sim.faults]]\nkind = "nan"\nat_s = 600.0\nduration_s = 0.95\n'
        '[[sim.faults]]\nkind = "timeout"\nat_s = 1800.0\n'))
    sensor = read_log(glitch).samples["sensor_m"]
    bad = int(np.count_nonzero(~np.isfinite(sensor)))
    assert bad == 11  # 10 NaN readings and one timeout
    proc = leveler("asd", str(glitch), "--json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == (f"leveler asd: note: {glitch}: bridged 11 non-finite 'sensor_m' "
                           f"samples (0.031% of {len(sensor)}) in 2 gaps, the longest 1 s, by "
                           "linear interpolation (held bad readings or driver errors)\n")
    spec = json.loads(proc.stdout)[str(glitch)]
    assert all(np.isfinite(spec["asd"])) and spec["freq_hz"][0] < 1e-3

    outage = _sim_log_with_faults(tmp_path, "outage", (
        '[[sim.faults]]\nkind = "nan"\nat_s = 600.0\nduration_s = 60.0\n'))
    proc = leveler("asd", str(outage), cwd=tmp_path)
    assert proc.returncode == 2
    (line,) = proc.stderr.splitlines()
    assert line.startswith(f"leveler asd: error: {outage}: 600 non-finite values in "
                           "'sensor_m' (sensor faults?) in 1 gaps, 1.67% of the record, the "
                           "longest 60 s; asd bridges gaps only up to 1% of the record and "
                           "10 s each: cut the log around them first"), line


@pytest.mark.parametrize(
    ("x", "fs", "samples", "gaps", "trimmed", "refused"),
    [
        (np.r_[np.ones(100), np.nan, np.ones(99)], 1.0, 1, 1, 0, None),
        (np.r_[np.nan, np.nan, np.ones(200), np.nan], 1.0, 0, 0, 3, None),
        (np.r_[np.ones(100), [np.nan] * 3, np.ones(97)], 1.0, None, None, None, "1.50% of"),
        (np.r_[np.ones(5000), [np.nan] * 11, np.ones(5000)], 1.0, None, None, None,
         "the longest 11 s"),
        (np.r_[np.ones(5000), [np.nan] * 11, np.ones(5000)], 2.0, 11, 1, 0, None),
        (np.full(20, np.nan), 1.0, None, None, None, "every value"),
    ],
)
def test_bridge_gaps_bounds(x: np.ndarray, fs: float, samples: int | None, gaps: int | None,
                            trimmed: int | None, refused: str | None) -> None:
    from leveler.cli.asd import bridge_gaps
    from leveler.log.reader import LogError

    if refused is not None:
        with pytest.raises(LogError, match=re.escape(refused)):
            bridge_gaps(x, fs, "sensor_m", "a.mcap")
        return
    out, b = bridge_gaps(x, fs, "sensor_m", "a.mcap")
    assert (b.samples, b.gaps, b.trimmed) == (samples, gaps, trimmed)
    assert np.all(np.isfinite(out)) and len(out) == len(x) - trimmed
    np.testing.assert_allclose(out, 1.0)  # a straight line between equal neighbours


def test_the_license_is_an_spdx_expression() -> None:
    """Packaging tools read the license from its SPDX expression (PEP 639), not a free text."""
    import importlib.metadata

    meta = importlib.metadata.metadata("lab-leveler")
    assert meta["License-Expression"] == "BSD-3-Clause"
    assert "LICENSE" in (meta.get_all("License-File") or [])
