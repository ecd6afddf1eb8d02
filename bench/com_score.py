"""`leveler calibrate-com LOG` scored on recordings leveler did not make.

Each seed of the independent tiltmeter generator (bench/independent/tiltmeter.py: a hanging
beam balance, the lab's stated values 1-2 sigma off the truth, a day of stepped sine sweep in a
logger's own CSV with stray rows) is imported with `leveler import-csv` as a lab would (the
column names and units the file's preamble states, the stated counts scale), given a config
built from the stated values only, and analysed by `leveler calibrate-com`. Printed per seed:
the true and recovered centre-of-mass distance, the error in per cent and in the reported
sigma; then how often the truth fell within 1 and 2 sigma (a Gaussian's 68 % and 95 %) and
the median relative error.

    python bench/com_score.py --seeds 201-210 [--drift-scale 0.1] [--drive square] [--json F]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.common import seeds  # noqa: E402
from bench.independent.tiltmeter import write_recording  # noqa: E402

LEVELER = [sys.executable, "-m", "leveler.cli"]


def stand_config(truth: dict) -> str:
    """The config a lab writes from what it states: no d, k and Q as stated, tolerances, its
    sensor's noise as the data sheet gives it (the generator's nominal levels: each log's are
    10-25 % off), no thermal coupling known, no cooler, a converter finer than the noise."""
    s, noise = truth["stated"], truth["noise"]
    fs = truth["sample_rate_hz"]
    white = noise["white_nominal_m"] * math.sqrt(2 / fs)  # per sample -> one-sided ASD
    walk = noise["drift_walk_nominal_m"] * noise["drift_scale"] * math.sqrt(fs)
    j, m, k, q = (s["J_kg_m2"]["value"], s["m_kg"]["value"], s["k_N_m_per_rad"]["value"],
                  s["Q"]["value"])
    return (f"[plant.pendulum]\nmass_kg = {m!r}\ncom_length_m = -1e-6\n"
            f"flexure_stiffness_nm_per_rad = {k!r}\ninertia_kgm2 = {j!r}\n"
            f"damping_nms_per_rad = {math.sqrt(j * k) / q!r}\n"
            f"sensor_arm_m = {s['sensor_arm_m']['value']!r}\n"
            f"[plant.piezo]\ngain_m_per_v = {s['piezo_gain_m_per_V']['value']!r}\n"
            f"[plant.platform]\nsupport_spacing_m = {s['support_spacing_m']['value']!r}\n"
            "[plant.thermal]\ntilt_per_kelvin_rad_per_k = 0.0\n"
            "[plant.cooler]\npeak_to_peak_rad = 0.0\n"
            f"[plant.sensor]\nnoise_m_per_rthz = {white!r}\ndrift_m_per_sqrt_s = {walk!r}\n"
            "adc_bits = 24\n"
            "[plant.uncertainty]\nmass_rel = 0.005\ninertia_rel = 0.03\nsensor_arm_rel = 0.02\n"
            "sensor_gain_rel = 0.02\npiezo_gain_rel = 0.03\nsupport_spacing_rel = 0.01\n")


def import_args(truth: dict, csv: Path, log: Path) -> list[str]:
    """`leveler import-csv` as the file's preamble tells a lab to call it."""
    t, sensor, actuator, temp = truth["columns"]
    return ["import-csv", str(csv), "--out", str(log), "--column", f"t={t}",
            "--column", f"sensor={sensor}", "--column", f"actuator={actuator}",
            "--column", f"temperature={temp}", "--time-unit", "days",
            "--scale", f"sensor={truth['scale_m_per_count']['stated']!r}",
            "--offset", "temperature=273.15", "--skip-bad", "--resample"]


def score(seed: int, drive: str, drift_scale: float, work: Path) -> dict:
    out = work / str(seed)
    truth = write_recording(seed, out, drive, drift_scale)
    log, cfg = out / "run.mcap", out / "stand.toml"
    cfg.write_text(stand_config(truth))
    subprocess.run([*LEVELER, *import_args(truth, Path(truth["csv_path"]), log)], check=True,
                   capture_output=True, text=True)
    run = subprocess.run([*LEVELER, "calibrate-com", str(log), "--model", str(cfg), "--json"],
                         capture_output=True, text=True)
    if run.returncode != 0:
        return {"seed": seed, "error": run.stderr.strip(), "d_true_m": truth["d_true_m"]}
    r = json.loads(run.stdout)
    d_true, d = truth["d_true_m"], -r["com_length_m"]
    return {"seed": seed, "d_true_m": d_true, "d_m": d, "sigma_m": r["com_length_sigma_m"],
            "error_rel": d / d_true - 1, "pull": (d - d_true) / r["com_length_sigma_m"],
            "f_z_hz": truth["f_z_hz"], "lines": len(r["lines"]),
            "steps": len(truth["drive"]["steps"])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=seeds, default=seeds("201-210"))
    ap.add_argument("--drive", choices=("sine", "square"), default="sine")
    ap.add_argument("--drift-scale", type=float, default=1.0)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="com-score-") as tmp:
        print(f"{'seed':>5} {'d true [um]':>12} {'d [um]':>9} {'sigma [um]':>11} "
              f"{'error':>8} {'pull':>6} {'lines/steps':>11}")
        for seed in a.seeds:
            row = score(seed, a.drive, a.drift_scale, Path(tmp))
            rows.append(row)
            if "error" in row:
                print(f"{seed:5d} {row['d_true_m'] * 1e6:12.4g}  failed: {row['error']}")
                continue
            print(f"{seed:5d} {row['d_true_m'] * 1e6:12.4g} {row['d_m'] * 1e6:9.4g} "
                  f"{row['sigma_m'] * 1e6:11.2g} {row['error_rel']:+8.1%} {row['pull']:+6.2f} "
                  f"{row['lines']:>5}/{row['steps']:<5}", flush=True)
    ok = [r for r in rows if "error" not in r]
    within = [sum(abs(r["pull"]) < k for r in ok) for k in (1, 2)]
    errors = sorted(abs(r["error_rel"]) for r in ok)
    median = errors[len(errors) // 2] if errors else math.nan
    print(f"\n{len(ok)} of {len(rows)} analysed ({a.drive} sweep, sensor walk x{a.drift_scale:g});"
          f" truth within 1 sigma {within[0]}/{len(ok)}, within 2 sigma {within[1]}/{len(ok)};"
          f" median |error| {median:.1%}; within 10 % {sum(e < 0.1 for e in errors)}/{len(ok)}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
