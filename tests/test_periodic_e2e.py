"""From diagnosis to a better loop, through the real commands (issue 21): three simulated
hours of a stand whose water cooler the lab's model lacks; `leveler diagnose` names the
periodic disturbance; `leveler tune --suggest --model FITTED.toml --apply --persist` designs
resonant terms, checks them and switches them on in a running daemon; the stand simulated
again with the persisted config shows the cooler's lines gone from the true tilt."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from leveler.analysis.periodic import floor_tilt
from leveler.analysis.spectral import asd_at
from leveler.log.reader import read_log
from leveler.settings import load_config

from conftest import REPO, run_cli  # isort: skip

SEED = 3
HOURS = 3


def _sim(config: Path, out: Path) -> np.ndarray:
    run_cli("sim", "--config", str(config), "--duration", f"{HOURS}h", "--seed", str(SEED),
         "--out", str(out), "--json", cwd=out.parent)
    return read_log(out).truth["tilt_rad"]


def test_diagnose_suggest_apply_and_the_lines_drop(tmp_path: Path, start_daemon) -> None:  # type: ignore[no-untyped-def]
    truth = REPO / "config" / "sim.toml"
    text = truth.read_text()
    assert "peak_to_peak_rad = 2.8e-8" in text
    lab = tmp_path / "lab-model.toml"  # the lab's model: no cooler in it
    lab.write_text(text.replace("peak_to_peak_rad = 2.8e-8", "peak_to_peak_rad = 0.0", 1))

    before = _sim(truth, tmp_path / "before.mcap")
    fitted = tmp_path / "fitted.toml"
    found = json.loads(run_cli("diagnose", str(tmp_path / "before.mcap"), "--model", str(lab),
                            "--model-out", str(fitted), "--max-effects", "1", "--json",
                            cwd=tmp_path))
    periodic = [e for e in found["effects"] if e["name"] == "periodic_disturbance"]
    assert periodic and abs(periodic[0]["params"]["period_s"] - 300.0) < 3.0, found["effects"]

    d = start_daemon(rate_hz=10.0)
    out = d.cli("tune", "--suggest", "--model", str(fitted), "--log",
                str(tmp_path / "before.mcap"), "--apply", "--persist",
                "--predict-hours", str(HOURS), timeout=120)
    assert out.returncode == 0, out.stderr
    assert "Suggested: resonant terms at harmonics 1-" in out.stdout
    # the replay what-if on the diagnosed log: the reading at the first line comes down
    what_if = out.stdout.split("own run (the replay what-if")[1].splitlines()
    line1 = next(r for r in what_if if "(line 1)" in r).split()
    assert float(line1[-2]) < float(line1[-1]) / 1.5, what_if
    assert "closed loop                       stable (17 models)" in out.stdout
    assert "resonant terms at" in out.stdout and "written to the config file" in out.stdout
    status = json.loads(d.cli("status", "--json").stdout)
    shown = d.cli("status").stdout  # what the physicist sees
    d.stop()
    tune = [e for e in read_log(next(d.logs.glob("*.mcap"))).events if e["kind"] == "tune"]
    assert tune and "periodic_gains_v_per_m_s" in tune[-1]["detail"], tune
    assert status["state"] == "engaged"

    cfg, _ = load_config(d.config)  # the daemon's config, with the terms persisted
    terms = cfg.controller.periodic_terms()
    assert terms is not None and abs(terms.period_s - 300.0) < 3.0
    n = len(terms.gains_v_per_m_s)
    assert f"resonant terms at harmonics 1-{n} of {terms.period_s:g} s" in shown, shown
    after = _sim(d.config, tmp_path / "after.mcap")

    lines = [h / terms.period_s for h in (1, 2, 3)]
    floor = asd_at(floor_tilt(cfg, len(before), SEED), cfg.loop.rate_hz, lines)
    was, now = (asd_at(x, cfg.loop.rate_hz, lines) / floor for x in (before, after))
    assert np.all(was > 1.5), was  # the cooler stood out of the floor at its lines
    assert np.all(now < 1.3), now  # and is down to it
