"""Thrust stiffness and compliance against tilt: identification, regimes, fits, tilt budget, CLI."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from figure_capture import saved_figures

from leveler.cli.main import main
from leveler.procedures import stiffness as st
from leveler.sim.torsion import TorsionParams

REPO = Path(__file__).resolve().parents[1]
P = TorsionParams()
# The least-squares 0 Hz value underweights the gravity deflection by the ringing after each
# edge: r_identified / r_true = 200 s / (200 s + 2 x 2.5 s) for the default pendulum (Q = 10).
RING_BIAS = 0.03


@pytest.fixture(scope="module")
def sweep_1un() -> list[st.TiltPoint]:
    return st.tilt_sweep(P, 1e-6, st.sweep_tilts(20e-6, 5e-6))


@pytest.fixture(scope="module")
def sweep_01un() -> list[st.TiltPoint]:
    return st.tilt_sweep(P, 1e-7, 1e-6 * np.array([-10.0, -2.5, 0.0, 5.0]))


def test_identified_compliance_follows_the_paper_formula(sweep_1un: list[st.TiltPoint]) -> None:
    for pt in sweep_1un:
        r_true = P.coupling_ratio(1e-6, pt.tilt_rad)
        # S = (1 + r) / K0: nothing in the identification knows r
        assert pt.compliance_rad_per_nm == pytest.approx((1 + r_true) / 0.2, rel=RING_BIAS)
        assert pt.coupling_ratio == pytest.approx(r_true, rel=RING_BIAS, abs=1e-9)
        # the pendulum's own (incremental) stiffness and dynamics do not depend on tilt
        assert pt.incremental_stiffness_nm_per_rad == pytest.approx(0.2, rel=5e-3)
        assert pt.fit.natural_frequency_hz == pytest.approx(P.natural_frequency_hz, rel=5e-3)
        assert pt.fit.quality_factor == pytest.approx(P.quality_factor, rel=0.05)


def test_without_tilt_coupling_stiffness_is_k0_at_every_tilt() -> None:
    flat = TorsionParams(com_y_m=0.0)
    for pt in st.tilt_sweep(flat, 1e-6, np.array([-20e-6, 0.0, 20e-6])):
        assert pt.stiffness_nm_per_rad == pytest.approx(0.2, rel=5e-3)


def test_regime_names() -> None:
    assert st.regime(0.3) == st.SOFTENING
    assert st.regime(-0.3) == st.STIFFENING
    assert st.regime(-1.5) == st.NEGATIVE
    assert st.regime(0.0) == st.LEVEL


def test_three_regimes_appear_at_the_smaller_thrust(sweep_01un: list[st.TiltPoint]) -> None:
    by_tilt = {round(pt.tilt_rad * 1e6, 1): pt for pt in sweep_01un}
    # r = 1.18 per 5 urad at 0.1 uN: -10 urad gives r = -2.35, -2.5 urad r = -0.59
    assert by_tilt[-10.0].regime == st.NEGATIVE
    assert by_tilt[-10.0].stiffness_nm_per_rad < 0
    assert by_tilt[-2.5].regime == st.STIFFENING
    assert by_tilt[-2.5].stiffness_nm_per_rad > 0.2
    assert by_tilt[5.0].regime == st.SOFTENING
    assert 0 < by_tilt[5.0].stiffness_nm_per_rad < 0.2
    for pt in sweep_01un:
        assert math.isfinite(pt.compliance_rad_per_nm)
        assert st.regime(pt.model_coupling_ratio) == pt.regime  # the same verdict as the model


def test_compliance_is_linear_and_stiffness_a_two_term_exponential(
        sweep_1un: list[st.TiltPoint]) -> None:
    lin = st.fit_compliance(sweep_1un)
    assert lin.r_squared > 0.9999
    assert lin.intercept_rad_per_nm == pytest.approx(1 / 0.2, rel=5e-3)
    # slope = M g l_cm / (F L K0)
    model_slope = P.tilt_sensitivity_nm_per_rad / (1e-6 * P.arm_m * 0.2)
    assert lin.slope_rad_per_nm_per_rad == pytest.approx(model_slope, rel=RING_BIAS)
    fit = st.fit_stiffness(sweep_1un)
    assert fit.r_squared > 0.9999
    assert fit.max_rel_error < 0.01
    # stiffening below level, softening above, and not symmetric about level (paper, Fig. 5)
    k_low, k_0, k_high = fit(np.array([-20.0, 0.0, 20.0]))
    assert k_low - k_0 > k_0 - k_high > 0


def test_stiffness_fit_refuses_negative_stiffness(sweep_01un: list[st.TiltPoint]) -> None:
    with pytest.raises(ValueError, match="K > 0"):
        st.fit_stiffness(sweep_01un)


def test_tilt_budget_from_the_quarter_torque_rule(sweep_1un: list[st.TiltPoint]) -> None:
    true_budget = math.asin(1e-6 * P.arm_m / (4 * P.tilt_sensitivity_nm_per_rad))
    assert true_budget == pytest.approx(10.62e-6, rel=1e-3)
    assert st.tilt_budget_rad(P.tilt_sensitivity_nm_per_rad, 1e-6, P.arm_m) == pytest.approx(
        true_budget)
    sens = st.tilt_sensitivity_nm_per_rad(st.fit_compliance(sweep_1un), 1e-6, P.arm_m)
    measured = st.tilt_budget_rad(sens, 1e-6, P.arm_m)
    assert measured == pytest.approx(true_budget, rel=RING_BIAS)
    # at the budget the gravity torque is a quarter of the thrust torque: |r| = 1/4
    assert P.coupling_ratio(1e-6, true_budget) == pytest.approx(0.25)
    assert st.tilt_budget_rad(sens, 1e-7, P.arm_m) == pytest.approx(measured / 10, rel=1e-6)
    assert st.tilt_budget_rad(0.0, 1e-7, P.arm_m) == pytest.approx(math.pi / 2)


def test_negative_stiffness_boundary() -> None:
    s = P.tilt_sensitivity_nm_per_rad
    edge = st.negative_stiffness_tilt_rad(s, 1e-7, P.arm_m)
    assert edge == pytest.approx(-4.249e-6, rel=1e-3)
    assert P.coupling_ratio(1e-7, edge) == pytest.approx(-1.0)
    assert st.negative_stiffness_tilt_rad(s, 1.0, P.arm_m) is None


def test_sweep_needs_the_level_point() -> None:
    with pytest.raises(ValueError, match="include 0"):
        st.tilt_sweep(P, 1e-6, np.array([1e-6, 2e-6]))
    assert list(st.sweep_tilts(20e-6, 10e-6) * 1e6) == pytest.approx([-20, -10, 0, 10, 20])


def test_analyze_help_explains(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (["analyze", "--help"], ["analyze", "stiffness", "--help"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "usage: leveler analyze stiffness" in out
    for phrase in ("compliance", "r = M g sin(tilt) l_cm / (F L)", "negative stiffness",
                   "1/4", "--plot-dir", "--json", "two-term exponential"):
        assert phrase in out


def test_cli_json_and_plots(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "leveler.cli", "analyze", "stiffness", "--stiffness-nm-per-rad",
         "0.2", "--tilt-step-rad", "10e-6", "--json", "--plot-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    first, second = r["sweeps"]
    assert (first["thrust_n"], second["thrust_n"]) == (1e-6, 1e-7)
    assert first["stiffness_fit"]["r_squared"] > 0.999
    assert first["tilt_budget_rad"] == pytest.approx(10.62e-6, rel=RING_BIAS)
    assert second["stiffness_fit"] is None and "K > 0" in second["stiffness_fit_skipped"]
    assert second["regimes_seen"][st.NEGATIVE] == pytest.approx([-20e-6, -10e-6])
    assert second["regimes_seen"][st.SOFTENING] == pytest.approx([10e-6, 20e-6])
    assert first["regimes_seen"][st.STIFFENING] == pytest.approx([-20e-6, -10e-6])
    assert all(pt["stiffness_nm_per_rad"] is not None for pt in second["points"])
    for name in ("transfer_1uN.png", "transfer_0.1uN.png", "stiffness.png", "compliance.png",
                 "regimes.png"):
        assert (tmp_path / name).stat().st_size > 10_000


def test_transfer_legends_name_each_k0_and_tilt_once(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Colour is K0 and line style the tilt: a legend for each, rather than ten entries each
    repeating "K0 = 0.2 N m/rad"; a tilt whose H(0) is negative says so once."""
    from matplotlib.legend import Legend

    figures = saved_figures(monkeypatch)
    assert main(["analyze", "stiffness", "--tilt-step-rad", "10e-6", "--json", "--plot-dir",
                 str(tmp_path)]) == 0
    for fig, negative in zip(figures[:2], ([], ["-20 urad", "-10 urad"]), strict=True):
        [ax] = fig.axes
        [colours] = [a for a in ax.artists if isinstance(a, Legend)]  # added beside the other
        tilts = ax.get_legend()
        assert [t.get_text() for t in colours.get_texts()] == ["K0 = 0.2 N m/rad",
                                                               "K0 = 0.02 N m/rad"]
        assert tilts.get_title().get_text() == "base tilt"
        texts = [t.get_text() for t in tilts.get_texts()]
        assert [t.split(" (")[0] for t in texts] == ["-20 urad", "-10 urad", "+0 urad",
                                                    "+10 urad", "+20 urad"]
        assert [t.split(" (")[0] for t in texts if "(H(0) < 0)" in t] == negative
        assert ax.get_ylabel().endswith("[m/N]") and ax.get_xlabel() == "Frequency [Hz]"


def test_cli_rejects_a_bad_sweep(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "stiffness", "--tilt-step-rad", "0"]) == 2
    assert "tilt step" in capsys.readouterr().err
