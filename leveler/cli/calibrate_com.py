"""`leveler calibrate-com`: the paper's dual-frequency centre-of-mass calibration (Fig. 11)."""

from __future__ import annotations

import argparse
import json
import sys

from leveler.procedures.calibrate_com import ComResult, calibrate_offsets, figure_spectrum
from leveler.sim.torsion import DEFAULT_BALANCED_MASS_KG, DEFAULT_COUNTERWEIGHT_KG, TorsionParams


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
    from leveler.analysis.plots import plot_asd

    curves = [(f"counterweight at {r.counterweight_offset_m * 1e3:g} mm",
               figure_spectrum(r.displacement_m, fs_hz)) for r in results]
    plot_asd(curves, path, ylabel="End displacement ASD [m/√Hz]",
             title=f"CoM calibration: pitch {drive['tilt_amplitude_rad'] * 1e6:g} urad at "
             f"{drive['tilt_frequency_hz']:g} Hz + force {drive['force_amplitude_n'] * 1e6:g} uN "
             f"at {drive['force_frequency_hz']:g} Hz (cf. paper Fig. 11)")


def run_com_command(args: argparse.Namespace) -> int:
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
