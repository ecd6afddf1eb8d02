"""Replay and diagnose of a day-long log: samples per second, against reading the log.

The log is a closed-loop day at 10 Hz with a hidden water-cooler-like sawtooth (what
`leveler diagnose` exists to find); the baseline is reading that log, timed in the same
run. The goal from issue 4: a 24 h log diagnosed in at most 2 minutes on 2 cores.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from leveler.diagnose import diagnose
from leveler.hidden import make_measured
from leveler.predict import load_measured
from leveler.replay import replay
from leveler.settings import load_config
from leveler.sim.effects import PeriodicDisturbance

REPO = Path(__file__).resolve().parents[1]
GOAL_S = 120.0


def main(duration_s: float) -> dict:
    cfg, text = load_config(REPO / "config" / "sim.toml")
    truth = PeriodicDisturbance(shape="sawtooth", period_s=287.0, peak_to_peak_rad=2.4e-7,
                                phase_s=40.0)
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "night.mcap"
        make_measured(log, cfg, text, truth, duration_s=duration_s, seed=7)
        start = time.perf_counter()
        meas = load_measured(log)
        read_s = time.perf_counter() - start
        start = time.perf_counter()
        replay(meas)
        replay_s = time.perf_counter() - start
        start = time.perf_counter()
        found = diagnose(meas)
        diagnose_s = time.perf_counter() - start
    n = len(meas.y_m)
    names = [f.effect.describe() for f in found.effects]
    goal = GOAL_S * duration_s / 86400.0
    print(f"\nreplay and diagnose of {duration_s / 3600:g} h ({n} samples), hidden: "
          f"{truth.describe()}")
    print(f"{'what':<34} {'wall [s]':>9} {'x baseline':>11} {'samples/s':>11}")
    for what, secs in (("read the log (baseline)", read_s), ("replay", replay_s),
                       ("diagnose", diagnose_s)):
        print(f"{what:<34} {secs:9.2f} {secs / read_s:10.2f}x {n / secs:11.3g}")
    print(f"diagnose goal: <= {goal:.0f} s for this length "
          f"({'met' if diagnose_s <= goal else 'MISSED'}); found: {names or 'nothing'}")
    return {"samples": n, "read_s": read_s, "replay_s": replay_s, "diagnose_s": diagnose_s,
            "goal_s": goal, "found": names}
