"""The `leveler` command line: help everywhere, asd on real logs, recover, clear errors."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from leveler.cli import build_parser, main
from leveler.logreader import read_log

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
    assert "ASD of tilt_rad" in proc.stdout
    row = next(ln for ln in proc.stdout.splitlines() if ln.strip().startswith("0.001 Hz"))
    ratio = float(row.split()[-1].rstrip("x"))
    assert ratio < 0.5  # closed loop well below open loop at 1 mHz
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


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
