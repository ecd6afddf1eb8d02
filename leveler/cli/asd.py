"""`leveler asd`: the spectrum (ASD) of a logged channel, optionally against a second log."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING

from leveler.errors import LogError

if TYPE_CHECKING:
    import numpy as np

    from leveler.analysis.spectral import Spectrum
    from leveler.log.reader import LogData

TABLE_FREQS_HZ = (1e-4, 1e-3, 1e-2, 1e-1, 1.0)
#: non-finite samples (held bad readings) asd bridges: at most this fraction of the record,
MAX_BRIDGED_FRACTION = 0.01
#: and no single gap longer than this [s]
MAX_GAP_S = 10.0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "asd", help="amplitude spectral density of a logged channel (LPSD, log-spaced)",
        description="Estimate the ASD of one channel of a leveler MCAP log with the LPSD "
        "method (Troebs & Heinzel 2006), which keeps many averages at high frequency and "
        "still reaches 0.1 mHz in a long log. Channels: any numeric field of the sample "
        "topic (sensor_m, applied_v, error_m, ...) or, in simulated logs, the truth topic "
        "(tilt_rad, thermal_tilt_rad, pendulum_rad, ...), in imported logs the measured "
        "surroundings (temperature_k) and a thrust stand's channels (displacement_m, "
        "thrust_n, tilt_rad). Values a daemon logged as null "
        "(held bad readings, driver errors) are bridged by linear interpolation if they are "
        "at most 1% of the record and no gap is longer than 10 s, and cut off if they are at "
        "its start or end; a note on stderr says how many. Beyond that the log is refused.")
    p.add_argument("log", help="MCAP log written by leveler")
    p.add_argument("--channel", default="sensor_m",
                   help="field to analyse (default: %(default)s)")
    p.add_argument("--compare", default=None,
                   help="a second log (e.g. open loop) drawn and tabulated against the first; "
                   "the table's last column is the second's ASD over the first's")
    p.add_argument("--plot", default=None, help="save the ASD plot as PNG")
    p.add_argument("--json", action="store_true", help="print the spectrum as JSON")
    p.set_defaults(func=run)


def channel(log: LogData, name: str, path: str) -> tuple[np.ndarray, float]:
    """The named numeric series of a log and its sample rate (from the loop times)."""
    import numpy as np

    tables = (log.samples, log.truth, log.thrust_stand, log.environment)
    # a table that holds the channel with data first (an imported stand's log has an empty
    # sample table), then one that holds it empty: "only 0 samples" says why
    for table in sorted((t for t in tables if name in t), key=lambda t: not len(t[name])):
        values = np.asarray(table[name])
        t = np.asarray(table["t_s"], dtype=float)
        break
    else:
        names = sorted({k for tab in tables for k, v in tab.items()
                        if len(v) and np.asarray(v).dtype.kind in "fi"})
        raise LogError(f"{path}: no channel {name!r}; numeric channels: {', '.join(names)}")
    if values.dtype.kind not in "fi":
        raise LogError(f"{path}: channel {name!r} is not numeric")
    if len(values) < 16:
        early = f" (the log is incomplete: {log.stop_reason})" if not log.complete else ""
        if len(log.thrust_stand.get("t_s", ())):
            early += "; it holds a thrust stand's channels: --channel displacement_m"
        raise LogError(f"{path}: only {len(values)} samples of {name!r}; need at least 16"
                       f"{early}")
    step = float(np.median(np.diff(t)))
    if not step > 0:  # also NaN: times that do not advance have no sample rate
        raise LogError(f"{path}: the sample times do not advance (median step {step:g} s)")
    fs = 1.0 / step
    return values.astype(float), fs


@dataclass(frozen=True)
class Bridged:
    """What `bridge_gaps` did to a series."""

    samples: int  # non-finite samples replaced by linear interpolation
    gaps: int  # runs of them
    longest_s: float  # the longest run
    trimmed: int  # non-finite samples cut from the start and the end (nothing to bridge to)


def _runs(bad: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    import numpy as np

    edges = np.flatnonzero(np.diff(np.r_[0, bad.astype(np.int8), 0]))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def bridge_gaps(x: np.ndarray, fs: float, name: str, path: str) -> tuple[np.ndarray, Bridged]:
    """`x` with short runs of non-finite samples (held bad readings, logged as null) filled
    by linear interpolation, and non-finite samples at either end cut off.

    A daemon log that had a glitch holds a few of them; LPSD needs a gap-free series, and a
    straight line across at most MAX_BRIDGED_FRACTION of the record, no run longer than
    MAX_GAP_S, changes the spectrum far less than the glitch did. Beyond either bound the
    log is refused: the faults are then part of what the spectrum would show."""
    import numpy as np

    bad = ~np.isfinite(x)
    if not bad.any():
        return x, Bridged(0, 0, 0.0, 0)
    good = np.flatnonzero(~bad)
    if len(good) == 0:
        raise LogError(f"{path}: every value of {name!r} is non-finite (sensor faults?)")
    first, last = int(good[0]), int(good[-1])
    trimmed = first + (len(x) - 1 - last)
    x, bad = x[first:last + 1], bad[first:last + 1]
    runs = _runs(bad)
    n_bad = int(np.count_nonzero(bad))
    longest_s = max(stop - start for start, stop in runs) / fs if runs else 0.0
    if n_bad > MAX_BRIDGED_FRACTION * len(x) or longest_s > MAX_GAP_S:
        raise LogError(
            f"{path}: {n_bad} non-finite values in {name!r} (sensor faults?) in {len(runs)} "
            f"gaps, {n_bad / len(x):.2%} of the record, the longest {longest_s:.3g} s; asd "
            f"bridges gaps only up to {MAX_BRIDGED_FRACTION:.0%} of the record and "
            f"{MAX_GAP_S:g} s each: cut the log around them first")
    out = x
    if runs:
        idx = np.arange(len(x))
        out = x.copy()
        out[bad] = np.interp(idx[bad], idx[~bad], x[~bad])
    return out, Bridged(n_bad, len(runs), longest_s, trimmed)


def bridge_note(path: str, name: str, total: int, b: Bridged) -> str:
    parts = []
    if b.samples:
        parts.append(f"bridged {b.samples} non-finite {name!r} samples "
                     f"({b.samples / total:.3%} of {total}) in {b.gaps} gap"
                     f"{'s' if b.gaps != 1 else ''}, the longest {b.longest_s:.3g} s, by "
                     "linear interpolation")
    if b.trimmed:
        parts.append(f"cut {b.trimmed} non-finite samples at the start or end")
    return f"note: {path}: {'; '.join(parts)} (held bad readings or driver errors)"


def _at(spec: Spectrum, f: float) -> float | None:
    import numpy as np

    if f < spec.freq_hz[0] or f > spec.freq_hz[-1]:
        return None
    return float(np.exp(np.interp(np.log(f), np.log(spec.freq_hz), np.log(spec.asd))))


def _short_labels(paths: list[str]) -> list[str]:
    """A legend entry per log: its file name, with its directory when two names are alike
    in different directories, and '(compare)' on the second when that still leaves them
    alike (the same file twice)."""
    from pathlib import Path

    names = [Path(p).name for p in paths]
    dirs = [Path(p).resolve().parent for p in paths]
    labels = [n if len({d for d, m in zip(dirs, names, strict=True) if m == n}) == 1
              else str(Path(Path(p).parent.name) / n)
              for p, n in zip(paths, names, strict=True)]
    return [f"{label} (compare)" if labels[:i].count(label) else label
            for i, label in enumerate(labels)]


def run(args: argparse.Namespace) -> int:
    from leveler.analysis.spectral import lpsd
    from leveler.cli.progress import fraction, reading
    from leveler.log.reader import partial_note, read_log

    curves: list[tuple[str, Spectrum]] = []
    paths = [args.log, *([args.compare] if args.compare else [])]
    labels = _short_labels(paths)
    unit = ""
    for path, label in zip(paths, labels, strict=True):
        with reading(path, quiet=args.json) as b:
            log = read_log(path, fraction(b))
        unit = unit or log.units.get(args.channel, "")
        x, fs = channel(log, args.channel, path)
        if not log.complete:
            print(f"leveler asd: {partial_note(path, log.stop_reason, len(x), log.live)}",
                  file=sys.stderr)
        total = len(x)
        x, bridged = bridge_gaps(x, fs, args.channel, path)
        if bridged.samples or bridged.trimmed:
            print(f"leveler asd: {bridge_note(path, args.channel, total, bridged)}",
                  file=sys.stderr)
        if len(x) < 16:
            raise LogError(f"{path}: only {len(x)} samples of {args.channel!r} left after "
                           "cutting the non-finite ones at its ends; need at least 16")
        curves.append((label, lpsd(x, fs)))
    per_rthz = f"{unit}/sqrt(Hz)" if unit else "per sqrt(Hz); the log's schema gives no unit"
    if args.json:
        print(json.dumps({path: {"freq_hz": s.freq_hz.tolist(), "asd": s.asd.tolist()}
                          for path, (_, s) in zip(paths, curves, strict=True)}))
    else:
        header = f"{'frequency':>12}" + "".join(f"  {label[-28:]:>28}" for label, _ in curves)
        if len(curves) == 2:
            header += f"  {'2nd/1st':>8}"
        print(f"ASD of {args.channel} [{per_rthz}]")
        print(header)
        for f in TABLE_FREQS_HZ:
            vals = [_at(s, f) for _, s in curves]
            row = f"{f:>10.4g} Hz" + "".join(
                f"  {v:>28.4g}" if v is not None else f"  {'(out of range)':>28}" for v in vals)
            if len(vals) == 2 and None not in vals:
                row += f"  {vals[1] / vals[0]:>7.2f}x"
            print(row)
    if args.plot:
        from leveler.analysis.plots import plot_asd

        plot_asd(curves, args.plot, ylabel=f"ASD of {args.channel} "
                 f"[{per_rthz.replace('sqrt(Hz)', '√Hz')}]",
                 title=f"leveler asd: {args.channel}")
        print(f"plot: {args.plot}")
    return 0
