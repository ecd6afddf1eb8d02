"""The `leveler asd` command: a logged channel's ASD, optionally against a second log."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from leveler.logreader import LogData, LogError, partial_note, read_log
from leveler.spectral import Spectrum, lpsd

TABLE_FREQS_HZ = (1e-4, 1e-3, 1e-2, 1e-1, 1.0)


def channel(log: LogData, name: str, path: str) -> tuple[np.ndarray, float]:
    """The named numeric series of a log and its sample rate (from the loop times)."""
    for table in (log.samples, log.truth):
        if name in table:
            values = np.asarray(table[name])
            t = np.asarray(table["t_s"], dtype=float)
            break
    else:
        names = sorted(k for tab in (log.samples, log.truth) for k, v in tab.items()
                       if np.asarray(v).dtype.kind in "fi")
        raise LogError(f"{path}: no channel {name!r}; numeric channels: {', '.join(names)}")
    if values.dtype.kind not in "fi":
        raise LogError(f"{path}: channel {name!r} is not numeric")
    if len(values) < 16:
        early = f" (the log is incomplete: {log.stop_reason})" if not log.complete else ""
        raise LogError(f"{path}: only {len(values)} samples of {name!r}; need at least 16"
                       f"{early}")
    step = float(np.median(np.diff(t)))
    if not step > 0:  # also NaN: times that do not advance have no sample rate
        raise LogError(f"{path}: the sample times do not advance (median step {step:g} s)")
    fs = 1.0 / step
    values = values.astype(float)
    if not np.all(np.isfinite(values)):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        raise LogError(f"{path}: {bad} non-finite values in {name!r} (sensor faults?); "
                       "cut the log around them first")
    return values, fs


def _at(spec: Spectrum, f: float) -> float | None:
    if f < spec.freq_hz[0] or f > spec.freq_hz[-1]:
        return None
    return float(np.exp(np.interp(np.log(f), np.log(spec.freq_hz), np.log(spec.asd))))


def run_asd_command(args: argparse.Namespace) -> int:
    curves: list[tuple[str, Spectrum]] = []
    for path in [args.log, *([args.compare] if args.compare else [])]:
        log = read_log(path)
        x, fs = channel(log, args.channel, path)
        if not log.complete:
            print(f"leveler asd: {partial_note(path, log.stop_reason, len(x))}",
                  file=sys.stderr)
        curves.append((path, lpsd(x, fs)))
    if args.json:
        print(json.dumps({label: {"freq_hz": s.freq_hz.tolist(), "asd": s.asd.tolist()}
                          for label, s in curves}))
    else:
        header = f"{'frequency':>12}" + "".join(f"  {label[-28:]:>28}" for label, _ in curves)
        if len(curves) == 2:
            header += f"  {'ratio':>8}"
        print(f"ASD of {args.channel} [unit/sqrt(Hz)]")
        print(header)
        for f in TABLE_FREQS_HZ:
            vals = [_at(s, f) for _, s in curves]
            row = f"{f:>10.4g} Hz" + "".join(
                f"  {v:>28.4g}" if v is not None else f"  {'(out of range)':>28}" for v in vals)
            if len(vals) == 2 and None not in vals:
                row += f"  {vals[1] / vals[0]:>7.2f}x"
            print(row)
    if args.plot:
        from leveler.plots import plot_asd

        plot_asd(curves, args.plot, ylabel=f"ASD of {args.channel} [unit/√Hz]",
                 title=f"leveler asd: {args.channel}")
        print(f"plot: {args.plot}")
    return 0
