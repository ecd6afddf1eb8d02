"""From a diagnosed mode to a notch in the running loop, through the real commands (issue 21):
an hour of a stand with a table mode at 1.5 Hz rung by the floor, which the lab's model
lacks and the loop copies onto the table; `leveler diagnose` names it; `leveler tune
--suggest --model FITTED.toml --apply --persist` designs a notch, checks it over the
model's tolerances and switches it on in a running daemon; the stand simulated again with
the persisted config shows the mode gone from the true tilt."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from leveler.analysis.periodic import floor_tilt
from leveler.analysis.spectral import asd_at
from leveler.log.reader import read_log
from leveler.settings import load_config

from conftest import REPO, run_cli  # isort: skip

SEED = 5
MODE = "\n[plant.effects.extra_resonance]\nfrequency_hz = 1.5\nq = 12.0\nnoise_rms_m = 2.0e-9\n"


def _sim(config: Path, out: Path) -> np.ndarray:
    run_cli("sim", "--config", str(config), "--duration", "1h", "--seed", str(SEED),
         "--out", str(out), "--json", cwd=out.parent)
    return read_log(out).truth["tilt_rad"]


@pytest.mark.slow  # 18 s; make test-slow (make test: test_periodic_e2e's chain, test_notch)
def test_diagnose_suggest_apply_and_the_mode_leaves_the_tilt(tmp_path: Path, start_daemon) -> None:  # type: ignore[no-untyped-def]
    truth = tmp_path / "truth.toml"
    truth.write_text((REPO / "config" / "sim.toml").read_text() + MODE)
    before = _sim(truth, tmp_path / "before.mcap")
    fitted = tmp_path / "fitted.toml"
    found = json.loads(run_cli("diagnose", str(tmp_path / "before.mcap"), "--model",
                            str(REPO / "config" / "sim.toml"), "--model-out", str(fitted),
                            "--max-effects", "1", "--json", cwd=tmp_path))
    mode = [e for e in found["effects"] if e["name"] == "extra_resonance"]
    assert mode and abs(mode[0]["params"]["frequency_hz"] - 1.5) < 0.05, found["effects"]

    d = start_daemon(rate_hz=10.0, edit=lambda text: text + MODE)
    out = d.cli("tune", "--suggest", "--model", str(fitted), "--apply", "--persist",
                "--predict-hours", "0", timeout=120)
    assert out.returncode == 0, out.stderr
    assert "Suggested: a notch on the reading at 1.5" in out.stdout, out.stdout
    assert "written to the config file" in out.stdout
    shown = d.cli("status").stdout
    d.stop()
    tune = [e for e in read_log(next(d.logs.glob("*.mcap"))).events if e["kind"] == "tune"]
    assert tune and "notch_frequency_hz" in tune[-1]["detail"], tune

    cfg, _ = load_config(d.config)  # the daemon's config, with the notch persisted
    n = cfg.controller.notch()
    assert n is not None and abs(n.frequency_hz - 1.5) < 0.05
    assert f"notch on the reading at {n.frequency_hz:.4g} Hz" in shown, shown
    after = _sim(d.config, tmp_path / "after.mcap")

    rate = cfg.loop.rate_hz
    floor = asd_at(floor_tilt(cfg, len(before), SEED), rate, [1.5])[0]
    was, now = (asd_at(x[600:], rate, [1.5])[0] / floor for x in (before, after))
    assert was > 5, was  # the loop copied the mode onto the table
    assert now < was / 4 and now < 3, (was, now)  # and no longer does
