"""What temperature feedforward buys (leveler.analysis.feedforward), told by `tune --suggest
--model` for a model with a fitted temperature coupling: nothing on the default stand,
whose loop holds the temperature's tilt under the sensor floor; several times at the mHz on
a slow integral-only loop; and nothing reachable where the temperature tilts the table
beyond the piezo's stroke. The feedforward in the loop: tests/test_temperature_feedforward.py."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from leveler.analysis import feedforward
from leveler.settings import Config, load_config
from leveler.sim.effects import TemperatureCoupling

from conftest import REPO  # isort: skip

COUPLING = ("\n[plant.effects.temperature_coupling]\ntilt_per_kelvin_rad_per_k = {k}\n"
            "lag_s = 600.0\n")


def _coupled(base: str, k: float) -> Config:
    cfg = load_config(REPO / "config" / base)[0]
    fx = TemperatureCoupling(tilt_per_kelvin_rad_per_k=k, lag_s=600.0)
    return dataclasses.replace(cfg, plant=dataclasses.replace(
        cfg.plant, effects=cfg.plant.effects.with_effect(fx)))


def test_the_default_loop_leaves_feedforward_nothing_to_buy() -> None:
    b = feedforward.bound(_coupled("sim.toml", 5e-6), 12 * 3600.0)
    most, _ = b.gain()
    assert most < feedforward.WORTH, most
    assert b.railed == 0.0
    assert "not worth it" in feedforward.report(["x"], b)


def test_a_slow_loop_gains_from_it_and_an_error_in_gain_costs_some() -> None:
    b = feedforward.bound(_coupled("lab.toml", 5e-6), 12 * 3600.0)
    most, where = b.gain()
    off, _ = b.gain(b.off)
    assert most > 3.0 and 1e-4 < where < 3e-3, (most, where)  # at the mHz, below crossover
    assert 1.0 < off < most, (off, most)
    # a perfect one leaves the floor (within the estimate's scatter) where it buys most
    i = list(b.freqs_hz).index(where)
    assert b.best[i] == pytest.approx(b.floor[i], rel=0.3)


def test_beyond_the_stroke_it_says_so() -> None:
    b = feedforward.bound(_coupled("lab.toml", 5e-5), 24 * 3600.0)
    assert b.railed > feedforward.MAX_RAILED
    assert "more stroke" in feedforward.report(["x"], b)


def test_tune_suggest_model_on_a_stand_without_a_thermometer_applies_nothing(
        tmp_path: Path) -> None:
    """What the feedforward buys is the docs transcript's (docs/replay.md, a stand with a
    thermometer); here config/lab.toml reads none, so --apply has nothing to send."""
    model = tmp_path / "fitted.toml"
    model.write_text((REPO / "config" / "lab.toml").read_text() + COUPLING.format(k=5e-6))
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "tune", "--suggest", "--model",
                           str(model), "--config", str(REPO / "config" / "lab.toml"),
                           "--predict-hours", "0", "--apply", "--socket",
                           str(tmp_path / "none.sock")],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "No resonant terms: the loop has too little gain" in out  # the cooler, said
    assert "[plant.effects.temperature_coupling] 5e-06 rad/K through 600 s" in out
    assert "Suggested feedforward (-50 V/K through 1800 s; -25 V/K through 600 s)" in out
    assert "lab.toml reads no thermometer, so the feedforward cannot run there" in out
    assert out.rstrip().endswith("nothing to apply"), out  # nothing reached a daemon
