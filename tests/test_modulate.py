"""`leveler modulate`: the square and triangle waves, their read-back, the simulated
procedure, and the daemon executing it as a logged procedure (a real process over its real
socket)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from figure_capture import saved_figures

from leveler.daemon.protocol import ProtocolError, modulate_args
from leveler.log.reader import read_log
from leveler.loop.modulation import Wave
from leveler.procedures.tilt_modulation import coherent, response


def test_square_wave_shape_and_end() -> None:
    w = Wave(75.0, 5.0, 10.0, 2, start_t_s=100.0)
    assert [w.command_v(t) for t in (100.0, 104.9, 105.0, 109.9, 110.0, 115.0)] == [
        80.0, 80.0, 70.0, 70.0, 80.0, 70.0]
    assert w.command_v(120.0) is None and w.end_t_s == 120.0
    for bad in ({"amplitude_v": 0.0}, {"period_s": -1.0}, {"cycles": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            Wave(**{"center_v": 75.0, "amplitude_v": 1.0, "period_s": 1.0, "cycles": 1,
                    **bad})  # type: ignore[arg-type]


def test_triangle_wave_starts_and_ends_at_its_centre_without_a_step() -> None:
    w = Wave(75.0, 4.0, 10.0, 2, start_t_s=100.0, shape="triangle")
    assert [w.command_v(t) for t in (100.0, 101.25, 102.5, 105.0, 107.5, 110.0, 112.5)] == \
        pytest.approx([75.0, 77.0, 79.0, 75.0, 71.0, 75.0, 79.0])
    v = np.array([w.command_v(t) for t in np.arange(100.0, 119.99, 0.01)])
    assert np.max(np.abs(np.diff(v))) == pytest.approx(4 * 4.0 / 10.0 * 0.01, rel=1e-6)
    assert w.command_v(120.0) is None
    with pytest.raises(ValueError, match="shape must be one of square, triangle"):
        Wave(75.0, 1.0, 1.0, 1, shape="sine")


def test_the_protocol_takes_a_shape_and_names_the_shapes_it_knows() -> None:
    req = {"v": 1, "verb": "modulate", "amplitude_v": 1.0, "period_s": 2.0, "cycles": 2}
    assert modulate_args(req) == (1.0, 2.0, 2, "square", False)
    assert modulate_args(req | {"shape": "triangle"})[3] == "triangle"
    for bad in ("sine", 3, None, ["triangle"]):
        with pytest.raises(ProtocolError, match="shape must be one of square, triangle"):
            modulate_args(req | {"shape": bad})


def test_a_wave_at_a_known_disturbances_period_is_flagged() -> None:
    """A cooler's harmonic on an odd harmonic of the wave repeats every cycle; an even one,
    or a period apart from it, does not."""
    def flagged(period_s: float, cycles: int = 3) -> bool:
        return bool(coherent(Wave(75.0, 5.0, period_s, cycles, shape="triangle"),
                             [(300.0, 2.8e-8)], 0.45))

    assert flagged(300.0) and flagged(100.0) and flagged(150.0) and flagged(60.0)
    assert not flagged(120.0) and not flagged(200.0) and not flagged(600.0)
    assert flagged(290.0, cycles=3) and not flagged(290.0, cycles=30)  # resolution
    [said] = coherent(Wave(75.0, 5.0, 100.0, 3), [(300.0, 2.8e-8)], 0.45)
    assert "harmonic 3 on the wave's 1): about 2.7 nm" in said  # 2 x 12.6 nm / (3 pi)


def test_response_reads_the_step_through_drift_and_noise() -> None:
    w = Wave(0.0, 1.0, 20.0, 4)
    t = np.arange(0.0, 80.0, 0.05)
    rng = np.random.default_rng(3)
    y = (3e-6 * (np.array([w.command_v(x) for x in t]) > 0)  # 3 um step
         + 2e-8 * t + 5e-9 * rng.standard_normal(len(t)))  # drift 1.6 um over the run
    r = response(w, t, y)
    assert r.peak_to_peak == pytest.approx(3e-6, rel=1e-3)
    assert r.steps == 6 and r.scatter < 5e-9
    with pytest.raises(ValueError, match="no samples in half period"):
        response(w, t[t < 50], y[t < 50])


def test_plot_says_what_wave_on_what_stand(tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from leveler.cli.modulate import _plot

    w = Wave(75.0, 5.0, 120.0, 2, start_t_s=10.0)
    t = np.arange(10.0, 250.0, 0.1)
    v = np.array([w.command_v(x) or 75.0 for x in t])
    figures = saved_figures(monkeypatch)
    _plot(str(tmp_path / "m.png"), w, t, 0.09e-6 * (v - 75.0), v)
    [fig] = figures
    top, bottom = fig.axes
    assert top.get_title() == ("Tilt modulation on the simulated stand: 2 × 120 s square "
                               "wave, piezo 75 V ± 5 V")
    assert top.get_ylabel() == "inverted pendulum reading [µm]"
    assert bottom.get_ylabel() == "piezo voltage [V]"
    assert bottom.get_xlabel() == "time since the wave started [s]"


def _cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "leveler.cli", "modulate", *args],
                          capture_output=True, text=True, timeout=timeout)


def test_simulated_procedure_recovers_the_piezo_geometry(tmp_path: Path) -> None:
    out = _cli("--sim", "--amplitude-v", "5", "--period", "60s", "--cycles", "3",
               "--settle", "10s", "--json", "--plot", str(tmp_path / "m.png"))
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    # 10 V p-p x 0.1 um/V over 0.5 m = 2 urad; x 8.99 x 5 cm = 0.899 um at the sensor.
    assert r["model_tilt_peak_to_peak_rad"] == pytest.approx(2e-6, rel=1e-6)
    assert r["true_tilt_peak_to_peak_rad"] == pytest.approx(2e-6, rel=0.01)
    assert r["ip_peak_to_peak_m"] == pytest.approx(0.899e-6, rel=0.02)
    assert r["measured_over_model"] == pytest.approx(1.0, abs=0.02)
    assert (tmp_path / "m.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    helped = _cli("--help")
    assert helped.returncode == 0
    for words in ("--amplitude-v", "--force", "refuses while the", "--tp-peak-to-peak-m",
                  "roll/pitch split", "virtual time"):
        assert words in " ".join(helped.stdout.split()), words
    bad = _cli("--sim", "--amplitude-v", "100", "--period", "60s")
    assert bad.returncode == 2 and "output" not in bad.stdout  # refused, no traceback
    assert "Traceback" not in bad.stderr


def test_daemon_refuses_while_engaged_runs_when_forced_and_closes_the_loop_again(
        start_daemon: Callable[..., object]) -> None:
    # A well damped pendulum (Q ~ 0.7) settles within each 3 s half period.
    d = start_daemon(rate_hz=20.0, replace={"damping_nms_per_rad = 1.2e-4":
                                            "damping_nms_per_rad = 6.0e-3"})
    d.wait_status_lines(2)  # type: ignore[attr-defined]
    sock = str(d.socket)  # type: ignore[attr-defined]
    refused = _cli("--amplitude-v", "2", "--period", "2s", "--socket", sock)
    assert refused.returncode == 2 and "engaged" in refused.stderr
    too_big = _cli("--amplitude-v", "80", "--period", "2s", "--force", "--socket", sock)
    assert too_big.returncode == 2 and "output range" in too_big.stderr
    out = _cli("--amplitude-v", "2", "--period", "6s", "--cycles", "2", "--force", "--json",
               "--socket", sock)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    assert r["where"] == "daemon" and r["piezo_peak_to_peak_v"] == pytest.approx(4.0, abs=0.01)
    # 4 V p-p: 0.8 urad, 0.36 um at the sensor.
    assert r["measured_over_model"] == pytest.approx(1.0, abs=0.05)
    deadline = time.monotonic() + 5
    while json.loads(d.cli("status", "--json").stdout)["state"] != "engaged":  # type: ignore[attr-defined]
        assert time.monotonic() < deadline, "the loop did not close again"
        time.sleep(0.1)
    # A wave started from idle is aborted by `leveler stop`, back at its centre voltage.
    assert d.cli("stop").returncode == 0  # type: ignore[attr-defined]
    held = json.loads(d.cli("status", "--json").stdout)["sample"]["applied_v"]  # type: ignore[attr-defined]
    started = subprocess.Popen([sys.executable, "-m", "leveler.cli", "modulate",
                                "--amplitude-v", "1", "--period", "10s", "--socket", sock],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 5
    while (st := json.loads(d.cli("status", "--json").stdout))["state"] != "modulating":  # type: ignore[attr-defined]
        assert time.monotonic() < deadline, "never modulating"
        time.sleep(0.05)
    assert st["modulation"]["center_v"] == pytest.approx(held, abs=1e-9)
    assert d.cli("start").returncode == 2  # type: ignore[attr-defined]  # not while modulating
    assert d.cli("stop").returncode == 0  # type: ignore[attr-defined]
    _, err = started.communicate(timeout=10)
    assert started.returncode == 2 and "ended early: the daemon is idle" in err
    time.sleep(0.3)
    st = json.loads(d.cli("status", "--json").stdout)  # type: ignore[attr-defined]
    assert st["state"] == "idle" and st["sample"]["applied_v"] == pytest.approx(held, abs=1e-6)
    d.stop()  # type: ignore[attr-defined]
    log = read_log(next(d.logs.glob("*.mcap")))  # type: ignore[attr-defined]
    procs = [e["reason"] for e in log.events if e["kind"] == "procedure"]
    assert procs[:3] == ["modulation started", "modulation done", "modulation started"]
    assert procs[3].startswith("modulation aborted: stop by uid") and len(procs) == 4
    states = [e["detail"]["new"] for e in log.events if e["kind"] == "state"]
    assert states[:5] == ["engaged", "idle", "modulating", "idle", "engaged"]
    s = log.samples
    assert (s["state"] == "modulating").sum() >= 2 * 6 * 20  # every sample logged


def test_torsion_pendulum_ratio_and_the_roll_pitch_split_it_implies() -> None:
    out = _cli("--sim", "--amplitude-v", "5", "--period", "120s", "--cycles", "2",
               "--tilt-axis-deg", "40", "--tp-com-x-m", "2e-4", "--json")
    assert out.returncode == 0, out.stderr
    tp = json.loads(out.stdout)["tp"]
    assert tp["tilt_axis_deg"] == pytest.approx(40.0, abs=2.0)  # recovered from the two steps
    assert tp["ip_over_tp"] > 1
    # Without l_cm,x the roll cannot be told apart: the ratio still comes, the split does not.
    out = _cli("--sim", "--amplitude-v", "5", "--period", "120s", "--cycles", "2",
               "--tp-com-x-m", "0")
    assert out.returncode == 0 and "needs l_cm,x" in out.stdout


def test_a_modulation_cut_short_by_sigterm_is_logged_as_aborted(
        start_daemon: Callable[..., object]) -> None:
    """Whoever analyses the log must see that the wave did not run its course."""
    d = start_daemon(rate_hz=20.0, engage=False)
    d.wait_status_lines(1)  # type: ignore[attr-defined]
    started = subprocess.Popen([sys.executable, "-m", "leveler.cli", "modulate",
                                "--amplitude-v", "1", "--period", "10s", "--socket",
                                str(d.socket)],  # type: ignore[attr-defined]
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 5
    while json.loads(d.cli("status", "--json").stdout)["state"] != "modulating":  # type: ignore[attr-defined]
        assert time.monotonic() < deadline, "never modulating"
        time.sleep(0.05)
    d.stop()  # type: ignore[attr-defined]
    started.communicate(timeout=10)
    log = read_log(next(d.logs.glob("*.mcap")))  # type: ignore[attr-defined]
    procs = [e["reason"] for e in log.events if e["kind"] == "procedure"]
    assert procs == ["modulation started", "modulation aborted: SIGTERM"]
    assert log.events[-1]["kind"] == "stop" and log.events[-1]["detail"]["safe"]


def _sim_triangle(tmp_path: Path, effect: str, period: str,
                  cycles: int = 3) -> dict:  # type: ignore[type-arg]
    config = tmp_path / f"sim{len(list(tmp_path.glob('*.toml')))}.toml"
    config.write_text(Path("config/sim.toml").read_text() + effect)
    out = _cli("--sim", "--config", str(config), "--shape", "triangle", "--amplitude-v", "5",
               "--period", period, "--cycles", str(cycles), "--settle", "30s", "--json")
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)  # type: ignore[no-any-return]


def test_a_triangle_on_the_simulated_stand_opens_for_a_hysteresis_and_a_lag(
        tmp_path: Path) -> None:
    """The sweeps' opening: none beyond its scatter on the nominal stand; 2 fraction width
    (0.2 V) for a play of 0.5 V half-width and fraction 0.2; for a 1 s delay, a lag of
    1 s at two sweep rates, where its opening in volts scales with the rate."""
    null = _sim_triangle(tmp_path, "", "120s")
    assert null["wave"]["shape"] == "triangle" and null["coherent"] == []
    assert null["measured_over_model"] == pytest.approx(1.0, abs=0.02)
    assert abs(null["opening_z"]) < 3
    hyst = _sim_triangle(tmp_path, "\n[plant.effects.actuator_hysteresis]\nwidth_v = 0.5\n"
                         "fraction = 0.2\n", "120s")
    sigma_v = hyst["opening_sigma_m"] / hyst["ip_m_per_v"]
    assert hyst["opening_z"] > 5 and abs(hyst["opening_v"] - 0.2) < 3 * sigma_v
    openings = []
    for period in ("120s", "200s"):
        lag = _sim_triangle(tmp_path, "\n[plant.effects.actuator_delay]\ndelay_s = 1.0\n",
                            period, cycles=5)
        sigma_s = lag["opening_sigma_m"] / lag["opening_m"] * lag["opening_as_lag_s"]
        assert lag["opening_z"] > 5 and abs(lag["opening_as_lag_s"] - 1.0) < 3 * sigma_s
        openings.append(lag["opening_v"])
    assert openings[0] / openings[1] == pytest.approx(200 / 120, rel=0.3)
    at_cooler = _sim_triangle(tmp_path, "", "300s")
    assert "300 s disturbance repeats with this wave" in at_cooler["coherent"][0]


def test_the_daemon_runs_a_triangle_through_a_damped_pendulum_without_opening(
        start_daemon: Callable[..., object]) -> None:
    """With Q ~ 0.7 the reading lags a 1.3 V/s sweep by ~0.6 s, a 1.6 V opening were the
    pendulum's dynamics not in the fit; the procedure event says the shape."""
    d = start_daemon(rate_hz=20.0, engage=False, replace={
        "damping_nms_per_rad = 1.2e-4": "damping_nms_per_rad = 6.0e-3"})
    d.wait_status_lines(1)  # type: ignore[attr-defined]
    out = _cli("--shape", "triangle", "--amplitude-v", "2", "--period", "6s", "--cycles", "2",
               "--json", "--socket", str(d.socket))  # type: ignore[attr-defined]
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    assert r["wave"]["shape"] == "triangle" and r["where"] == "daemon"
    assert r["piezo_peak_to_peak_v"] == pytest.approx(4.0, abs=0.02)
    assert r["measured_over_model"] == pytest.approx(1.0, abs=0.05)
    assert abs(r["opening_of_swing"]) < 0.03
    d.stop()  # type: ignore[attr-defined]
    log = read_log(next(d.logs.glob("*.mcap")))  # type: ignore[attr-defined]
    [started] = [e for e in log.events if e["reason"] == "modulation started"]
    assert started["detail"]["shape"] == "triangle"


@pytest.mark.parametrize(("family", "severity", "opens"), [
    (None, "medium", False), ("actuator_hysteresis", "medium", True)])
def test_a_recorded_triangle_of_the_independent_generator(
        tmp_path: Path, family: str | None, severity: str, opens: bool) -> None:
    """`leveler modulate LOG` on an hour's log of bench/independent (seed 201: a 167 s
    triangle, its own phase, calibration offsets, noise, a start out of equilibrium; the
    hysteresis a Bouc-Wen loop): the shape is found, and the opening stands out for the
    hysteresis and not for the null. bench/opening_score.py scores more seeds."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from independent.generator import generate

    log = tmp_path / "t.mcap"
    truth = generate(family, severity, 201, log, hours=1.0, modulated=True)
    assert truth["modulation"]["shape"] == "triangle"
    out = subprocess.run([sys.executable, "-m", "leveler.cli", "modulate", str(log), "--json"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    (w,) = json.loads(out.stdout)["waves"]
    assert w["wave"]["shape"] == "triangle"
    assert w["wave"]["period_s"] == pytest.approx(truth["modulation"]["period_s"], rel=0.005)
    assert (w["opening_z"] >= 3) is opens
