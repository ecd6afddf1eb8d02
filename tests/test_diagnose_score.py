"""The scoreboard's own arithmetic (bench/diagnose_score.py): which sensor gain errors a
log can tell from a calibration, and the rates it prints."""

from __future__ import annotations

import math
import sys
from typing import Any

import pytest
from conftest import REPO

sys.path.insert(0, str(REPO / "bench"))

import diagnose_score as ds

ZERO = {"piezo_gain_rel": 0.0, "support_spacing_rel": 0.0, "sensor_arm_rel": 0.0,
        "sensor_gain_rel": 0.0, "amplification_rel": 0.0}
SIGMA = math.hypot(math.sqrt(0.02**2 + 0.02**2 + 0.03**2), math.hypot(0.03, 0.01))


def case(family: str, predicted: str, severity: str | None = "strong", error: float = 0.0,
         **cal: float) -> dict[str, Any]:
    params = {"gain_error": error} if family == "sensor_gain_error" else {}
    return {"family": family, "severity": severity, "predicted": predicted, "seed": 1,
            "named": [] if predicted == "none" else [predicted], "modulated": True,
            "truth": {"family": family, "params": params, "calibration_rel": {**ZERO, **cal}}}


def test_the_loop_gain_pull_compounds_the_error_with_both_paths_offsets() -> None:
    assert ds.loop_gain_pull(case("sensor_gain_error", "none", error=0.1)["truth"]) \
        == pytest.approx(0.1 / SIGMA)
    # a piezo 10 % weak undoes a sensor reading 11.1 % high: the loop is nominal
    cancelled = case("sensor_gain_error", "none", error=1 / 0.9 - 1, piezo_gain_rel=-0.1)
    assert ds.loop_gain_pull(cancelled["truth"]) == pytest.approx(0.0, abs=1e-12)
    # a null's offsets count alone; a wider support spacing lowers the tilt per volt
    null = case("none", "none", severity=None, sensor_gain_rel=0.04, support_spacing_rel=0.02)
    assert ds.loop_gain_pull(null["truth"]) == pytest.approx((1.04 / 1.02 - 1) / SIGMA)


def test_gain_errors_within_the_nulls_offsets_are_split_off_not_dropped() -> None:
    far = case("none", "none", severity=None, sensor_gain_rel=0.2)  # 3.85 sigma, a null
    cases = [case("none", "none", severity=None), far,
             case("sensor_gain_error", "sensor_gain_error", error=0.3),  # 5.8 sigma: seen
             case("sensor_gain_error", "none", error=0.15),  # 2.9 sigma: inside the nulls'
             case("sensor_gain_error", "none", "weak", error=0.18),  # 3.5: inside too
             case("actuator_delay", "none", "medium")]
    s = ds.summarize(cases)
    gain = s["sensor_gain_vs_tolerance"]
    assert gain["line_sigma"] == pytest.approx(0.2 / SIGMA)
    assert gain["beyond"] == {"logs": 1, "named_first": 1, "medium_strong": 1,
                              "medium_strong_named_first": 1}
    assert gain["within"]["logs"] == 2 and gain["within"]["medium_strong"] == 1
    ms = s["combined"]["medium_strong"]
    assert (ms["logs"], ms["named_first"]) == (3, 1)
    assert (ms["logs_beyond_calibration"], ms["named_first_beyond"]) == (2, 1)
    assert (s["combined"]["all"]["logs"], s["combined"]["all"]["logs_beyond_calibration"]) \
        == (4, 2)
    text = ds.render(s, cases, "board")
    assert "medium and strong: 1/3 = 33 % first" in text
    assert "1/2 = 50 %" in text and "largest null log's, 3.85 sigma" in text
