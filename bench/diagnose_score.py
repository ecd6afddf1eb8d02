"""Score `leveler diagnose` against logs from the independent generator (bench/independent/).

Every case is one measured log written by `independent.generator.generate` (its own plant,
calibration offsets, scaled noises, a start out of equilibrium and, for an effect case, one
missing effect in the generator's own form), then `leveler diagnose LOG --json` run on it as a
subprocess. Printed (and written as JSON to --out):

- the confusion matrix: true family (rows, "none" for nulls) against the first effect diagnose
  named (columns; "none" when it named nothing, "other" for a name outside the eight);
- the false-alarm rate on the null logs with its Wilson 95 % interval;
- per severity, the fraction of effect logs whose family diagnose named first (and anywhere);
- per case, the residual gap diagnose reports before and after its fit and their ratio.

Seeds: by default the TUNING seeds (101, 102, 103), which anyone may look at while improving
the detector. `--untouched` takes the next three seeds of a separate fixed list (9011-9070;
9041-9070 added at stop 53, when 9040 was the last unused, none of them ever generated)
that no board has used yet (`UNTOUCHED_USED`): run it only to report a final figure, never to
decide a change, or it stops being a test; then add the three to `UNTOUCHED_USED`.
The first list, 9001-9010, is retired: each was looked at once, and 9001 and 9003-9005
were then tuned on (docs/replay.md).

    python bench/diagnose_score.py [--quick] [--jobs 2] [--untouched] [--seeds 101,102]
        [--families a,b] [--severities weak,strong] [--nulls 50] [--hours 6] [--out FILE]

`--quick`: 1 seed, weak and strong, 6 nulls, 3 h logs (10-20 minutes on 2 cores).
Null logs alternate modulated (open-loop square/triangle first third) and closed-loop only;
effect logs are all modulated (actuator effects need the excitation).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from independent.effects import FAMILIES, SEVERITIES  # noqa: E402
from independent.generator import generate  # noqa: E402

from leveler.analysis.recalibrate import PULL_LIMIT  # noqa: E402
from leveler.analysis.workers import one_blas_thread  # noqa: E402
from leveler.settings import load_config  # noqa: E402

TUNING_SEEDS = (101, 102, 103)
#: never looked at while tuning; labelled untouched however they are asked for
UNTOUCHED_SEEDS = tuple(range(9011, 9071))
#: those a board has reported on, each once (docs/replay.md): no longer untouched for the next
UNTOUCHED_USED = tuple(range(9011, 9064))
SHORT = {
    "none": "none",
    "periodic_disturbance": "period",
    "temperature_coupling": "temp",
    "actuator_delay": "delay",
    "actuator_hysteresis": "hyst",
    "extra_resonance": "reson",
    "sensor_gain_error": "gain",
    "sensor_drift": "drift",
    "adc_quantization": "quant",
    "ambiguous": "ambig",
    "unexplained": "unexpl",
    "other": "other",
    "error": "error",
}
DIAGNOSE_TIMEOUT_S = 3600.0


def leveler_command() -> list[str]:
    exe = Path(sys.executable).with_name("leveler")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "leveler.cli"]


def predicted_label(report: dict[str, Any]) -> tuple[str, list[str]]:
    """(column, every name diagnose gave) from its --json report."""
    names = [str(e.get("name", "?")) for e in report.get("effects") or []]
    for flag in ("ambiguous", "unexplained"):
        if report.get(flag) and not names:
            return flag, names
    if not names:
        return "none", names
    first = names[0]
    if first in FAMILIES or first in ("ambiguous", "unexplained"):
        return first, names
    return "other", names


def _rel_close(a: float | None, b: float | None, tol: float) -> bool:
    return (a is not None and b is not None and b != 0
            and math.copysign(1, a) == math.copysign(1, b) and abs(a / b - 1) <= tol)


def params_match(family: str, truth: dict[str, Any], fitted: dict[str, Any]) -> bool | None:
    """Whether diagnose's fit of the true family agrees with the truth on what both forms
    share (None where the forms share nothing comparable, e.g. Bouc-Wen vs a play operator)."""
    g = fitted.get
    if family == "periodic_disturbance":  # its period, or a harmonic of it
        period = g("period_s")
        return bool(period) and any(abs(truth["period_s"] / k / period - 1) <= 0.05
                                    for k in (1, 2, 3))
    if family == "extra_resonance":
        return _rel_close(g("frequency_hz"), truth["frequency_hz"], 0.1)
    if family == "actuator_delay":
        return _rel_close(g("delay_s"), truth["delay_s"], 0.5)
    if family == "sensor_gain_error":
        return _rel_close(g("gain_error"), truth["gain_error"], 0.5)
    if family == "sensor_drift":  # the mean rate of the trend
        return _rel_close(g("rate_m_per_s"), truth["rate_m_per_s"]
                          * (1 + truth["curvature"]), 0.5)
    if family == "temperature_coupling":
        return _rel_close(g("tilt_per_kelvin_rad_per_k"),
                          truth["tilt_per_kelvin_rad_per_k"], 1.0)
    if family == "adc_quantization":
        return _rel_close(g("step_m"), truth["step_m"], 0.25)
    return None


def annotate(case: dict[str, Any]) -> None:
    """Add `params_match` and `cooler_alarm` (a periodic disturbance named at the modelled
    cooler's period: its amplitude is scaled in every log) from the case's effects."""
    effects = case.get("effects") or []
    truth = case.get("truth") or {}
    cooler_s = truth.get("nominal_cooler_period_s") or 300.0
    case["cooler_alarm"] = any(
        e.get("name") == "periodic_disturbance"
        and abs((e.get("params") or {}).get("period_s", 0) / cooler_s - 1) < 0.03
        for e in effects)
    fit = next((e for e in effects if e.get("name") == case["family"]), None)
    case["params_match"] = (None if fit is None
                            else params_match(case["family"], truth.get("params") or {},
                                              fit.get("params") or {}))


def run_case(case: dict[str, Any], workdir: str, hours: float, platform_inertia: bool,
             keep: bool) -> dict[str, Any]:
    """Generate one log, diagnose it, return the case with truth and verdict."""
    tag = f"{case['family']}-{case['severity'] or 'null'}-{case['seed']}"
    log = Path(workdir) / f"{tag}.mcap"
    t0 = time.perf_counter()
    truth = generate(None if case["family"] == "none" else case["family"],
                     case["severity"] or "medium", case["seed"], log, hours=hours,
                     modulated=case["modulated"], nominal_config=REPO / "config/sim.toml",
                     platform_inertia=platform_inertia)
    gen_s = time.perf_counter() - t0
    cmd = [*leveler_command(), "diagnose", str(log), "--json", "--jobs", "1",
           "--model-out", str(log.with_suffix(".fitted.toml"))]  # the cases fill the cores
    t1 = time.perf_counter()
    result: dict[str, Any] = {**case, "truth": truth, "generate_s": gen_s}
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=DIAGNOSE_TIMEOUT_S,
                              cwd=REPO)
        result["diagnose_s"] = time.perf_counter() - t1
        result["returncode"] = proc.returncode
        report = json.loads(proc.stdout) if proc.returncode == 0 else None
        if report is None:
            result["error"] = (proc.stderr or proc.stdout).strip()[-2000:]
    except (subprocess.TimeoutExpired, json.JSONDecodeError) as e:
        result["diagnose_s"] = time.perf_counter() - t1
        result["error"] = f"{type(e).__name__}: {e}"[:2000]
        report = None
    if report is None:
        result["predicted"], result["named"] = "error", []
    else:
        result["predicted"], result["named"] = predicted_label(report)
        result["effects"] = report.get("effects")
        result["gap_before"] = report.get("gap_before")
        result["gap_after"] = report.get("gap_after")
        result["recalibration"] = report.get("recalibration")
        result["diagnose_wall_s"] = report.get("wall_s")
        annotate(result)
    if not keep:
        for path in (log, log.with_suffix(".fitted.toml")):
            path.unlink(missing_ok=True)
    return result


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval for k successes in n trials."""
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))


def shrink(case: dict[str, Any]) -> dict[str, Any]:
    """rms before/after [m], their ratio, and the band that shrank most."""
    before, after = case.get("gap_before") or {}, case.get("gap_after") or {}
    b, a = before.get("rms_m"), after.get("rms_m")
    out: dict[str, Any] = {"rms_before_m": b, "rms_after_m": a,
                           "ratio": (b / a) if b and a else None,
                           "best_band": None, "best_band_ratio": None}
    bb, ab = before.get("band_rms_m") or {}, after.get("band_rms_m") or {}
    ratios = {k: bb[k] / ab[k] for k in bb if ab.get(k)}
    if ratios:
        band = max(ratios, key=ratios.get)
        out["best_band"], out["best_band_ratio"] = band, ratios[band]
    return out


def loop_gain_pull(truth: dict[str, Any]) -> float:
    """A log's whole loop gain (reading per piezo volt: the sensor path times the actuator
    path, with the calibration offsets the generator drew and a sensor gain error's own
    error) from nominal, over the tolerance the model file states for it. It is what a log
    pins most tightly (the modulation's response, the loop's dynamics); the two paths apart
    it pins only through disturbance levels known to tens of per cent. A null log's offsets
    (each 1-2 sigma) reach 3-4 sigma of this: a gain error inside that is an in-tolerance
    calibration to any detector that keeps its false alarms at a per cent."""
    u = load_config(REPO / "config" / "sim.toml")[0].plant.uncertainty
    cal = truth["calibration_rel"]
    error = truth["params"]["gain_error"] if truth["family"] == "sensor_gain_error" else 0.0
    total = ((1 + error) * (1 + cal["sensor_gain_rel"]) * (1 + cal["sensor_arm_rel"])
             * (1 + cal["amplification_rel"]) * (1 + cal["piezo_gain_rel"])
             / (1 + cal["support_spacing_rel"]) - 1)
    return total / math.hypot(u.sensor_path_rel, u.actuator_path_rel)


def summarize(cases: list[dict[str, Any]]) -> dict[str, Any]:
    rows = sorted({c["family"] for c in cases},
                  key=lambda f: (f == "none", FAMILIES.index(f) if f in FAMILIES else 99))
    cols = ["none", *FAMILIES]
    for extra in ("ambiguous", "unexplained", "other", "error"):
        if any(c["predicted"] == extra for c in cases):
            cols.append(extra)
    matrix = {r: {c: 0 for c in cols} for r in rows}
    for c in cases:
        matrix[c["family"]][c["predicted"]] += 1
    nulls = [c for c in cases if c["family"] == "none" and c["predicted"] != "error"]
    alarms = [c for c in nulls if c["predicted"] != "none"]
    fa = {"alarms": len(alarms), "nulls": len(nulls),
          "rate": len(alarms) / len(nulls) if nulls else None,
          "wilson95": wilson(len(alarms), len(nulls))}
    for mod in (True, False):
        sub = [c for c in nulls if c["modulated"] is mod]
        k = sum(c["predicted"] != "none" for c in sub)
        fa["modulated" if mod else "closed_loop_only"] = {
            "alarms": k, "nulls": len(sub), "wilson95": wilson(k, len(sub))}
    per_sev: dict[str, Any] = {}
    effects = [c for c in cases if c["family"] != "none"]
    for sev in SEVERITIES:
        sub = [c for c in effects if c["severity"] == sev]
        if not sub:
            continue
        first = sum(c["predicted"] == c["family"] for c in sub)
        anywhere = sum(c["family"] in c["named"] for c in sub)
        matched = sum(c["predicted"] == c["family"] and c.get("params_match") is not False
                      for c in sub)
        per_sev[sev] = {"logs": len(sub), "named_first": first, "named_anywhere": anywhere,
                        "named_first_params_agree": matched,
                        "fraction_first": first / len(sub),
                        "fraction_anywhere": anywhere / len(sub),
                        "wilson95_first": wilson(first, len(sub))}
    # A gain error is told from a calibration only beyond what the nulls' offsets reach.
    null_pulls = [abs(loop_gain_pull(c["truth"])) for c in nulls]
    line = max([PULL_LIMIT, *null_pulls])
    gain: dict[str, Any] = {"line_sigma": line, "null_max_sigma": max(null_pulls, default=None)}
    for beyond in (True, False):
        sub = [c for c in effects if c["family"] == "sensor_gain_error"
               and (abs(loop_gain_pull(c["truth"])) > line) is beyond]
        gain["beyond" if beyond else "within"] = {
            "logs": len(sub), "named_first": sum(c["predicted"] == c["family"] for c in sub),
            "medium_strong": sum(c["severity"] != "weak" for c in sub),
            "medium_strong_named_first": sum(c["severity"] != "weak"
                                             and c["predicted"] == c["family"] for c in sub)}
    hidden = {id(c) for c in effects if c["family"] == "sensor_gain_error"
              and abs(loop_gain_pull(c["truth"])) <= line}
    combined = {}
    for key, sevs in (("medium_strong", ("medium", "strong")), ("all", SEVERITIES)):
        sub = [c for c in effects if c["severity"] in sevs]
        seen = [c for c in sub if id(c) not in hidden]
        first, first_seen = (sum(c["predicted"] == c["family"] for c in x) for x in (sub, seen))
        combined[key] = {"logs": len(sub), "named_first": first,
                         "wilson95_first": wilson(first, len(sub)),
                         "logs_beyond_calibration": len(seen), "named_first_beyond": first_seen,
                         "wilson95_first_beyond": wilson(first_seen, len(seen))}
    return {"rows": rows, "columns": cols, "confusion": matrix, "false_alarm": fa,
            "per_severity": per_sev, "combined": combined, "sensor_gain_vs_tolerance": gain}


def _nm(x: float | None) -> str:
    return "—" if x is None else f"{x * 1e9:.3g}"


def render(summary: dict[str, Any], cases: list[dict[str, Any]], header: str) -> str:
    lines = [header, ""]
    cols, matrix = summary["columns"], summary["confusion"]
    lines.append("Confusion matrix [number of logs]: rows = true family, columns = first effect "
                 "`leveler diagnose` named")
    w = 7
    corner = "true \\ named"
    lines.append(f"{corner:>14}" + "".join(f"{SHORT.get(c, c)[:w]:>{w + 1}}" for c in cols)
                 + f"{'total':>{w + 1}}")
    for r in summary["rows"]:
        counts = [matrix[r][c] for c in cols]
        cells = "".join(f"{(str(k) if k else '.'):>{w + 1}}" for k in counts)
        lines.append(f"{SHORT.get(r, r):>14}{cells}{sum(counts):>{w + 1}}")
    lines.append("  legend: " + ", ".join(f"{SHORT[f]} = {f}" for f in FAMILIES))
    fa = summary["false_alarm"]
    lines.append("")
    if fa["nulls"]:
        lo, hi = fa["wilson95"]
        lines.append(f"False alarms on null logs: {fa['alarms']}/{fa['nulls']} = "
                     f"{100 * fa['rate']:.0f} % (Wilson 95 %: {100 * lo:.0f}-{100 * hi:.0f} %)")
        for key, label in (("modulated", "modulated"), ("closed_loop_only", "closed loop only")):
            sub = fa[key]
            if sub["nulls"]:
                lo, hi = sub["wilson95"]
                lines.append(f"  {label}: {sub['alarms']}/{sub['nulls']} "
                             f"(Wilson 95 %: {100 * lo:.0f}-{100 * hi:.0f} %)")
        named: dict[str, int] = {}
        for c in cases:
            if c["family"] == "none":
                for name in c["named"]:
                    named[name] = named.get(name, 0) + 1
        if named:
            lines.append("  named on nulls: " + ", ".join(f"{k} x{v}" for k, v in
                                                           sorted(named.items())))
        cooler = sum(1 for c in cases if c["family"] == "none" and c.get("cooler_alarm"))
        if cooler:
            lines.append(f"  of which at the modelled cooler's period (its amplitude is scaled "
                         f"by 0.75-1.25 in every log): {cooler}")
    lines.append("")
    lines.append("Per severity: effect logs whose true family diagnose named first (anywhere; "
                 "first and its fitted parameters agreeing with the truth)")
    for sev, s in summary["per_severity"].items():
        lo, hi = s["wilson95_first"]
        lines.append(f"  {sev:>6}: {s['named_first']}/{s['logs']} = "
                     f"{100 * s['fraction_first']:.0f} % first (95 %: {100 * lo:.0f}-"
                     f"{100 * hi:.0f} %), {s['named_anywhere']}/{s['logs']} anywhere, "
                     f"{s['named_first_params_agree']}/{s['logs']} with agreeing parameters")
    for key, label in (("medium_strong", "medium and strong"), ("all", "all")):
        s = summary.get("combined", {}).get(key)
        if not s or not s["logs"]:
            continue
        lo, hi = s["wilson95_first"]
        line = (f"  {label}: {s['named_first']}/{s['logs']} = "
                f"{100 * s['named_first'] / s['logs']:.0f} % first (95 %: {100 * lo:.0f}-"
                f"{100 * hi:.0f} %)")
        if s["logs_beyond_calibration"] < s["logs"] and s["logs_beyond_calibration"]:
            lo, hi = s["wilson95_first_beyond"]
            line += (f"; less the gain errors within the nulls' loop-gain offsets (below): "
                     f"{s['named_first_beyond']}/{s['logs_beyond_calibration']} = "
                     f"{100 * s['named_first_beyond'] / s['logs_beyond_calibration']:.0f} % "
                     f"(95 %: {100 * lo:.0f}-{100 * hi:.0f} %)")
        lines.append(line)
    gain = summary.get("sensor_gain_vs_tolerance")
    if gain and gain["beyond"]["logs"] + gain["within"]["logs"]:
        b, w_ = gain["beyond"], gain["within"]
        top = gain["null_max_sigma"]
        lines.append(f"  sensor gain errors whose whole loop gain (with the drawn calibration "
                     f"offsets) is beyond {gain['line_sigma']:.3g} sigma of the stated "
                     f"tolerance ({PULL_LIMIT:g} sigma, or the largest null log's"
                     + (f", {top:.3g} sigma" if top is not None else "") + "): "
                     f"{b['named_first']}/{b['logs']} named first "
                     f"({b['medium_strong_named_first']}/{b['medium_strong']} medium and "
                     f"strong); within it (an in-tolerance calibration to the model): "
                     f"{w_['named_first']}/{w_['logs']} "
                     f"({w_['medium_strong_named_first']}/{w_['medium_strong']})")
    lines.append("")
    lines.append("Per case: residual gap as diagnose reports it (rms over the analysed span, nm), "
                 "before -> after its fit")
    lines.append("  (fit: y/n = diagnose's parameters for the true family agree with the truth "
                 "or not, '-' not named or not comparable)")
    lines.append(f"{'true family':<21}{'sev':<7}{'seed':>6} {'mod':<4}{'named':<30}{'fit':<4}"
                 f"{'before':>8}{'after':>8}{'ratio':>7}  best band (ratio)")
    for c in sorted(cases, key=lambda c: (c["family"] == "none", c["family"],
                                          SEVERITIES.index(c["severity"])
                                          if c["severity"] else 0, c["seed"])):
        s = shrink(c)
        named = ",".join(SHORT.get(n, n) for n in c["named"]) or c["predicted"]
        ratio = "—" if s["ratio"] is None else f"{s['ratio']:.2f}"
        band = ("" if s["best_band"] is None
                else f"{s['best_band']} ({s['best_band_ratio']:.2f})")
        fit = {True: "y", False: "n"}.get(c.get("params_match"), "-")
        lines.append(f"{c['family']:<21}{c['severity'] or '-':<7}{c['seed']:>6} "
                     f"{'y' if c['modulated'] else 'n':<4}{named[:29]:<30}{fit:<4}"
                     f"{_nm(s['rms_before_m']):>8}{_nm(s['rms_after_m']):>8}{ratio:>7}  {band}")
    return "\n".join(lines)


def build_cases(families: list[str], severities: list[str], seeds: list[int],
                nulls: int) -> list[dict[str, Any]]:
    cases = [{"family": f, "severity": s, "seed": seed, "modulated": True}
             for seed in seeds for s in severities for f in families]
    null_cases = [{"family": "none", "severity": None,
                   "seed": seeds[i % len(seeds)] * 1000 + i, "modulated": i % 2 == 0}
                  for i in range(nulls)]
    # interleave so progress and ETA are representative from the start
    out: list[dict[str, Any]] = []
    while cases or null_cases:
        if cases:
            out.append(cases.pop(0))
        if null_cases:
            out.append(null_cases.pop(0))
    return out


def calibrate_thresholds(workdir: str, hours: float, runs: int, jobs: int,
                         platform_inertia: bool, nulls: int, effects: bool) -> str:
    """Run diagnose's null calibration once per log shape the cases have (modulated,
    closed loop only), on a template log of that shape, so every case finds it cached;
    what the thresholds rest on, for the header."""
    if runs <= 0:
        return "BIC penalties (no null calibration)"
    shapes = ([True] if effects or nulls else []) + ([False] if nulls > 1 else [])
    said = []
    for modulated in shapes:
        log = Path(workdir) / f"calibration-template-{'mod' if modulated else 'closed'}.mcap"
        generate(None, "medium", 7_000_000 + int(modulated), log, hours=hours,
                 modulated=modulated, nominal_config=REPO / "config/sim.toml",
                 platform_inertia=platform_inertia)
        t0 = time.perf_counter()
        proc = subprocess.run([*leveler_command(), "diagnose", str(log), "--json",
                               "--null-runs", str(runs), "--jobs", str(max(1, jobs)),
                               "--model-out", str(log.with_suffix(".fitted.toml"))],
                              capture_output=True, text=True, cwd=REPO,
                              timeout=DIAGNOSE_TIMEOUT_S * 4)
        if proc.returncode != 0:
            raise SystemExit(f"null calibration failed: {proc.stderr.strip()[-2000:]}")
        th = json.loads(proc.stdout)["thresholds"]
        print(f"null calibration ({'modulated' if modulated else 'closed loop'}): "
              f"{th['runs']} runs in {time.perf_counter() - t0:.0f} s: {th['by_family']}",
              file=sys.stderr)
        said.append(f"{'modulated' if modulated else 'closed loop'} "
                    + ", ".join(f"{SHORT[k]} {v:.3g}" for k, v in th["by_family"].items()))
    return f"null-calibrated ({runs} runs per shape): " + "; ".join(said)


def _clock(s: float) -> str:
    s = max(0, int(s))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", help="comma-separated seeds (default: tuning seeds "
                    + ",".join(map(str, TUNING_SEEDS)) + ")")
    ap.add_argument("--untouched", action="store_true",
                    help="use the next three untouched seeds no board has used (report only; "
                         "never tune on them)")
    ap.add_argument("--families", help="comma-separated families (default: all eight; "
                    "'none': null logs only)")
    ap.add_argument("--severities", help="comma-separated: weak,medium,strong (default all)")
    ap.add_argument("--nulls", type=int, default=None, help="null logs (default 50)")
    ap.add_argument("--hours", type=float, default=None, help="log length (default 6)")
    ap.add_argument("--quick", action="store_true",
                    help="1 seed, weak and strong, 6 nulls, 3 h logs")
    ap.add_argument("--jobs", type=int, default=2, help="parallel cases (default 2)")
    ap.add_argument("--null-runs", type=int, default=None,
                    help="null runs of diagnose's threshold calibration, one per log shape "
                    "(modulated, closed loop only), made first and cached (default 50, "
                    "--quick 20; 0: BIC penalties)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/diagnose-score.json"))
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep the logs in this directory (default: a temp dir, removed)")
    ap.add_argument("--show", type=Path, default=None,
                    help="print the tables of a saved --out file and exit")
    ap.add_argument("--no-platform-inertia", action="store_true",
                    help="drop the J phi'' term from the generator's pendulum (comparison only)")
    args = ap.parse_args(argv)

    if args.show:
        doc = json.loads(args.show.read_text())
        for c in doc["cases"]:
            annotate(c)
        print(render(summarize(doc["cases"]), doc["cases"], doc["header"]))
        return 0
    if args.untouched and args.seeds:
        ap.error("--untouched and --seeds exclude each other")
    fresh = [s for s in UNTOUCHED_SEEDS if s not in UNTOUCHED_USED][:3]
    if args.untouched and not fresh:
        ap.error("every untouched seed has been used: add a new list before reporting again")
    seeds = (fresh if args.untouched
             else [int(s) for s in args.seeds.split(",")] if args.seeds else list(TUNING_SEEDS))
    families = args.families.split(",") if args.families else list(FAMILIES)
    if families == ["none"]:  # nulls only
        families = []
    for f in families:
        if f not in FAMILIES:
            ap.error(f"unknown family {f!r}; one of {', '.join(FAMILIES)}")
    severities = (args.severities.split(",") if args.severities
                  else ["weak", "strong"] if args.quick else list(SEVERITIES))
    for s in severities:
        if s not in SEVERITIES:
            ap.error(f"unknown severity {s!r}")
    if args.quick and not args.seeds and not args.untouched:
        seeds = seeds[:1]
    nulls = args.nulls if args.nulls is not None else (6 if args.quick else 50)
    hours = args.hours if args.hours is not None else (3.0 if args.quick else 6.0)

    cases = build_cases(families, severities, seeds, nulls)
    # seeds from the untouched list are labelled so however they were asked for
    untouched = args.untouched or all(s in UNTOUCHED_SEEDS for s in seeds)
    header = (f"leveler diagnose against the independent generator: {len(cases)} logs of "
              f"{hours:g} h ({len(cases) - nulls} effect, {nulls} null), seeds "
              f"{','.join(map(str, seeds))}{' (UNTOUCHED)' if untouched else ' (tuning)'}"
              f", platform inertia {'off' if args.no_platform_inertia else 'on'}")
    print(header, file=sys.stderr)

    tmp = None
    if args.keep:
        args.keep.mkdir(parents=True, exist_ok=True)
        workdir = str(args.keep)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="diagnose-score-")
        workdir = tmp.name
    null_runs = args.null_runs if args.null_runs is not None else (20 if args.quick else 50)
    thresholds = calibrate_thresholds(workdir, hours, null_runs, args.jobs,
                                      not args.no_platform_inertia, nulls, bool(families))
    header += f"; acceptance thresholds: {thresholds}"
    results: list[dict[str, Any]] = []
    start = time.monotonic()
    try:
        with ProcessPoolExecutor(max_workers=max(1, args.jobs),
                                 initializer=one_blas_thread) as pool:
            futures = {pool.submit(run_case, c, workdir, hours, not args.no_platform_inertia,
                                   args.keep is not None): c for c in cases}
            for fut in as_completed(futures):
                case = futures[fut]
                try:
                    res = fut.result()
                except Exception as e:  # the generator failed: record it, go on
                    res = {**case, "predicted": "error", "named": [],
                           "error": f"{type(e).__name__}: {e}"}
                results.append(res)
                done, total = len(results), len(cases)
                elapsed = time.monotonic() - start
                eta = elapsed / done * (total - done)
                took = res.get("diagnose_s")
                print(f"[{done}/{total}] {_clock(elapsed)} elapsed, ETA {_clock(eta)}: "
                      f"{case['family']} {case['severity'] or ''} seed {case['seed']} -> "
                      f"{','.join(res['named']) or res['predicted']}"
                      + (f" ({took:.0f} s)" if took else ""), file=sys.stderr, flush=True)
    finally:
        if tmp is not None:
            tmp.cleanup()

    summary = summarize(results)
    text = render(summary, results, header)
    print(text)
    for c in results:
        c["shrink"] = shrink(c) if c.get("gap_before") else None
    doc = {"header": header, "args": {k: (str(v) if isinstance(v, Path) else v)
                                      for k, v in vars(args).items()},
           "seeds": seeds, "hours": hours, "summary": summary, "cases": results,
           "elapsed_s": time.monotonic() - start, "cpu_count": os.cpu_count()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1, default=str))
    print(f"\nwritten: {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
