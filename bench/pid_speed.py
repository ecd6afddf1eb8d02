"""PID update: leveler.loop.pid.PID.update against simple_pid.PID on the same inputs.

leveler's PID runs with everything it offers switched on: P, I and D, a derivative
low-pass, a setpoint ramp (moving: the setpoint changes during the run), an output slew
limit and back-calculation anti-windup (the output reaches both rails). simple-pid gets
the same gains, limits and measurements with `dt` passed in, as a simulation would call
it. Both are called in the same plain loop; the best of several interleaved repeats
counts. Goal: no slower (ratio of time per update <= 1.0x).

Also shown, to explain the figure: the part of leveler's update spent building the
PIDOutput record it returns.
"""

from __future__ import annotations

import math
import random
import time
from typing import Any

from common import at_most, row  # beside this script

from leveler.loop.pid import PID, PIDConfig, PIDGains, PIDOutput

SECTION = "pid"
DT = 1e-3
KP, KI, KD = 2.0e5, 7.0e5, 1.0e2  # V/m, V/(m s), V s/m
LO, HI = 0.0, 150.0


def measurements(n: int) -> list[float]:
    """A slow swing of the pendulum end big enough to rail the output, plus noise [m]."""
    rng = random.Random(1)
    return [1e-4 * math.sin(2 * math.pi * k / 20_000) + 1e-8 * rng.gauss(0.0, 1.0)
            for k in range(n)]


def leveler_pid() -> PID:
    cfg = PIDConfig(PIDGains(KP, KI, KD), LO, HI, setpoint_m=0.0, slew_v_per_s=1.0e4,
                    d_filter_tau_s=0.005, setpoint_ramp_m_per_s=1.0e-6)
    pid = PID(cfg, initial_output_v=75.0)
    pid.set_setpoint(2.0e-6)  # ramps over the first two seconds of updates
    return pid


def time_leveler(ms: list[float]) -> float:
    update = leveler_pid().update
    start = time.perf_counter()
    for m in ms:
        update(m, DT)
    return (time.perf_counter() - start) / len(ms)


def time_simple_pid(ms: list[float]) -> float:
    import simple_pid

    pid = simple_pid.PID(KP, KI, KD, setpoint=2.0e-6, sample_time=None,
                         output_limits=(LO, HI), starting_output=75.0)
    start = time.perf_counter()
    for m in ms:
        pid(m, dt=DT)
    return (time.perf_counter() - start) / len(ms)


def time_output_record(ms: list[float]) -> float:
    """Building one PIDOutput, as update's return statement does."""
    start = time.perf_counter()
    for m in ms:
        PIDOutput(m, m, m, m, m, m, False)
    return (time.perf_counter() - start) / len(ms)


def run(quick: bool) -> list[dict[str, Any]]:
    try:
        import simple_pid  # noqa: F401
    except ImportError as e:
        raise RuntimeError("simple-pid is not installed: `make bench` installs it "
                           "(pip install -e '.[bench]')") from e
    n = 200_000 if quick else 500_000
    repeats = 3 if quick else 4
    ms = measurements(n)
    lev, ref, rec = math.inf, math.inf, math.inf
    for _ in range(repeats):  # interleaved: both see the machine's load alike
        lev = min(lev, time_leveler(ms))
        ref = min(ref, time_simple_pid(ms))
        rec = min(rec, time_output_record(ms))
    ratio = lev / ref
    return [
        row(SECTION, "simple_pid.PID, dt given (baseline)", ref * 1e9, "ns/update",
            note=f"{n} updates, best of {repeats}; clamps output and integral, no slew, "
                 "no derivative filter, no setpoint ramp"),
        row(SECTION, "leveler PID.update, all features on", lev * 1e9, "ns/update",
            baseline="simple-pid", ratio=ratio, goal="<= 1.0x", met=at_most(ratio, 1.0),
            note="slew limit, derivative filter, setpoint ramp, back-calculation "
                 "anti-windup; the output rails both ways"),
        row(SECTION, "  of which: building its PIDOutput", rec * 1e9, "ns/update",
            note=f"{rec / lev:.0%} of the update: " + (
                "a frozen dataclass, each field set through object.__setattr__"
                if PIDOutput.__dataclass_params__.frozen else "a plain slotted dataclass")),
    ]
