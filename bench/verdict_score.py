"""`leveler replay`'s verdict scored on logs leveler did not make.

The verdict says whether a replay's residual is what the model itself calls unpredictable
(`leveler.analysis.drift`); it is a detector of "something is not in the model". Each log of
the independent generator (bench/independent/generator.py: calibration offsets 1-2 sigma off,
noise levels 10-25 % off, a start out of equilibrium, one hidden effect or none) is replayed
against the nominal model it was made for. Printed: per family and severity how often the
verdict said "something is not in the model", and on the null logs the false-alarm rate with
its Wilson 95 % interval.

    python bench/verdict_score.py --seeds 9101,9102 --nulls 20 [--hours 3] [--jobs 2]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from independent.effects import FAMILIES, SEVERITIES  # noqa: E402
from independent.generator import generate  # noqa: E402


def flagged(case: tuple[str | None, str, int, float, str]) -> tuple[str, str, int, bool, str]:
    """Make one log, replay it against the nominal model: did the verdict flag it?"""
    family, severity, seed, hours, work = case
    log = Path(work) / f"{family}-{severity}-{seed}.mcap"
    generate(family, severity, seed, log, hours=hours, modulated=True,
             nominal_config=REPO / "config" / "sim.toml", platform_inertia=True)
    run = subprocess.run([sys.executable, "-m", "leveler.cli", "replay", str(log), "--json"],
                         capture_output=True, text=True, check=True)
    r = json.loads(run.stdout)
    worst = max((b["residual_over_noise"], name) for name, b in r["bands"].items() if b)
    log.unlink()
    return (family or "none", severity, seed,
            not all(b["unpredictable"] for b in r["bands"].values() if b),
            f"{worst[1]} {worst[0]:.3g}")


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    if n == 0:
        return math.nan, math.nan
    p = k / n
    mid, half = p + z * z / (2 * n), z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (mid - half) / (1 + z * z / n), (mid + half) / (1 + z * z / n)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")],
                    default=[9101, 9102])
    ap.add_argument("--nulls", type=int, default=20)
    ap.add_argument("--hours", type=float, default=3.0)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="verdict-score-") as work:
        cases = [(f, s, seed, a.hours, work) for f in FAMILIES for s in SEVERITIES
                 for seed in a.seeds]
        cases += [(None, "weak", a.seeds[i % len(a.seeds)] * 1000 + i, a.hours, work)
                  for i in range(a.nulls)]
        with ProcessPoolExecutor(a.jobs) as pool:
            rows = list(pool.map(flagged, cases))
    print(f"replay's verdict on the independent generator: {len(rows)} logs of {a.hours:g} h, "
          f"seeds {','.join(map(str, a.seeds))}, against the nominal model\n")
    print(f"{'family':<22}" + "".join(f"{s:>10}" for s in SEVERITIES) + "   flagged / logs")
    for fam in FAMILIES:
        cells = [[r for r in rows if r[0] == fam and r[1] == s] for s in SEVERITIES]
        print(f"{fam:<22}" + "".join(f"{sum(r[3] for r in c):>6}/{len(c):<3}" for c in cells))
    effect = [r for r in rows if r[0] != "none"]
    nulls = [r for r in rows if r[0] == "none"]
    fa = sum(r[3] for r in nulls)
    lo, hi = wilson(fa, len(nulls))
    print(f"\nconfusion matrix [logs]: rows = truth, columns = verdict\n"
          f"{'':<10}{'flagged':>9}{'quiet':>7}\n"
          f"{'effect':<10}{sum(r[3] for r in effect):>9}{sum(not r[3] for r in effect):>7}\n"
          f"{'none':<10}{fa:>9}{len(nulls) - fa:>7}\n"
          f"false alarms {fa}/{len(nulls)} (Wilson 95 %: {lo:.0%}-{hi:.0%})")
    for r in nulls:
        if r[3]:
            print(f"  null seed {r[2]} flagged: worst band {r[4]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
