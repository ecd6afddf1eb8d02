"""Sanity of the independent generator itself (not of leveler): `pytest bench/independent`.

Logs are short (1-3 h of 10 Hz) and go to pytest's tmp_path.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from independent import effects as fx
from independent.generator import generate, nominal_parameters
from independent.plant import Mode, Pendulum, jittered_sawtooth, lag
from leveler.log.reader import read_log

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "config" / "sim.toml"


def _gen(tmp_path: Path, family: str | None, severity: str = "strong", seed: int = 7,
         hours: float = 1.0, modulated: bool = True, name: str = "") -> tuple[dict, object]:
    out = tmp_path / f"{name or family or 'null'}.mcap"
    truth = generate(family, severity, seed, out, hours=hours, modulated=modulated,
                     nominal_config=CONFIG)
    return truth, read_log(out)


def test_pendulum_static_amplification_and_resonance() -> None:
    p = nominal_parameters(CONFIG.read_text())["plant.pendulum"]
    mgl = p["mass_kg"] * p["gravity_m_per_s2"] * p["com_length_m"]
    pend = Pendulum(p["inertia_kgm2"], p["damping_nms_per_rad"],
                    p["flexure_stiffness_nm_per_rad"], mgl)
    assert pend.amplification == pytest.approx(1 / (p["flexure_stiffness_nm_per_rad"] / mgl - 1))
    # a constant tilt held long enough: theta = N phi, with and without the J phi'' term
    for inertial in (True, False):
        pend_i = Pendulum(pend.inertia, pend.damping, pend.k_flex, pend.mgl, inertial)
        s = pend_i.step(0.1)
        x = np.zeros(2)
        phi = 1e-6
        for _ in range(20000):
            x = s[:, :2] @ x + s[:, 2] * phi
        assert pend_i.deflection(x[0], phi) == pytest.approx(pend.amplification * phi, rel=1e-6)
    again = Pendulum.from_targets(pend.amplification, pend.f0_hz, pend.q, pend.inertia)
    assert again.k_flex == pytest.approx(pend.k_flex) and again.mgl == pytest.approx(pend.mgl)


def test_mode_peak_gain_and_noise_level() -> None:
    mode = Mode(2.0, 15.0, 0.1)
    dt = 0.001
    s = mode.step(dt)
    t = np.arange(0, 30, dt)
    phi = np.sin(2 * math.pi * 2.0 * t)
    rate = np.gradient(phi, dt)
    x = np.zeros(2)
    out = np.empty(len(t))
    for i, r in enumerate(rate):
        x = s[:, :2] @ x + s[:, 2] * r
        out[i] = x[0]
    assert np.max(np.abs(out[-5000:])) == pytest.approx(0.1, rel=0.02)
    noise = mode.noise(200000, 0.1, 1e-9, np.random.default_rng(1))
    assert np.std(noise) == pytest.approx(1e-9, rel=0.1)


def test_lag_is_exact_for_a_ramp() -> None:
    dt, tau = 0.5, 30.0
    t = np.arange(0, 600, dt)
    y = lag(t.copy(), dt, tau, 0.0)
    exact = t - tau * (1 - np.exp(-t / tau))
    assert np.max(np.abs(y - exact)) < 1e-9


def test_jittered_sawtooth_cycles() -> None:
    t = np.arange(0, 20000, 1.0)
    wave, starts = jittered_sawtooth(t, 400.0, 0.8, 0.03, np.random.default_rng(2), -100.0)
    assert wave.min() >= -0.5 and wave.max() <= 0.5
    lengths = np.diff(starts)
    assert abs(np.mean(lengths) / 400.0 - 1) < 0.03
    assert 0.005 < np.std(lengths) / 400.0 < 0.06


def test_null_log_reads_back(tmp_path: Path) -> None:
    truth, log = _gen(tmp_path, None, hours=1.0)
    s = log.samples
    assert log.complete
    assert len(s["seq"]) == 36000 == truth["samples"]
    assert np.array_equal(s["seq"], np.arange(36000))
    assert np.allclose(np.diff(s["t_s"]), 0.1)
    assert log.metadata["leveler"]["config"] == CONFIG.read_text()
    assert len(log.environment["temperature_k"]) == 36000
    assert np.all(np.isfinite(s["sensor_m"])) and np.all(s["status"] == 0)
    assert truth["family"] == "none" and truth["params"] == {}
    # in the open-loop third the piezo follows the modulation; then the loop holds the
    # reading near the setpoint
    n_open = round(truth["closed_loop_from_s"] * 10)
    assert set(s["state"][:n_open]) == {"modulating"}
    assert set(s["state"][n_open:]) == {"engaged"}
    amp = truth["modulation"]["amplitude_v"]
    assert np.ptp(s["applied_v"][:n_open]) == pytest.approx(2 * amp, rel=0.01)
    assert np.std(s["sensor_m"][-12000:]) < 2e-8
    # the reading is on the configured ADC's lattice: 20 V / 2^16 over 2e5 V/m
    counts = s["raw_counts"]
    assert np.allclose((-10 + counts * 20 / 65536) / 2e5, s["sensor_m"])
    # calibration offsets within 1-2 sigma, noise scalings off 1 by 10-25 %
    assert 0.03 <= abs(truth["calibration_rel"]["piezo_gain_rel"]) <= 0.06
    assert all(0.1 <= abs(v - 1) <= 0.25 for v in truth["noise_scale"].values())
    kinds = [e["kind"] for e in log.events]
    assert kinds[0] == "start" and kinds[-1] == "stop" and "procedure" in kinds


def test_closed_loop_only(tmp_path: Path) -> None:
    truth, log = _gen(tmp_path, None, hours=0.5, modulated=False)
    assert truth["modulation"] is None and truth["closed_loop_from_s"] == 0
    assert set(log.samples["state"]) == {"engaged"}
    # the integrator starts away from the held voltage's steady state
    assert abs(log.samples["i_v"][0] - 75.0) > 0.9


def test_same_seed_same_log(tmp_path: Path) -> None:
    a, la = _gen(tmp_path, "sensor_drift", "medium", seed=3, hours=0.3, name="a")
    b, lb = _gen(tmp_path, "sensor_drift", "medium", seed=3, hours=0.3, name="b")
    assert a["params"] == b["params"]
    assert np.array_equal(la.samples["sensor_m"], lb.samples["sensor_m"])


def _open_loop_difference(tmp_path: Path, family: str, seed: int) -> tuple[dict, dict, object,
                                                                            np.ndarray]:
    null, ln = _gen(tmp_path, None, seed=seed, hours=3.0, name="null")
    eff, le = _gen(tmp_path, family, "strong", seed=seed, hours=3.0)
    assert eff["calibration_rel"] == null["calibration_rel"]  # only the effect differs
    n_open = round(null["closed_loop_from_s"] * 10)
    assert np.array_equal(ln.samples["applied_v"][:n_open], le.samples["applied_v"][:n_open])
    diff = le.samples["sensor_m"][:n_open] - ln.samples["sensor_m"][:n_open]
    return null, eff, ln, diff


def test_sawtooth_adds_a_line_at_its_period(tmp_path: Path) -> None:
    _null, eff, _ln, diff = _open_loop_difference(tmp_path, "periodic_disturbance", 11)
    diff = diff - diff.mean()
    spec = np.abs(np.fft.rfft(diff * np.hanning(len(diff))))
    f = np.fft.rfftfreq(len(diff), 0.1)
    peak = f[1:][np.argmax(spec[1:])]
    assert peak == pytest.approx(1 / eff["params"]["period_s"], rel=0.15)
    # size: the pendulum end moves N * arm * tilt
    expected = abs(eff["params"]["peak_to_peak_rad"]) * eff["true_plant"]["amplification"] \
        * eff["true_plant"]["sensor_arm_m"]
    assert np.ptp(diff) == pytest.approx(expected, rel=0.35)


@pytest.mark.slow  # 7 s; make test-slow
def test_hysteresis_depends_on_the_direction_of_motion(tmp_path: Path) -> None:
    _null, eff, ln, diff = _open_loop_difference(tmp_path, "actuator_hysteresis", 12)
    v = ln.samples["applied_v"][: len(diff)]
    dv = np.diff(v)
    direction = np.zeros(len(v))
    last = 0.0
    for i in range(1, len(v)):
        if dv[i - 1] != 0:
            last = math.copysign(1.0, dv[i - 1])
        direction[i] = last
    up, down = diff[direction > 0].mean(), diff[direction < 0].mean()
    # after rising the Bouc-Wen variable is positive and the stroke falls short: lower reading
    assert up < down
    per_v = eff["true_plant"]["tilt_per_v_rad"] * eff["true_plant"]["amplification"] \
        * eff["true_plant"]["sensor_arm_m"]
    assert (down - up) > 0.2 * eff["params"]["a"] * eff["params"]["saturation_v"] * per_v


@pytest.mark.slow  # 8 s; make test-slow
def test_every_family_generates(tmp_path: Path) -> None:
    for family in fx.FAMILIES:
        truth, log = _gen(tmp_path, family, "medium", seed=5, hours=0.3)
        assert truth["family"] == family
        assert log.complete and np.all(np.isfinite(log.samples["sensor_m"]))
        assert truth["railed_samples"] == 0
