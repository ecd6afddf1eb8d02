"""`make bench`: how good leveler is on this PC, every figure beside a baseline timed in the
same run, in one table; also written to bench/results.json.

Each section is a module beside this script with `run(quick: bool) -> list[dict]` (rows as
`common.row` makes them). A section that is missing or raises becomes a row saying so; the
others still run, and the exit status is 0 whatever the figures: this reports, it does
not gate. `--quick` runs every section on shorter horizons (under two minutes on two
cores); docs/performance.md says what each figure means.

    python bench/run.py [--quick] [--only SECTION,...] [--out FILE] [--brief]
    python bench/run.py --show bench/results.json [--brief]    # a saved run's table
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib
import json
import math
import os
import platform
import sys
import textwrap
import time
import traceback
from pathlib import Path
from typing import Any

from common import REPO, row  # beside this script, which Python puts first on sys.path

# In the order they run and print: control first, speed after.
SECTIONS = (
    "control_quality",  # closed-loop performance against the paper (bench/control_quality.py)
    "loop_timing",  # the real-time loop's period and overruns (bench/loop_timing.py)
    "logging_speed",
    "sim_speed",
    "pid_speed",
    "control_socket",
    "daemon_startup",  # time to READY and RSS, simulated and hardware (bench/daemon_startup.py)
    "diagnose_speed",
)
KEYS = ("section", "what", "value", "unit", "baseline", "ratio", "goal", "met", "note")
WIDTH = 112


def run_section(module: str, quick: bool) -> tuple[str, list[dict[str, Any]]]:
    """(status, rows): status is "ok", "not available" or "error"."""
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name == module:
            return "not available", [row(module, "not available", math.nan, "",
                                         note=f"bench/{module}.py is not there")]
        return "error", [_error_row(module, e)]
    except Exception as e:
        return "error", [_error_row(module, e)]
    section = getattr(mod, "SECTION", module)
    try:
        rows = list(mod.run(quick))
        for r in rows:
            if not isinstance(r, dict) or not set(KEYS) <= set(r):
                raise TypeError(f"{module}.run returned a malformed row: {r!r}")
    except Exception as e:
        return "error", [_error_row(section, e)]
    return "ok", rows


def _error_row(section: str, e: BaseException) -> dict[str, Any]:
    traceback.print_exception(e, file=sys.stderr)
    return row(section, "error", math.nan, "", note=f"{type(e).__name__}: {e}")


def _value(v: float) -> str:
    if not math.isfinite(v):
        return "—"
    if abs(v) >= 100:
        return f"{v:,.0f}"
    return f"{v:.3g}"


def _ratio(r: float | None) -> str:
    if r is None or not math.isfinite(r):
        return "—"
    return f"{r:,.0f}x" if abs(r) >= 100 else f"{r:.3g}x"


def _met(m: bool | None) -> str:
    return "—" if m is None else "yes" if m else "NO"


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 1] + "…"


def table(rows: list[dict[str, Any]], notes: bool = True) -> str:
    """One table, grouped by section; each row's note wrapped on the lines below it.
    Columns fit their contents up to a cap; a longer name gets a line of its own."""
    w_what = min(max([len(r["what"]) for r in rows] + [20]), 56)
    w_unit = min(max([len(r["unit"]) for r in rows] + [4]), 12)
    w_vs = min(max([len(r["baseline"]) for r in rows] + [2]), 24)
    w_goal = min(max([len(r["goal"]) for r in rows] + [4]), 18)
    head = (f"{'what':<{w_what}} {'value':>10} {'unit':<{w_unit}} {'ratio':>8}  "
            f"{'vs':<{w_vs}} {'goal':<{w_goal}} met")
    lines = [head, "-" * len(head)]
    section = None
    for r in rows:
        if r["section"] != section:
            section = r["section"]
            lines.append(f"[{section}]")
        what = r["what"]
        if len(what) > w_what:
            lines.append(what)
            what = ""
        lines.append(f"{what:<{w_what}} {_value(r['value']):>10} "
                     f"{_cut(r['unit'], w_unit):<{w_unit}} {_ratio(r['ratio']):>8}  "
                     f"{_cut(r['baseline'], w_vs):<{w_vs}} {_cut(r['goal'], w_goal):<{w_goal}} "
                     f"{_met(r['met'])}")
        if notes and r["note"]:
            lines += textwrap.wrap(r["note"], WIDTH, initial_indent="      ",
                                   subsequent_indent="      ")
    return "\n".join(lines)


def _heading(quick: bool, date: str, info: dict[str, Any], wall_s: float) -> str:
    return (f"leveler bench, {'quick' if quick else 'full'} mode, {date}: "
            f"{info['cpus_usable']} CPUs ({info['cpu_model'] or info['machine']}), "
            f"Python {info['python']}, kernel {info['kernel']}, load "
            f"{info['load_average_at_start'][0]:.2f} at start; {wall_s:.0f} s")


def machine() -> dict[str, Any]:
    cpu = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)),
        "cpu_model": cpu,
        "python": platform.python_version(),
        "kernel": platform.release(),
        "machine": platform.machine(),
        "load_average_at_start": list(os.getloadavg()),
    }


def _json_safe(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_json_safe(v) for v in x]
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="shorter horizons: every section in under two minutes")
    ap.add_argument("--only", metavar="SECTION,...",
                    help=f"run only these sections (of: {', '.join(SECTIONS)})")
    ap.add_argument("--out", type=Path, default=None,
                    help="results file (default bench/results.json; not written with --only "
                         "unless given)")
    ap.add_argument("--show", type=Path, metavar="RESULTS",
                    help="print the table of a results file; run nothing")
    ap.add_argument("--brief", action="store_true", help="the table without the notes")
    args = ap.parse_args(argv)
    if args.show:
        saved = json.loads(args.show.read_text())
        rows = [{k: (math.nan if k == "value" and v is None else v) for k, v in r.items()}
                for r in saved["rows"]]
        print(_heading(saved["quick"], saved["date_utc"], saved["machine"], saved["wall_s"]))
        print(table(rows, notes=not args.brief))
        return 0
    sections = SECTIONS
    if args.only:
        sections = tuple(s.strip() for s in args.only.split(",") if s.strip())
        unknown = [s for s in sections if s not in SECTIONS]
        if unknown:
            ap.error(f"unknown section(s): {', '.join(unknown)}")
    out = args.out
    if out is None and not args.only:
        out = REPO / "bench" / "results.json"

    info = machine()
    started = dt.datetime.now(dt.UTC)
    start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    walls: dict[str, dict[str, Any]] = {}
    for k, module in enumerate(sections, 1):
        print(f"[{k}/{len(sections)}] {module} ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        status, got = run_section(module, args.quick)
        wall = time.perf_counter() - t0
        walls[module] = {"wall_s": round(wall, 2), "status": status}
        print(f"[{k}/{len(sections)}] {module}: {status}, {wall:.1f} s", file=sys.stderr,
              flush=True)
        rows += got
    total = time.perf_counter() - start

    print()
    print(_heading(args.quick, started.isoformat(timespec="seconds"), info, total))
    print(table(rows, notes=not args.brief))
    judged = [r["met"] for r in rows if r["met"] is not None]
    summary = (f"goals: {sum(judged)} met, {len(judged) - sum(judged)} missed, "
               f"{sum(1 for r in rows if r['goal'] and r['met'] is None)} not judged")
    print(summary + (f"; written to {out}" if out else ""))
    if out:
        result = {"date_utc": started.isoformat(timespec="seconds"), "quick": args.quick,
                  "wall_s": round(total, 2), "machine": info, "sections": walls,
                  "rows": rows}
        out.write_text(json.dumps(_json_safe(result), indent=1, ensure_ascii=False) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
