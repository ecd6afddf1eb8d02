"""`leveler modulate LOG`'s triangle opening scored on logs leveler did not make.

Each seed of the independent generator (bench/independent/generator.py: calibration offsets,
noise levels off by 10-25 %, a start out of equilibrium, an open-loop first third modulated
by a square or a triangle of its own phase) is written for an hour, with nothing missing, a
Bouc-Wen hysteresis (weak, medium, strong) or an actuator delay (medium: a lag, which opens
a triangle too). Seeds whose modulation is a square are skipped: only a triangle sweeps.
Each log is read by `leveler modulate LOG --json`; "opened" is an opening at 3 sigma or
more of its scatter over the cycles. Printed per log: the wave found, the opening in nm,
its z and the lag it would be, and whether a known disturbance repeats with the wave; then
the confusion of opened against the truth, with the false-alarm rate among the null logs
and its Wilson 95 % interval.

    python bench/opening_score.py --seeds 201-230
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.common import seeds  # noqa: E402
from bench.diagnose_score import wilson  # noqa: E402
from bench.independent.generator import generate  # noqa: E402

CASES = [(None, "medium"), ("actuator_hysteresis", "weak"), ("actuator_hysteresis", "medium"),
         ("actuator_hysteresis", "strong"), ("actuator_delay", "medium")]
Z_OPENED = 3.0


def score(family: str | None, severity: str, seed: int, tmp: Path) -> dict[str, Any] | None:
    """One log's triangle as `leveler modulate` reads it; None where the seed drew a square."""
    log = tmp / f"{family}_{severity}_{seed}.mcap"
    truth = generate(family, severity, seed, log, hours=1.0, modulated=True)
    if truth["modulation"]["shape"] != "triangle":
        log.unlink()
        return None
    out = subprocess.run([sys.executable, "-m", "leveler.cli", "modulate", str(log), "--json"],
                         capture_output=True, text=True, timeout=300, cwd=REPO)
    log.unlink()
    if out.returncode:
        return {"error": out.stderr.strip().splitlines()[-1]}
    (w,) = json.loads(out.stdout)["waves"]
    return w


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="201-230", help="seeds, e.g. 201-230 or 1,4,9")
    args = ap.parse_args()
    counts: dict[str, list[int]] = {}
    with tempfile.TemporaryDirectory() as d:
        for family, severity in CASES:
            name = f"{family or 'none'} {severity}"
            counts[name] = [0, 0]
            for seed in seeds(args.seeds):
                w = score(family, severity, seed, Path(d))
                if w is None:
                    continue
                if "error" in w:
                    print(f"{name:28s} {seed}: error {w['error']}", flush=True)
                    counts[name][1] += 1
                    continue
                z = w["opening_z"]
                opened = z is not None and z >= Z_OPENED
                counts[name][0] += opened
                counts[name][1] += 1
                print(f"{name:28s} {seed}: {w['wave']['shape']} {w['wave']['period_s']:.1f} s "
                      f"x {w['wave']['cycles']}, opening {w['opening_m'] * 1e9:+.2f} nm, "
                      f"z {z if z is None else round(z, 1)}, as a lag "
                      f"{w['opening_as_lag_s'] * 1e3:+.0f} ms"
                      + (", a known disturbance repeats with it" if w["coherent"] else ""),
                      flush=True)
    print(f"\nopened (z >= {Z_OPENED:g}) per case, triangle logs only:")
    for name, (k, n) in counts.items():
        lo, hi = wilson(k, n)
        print(f"  {name:28s} {k:3d} / {n:3d}  (Wilson 95 %: {lo * 100:.0f}-{hi * 100:.0f} %)")
    k, n = counts["none medium"]
    print(f"false alarms: {k} / {n} null logs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
