"""From a diagnosed temperature coupling to a feedforward in the running loop, through the
real commands (issue 21): six hours of the integral-only lab loop on a table that tilts
with its temperature more than its model says; `leveler diagnose` names the coupling from
the logged thermometer; `leveler tune --suggest --model FITTED.toml --apply --persist`
switches the feedforward on in a running daemon; the stand simulated again with the
persisted config shows the temperature's tilt gone from the true tilt. Slow (a diagnosis
of a 6 h log): make test-slow; tests/test_feedforward_e2e.py covers the daemon's side in
make test."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from leveler.analysis.periodic import floor_tilt
from leveler.analysis.spectral import asd_at
from leveler.log.reader import read_log
from leveler.settings import load_config

from conftest import daemon_config, run_cli  # isort: skip

SEED = 8
THERMOMETER = '\n[thermometer]\nbackend = "sim"\n'
COUPLING = ("\n[plant.effects.temperature_coupling]\ntilt_per_kelvin_rad_per_k = 5.0e-6\n"
            "lag_s = 600.0\n")
INTEGRAL_ONLY = {"ki_v_per_m_s = 2.2e7": "ki_v_per_m_s = 7.0e5",
                 "kd_v_s_per_m = 1.9e6": "kd_v_s_per_m = 0.0"}
BAND_HZ = [4e-4, 7e-4, 1e-3, 1.5e-3, 2.2e-3]


def _sim(config: Path, out: Path) -> np.ndarray:
    run_cli("sim", "--config", str(config), "--duration", "6h", "--seed", str(SEED),
            "--out", str(out), "--json", cwd=out.parent)
    return read_log(out).truth["tilt_rad"]


@pytest.mark.slow
def test_diagnose_suggest_apply_and_the_temperature_leaves_the_tilt(tmp_path: Path,
                                                                   start_daemon) -> None:  # type: ignore[no-untyped-def]
    model = tmp_path / "model.toml"  # the lab's model: the thermal path, no coupling
    model.write_text(daemon_config(tmp_path, tmp_path / "unused.sock", rate_hz=10.0,
                                   replace=INTEGRAL_ONLY,
                                   edit=lambda t: t + THERMOMETER).read_text())
    truth = tmp_path / "truth.toml"
    truth.write_text(model.read_text() + COUPLING)
    before = _sim(truth, tmp_path / "before.mcap")
    fitted = tmp_path / "fitted.toml"
    found = json.loads(run_cli("diagnose", str(tmp_path / "before.mcap"), "--model",
                               str(model), "--model-out", str(fitted), "--json", cwd=tmp_path))
    named = [e for e in found["effects"] if e["name"] == "temperature_coupling"]
    assert named, found["effects"]
    k = named[0]["params"]["tilt_per_kelvin_rad_per_k"]
    assert 3e-6 < k < 7e-6, named

    d = start_daemon(rate_hz=10.0, replace=INTEGRAL_ONLY, edit=lambda t: t + THERMOMETER)
    out = d.cli("tune", "--suggest", "--model", str(fitted), "--apply", "--persist",
                "--predict-hours", "0", timeout=120)
    assert out.returncode == 0, out.stderr
    assert "temperature feedforward over 2 path(s); written to the config file" in out.stdout
    d.stop()

    cfg, _ = load_config(d.config)
    assert cfg.controller.feedforward() is not None
    persisted = tmp_path / "after.toml"
    persisted.write_text(d.config.read_text() + COUPLING)  # the same table, now fed forward
    after = _sim(persisted, tmp_path / "after.mcap")
    rate = cfg.loop.rate_hz
    floor = asd_at(floor_tilt(cfg, len(before), SEED), rate, BAND_HZ)
    was, now = (asd_at(x, rate, BAND_HZ) / floor for x in (before, after))
    print(f"named: {named[0]['params']}\ntrue tilt over the floor at {BAND_HZ} Hz: "
          f"before {np.round(was, 2)}, after {np.round(now, 2)}")
    assert (was > 3).all(), was  # the temperature's tilt stood over the floor
    assert (now < 1.5).all() and (now < was / 3).all(), (was, now)  # and no longer does
