"""`leveler analyze stiffness LOG`: a thrust stand's K0 and tilt coupling from its recording."""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from leveler.procedures.stiffness_log import Recording, StandFit

#: The sweep's options, which mean nothing for a recording.
SIM_ONLY = ("stiffness_nm_per_rad", "max_tilt_rad", "tilt_step_rad", "seed")
DEFAULT_DRIFT = "poly:2"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options that only a recording takes (LOG given)."""
    g = p.add_argument_group("with LOG (a thrust stand's recording)")
    g.add_argument("--arm-m", type=float, metavar="L",
                   help="thrust arm L [m]: the thrust's lever and the displacement sensor's "
                   "distance from the axis (needed with LOG)")
    g.add_argument("--arm-sigma-m", type=float, default=0.0, metavar="SIGMA",
                   help="1-sigma of L [m], added to the uncertainties (default: 0)")
    g.add_argument("--thrust-sigma-rel", type=float, default=0.0, metavar="REL",
                   help="1-sigma of the thrust channel's calibration, relative (default: 0)")
    g.add_argument("--tilt-sigma-rel", type=float, default=0.0, metavar="REL",
                   help="1-sigma of the tilt channel's gain, relative (default: 0)")
    g.add_argument("--drift", default=DEFAULT_DRIFT, metavar="poly:N|none",
                   help="the displacement sensor's slow zero drift, fitted as a Legendre "
                   "polynomial of order N over the record (default: %(default)s)")


def given_without_log(args: argparse.Namespace) -> list[str]:
    """The recording's options set on a simulated sweep, where they would be ignored."""
    given = ["--arm-m"] if args.arm_m is not None else []
    given += [f"--{k.replace('_', '-')}" for k in ("arm_sigma_m", "thrust_sigma_rel",
                                                    "tilt_sigma_rel") if getattr(args, k)]
    return given + (["--drift"] if args.drift != DEFAULT_DRIFT else [])


def load(path: str, quiet: bool = False) -> tuple[Recording, str]:
    """The thrust-stand channels of a log, and a note if the log was cut short; `quiet`:
    no progress bar (--json)."""
    import numpy as np

    from leveler.cli.progress import fraction, reading
    from leveler.log.reader import partial_note, read_log
    from leveler.procedures.stiffness_log import Recording

    with reading(path, quiet=quiet) as b:
        log = read_log(path, fraction(b))
    stand = log.thrust_stand
    if not stand or len(stand["t_s"]) == 0:
        raise ValueError(f"{path} has no thrust-stand channels (/leveler/thrust_stand): import "
                         "the stand's recording with leveler import-csv --column thrust=NAME "
                         "--column displacement=NAME [--column tilt=NAME]")
    t, f, x = stand["t_s"], stand["thrust_n"], stand["displacement_m"]
    bad = ~(np.isfinite(f) & np.isfinite(x))
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} samples lack a thrust or a displacement "
                         f"(the first at t = {t[np.argmax(bad)]:.6g} s)")
    tilt = stand["tilt_rad"]
    if np.isnan(tilt).all():
        tilt = None
    elif not np.isfinite(tilt).all():
        raise ValueError(f"{path}: the tilt is missing in {int((~np.isfinite(tilt)).sum())} "
                         "samples")
    note = "" if log.complete else partial_note(path, log.stop_reason, len(t), log.live)
    return Recording(t, f, x, tilt), note


def drift_order(text: str) -> int:
    """poly:N -> N, none -> -1; a clear error for anything else."""
    if text == "none":
        return -1
    if text.startswith("poly:") and text[5:].isdigit() and int(text[5:]) <= 20:
        return int(text[5:])
    raise ValueError(f"--drift {text!r}: use poly:N (N = 0..20) or none")


def to_json(fit: StandFit, path: str) -> dict:
    out = asdict(fit)
    out |= {"log": path, "coupling_significance": fit.coupling_significance,
            "tilt_budget_rad": fit.tilt_budget_rad,
            "negative_stiffness_tilt_rad": fit.negative_stiffness_tilt_rad,
            "compliance_rad_per_nm": 1 / fit.stiffness_nm_per_rad}
    for pl in out["plateaus"]:
        if not math.isfinite(pl["stiffness_nm_per_rad"]):
            pl["stiffness_nm_per_rad"] = None
    return out


def report(fit: StandFit, path: str) -> str:
    from leveler.procedures.stiffness import BUDGET_FRACTION

    k0, sk = fit.stiffness_nm_per_rad, fit.stiffness_sigma_nm_per_rad
    tilt = ("no tilt column" if fit.tilt_range_rad is None else
            f"tilt {fit.tilt_range_rad[0] * 1e6:+.2f} .. {fit.tilt_range_rad[1] * 1e6:+.2f} urad")
    drift = f"poly:{fit.drift_order}" if fit.drift_order >= 0 else "none"
    hold = ("joined by lines between samples" if fit.hold == "foh" else
            "held from sample to sample")
    lines = [
        f"Thrust stand recording {path}: {fit.duration_s / 3600:.3g} h, thrust step F = "
        f"{fit.thrust_n * 1e6:.4g} uN, {tilt}, arm L = {fit.arm_m:g} m",
        "Fitted to the whole record: J theta'' + lambda theta' + K0 theta = F L + M g sin(tilt) "
        f"l_cm, with the start's ringing and the sensor drift ({drift})",
        f"  pendulum: f0 = {fit.natural_frequency_hz:.4g} Hz, Q = {fit.quality_factor:.3g}; "
        f"residual {fit.rms_residual_m * 1e9:.3g} nm rms; forces {hold} (fits better)",
        f"  stiffness K0 = {k0:.5g} +- {sk:.2g} N m/rad (compliance 1/K0 = {1 / k0:.5g} "
        "rad/(N m))",
    ]
    sens, ss = fit.tilt_sensitivity_nm_per_rad, fit.tilt_sensitivity_sigma_nm_per_rad
    if sens is None or ss is None:
        lines.append("  tilt coupling: not measurable, the record has no tilt column "
                     "(import-csv --column tilt=NAME)")
        return "\n".join(lines)
    z = fit.coupling_significance or 0.0
    verdict = (f"{z:.1f} sigma from zero: the stand feels the base tilt" if z >= 3 else
               f"only {z:.1f} sigma from zero: no tilt coupling shown; |M g l_cm| < "
               f"{abs(sens) + 2 * ss:.2g} uN m/urad (2 sigma)")
    lines.append(f"  tilt coupling M g l_cm = {sens:.4g} +- {ss:.2g} uN m/urad ({verdict})")
    if fit.plateaus:
        lines += ["", "Per tilt plateau (paper Figs. 5, 6; times from the first sample): r = "
                  "M g sin(tilt) l_cm / (F L), K = K0 / (1 + r)",
                  f"  {'tilt [urad]':>11} {'from [s]':>9} {'to [s]':>9} {'r (measured)':>13} "
                  f"{'r (fit)':>8} {'K [N m/rad]':>12}  regime"]
        for pl in fit.plateaus:
            k = pl.stiffness_nm_per_rad
            lines.append(f"  {pl.tilt_rad * 1e6:11.2f} {pl.start_s:9.0f} {pl.end_s:9.0f} "
                         f"{pl.coupling_ratio:13.3f} {pl.model_coupling_ratio:8.3f} "
                         f"{'inf' if not math.isfinite(k) else f'{k:.4g}':>12}  {pl.regime}")
    budget, neg = fit.tilt_budget_rad, fit.negative_stiffness_tilt_rad
    if budget is not None and z >= 3:
        neg_text = ("never (|r| < 1 at any tilt)" if neg is None else
                    f"{'below' if neg < 0 else 'above'} {neg * 1e6:+.3g} urad")
        lines += ["", f"At F = {fit.thrust_n * 1e6:.4g} uN: tilt budget (gravity torque <= "
                  f"{BUDGET_FRACTION:g} F L) |tilt| <= {budget * 1e6:.3g} urad; negative "
                  f"stiffness (r < -1, unstable) {neg_text}"]
    return "\n".join(lines)


def plot(rec: Recording, fit: StandFit, out_dir: Path, name: str = "Recording") -> Path:
    """stiffness_log.png: the channels against time, and r per plateau on the fitted line."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    out_dir.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(9, 9), layout="constrained")
    FigureCanvasAgg(fig)
    top, mid, bottom = fig.subplots(3, 1, height_ratios=(2, 1, 2))
    hours = (rec.t_s - rec.t_s[0]) / 3600
    top.plot(hours, rec.displacement_m * 1e9, lw=0.5, color="C0")
    top.set_ylabel("Displacement [nm]")
    fig.suptitle(f"{name}: thrust stand fit, K0 = {fit.stiffness_nm_per_rad:.4g} ± "
                 f"{fit.stiffness_sigma_nm_per_rad:.2g} N m/rad, f0 = "
                 f"{fit.natural_frequency_hz:.3g} Hz, Q = {fit.quality_factor:.3g}")
    mid.plot(hours, rec.thrust_n * 1e6, lw=0.6, color="C1")
    mid.set_ylabel("Thrust [uN]", color="C1")
    mid.set_xlabel("Time from the first sample [h]")
    if rec.tilt_rad is not None:
        twin = mid.twinx()
        twin.plot(hours, rec.tilt_rad * 1e6, lw=0.8, color="C2")
        twin.set_ylabel("Tilt [urad]", color="C2")
    top.sharex(mid)
    top.tick_params(labelbottom=False)  # the time axis is labelled once, under the channels
    if fit.tilt_sensitivity_nm_per_rad is not None and fit.tilt_range_rad is not None:
        lo, hi = fit.tilt_range_rad
        dense = np.linspace(min(lo, -abs(hi)), max(hi, abs(lo)), 200)
        line = np.array([fit.coupling_ratio(a) for a in dense])
        bottom.plot(dense * 1e6, line, "-", label=f"fit: M g l_cm = "
                    f"{fit.tilt_sensitivity_nm_per_rad:.3g} ± "
                    f"{fit.tilt_sensitivity_sigma_nm_per_rad:.2g} uN m/urad")
        if fit.plateaus:
            bottom.plot([p.tilt_rad * 1e6 for p in fit.plateaus],
                        [p.coupling_ratio for p in fit.plateaus], "o",
                        label="measured on each tilt plateau")
        # zoomed on the data; the regime bands only where they fall inside
        seen = np.concatenate([line, [p.coupling_ratio for p in fit.plateaus]])
        reach = 1.15 * max(float(np.max(np.abs(seen))), 0.02)
        bottom.set_ylim(-reach, reach)
        bottom.axhspan(0, reach, color="C8", alpha=0.1, label="softening, r > 0")
        bottom.axhspan(max(-1, -reach), 0, color="C9", alpha=0.1,
                       label="stiffening, -1 < r < 0")
        if reach > 1:
            bottom.axhspan(-reach, -1, color="C3", alpha=0.1,
                           label="negative stiffness (unstable), r < -1")
        bottom.axhline(0, color="0.5", lw=0.6)
        bottom.legend(fontsize=8)
    else:
        bottom.text(0.5, 0.5, "no tilt column: the coupling is not measurable",
                    ha="center", va="center", transform=bottom.transAxes)
    bottom.set_xlabel("Pitch tilt [urad]")
    bottom.set_ylabel(f"r = M g sin(tilt) l_cm / (F L), F = {fit.thrust_n * 1e6:.3g} uN")
    bottom.grid(True, alpha=0.3)
    path = out_dir / "stiffness_log.png"
    fig.savefig(path, dpi=120)
    return path


def run(args: argparse.Namespace) -> int:
    from leveler.procedures.stiffness_log import fit_recording

    given = [f"--{k.replace('_', '-')}" for k in SIM_ONLY if getattr(args, k) is not None]
    try:
        if given:
            raise ValueError(f"{', '.join(given)} belong to the simulated sweep, not to LOG")
        if args.arm_m is None:
            raise ValueError("LOG needs --arm-m, the thrust arm [m] (the stiffness goes as its "
                             "square)")
        if args.thrust_n is not None and len(args.thrust_n) != 1:
            raise ValueError("with LOG, --thrust-n takes one F (the thrust r refers to)")
        for name in ("arm_sigma_m", "thrust_sigma_rel", "tilt_sigma_rel"):
            if not getattr(args, name) >= 0:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0")
        order = drift_order(args.drift)
        rec, note = load(args.log, quiet=args.json)
        fit = fit_recording(rec, args.arm_m, drift_order=order,
                            thrust_n=None if args.thrust_n is None else args.thrust_n[0],
                            arm_sigma_m=args.arm_sigma_m,
                            thrust_sigma_rel=args.thrust_sigma_rel,
                            tilt_sigma_rel=args.tilt_sigma_rel)
    except ValueError as exc:
        print(f"leveler analyze stiffness: error: {exc}", file=sys.stderr)
        return 2
    if note:
        print(note, file=sys.stderr)
    out = to_json(fit, args.log)
    if args.plot_dir:
        out["plots"] = [str(plot(rec, fit, Path(args.plot_dir), Path(args.log).name))]
    if args.json:
        print(json.dumps(out))
    else:
        print(report(fit, args.log))
        if args.plot_dir:
            print("\nplots: " + ", ".join(out["plots"]))
    return 0
