"""`leveler import-csv`: another system's CSV recording as a leveler log, for the analyses."""

from __future__ import annotations

import argparse
import sys


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "import-csv", help="convert another system's CSV recording into a leveler MCAP log",
        description="Convert data recorded by another system into a leveler MCAP log, so "
        "replay, diagnose and asd can analyse it. FILE is UTF-8 text, comma-separated; blank "
        "lines and lines starting with # are skipped; the first other line is the header. "
        "Columns, named in the header (case-insensitive, any order): t_s (time [s], strictly "
        "increasing, uniformly sampled), actuator_V (voltage applied to the actuator [V]), "
        "sensor_m (displacement at the pendulum end [m]) and optionally temperature_K (table "
        "temperature [K]); other columns are ignored. Values are SI as given, not converted. "
        "At least 16 rows. A bad row (reported by line number) fails the import unless "
        "--skip-bad; no output is left behind on error. Details: docs/log-format.md, "
        "\"Importing other systems' data (CSV)\".")
    p.add_argument("csv", metavar="FILE.csv", help="the CSV file to import (left untouched)")
    p.add_argument("--out", required=True, metavar="LOG.mcap", help="the MCAP log to write")
    p.add_argument("--skip-bad", action="store_true",
                   help="leave bad rows out (listed on stderr) instead of failing")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Skipped rows go to stderr, the summary to stdout."""
    from leveler.log.import_csv import import_csv, listing, summary

    data = import_csv(args.csv, args.out, skip_bad=args.skip_bad, force=args.force)
    if data.bad:
        print(f"leveler import-csv: skipped {len(data.bad)} bad "
              f"row{'s' if len(data.bad) > 1 else ''}:\n{listing(data.bad)}", file=sys.stderr)
    print(summary(data, args.out))
    return 0
