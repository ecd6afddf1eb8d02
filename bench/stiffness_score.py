"""`leveler analyze stiffness LOG` scored on recordings leveler did not make.

Each seed of the independent thrust-stand generator (bench/independent/thrust_stand.py: a
torsion pendulum drawn per seed, the lab's own column names, units and delimiter, thrust and
tiltmeter calibrations off within their tolerances, a sensor that drifts and a record that
starts ringing) is imported with `leveler import-csv` as the file's import block says, and
analysed with the lab's stated arm length and its sigma; the stated tolerances (a +- bound
each) enter as 1-sigma = bound / sqrt(3), a rectangular distribution's. Scenarios: `stepped`
(the paper's tilt plateaus), `drift` (a thermal day and a cooler), `dual` (the paper's
dual-frequency drive and a square-wave section) and `null` (`stepped` with l_cm = 0).

Printed per log: K0 and M g l_cm, true and recovered, errors in per cent and in the reported
sigma; then per scenario how often the truth fell within 1 and 2 sigma, and the confusion
matrix of "tilt coupling shown" (|M g l_cm| >= 3 sigma) against the truth, with the
false-alarm rate on the null logs.

    python bench/stiffness_score.py --seeds 301-310 [--scenarios stepped,null] [--json F]
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
sys.path.insert(0, str(REPO))

from bench.common import seeds  # noqa: E402
from bench.independent.thrust_stand import write_recording  # noqa: E402

LEVELER = [sys.executable, "-m", "leveler.cli"]
SCENARIOS = ("stepped", "drift", "dual", "null")
SHOWN_SIGMA = 3.0  # the report's threshold for "the stand feels the base tilt"
TIME_UNITS = {"s": "s", "ms": "ms", "days": "days"}


def import_args(truth: dict, csv: Path, log: Path) -> list[str]:
    """`leveler import-csv` as the truth's import block (the file's preamble) tells."""
    imp = truth["import"]
    args = ["import-csv", str(csv), "--out", str(log), "--delimiter", imp["delimiter_name"]]
    for role, spec in imp["roles"].items():
        args += ["--column", f"{role}={spec['column']}"]
        if role == "t":
            args += ["--time-unit", TIME_UNITS[spec["unit"]]]
            continue
        if spec["scale"] != 1.0:
            args += ["--scale", f"{role}={spec['scale']!r}"]
        if spec["offset"] != 0.0:
            args += ["--offset", f"{role}={spec['offset']!r}"]
    return args


def analyze_args(truth: dict, log: Path) -> list[str]:
    """What the lab states: L and its sigma, the thrust's and tiltmeter's tolerances."""
    cal = truth["calibration"]
    return ["analyze", "stiffness", str(log), "--json",
            "--arm-m", repr(truth["stated"]["L_m"]["value"]),
            "--arm-sigma-m", repr(truth["stated"]["L_m"]["sigma"]),
            "--thrust-sigma-rel", repr(cal["thrust"]["tolerance_rel"] / math.sqrt(3)),
            "--tilt-sigma-rel", repr(cal["tiltmeter"]["gain_tolerance_rel"] / math.sqrt(3))]


def _run(args: list[str]) -> str:
    done = subprocess.run(LEVELER + args, capture_output=True, text=True, cwd=REPO, check=False)
    if done.returncode:
        raise RuntimeError(f"leveler {' '.join(args[:2])} failed: {done.stderr.strip()}")
    return done.stdout


def score(seed: int, scenario: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        truth = write_recording(seed, work, scenario=scenario)
        csv = work / f"thrust_stand_{seed}_{scenario}.csv"
        log = work / "stand.mcap"
        _run(import_args(truth, csv, log))
        r = json.loads(_run(analyze_args(truth, log)))
    p = truth["pendulum"]
    k0, mgl = p["K0_N_m_per_rad"], p["Mgl_cm_N_m_per_rad"]
    out = {"seed": seed, "scenario": scenario, "k0_true": k0,
           "k0": r["stiffness_nm_per_rad"], "k0_sigma": r["stiffness_sigma_nm_per_rad"],
           "mgl_true": mgl, "mgl": r["tilt_sensitivity_nm_per_rad"],
           "mgl_sigma": r["tilt_sensitivity_sigma_nm_per_rad"],
           "significance": r["coupling_significance"], "f0_true": p["f0_hz"],
           "f0": r["natural_frequency_hz"], "q_true": p["Q"], "q": r["quality_factor"]}
    out["k0_pull"] = (out["k0"] - k0) / out["k0_sigma"]
    out["mgl_pull"] = (out["mgl"] - mgl) / out["mgl_sigma"]
    out["shown"] = out["significance"] >= SHOWN_SIGMA
    return out


def summary(rows: list[dict]) -> list[str]:
    lines = []
    for sc in dict.fromkeys(r["scenario"] for r in rows):
        rs = [r for r in rows if r["scenario"] == sc]
        n = len(rs)
        k1 = sum(abs(r["k0_pull"]) <= 1 for r in rs)
        k2 = sum(abs(r["k0_pull"]) <= 2 for r in rs)
        kerr = sorted(abs(r["k0"] / r["k0_true"] - 1) for r in rs)
        line = (f"{sc:8s} K0: {k1}/{n} within 1 sigma, {k2}/{n} within 2, median error "
                f"{100 * kerr[n // 2]:.2f} %")
        if sc != "null":
            m1 = sum(abs(r["mgl_pull"]) <= 1 for r in rs)
            m2 = sum(abs(r["mgl_pull"]) <= 2 for r in rs)
            merr = sorted(abs(r["mgl"] / r["mgl_true"] - 1) for r in rs)
            line += (f"; M g l_cm: {m1}/{n} within 1 sigma, {m2}/{n} within 2, median error "
                     f"{100 * merr[n // 2]:.1f} %")
        else:
            m2 = sum(abs(r["mgl_pull"]) <= 2 for r in rs)
            line += f"; M g l_cm = 0: {m2}/{n} within 2 sigma of zero"
        lines.append(line)
    pos = [r for r in rows if r["scenario"] != "null"]
    neg = [r for r in rows if r["scenario"] == "null"]
    tp, fn = sum(r["shown"] for r in pos), sum(not r["shown"] for r in pos)
    fp, tn = sum(r["shown"] for r in neg), sum(not r["shown"] for r in neg)
    lines += ["", f"tilt coupling shown (>= {SHOWN_SIGMA:g} sigma)   truth: coupled   truth: "
              "l_cm = 0",
              f"  shown                              {tp:13d}   {fp:13d}",
              f"  not shown                          {fn:13d}   {tn:13d}"]
    if neg:
        lines.append(f"  false-alarm rate {fp}/{len(neg)} = {fp / len(neg):.0%}")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="301-310")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", default=None, help="write every row to this file")
    a = ap.parse_args()
    jobs = [(s, sc) for sc in a.scenarios.split(",") for s in seeds(a.seeds)]
    with ProcessPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(score, *zip(*jobs, strict=True)))
    print(f"{'scenario':8s} {'seed':>5s} {'K0 true':>9s} {'K0 fit':>9s} {'pull':>6s} "
          f"{'Mgl true':>10s} {'Mgl fit':>10s} {'+-':>8s} {'pull':>6s} {'sigmas':>7s}"
          "   [N m/rad; M g l_cm in uN m/urad]")
    for r in rows:
        print(f"{r['scenario']:8s} {r['seed']:5d} {r['k0_true']:9.4g} {r['k0']:9.4g} "
              f"{r['k0_pull']:6.2f} {r['mgl_true']:10.3g} {r['mgl']:10.3g} "
              f"{r['mgl_sigma']:8.2g} {r['mgl_pull']:6.2f} {r['significance']:7.1f}")
    print("\n" + "\n".join(summary(rows)))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
