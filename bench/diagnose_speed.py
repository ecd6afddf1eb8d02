"""Replay and diagnose of a day-long log: samples per second, against reading the log.

The log is a closed-loop day at 10 Hz with a hidden water-cooler-like sawtooth (what
`leveler diagnose` exists to find); the baseline is reading that log, timed in the same
run. `leveler replay` is reading plus replaying. The goal from issue 4: a 24 h log
diagnosed in at most 2 minutes on 2 cores, reading the log included (as the command does).

A fresh null calibration (`leveler diagnose --null-runs 50`, issue 17's goal: 15 min for a
day on 2 cores) simulates a null log per run on the log's schedule; the rows time one
such simulation by the objects (the baseline) and with its uneventful samples in the
compiled kernel, and check the two logs are the same to the bit; and the replay of the
logged controller that tells each log's excitation (`excitation_v`), likewise. The whole calibration
takes too long for this bench: docs/replay.md gives it, measured by hand.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import REPO, bench_tmpdir, row  # beside this script

from leveler.analysis.diagnose import diagnose
from leveler.analysis.nullcal import simulate_null
from leveler.analysis.predict import _excitation_v, load_measured
from leveler.analysis.replay import replay
from leveler.analysis.synthetic import make_measured
from leveler.settings import load_config
from leveler.sim.effects import PeriodicDisturbance

SECTION = "replay and diagnose"
DAY_S = 86400.0
GOAL_S = 120.0


def measure(duration_s: float) -> dict[str, Any]:
    """Write the log, then time reading it, replaying it and diagnosing it."""
    cfg, text = load_config(REPO / "config" / "sim.toml")
    truth = PeriodicDisturbance(shape="sawtooth", period_s=287.0, peak_to_peak_rad=2.4e-7,
                                phase_s=40.0)
    with bench_tmpdir() as tmp:
        log = Path(tmp) / "night.mcap"
        make_measured(log, cfg, text, truth, duration_s=duration_s, seed=7)
        start = time.perf_counter()
        meas = load_measured(log)
        read_s = time.perf_counter() - start
        start = time.perf_counter()
        replay(meas)
        replay_s = time.perf_counter() - start
        start = time.perf_counter()
        found = diagnose(meas, jobs=os.cpu_count() or 1)  # as the command does
        diagnose_s = time.perf_counter() - start
        null_s, logs = {}, {}
        simulate_null(meas, 1)  # numba's compile (or its cache's load) is not the run's
        for kernel in ("off", "auto"):
            start = time.perf_counter()
            logs[kernel] = simulate_null(meas, 1, kernel=kernel).y_m
            null_s[kernel] = time.perf_counter() - start
        same = bool(np.array_equal(logs["off"], logs["auto"]))
        exc_s, excs = {}, {}
        _excitation_v(meas)  # the compile again
        for kernel in ("off", "auto"):
            start = time.perf_counter()
            excs[kernel] = _excitation_v(meas, kernel=kernel)
            exc_s[kernel] = time.perf_counter() - start
        exc_same = bool(np.array_equal(excs["off"], excs["auto"]))
    return {"samples": len(meas.y_m), "read_s": read_s, "replay_s": replay_s,
            "diagnose_s": diagnose_s, "hidden": truth.describe(),
            "found": [f.effect.describe() for f in found.effects],
            "null_objects_s": null_s["off"], "null_kernel_s": null_s["auto"],
            "null_same": same, "exc_objects_s": exc_s["off"], "exc_kernel_s": exc_s["auto"],
            "exc_same": exc_same}


def run(quick: bool) -> list[dict[str, Any]]:
    duration_s = 3600.0 if quick else DAY_S
    d = measure(duration_s)
    n = d["samples"]
    read_rate = n / d["read_s"]
    cmd_rate = n / (d["read_s"] + d["replay_s"])
    hours = f"{duration_s / 3600:g} h log, {n} samples"
    found = "; ".join(d["found"]) or "nothing"
    kind_and_period = ",".join(d["hidden"].split(",")[:2])
    hit = any(f.startswith(kind_and_period) for f in d["found"])
    total = d["read_s"] + d["diagnose_s"]  # what the command does
    if quick:
        met, goal_note = None, ("; quick mode: a 1 h log, not judged (diagnose has a fixed "
                                "cost of several seconds, so the time does not scale)")
    else:
        met, goal_note = total <= GOAL_S, ""
    return [
        row(SECTION, "read the log (baseline)", read_rate, "samples/s", note=hours),
        row(SECTION, "`leveler replay`: read + replay", cmd_rate, "samples/s",
            baseline="read", ratio=cmd_rate / read_rate,
            note=f"the model's prediction alone: {n / d['replay_s']:.3g} samples/s"),
        row(SECTION, f"`leveler diagnose` of a {duration_s / 3600:g} h log", total, "s",
            goal=f"<= {GOAL_S:g} s (24 h)", met=met,
            note=f"read {d['read_s']:.1f} s + diagnose {d['diagnose_s']:.1f} s; "
                 f"hidden: {d['hidden']}; found: {found}"
                 f"{'' if hit else ' (NOT the hidden effect)'}{goal_note}"),
        row(SECTION, "a null calibration run's log, simulated by the objects (baseline)",
            d["null_objects_s"], "s", note=hours),
        row(SECTION, "  the same, its uneventful samples in the compiled kernel",
            d["null_kernel_s"], "s", baseline="objects",
            ratio=d["null_objects_s"] / d["null_kernel_s"],
            note="the same log to the bit" if d["null_same"]
            else "NOT the objects' log: a bug"),
        row(SECTION, "the logged controller replayed for the excitation, by the PID "
            "object (baseline)", d["exc_objects_s"], "s", note=hours),
        row(SECTION, "  the same, after each engage in the compiled kernel",
            d["exc_kernel_s"], "s", baseline="PID object",
            ratio=d["exc_objects_s"] / d["exc_kernel_s"],
            note="the same excitation to the bit" if d["exc_same"]
            else "NOT the object's excitation: a bug"),
    ]
