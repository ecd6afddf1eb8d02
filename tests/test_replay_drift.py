"""leveler replay tells signal from drift: the residual against the model's own noise per band,
the slow drift set aside by the user's choice, the pendulum's start fitted, and one sentence
that says whether what is left is what the model itself calls unpredictable."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from leveler.analysis.drift import smoothed_walk
from leveler.analysis.predict import Predictor, load_measured
from leveler.analysis.replay import replay
from leveler.analysis.synthetic import make_measured
from leveler.cli.main import main
from leveler.settings import load_config
from leveler.sim.params import PendulumParams, PlantParams
from leveler.sim.pendulum import PendulumModel

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def evening(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three hours of closed-loop leveling of the nominal plant, temperature logged."""
    cfg, text = load_config(REPO / "config" / "sim.toml")
    log = tmp_path_factory.mktemp("drift") / "evening.mcap"
    make_measured(log, cfg, text, None, duration_s=3 * 3600, seed=21)
    return log


def test_own_model_residual_is_its_own_noise_in_every_band(evening: Path) -> None:
    result = replay(load_measured(evening))[0]
    for band, b in result["bands"].items():
        if b is not None:
            assert 0.6 < b["residual_over_noise"] < 1.5, (band, b)
            assert b["unpredictable"]
    assert result["verdict"].startswith("The residual is what the model itself calls "
                                        "unpredictable (sensor noise, its zero's drift)")
    # the drift set aside is the slow part: the lowest band is nearly all of it
    assert result["bands"]["0.1-1 mHz"]["variance_explained_less_drift"] > 0.9


def test_without_the_temperature_its_tilt_is_named_unpredictable(evening: Path) -> None:
    """Without the thermometer the model cannot predict the thermal tilt, and says so."""
    meas = load_measured(evening)
    meas.sig = type(meas.sig)(meas.sig.t_s, meas.sig.dt_s, None)
    result = replay(meas)[0]
    assert "the unlogged temperature's tilt" in result["verdict"]
    assert result["bands"]["0.1-1 mHz"]["unpredictable"], result["bands"]["0.1-1 mHz"]


def test_a_missing_cooler_is_named_by_its_band(evening: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """Replayed against a model without the 300 s cooler, the residual stands far above the
    model's noise in 1-10 mHz (its fundamental at 3.3 mHz), and the sentence says so."""
    text = (REPO / "config" / "sim.toml").read_text()
    model = tmp_path / "no-cooler.toml"
    model.write_text(text.replace("peak_to_peak_rad = 2.8e-8", "peak_to_peak_rad = 0.0"))
    assert main(["replay", str(evening), "--model", str(model), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["bands"]["1-10 mHz"]["residual_over_noise"] > 10
    assert not r["bands"]["1-10 mHz"]["unpredictable"]
    assert "exceeds what the model calls unpredictable" in r["verdict"]
    assert "1-10 mHz" in r["verdict"] and "leveler diagnose" in r["verdict"]
    assert main(["replay", str(evening), "--model", str(model)]) == 0
    text_out = capsys.readouterr().out
    assert "residual/noise" in text_out and "less the drift (model" in text_out


def test_drift_methods_from_the_command_line(evening: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(evening), "--drift", "poly:3", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["drift"] == "poly:3" and r["drift_rms_m"] > 0
    assert main(["replay", str(evening), "--drift", "none", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["drift_rms_m"] == 0 and r["variance_explained_less_drift"] == pytest.approx(
        r["variance_explained"])
    assert main(["replay", str(evening), "--drift", "spline"]) == 2
    assert "use model, poly:N (N = 0..20) or none" in capsys.readouterr().err


def _rts(y: np.ndarray, q2: float, r2: float) -> np.ndarray:
    """The textbook Kalman filter and Rauch-Tung-Striebel smoother of a random walk in white
    noise, written out sample by sample (started from the first reading with a large
    variance): what the steady-state kernel must equal away from the ends."""
    n = len(y)
    xf, pf, xp, pp = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    x, p = y[0], 1e6 * r2
    for k in range(n):
        xp[k], pp[k] = x, p + (q2 if k else 0.0)
        gain = pp[k] / (pp[k] + r2)
        x = xp[k] + gain * (y[k] - xp[k])
        p = (1 - gain) * pp[k]
        xf[k], pf[k] = x, p
    xs = xf.copy()
    for k in range(n - 2, -1, -1):
        c = pf[k] / pp[k + 1]
        xs[k] = xf[k] + c * (xs[k + 1] - xp[k + 1])
    return xs


@pytest.mark.parametrize("q,white", [(1e-11, 5e-10), (3e-10, 2e-10)])
def test_the_drift_smoother_is_the_kalman_smoother(q: float, white: float) -> None:
    dt = 0.5
    rng = np.random.default_rng(4)
    walk = np.cumsum(rng.normal(0, q * math.sqrt(dt), 4000))
    y = walk + rng.normal(0, white, 4000)
    fast = smoothed_walk(y, q, white, dt)
    slow = _rts(y, q * q * dt, white * white)
    inner = slice(400, 3600)  # the ends differ by the start: settled here, diffuse there
    assert np.max(np.abs(fast[inner] - slow[inner])) < 0.02 * white
    # and it does estimate the walk: better than the readings themselves
    assert np.std((fast - walk)[inner]) < 0.8 * white
    assert np.allclose(smoothed_walk(y, 0.0, white, dt), y.mean())


def test_a_ringing_start_is_fitted_not_replayed(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A hanging pendulum with Q = 2000 (it rings for 5 h) recorded from a swinging start: the
    replay with the right model fits the swing and leaves only the noise; started at rest,
    the model's missing swing would have stood hundreds of times above it."""
    pe = PendulumParams(mass_kg=1.0, com_length_m=-2e-5, flexure_stiffness_nm_per_rad=4e-4,
                        inertia_kgm2=0.05, damping_nms_per_rad=2.7e-6, sensor_arm_m=0.1)
    dt, n = 0.5, 20_000
    model = PendulumModel(pe, dt)
    model.settle(pe, 0.0)
    model.omega = 2e-7
    t = np.arange(n) * dt
    u = 50 + 5 * np.sin(2 * np.pi * 3e-3 * t)
    tilt_per_v = PlantParams().piezo.gain_m_per_v / PlantParams().platform.support_spacing_m
    y = np.array([model.step(tilt_per_v * v) for v in u]) * pe.sensor_arm_m
    y += np.random.default_rng(2).normal(0, 3e-10, n)
    csv, log = tmp_path / "ring.csv", tmp_path / "ring.mcap"
    csv.write_text("t_s,actuator_V,sensor_m\n" + "\n".join(
        f"{a!r},{b!r},{c!r}" for a, b, c in zip(t.tolist(), u.tolist(), y.tolist(),
                                                 strict=True)) + "\n")
    assert main(["import-csv", str(csv), "--out", str(log)]) == 0
    cfg = tmp_path / "ring.toml"
    cfg.write_text("[plant.pendulum]\nmass_kg = 1.0\ncom_length_m = -2e-5\n"
                   "flexure_stiffness_nm_per_rad = 4e-4\ninertia_kgm2 = 0.05\n"
                   "damping_nms_per_rad = 2.7e-6\nsensor_arm_m = 0.1\n"
                   "[plant.piezo]\nslew_v_per_s = 1e6\n[plant.cooler]\npeak_to_peak_rad = 0.0\n"
                   "[plant.sensor]\nnoise_m_per_rthz = 3e-10\ndrift_m_per_sqrt_s = 0.0\n"
                   "adc_bits = 24\n")  # the stand as it is: no cooler, a fine converter
    capsys.readouterr()
    meas = load_measured(log, cfg)
    result = replay(meas, drift_method="none")[0]
    assert result["rms_m"] < 1.3 * 3e-10
    assert result["bands"]["10-100 mHz"]["unpredictable"]  # the 17 mHz resonance's band
    at_rest = Predictor(meas.config.plant, meas)
    assert np.std((meas.y_m - at_rest.base.y_m)[n // 2:]) > 100 * 3e-10
