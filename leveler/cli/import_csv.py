"""`leveler import-csv`: another system's CSV recording as a leveler log, for the analyses."""

from __future__ import annotations

import argparse
import sys

from leveler.cli.durations import parse_duration


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "import-csv", help="convert another system's CSV recording into a leveler MCAP log",
        description="Convert data recorded by another system into a leveler MCAP log, so "
        "replay, diagnose and asd can analyse it. FILE is UTF-8 text, one row per line, "
        "columns separated by commas, semicolons, tabs or spaces (the first of those the "
        "header holds, or --delimiter); blank lines and lines starting with # are skipped; "
        "the first other line is the header. Columns are found by name (case-insensitive, "
        "any order): the time t_s, the actuator voltage actuator_V, the displacement at the "
        "pendulum end sensor_m and optionally the table temperature temperature_K; or, for "
        "a torsion-pendulum thrust stand (leveler analyze stiffness LOG), its thrust "
        "thrust_N, displacement displacement_m and optionally the base tilt tilt_rad "
        "(with or without the leveler's columns); or the names --column gives; other "
        "columns are ignored. Time is converted by --time-unit, "
        "each value as raw x --scale + --offset into SI; without them values are SI as "
        "given. At least 16 rows. A bad row (reported by line number) fails the import "
        "unless --skip-bad; a line repeating the header is skipped and reported. The time "
        "base must be uniform within 1 %% unless --resample. No output is left behind on "
        "error. Details: docs/log-format.md, \"Importing other systems' data (CSV)\".",
        epilog="Example (a logger's file: MJD in days, tilt in ADC counts, temperature in "
        "degrees C, semicolons, a few stray rows): leveler import-csv run7.csv --out run7.mcap "
        "--column t=MJD --column sensor=tilt_counts --column actuator=pzt_V --column "
        "temperature=T_degC --time-unit days --scale sensor=1.75e-9 --offset "
        "temperature=273.15 --skip-bad --resample")
    p.add_argument("csv", metavar="FILE.csv", help="the CSV file to import (left untouched)")
    p.add_argument("--out", required=True, metavar="LOG.mcap", help="the MCAP log to write")
    p.add_argument("--column", action="append", metavar="ROLE=NAME",
                   help="the header name of a column, ROLE one of t, actuator, sensor, "
                   "temperature, thrust, displacement, tilt (repeat per column; default "
                   "names t_s, actuator_V, sensor_m, temperature_K, thrust_N, "
                   "displacement_m, tilt_rad)")
    p.add_argument("--time-unit", default="s",
                   choices=("s", "ms", "us", "min", "h", "days", "iso"),
                   help="unit of the time column: s, ms, us, min, h, days (e.g. MJD), or iso "
                   "for ISO 8601 date-times such as 2024-05-01T12:00:00.5 (UTC unless an "
                   "offset is given) (default: s)")
    p.add_argument("--scale", action="append", metavar="ROLE=FACTOR",
                   help="multiply a column by FACTOR into SI, e.g. sensor=1.75e-9 for ADC "
                   "counts of 1.75 nm, thrust=1e-6 for uN (V for actuator, m for sensor and "
                   "displacement, K for temperature, N for thrust, rad for tilt)")
    p.add_argument("--offset", action="append", metavar="ROLE=VALUE",
                   help="add VALUE after scaling, e.g. temperature=273.15 for degrees C")
    p.add_argument("--delimiter", default="auto",
                   choices=("auto", "comma", "semicolon", "tab", "space"),
                   help="column separator (default: auto, the first of tab, semicolon, comma "
                   "in the header, else runs of spaces)")
    p.add_argument("--skip-bad", action="store_true",
                   help="leave bad rows out (listed on stderr) instead of failing")
    p.add_argument("--resample", action="store_true",
                   help="put a nearly uniform time base on an exact one: rows a little out of "
                   "order are sorted in, exact repeats dropped, gaps interpolated linearly; "
                   "each is reported by line, interpolated samples carry state "
                   "'interpolated' and every gap is an event in the log")
    p.add_argument("--max-gap", type=parse_duration, metavar="DURATION",
                   help="with --resample: the longest gap to interpolate across, e.g. 30s or "
                   "2min (default: 60 sample intervals); a longer one fails the import")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Skipped and changed rows go to stderr, the summary to stdout."""
    from leveler.log.import_csv import (
        ImportOptions,
        details,
        import_csv,
        listing,
        parse_assignments,
        rate_doubt,
        summary,
    )

    options = ImportOptions(
        columns=parse_assignments(args.column, "--column", numeric=False),
        time_unit=args.time_unit, scale=parse_assignments(args.scale, "--scale", numeric=True),
        offset=parse_assignments(args.offset, "--offset", numeric=True),
        delimiter=args.delimiter, resample=args.resample, max_gap_s=args.max_gap)
    data = import_csv(args.csv, args.out, skip_bad=args.skip_bad, force=args.force,
                      options=options)
    if data.bad:
        print(f"leveler import-csv: skipped {len(data.bad)} bad "
              f"row{'s' if len(data.bad) > 1 else ''}:\n{listing(data.bad)}", file=sys.stderr)
    for line in filter(None, (details(data), rate_doubt(data))):
        print(f"leveler import-csv: {line}", file=sys.stderr)
    print(summary(data, args.out))
    return 0
