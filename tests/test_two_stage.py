"""Two-stage torsion pendulum (paper Fig. 17): the decoupled estimate recovers the thrust."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from figure_capture import legend_texts, saved_figures
from scipy.signal import dlsim

from leveler.cli.main import main
from leveler.procedures.two_stage import TwoStageResult, run_two_stage
from leveler.sim.twostage import NullPID, TwoStageParams, closed_loop, discrete_response

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def result() -> TwoStageResult:
    return run_two_stage()


def test_decoupled_estimate_recovers_the_square_wave(result: TwoStageResult) -> None:
    assert result.correlation_decoupled >= 0.95
    # TP2 alone reads thrust plus its own tilt torque: clearly worse
    assert result.correlation_single < 0.8
    assert result.rms_error_n(result.decoupled_n) < 0.2 * result.rms_error_n(
        result.single_stage_n)


def test_kappa_calibration_finds_the_mass_com_ratio(result: TwoStageResult) -> None:
    p = result.params
    assert p.coupling_ratio == pytest.approx(1.0 * 1e-3 / (5.0 * 5e-3))
    assert result.kappa == pytest.approx(p.coupling_ratio, rel=0.02)


def test_without_tilt_single_stage_is_as_good() -> None:
    flat = run_two_stage(tilt_amplitude_rad=0.0)
    assert flat.correlation_single >= 0.95
    assert flat.correlation_single == pytest.approx(flat.correlation_decoupled, abs=0.02)


def test_quasi_static_balance_of_the_closed_loop() -> None:
    """At 0 Hz: phi1 = 0, K2 (phi2 - phi1) = F L + tau_2 and u = -(F L + tau_A)."""
    p = TwoStageParams()
    a, b, c, d = closed_loop(p, 0.1)
    dc = c @ np.linalg.solve(np.eye(a.shape[0]) - a, b) + d  # inputs: F L, tau_A-tau_2, tau_2, n1
    k2 = p.tp2.stiffness_nm_per_rad
    assert dc[0, :3] == pytest.approx([0, 0, 0], abs=1e-12)
    assert k2 * dc[1, :3] == pytest.approx([1, 0, 1], abs=1e-12)
    assert dc[2, :3] == pytest.approx([-1, -1, -1], abs=1e-12)


def test_modal_simulation_equals_a_plain_state_space_loop() -> None:
    a, b, c, d = closed_loop(TwoStageParams(), 0.1)
    w = np.random.default_rng(0).normal(size=(400, 4))
    _, want, _ = dlsim((a, b, c, d, 0.1), w)
    assert discrete_response(a, b, c, d, w) == pytest.approx(want, abs=1e-12 * np.abs(want).max())


def test_unstable_null_loop_is_reported() -> None:
    hot = replace(TwoStageParams(), pid=NullPID(kp_nm_per_rad=400.0, kd_nms_per_rad=50.0))
    with pytest.raises(ValueError, match="unstable"):
        closed_loop(hot, 0.1)


def test_plot_legends_beside_the_panels(result: TwoStageResult, tmp_path: Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The legends sit right of the panels: inside they hid the waves' crests. Every panel
    says what it shows in which unit."""
    from leveler.cli.analyze_two_stage import plot

    figures = saved_figures(monkeypatch)
    plot(result, str(tmp_path / "fig17.png"))
    [fig] = figures
    _, torque, thrust = fig.axes
    for ax in (torque, thrust):
        assert ax.get_legend().get_window_extent().x0 >= ax.get_window_extent().x1
    assert [ax.get_ylabel() for ax in fig.axes] == [
        "Base pitch [urad]", "TP1 balance torque [uN m]", "Thrust [uN]"]
    assert thrust.get_xlabel() == "Time [s]"
    assert legend_texts(fig)[0] == "-u, raw" and legend_texts(fig)[-1] == "true thrust"


def test_cli_help_json_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["analyze", "two-stage", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    for phrase in ("usage: leveler analyze two-stage", "null", "kappa", "correlation",
                   "--json", "--plot"):
        assert phrase in out
    png = tmp_path / "fig17.png"
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "analyze", "two-stage", "--json",
                           "--plot", str(png)], capture_output=True, text=True, timeout=300,
                          cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["correlation_two_stage"] >= 0.95
    assert r["correlation_single_stage"] < 0.8
    assert r["drive"]["tilt_amplitude_rad"] == 3e-6 and r["drive"]["tilt_frequency_hz"] == 0.01
    assert png.stat().st_size > 10_000
