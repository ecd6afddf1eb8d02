"""`leveler calibrate-com`: a centre of mass from a recording (`calibrate_com_log`), or the
paper's dual-frequency calibration on the simulated torsion pendulum (Fig. 11)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from leveler.procedures.calibrate_com import ComResult


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "calibrate-com", help="centre-of-mass offset: from a recorded drive of the table (LOG), "
        "or the paper's dual-frequency method on the simulated torsion pendulum (Fig. 11)",
        description="With LOG: find the drive lines in a recording (a stepped sine sweep or "
        "square modulation of the piezo, where the loop was open), estimate the transfer "
        "function from command to reading at each with its uncertainty (the slow drift and the "
        "pendulum's ringing fitted out, the noise measured beside each line), and fit the "
        "pendulum tiltmeter's "
        "response A (w^2 + g) / (w0^2 - w^2 + i w w0 / Q): its signed centre-of-mass distance "
        "L = g J / (m g) (a hanging pendulum's zero is at sqrt(m g d / J)), resonance, Q and "
        "scale, with 1-sigma uncertainties. The mass, inertia and stated scale come from the "
        "log's config or --model; an imported log carries none, so give --model. "
        "Without LOG: on the simulated torsion pendulum, modulate the base pitch at f1 and "
        "apply a calibration force at f2 together; the displacement ASD has a line at each. "
        "Their amplitude ratio, scaled by the known force, arm and mass (and the pendulum's "
        "response ratio |H(f2)/H(f1)|), gives the centre-of-mass offset l_cm = (A1/A2) F L / "
        "(M g sin(tilt)) |H(f2)/H(f1)|, and the counterweight position l_cm2 = l_cm (m1 + m2) / "
        "m2. Runs once per counterweight position and prints true against recovered.",
        epilog="Examples: leveler calibrate-com run7.mcap --model tiltmeter.toml --plot "
        "bode.png; leveler calibrate-com --plot fig11.png. Units are SI; the tables show mHz, "
        "nm/V, um, mm and um/rtHz.")
    p.add_argument("log", nargs="?", default=None,
                   help="a recording (leveler's log, or `leveler import-csv`'s) with a drive "
                   "of the table; without it, the simulated dual-frequency method runs")
    p.add_argument("--model", default=None, metavar="CONFIG",
                   help="with LOG: config whose [plant] gives the pendulum's mass, inertia and "
                   "the stated scale (default: the config stored in the log)")
    p.add_argument("--model-out", default=None, metavar="FITTED.toml",
                   help="with LOG: write the model with the fitted pendulum (com_length_m, "
                   "flexure stiffness, damping) to this file, for `leveler replay --model`")
    p.add_argument("--settle-fraction", type=float, default=0.25,
                   help="with LOG: fraction of each drive step left out for the pendulum to "
                   "ring down in the first fit; the second fits the ringing that one found "
                   "and uses the steps whole (default: %(default)g)")
    p.add_argument("--counterweight-offsets-m", type=float, nargs="+",
                   default=[1e-3, 2e-3, 3e-3, 4e-3, 5e-3], metavar="L",
                   help="counterweight distances from the axis [m] (default: 1..5 mm, the "
                   "paper's)")
    p.add_argument("--tilt-amplitude-rad", type=float, default=25e-6,
                   help="pitch modulation amplitude [rad] (default: %(default)g)")
    p.add_argument("--tilt-frequency-hz", type=float, default=0.1,
                   help="pitch modulation frequency f1 [Hz] (default: %(default)g)")
    p.add_argument("--force-amplitude-n", type=float, default=1e-6,
                   help="calibration force amplitude [N] (default: %(default)g)")
    p.add_argument("--force-frequency-hz", type=float, default=0.11,
                   help="calibration force frequency f2 [Hz] (default: %(default)g)")
    p.add_argument("--duration-s", type=float, default=4000.0,
                   help="length of each run [s] (default: %(default)g)")
    p.add_argument("--fs-hz", type=float, default=5.0,
                   help="sample rate [Hz] (default: %(default)g)")
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default: 0)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", default=None, metavar="FILE.png",
                   help="save the displacement ASDs, one per counterweight position")
    p.set_defaults(func=run)


def _row(r: ComResult) -> dict:
    return {"counterweight_offset_m": r.counterweight_offset_m,
            "com_offset_m": r.com_offset_m,
            "recovered_com_offset_m": r.recovered_com_offset_m,
            "recovered_counterweight_offset_m": r.recovered_counterweight_offset_m,
            "relative_error": r.relative_error,
            "tilt_peak_asd_m_per_rthz": r.tilt_peak_asd_m_per_rthz,
            "force_peak_asd_m_per_rthz": r.force_peak_asd_m_per_rthz,
            "tilt_line_m": r.tilt_line_m, "force_line_m": r.force_line_m}


def report(r: dict) -> str:
    a, m = r["drive"], r["model"]
    lines = [
        f"Centre-of-mass calibration (simulated TP: K0 {m['stiffness_nm_per_rad']:g} N m/rad, "
        f"J {m['inertia_kgm2']:g} kg m^2, L {m['arm_m']:g} m, m1 {m['balanced_mass_kg']:g} kg "
        f"+ counterweight m2 {m['counterweight_kg']:g} kg)",
        f"  pitch {a['tilt_amplitude_rad'] * 1e6:g} urad at {a['tilt_frequency_hz']:g} Hz and "
        f"force {a['force_amplitude_n'] * 1e6:g} uN at {a['force_frequency_hz']:g} Hz together, "
        f"{a['duration_s']:g} s at {a['fs_hz']:g} Hz; l_cm from the ratio of the ASD peaks",
        "",
        f"  {'counterweight':>13} {'l_cm true':>10} {'l_cm recovered':>15} {'error':>7} "
        f"{'l_cm2 recovered':>16} {'ASD @f1':>10} {'ASD @f2':>10}",
        f"  {'[mm]':>13} {'[um]':>10} {'[um]':>15} {'':>7} {'[mm]':>16} "
        f"{'[um/rtHz]':>10} {'[um/rtHz]':>10}",
    ]
    for row in r["offsets"]:
        lines.append(f"  {row['counterweight_offset_m'] * 1e3:13.3g} "
                     f"{row['com_offset_m'] * 1e6:10.2f} "
                     f"{row['recovered_com_offset_m'] * 1e6:15.2f} "
                     f"{row['relative_error']:+7.2%} "
                     f"{row['recovered_counterweight_offset_m'] * 1e3:16.4f} "
                     f"{row['tilt_peak_asd_m_per_rthz'] * 1e6:10.4g} "
                     f"{row['force_peak_asd_m_per_rthz'] * 1e6:10.4g}")
    worst = max(abs(row["relative_error"]) for row in r["offsets"])
    lines += ["", f"  worst error {worst:.2%}; the f1 (tilt) peak grows with the offset, the f2 "
              "(force) peak stays: paper Fig. 11"]
    if "plot" in r:
        lines.append(f"  plot: {r['plot']}")
    return "\n".join(lines)


def plot(results: list[ComResult], fs_hz: float, path: str, drive: dict) -> None:
    """Fig. 11: the ASD per counterweight position, with an inset around the two drive
    lines (10 mHz apart at 0.1 Hz, one spot on the log axis) reaching half their spacing
    beyond each, so the f1 line's growth against the constant f2 line shows."""
    from leveler.analysis.plots import plot_asd
    from leveler.procedures.calibrate_com import figure_spectrum

    curves = [(f"counterweight at {r.counterweight_offset_m * 1e3:g} mm",
               figure_spectrum(r.displacement_m, fs_hz)) for r in results]
    f_lo, f_hi = sorted((drive["tilt_frequency_hz"], drive["force_frequency_hz"]))
    margin = (f_hi - f_lo) / 2
    plot_asd(curves, path, ylabel="End displacement ASD [m/√Hz]",
             zoom_hz=(f_lo - margin, f_hi + margin),
             title=f"CoM calibration: pitch {drive['tilt_amplitude_rad'] * 1e6:g} urad at "
             f"{drive['tilt_frequency_hz']:g} Hz + force {drive['force_amplitude_n'] * 1e6:g} uN "
             f"at {drive['force_frequency_hz']:g} Hz (cf. paper Fig. 11)")


def run(args: argparse.Namespace) -> int:
    if args.log is not None:
        from leveler.cli.calibrate_com_log import run as run_log

        if not 0 <= args.settle_fraction < 1:
            print("leveler calibrate-com: error: --settle-fraction must be in [0, 1)",
                  file=sys.stderr)
            return 2
        return run_log(args)
    from leveler.procedures.calibrate_com import calibrate_offsets
    from leveler.sim.torsion import (
        DEFAULT_BALANCED_MASS_KG,
        DEFAULT_COUNTERWEIGHT_KG,
        TorsionParams,
    )

    drive = {"tilt_amplitude_rad": args.tilt_amplitude_rad,
             "tilt_frequency_hz": args.tilt_frequency_hz,
             "force_amplitude_n": args.force_amplitude_n,
             "force_frequency_hz": args.force_frequency_hz,
             "duration_s": args.duration_s, "fs_hz": args.fs_hz}
    base = TorsionParams()
    try:
        results = calibrate_offsets(base, tuple(args.counterweight_offsets_m), seed=args.seed,
                                    **drive)
    except ValueError as exc:
        print(f"leveler calibrate-com: error: {exc}", file=sys.stderr)
        return 2
    out: dict = {
        "model": {"stiffness_nm_per_rad": base.stiffness_nm_per_rad,
                  "inertia_kgm2": base.inertia_kgm2,
                  "damping_nms_per_rad": base.damping_nms_per_rad, "arm_m": base.arm_m,
                  "balanced_mass_kg": DEFAULT_BALANCED_MASS_KG,
                  "counterweight_kg": DEFAULT_COUNTERWEIGHT_KG},
        "drive": drive, "seed": args.seed,
        "offsets": [_row(r) for r in results],
        "max_abs_relative_error": max(abs(r.relative_error) for r in results),
    }
    if args.plot:
        plot(results, args.fs_hz, args.plot, drive)
        out["plot"] = args.plot
    print(json.dumps(out) if args.json else report(out))
    return 0
