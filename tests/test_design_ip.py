"""`leveler design ip`: the paper's N = 9, the counterweight pick, the stability limit, the CLI."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from leveler.cli.main import main
from leveler.procedures.design_ip import (
    DesignError,
    IpModel,
    evaluate,
    max_amplification_at,
    pick,
    table_masses,
)
from leveler.sim.params import G_STANDARD, PendulumParams
from leveler.sim.pendulum import equilibrium_angle

REPO = Path(__file__).resolve().parents[1]
TILT = 1e-3  # the paper's reference tilt


def ip_model(height_m: float = 0.05, frame_mass_kg: float = 0.0,
             frame_com_m: float = 0.0) -> IpModel:
    return IpModel(PendulumParams(flexure_stiffness_nm_per_rad=0.1), height_m, frame_mass_kg,
                   frame_com_m)


def leveler(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "leveler.cli", *args], capture_output=True,
                          text=True, timeout=60, cwd=REPO)


def test_paper_example_k_0p1_mgl_0p09_gives_n_9() -> None:
    model = ip_model()
    p = evaluate(model, 0.09 / (G_STANDARD * 0.05), TILT)
    assert p.gravity_stiffness_nm_per_rad == pytest.approx(0.09, rel=1e-12)
    assert p.n_small_angle == pytest.approx(9.0, rel=1e-9)
    assert p.n_at_tilt == pytest.approx(9.0, rel=0.01)
    assert p.n_at_tilt < p.n_small_angle  # sin() softens the gravity torque
    assert p.theta_rad is not None
    # theta really balances the torques at the 1 mrad tilt
    assert 0.09 * math.sin(p.theta_rad + TILT) == pytest.approx(0.1 * p.theta_rad, rel=1e-9)


@pytest.mark.parametrize("target_n", [0.5, 9.0, 10.0, 50.0, 150.0])
def test_picked_mass_reproduces_the_requested_n(target_n: float) -> None:
    model = ip_model(frame_mass_kg=0.05, frame_com_m=0.02)
    chosen = pick(model, target_n, TILT)
    theta = equilibrium_angle(model.pendulum(chosen.cw_mass_kg), TILT)
    assert theta / TILT == pytest.approx(target_n, rel=1e-9)
    assert model.pendulum(chosen.cw_mass_small_angle_kg).amplification == pytest.approx(
        target_n, rel=1e-9)
    # non-linear needs more gravity stiffness than small-angle for the same N
    assert chosen.cw_mass_kg > chosen.cw_mass_small_angle_kg


def test_n_10_needs_the_papers_180_to_190_g_on_the_default_stand() -> None:
    base = PendulumParams()  # 185 g at 49.6 mm on 0.1 N m/rad, as config/sim.toml
    chosen = pick(IpModel(base, base.com_length_m), 10.0, TILT)
    assert 0.180 <= chosen.cw_mass_kg <= 0.190
    # trimming: small-angle dN/dm, checked against a finite difference
    model = IpModel(base, base.com_length_m)
    dm = 1e-7
    n_hi = model.pendulum(chosen.cw_mass_small_angle_kg + dm).amplification
    n_lo = model.pendulum(chosen.cw_mass_small_angle_kg - dm).amplification
    assert chosen.dn_dm_per_kg == pytest.approx((n_hi - n_lo) / (2 * dm), rel=1e-5)


def test_stability_limit_is_where_mgl_equals_k() -> None:
    model = ip_model(frame_mass_kg=0.1, frame_com_m=0.02)
    limit = model.stability_limit_kg
    assert limit == pytest.approx((0.1 / G_STANDARD - 0.1 * 0.02) / 0.05, rel=1e-12)
    assert model.gravity_stiffness_nm_per_rad(limit) == pytest.approx(0.1, rel=1e-12)
    below, above = evaluate(model, limit * (1 - 1e-6), TILT), evaluate(model, limit * 1.001, TILT)
    assert below.stable and below.n_small_angle is not None and below.n_small_angle > 1e5
    # the non-linear N stays finite: u - sin(u) = phi, about (6 phi)^(1/3) / phi - 1
    assert below.n_at_tilt == pytest.approx(max_amplification_at(TILT), rel=1e-3)
    assert max_amplification_at(TILT) == pytest.approx((6 * TILT) ** (1 / 3) / TILT - 1,
                                                       rel=0.01)
    assert not above.stable and above.n_at_tilt is None and above.theta_rad is None


def test_requests_no_counterweight_meets_are_design_errors() -> None:
    model = ip_model()
    with pytest.raises(DesignError, match="stays below N = 180"):
        pick(model, 200.0, TILT)
    with pytest.raises(DesignError, match="must be > 0"):
        pick(model, -1.0, TILT)
    with pytest.raises(DesignError, match="frame alone already amplifies"):
        pick(ip_model(frame_mass_kg=0.5, frame_com_m=0.01), 0.5, TILT)
    with pytest.raises(DesignError, match="frame alone is unstable"):
        ip_model(frame_mass_kg=0.5, frame_com_m=0.05)
    with pytest.raises(DesignError, match="above the pivot"):
        ip_model(height_m=-0.01)
    with pytest.raises(DesignError, match="0 < MIN < MAX"):
        table_masses(0.2, 0.1, None)


def test_default_table_steps_are_round() -> None:
    assert table_masses(0.10, 0.22, None) == pytest.approx([0.10 + 0.01 * i for i in range(13)])


def test_help_says_what_it_does() -> None:
    proc = leveler("design", "ip", "--help")
    assert proc.returncode == 0, proc.stderr
    text = " ".join(proc.stdout.split())
    assert "usage: leveler design ip" in text
    for phrase in ("Figure 8", "m g L_cm sin(theta + phi) = k theta", "stability limit",
                   "--target-n", "--tilt-rad", "--mass-kg MIN MAX", "--json", "--plot"):
        assert phrase in text


def test_json_and_plot_via_the_real_cli(tmp_path: Path) -> None:
    png = tmp_path / "ip.png"
    proc = leveler("design", "ip", "--target-n", "9", "--mass-kg", "0.15", "0.22", "--step-kg",
                   "0.01", "--json", "--plot", str(png))
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert set(r) == {"config", "model", "configured", "tilt_rad", "stability_limit", "sweep",
                      "pick", "plot"}
    h = r["model"]["cw_height_m"]
    assert h == 0.0496 and r["tilt_rad"] == TILT and r["plot"] == str(png)
    limit = r["stability_limit"]["cw_mass_kg"]
    assert limit * G_STANDARD * h == pytest.approx(0.1, rel=1e-12)
    pk = r["pick"]
    assert pk["target_n"] == 9 and pk["n_at_tilt"] == pytest.approx(9.0, rel=1e-9)
    assert pk["cw_mass_small_angle_kg"] * G_STANDARD * h == pytest.approx(0.09, rel=1e-12)
    masses = [row["cw_mass_kg"] for row in r["sweep"]]
    assert masses == pytest.approx([0.15 + 0.01 * i for i in range(8)])
    for row in r["sweep"]:
        assert row["stable"] == (row["cw_mass_kg"] < limit)
        assert (row["n_at_tilt"] is None) == (not row["stable"])
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert struct.unpack(">II", data[16:24]) == (960, 600)  # 8 x 5 in at 120 dpi


def test_text_table_draws_the_limit_across_the_sweep(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["design", "ip", "--config", str(REPO / "config" / "sim.toml"),
                 "--mass-kg", "0.18", "0.22"]) == 0
    lines = capsys.readouterr().out.splitlines()
    marker = next(i for i, line in enumerate(lines) if "-- stability limit 0.2056 kg --" in line)
    assert lines[marker - 1].lstrip().startswith("0.2050")  # 5 g steps: 0.04 kg in <= 15 rows
    assert "unstable" in lines[marker + 1] and lines[marker + 1].lstrip().startswith("0.2100")


def test_unreachable_n_is_a_clear_error_not_a_traceback() -> None:
    proc = leveler("design", "ip", "--target-n", "500")
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert "leveler design ip: error: no counterweight gives N = 500" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("args", [["--mass-kg", "0.2", "0.1"], ["--tilt-rad=-1e-3"],
                                  ["--step-kg", "1e-9"], ["--cw-height-m", "0"]])
def test_bad_options_exit_2_with_a_message(args: list[str],
                                           capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["design", "ip", "--config", str(REPO / "config" / "sim.toml"), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("leveler design ip: error: ")
