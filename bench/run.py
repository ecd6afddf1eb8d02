"""`make bench`: speed figures as ratios to a baseline measured in the same run.

Absolute times on a shared machine mean little, so every figure is printed next to a
baseline timed moments before it: here the bare plant (the cheapest loop that still
simulates anything). Results also go to bench/results.json.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import control_socket  # beside this script, which Python puts first on sys.path
import diagnose_speed

from leveler.logwriter import LogWriter
from leveler.settings import load_config
from leveler.sim.plant import Plant
from leveler.simulate import run_virtual

REPO = Path(__file__).resolve().parents[1]
DAY_S = 86400.0


def bare_plant(cfg_path: Path, duration_s: float) -> float:
    """Seconds to step and measure the plant alone for duration_s of virtual time."""
    cfg, _ = load_config(cfg_path)
    plant = Plant(cfg.plant, 1.0 / cfg.loop.rate_hz, seed=1)
    n = round(duration_s * cfg.loop.rate_hz)
    start = time.perf_counter()
    for _ in range(n):
        plant.measure()
        plant.step()
    return time.perf_counter() - start


def full_loop(cfg_path: Path, duration_s: float, logged: bool) -> float:
    """Seconds for the daemon's loop (PID, drivers, truth) with or without the MCAP log."""
    cfg, text = load_config(cfg_path)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        if logged:
            with LogWriter(Path(tmp) / "bench.mcap", truth=True,
                           metadata={"config": text}) as writer:
                run_virtual(cfg, duration_s, 1, engaged=True, writer=writer)
        else:
            run_virtual(cfg, duration_s, 1, engaged=True)
        return time.perf_counter() - start


def main() -> int:
    cfg_path = REPO / "config" / "sim.toml"
    duration = DAY_S / 4 if "--quick" in sys.argv else DAY_S
    base = bare_plant(cfg_path, duration)
    loop = full_loop(cfg_path, duration, logged=False)
    logged = full_loop(cfg_path, duration, logged=True)
    samples = round(duration * 10)
    rows = [
        ("bare plant (baseline)", base, 1.0),
        ("loop, no log", loop, loop / base),
        ("loop + MCAP log of every sample", logged, logged / base),
    ]
    print(f"virtual time {duration / 3600:g} h at 10 Hz = {samples} samples, closed loop")
    print(f"{'what':<34} {'wall [s]':>9} {'x baseline':>11} {'us/sample':>10}")
    for name, secs, ratio in rows:
        print(f"{name:<34} {secs:9.2f} {ratio:10.2f}x {secs / samples * 1e6:10.2f}")
    results = {"duration_s": duration, "samples": samples,
               "rows": [{"what": n, "wall_s": s, "ratio": r} for n, s, r in rows],
               "control_socket": control_socket.main(),
               "diagnose": diagnose_speed.main(duration)}
    (REPO / "bench" / "results.json").write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
