"""`leveler replay`: how well the plant model predicts a log, and what other gains would do."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from leveler.errors import LogError


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "replay", help="how well the plant model predicts a log (residual, bands, what-if)",
        description="Drive the plant model with the logged actuator voltage (and the logged "
        "temperature, if any) and compare its prediction with the logged sensor reading. "
        "Prints the residual RMS, its RMS and mean ASD in the bands 0.1-1 mHz, 1-10 mHz, "
        "10-100 mHz and 0.1-1 Hz, and the fraction of the measured variance the model "
        "explains, as is and with the slow drift set aside (--drift), and per band the "
        "residual's power over the model's own noise (sensor noise, its zero's random walk, an "
        "unlogged temperature's tilt), with one sentence on whether the residual is what the "
        "model itself calls unpredictable. The first minutes are skipped and the pendulum's "
        "start is fitted (the log may start out of equilibrium); the table's unknown offset "
        "is removed. The model is the config stored in the log unless --model names another "
        "(e.g. one written by `leveler diagnose`).")
    p.add_argument("log", help="MCAP log written by leveler (or by `leveler import-csv`)")
    p.add_argument("--model", default=None, help="config file whose [plant] is the model "
                   "(default: the config stored in the log)")
    p.add_argument("--out", default=None, help="write measured, predicted and residual per "
                   "sample to this MCAP file (topic /leveler/replay)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", default=None, help="save time-series overlay and ASDs (PNG)")
    p.add_argument("--drift", default="model", metavar="METHOD",
                   help="how the slow drift is estimated and set aside: model (the model's "
                   "random-walk terms through a Kalman smoother), poly:N (a polynomial of "
                   "order N) or none (default: model)")
    p.add_argument("--gains", type=parse_gains, default=None, metavar="KP,KI,KD",
                   help="what-if: rerun the controller with these gains [V/m, V/(m s), "
                   "V s/m] against the model and the disturbance the log implies; prints "
                   "the sensor ASD they would have given at 0.1, 1 and 10 mHz")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from leveler.analysis.predict import load_measured
    from leveler.analysis.replay import plot_replay, replay, write_replay_log
    from leveler.cli.progress import fraction, reading
    from leveler.log.reader import partial_note

    with reading(args.log, quiet=args.json) as b:
        meas = load_measured(args.log, args.model, fraction(b))
    if meas.incomplete:
        note = partial_note(args.log, meas.incomplete, len(meas.y_m), meas.live)
        print(f"leveler replay: {note}", file=sys.stderr)
    try:
        result, pred, span = replay(meas, args.gains, args.drift)
    except ValueError as exc:
        raise LogError(str(exc)) from None
    if args.out:
        if Path(args.out).resolve() == Path(args.log).resolve():
            raise LogError(f"{args.out}: --out would overwrite the log being replayed")
        write_replay_log(args.out, meas, pred)
        result["out"] = args.out
    if args.plot:
        plot_replay(args.plot, meas, pred, span,
                    f"replay of {Path(args.log).name} against {meas.model_source}")
        result["plot"] = args.plot
    print(json.dumps(result) if args.json else report(result))
    return 0


def parse_gains(text: str) -> tuple[float, float, float]:
    """The option type of --gains: KP,KI,KD."""
    try:
        kp, ki, kd = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected KP,KI,KD (three numbers, V/m, V/(m s), V s/m), got {text!r}") from None
    if not all(math.isfinite(v) for v in (kp, ki, kd)):
        raise argparse.ArgumentTypeError("gains must be finite")
    return kp, ki, kd


def _fmt_m(v: float | None) -> str:
    return "   n/a" if v is None else f"{v * 1e9:8.3g}"


def report(r: dict[str, Any]) -> str:
    """The metrics as a table in nm, and the what-if if there is one."""
    from leveler.analysis.diagnose import BANDS_HZ

    lines = [f"replay of {r['log']} against {r['model']}",
             f"{r['samples']} samples at {r['rate_hz']:g} Hz; analysed "
             f"{r['analysed_s'][0] - r['first_t_s']:.0f}-"
             f"{r['analysed_s'][1] - r['first_t_s']:.0f} s from the first sample; temperature "
             f"{'used' if r['temperature_logged'] else 'not logged'}",
             f"residual RMS {r['rms_m'] * 1e9:.3g} nm; measured variance explained "
             f"{r['variance_explained'] * 100:.1f}%" if r["variance_explained"] is not None
             else f"residual RMS {r['rms_m'] * 1e9:.3g} nm",
             f"less the drift ({r['drift']}, RMS {r['drift_rms_m'] * 1e9:.3g} nm): "
             + (f"{r['variance_explained_less_drift'] * 100:.1f}% explained"
                if r["variance_explained_less_drift"] is not None else "n/a"), "",
             f"{'band':>12} {'residual RMS':>13} {'mean ASD':>11} {'explained':>10} "
             f"{'less drift':>10} {'residual/noise':>15}",
             f"{'':>12} {'[nm]':>13} {'[nm/rtHz]':>11} {'[%]':>10} {'[%]':>10} "
             f"{'[power]':>15}"]
    for band in BANDS_HZ:
        b = r["bands"][band]
        tail = (f"{b['variance_explained'] * 100:10.1f} "
                f"{b['variance_explained_less_drift'] * 100:10.1f} "
                f"{b['residual_over_noise']:15.3g}" if b else f"{'n/a':>10}")
        lines.append(f"{band:>12} {_fmt_m(r['band_rms_m'][band]):>13} "
                     f"{_fmt_m(r['band_asd_m_rthz'][band]):>11} {tail}")
    lines += ["", r["verdict"]]
    w = r.get("what_if")
    if w:
        g = w["gains"]
        lines += ["", f"what if kp={g['kp_v_per_m']:g}, ki={g['ki_v_per_m_s']:g}, "
                  f"kd={g['kd_v_s_per_m']:g} (logged: {w['logged_gains']['kp_v_per_m']:g}, "
                  f"{w['logged_gains']['ki_v_per_m_s']:g}, {w['logged_gains']['kd_v_s_per_m']:g}):",
                  f"{'frequency':>12} {'measured [nm/rtHz]':>19} {'predicted [nm/rtHz]':>20}"]
        for f, a, b in zip(w["freq_hz"], w["measured_asd_m_rthz"], w["predicted_asd_m_rthz"],
                           strict=True):
            lines.append(f"{f * 1e3:9.1f} mHz {_fmt_m(a):>19} {_fmt_m(b):>20}")
    return "\n".join(lines)
