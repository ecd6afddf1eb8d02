"""`leveler analyze two-stage`: thrust recovered under base tilt by a two-stage TP (Fig. 17)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from leveler.procedures.two_stage import TwoStageResult


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "two-stage", help="two-stage torsion pendulum: thrust recovered under base tilt "
        "(paper Fig. 17)",
        description="TP2 (the thrust balance, displacement mode) hangs on TP1, which a PID "
        "holds at null. Under base tilt TP2 reads F L + tau_2 and TP1's null-control torque "
        "balances F L + tau_A, with tau_2 = kappa tau_A, kappa = M2 L_cm2 / ((M1 + M2) L_cm1). "
        "A calibration run (thruster off, same tilt) measures kappa; the two-stage estimate "
        "(y2 - kappa b) / ((1 - kappa) L) removes the tilt, the single-stage estimate y2 / L "
        "(TP2 alone) does not. Prints both estimates' correlation with the true square-wave "
        "thrust and their rms error.",
        epilog="Example: leveler analyze two-stage --plot fig17.png. Units are SI.")
    p.add_argument("--tilt-amplitude-rad", type=float, default=3e-6,
                   help="base pitch amplitude [rad] (default: %(default)g, the paper's)")
    p.add_argument("--tilt-frequency-hz", type=float, default=0.01,
                   help="base pitch frequency [Hz] (default: %(default)g, the paper's)")
    p.add_argument("--thrust-n", type=float, default=1e-7,
                   help="square-wave thrust 0/F [N] (default: %(default)g)")
    p.add_argument("--thrust-period-s", type=float, default=200.0,
                   help="square-wave period [s] (default: %(default)g)")
    p.add_argument("--duration-s", type=float, default=1000.0,
                   help="length of each run [s] (default: %(default)g)")
    p.add_argument("--fs-hz", type=float, default=10.0,
                   help="sample and null-loop rate [Hz] (default: %(default)g)")
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default: 0)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", default=None, metavar="FILE.png",
                   help="save tilt, null-control torque and thrust estimates against time")
    p.set_defaults(func=run)


def summary(r: TwoStageResult, drive: dict) -> dict:
    import numpy as np

    from leveler.procedures.two_stage import NULL_LOWPASS_HZ

    p = r.params
    return {
        "drive": drive,
        "tp1": {"stiffness_nm_per_rad": p.tp1.stiffness_nm_per_rad,
                "inertia_kgm2": p.tp1.inertia_kgm2,
                "assembly_mass_kg": p.tp1.mass_kg, "assembly_com_m": p.tp1.com_y_m,
                "tilt_sensitivity_nm_per_rad": p.tp1.tilt_sensitivity_nm_per_rad,
                "pid": {"kp_nm_per_rad": p.pid.kp_nm_per_rad,
                        "ki_nm_per_rad_s": p.pid.ki_nm_per_rad_s,
                        "kd_nms_per_rad": p.pid.kd_nms_per_rad, "tf_s": p.pid.tf_s},
                "null_residual_rms_rad": float(np.std(r.run.phi1_rad))},
        "tp2": {"stiffness_nm_per_rad": p.tp2.stiffness_nm_per_rad,
                "inertia_kgm2": p.tp2.inertia_kgm2, "mass_kg": p.tp2.mass_kg,
                "com_m": p.tp2.com_y_m, "arm_m": p.tp2.arm_m,
                "natural_frequency_hz": p.tp2.natural_frequency_hz,
                "quality_factor": p.tp2.quality_factor,
                "tilt_sensitivity_nm_per_rad": p.tp2.tilt_sensitivity_nm_per_rad},
        "null_lowpass_hz": NULL_LOWPASS_HZ,
        "kappa_calibrated": r.kappa,
        "kappa_model": p.coupling_ratio,
        "correlation_single_stage": r.correlation_single,
        "correlation_two_stage": r.correlation_decoupled,
        "rms_error_single_stage_n": r.rms_error_n(r.single_stage_n),
        "rms_error_two_stage_n": r.rms_error_n(r.decoupled_n),
    }


def report(s: dict) -> str:
    d, t1, t2 = s["drive"], s["tp1"], s["tp2"]
    return "\n".join([
        f"Two-stage torsion pendulum (simulated {d['duration_s']:g} s at {d['fs_hz']:g} Hz): "
        f"base pitch {d['tilt_amplitude_rad'] * 1e6:g} urad at {d['tilt_frequency_hz']:g} Hz, "
        f"thrust 0/{d['thrust_n'] * 1e6:g} uN square wave, period {d['thrust_period_s']:g} s",
        f"  TP1 (null-controlled): K1 {t1['stiffness_nm_per_rad']:g} N m/rad, J1 "
        f"{t1['inertia_kgm2']:g} kg m^2, (M1+M2) g L_cm1 = "
        f"{t1['tilt_sensitivity_nm_per_rad']:.4g} uN m/urad; TP1 held to "
        f"{t1['null_residual_rms_rad'] * 1e9:.3g} nrad rms",
        f"  TP2 (displacement mode): K2 {t2['stiffness_nm_per_rad']:g} N m/rad, f0 "
        f"{t2['natural_frequency_hz']:.3f} Hz, Q {t2['quality_factor']:.2g}, M2 g L_cm2 = "
        f"{t2['tilt_sensitivity_nm_per_rad']:.4g} uN m/urad, arm {t2['arm_m']:g} m",
        f"  (M1+M2) L_cm1 / (M2 L_cm2) = {1 / s['kappa_model']:.3g}",
        f"Calibration (thruster off, same tilt): kappa = {s['kappa_calibrated']:.5f} "
        f"(model M2 L_cm2 / ((M1+M2) L_cm1) = {s['kappa_model']:.5f})",
        "",
        f"  {'thrust estimate':<44} {'correlation':>11} {'rms error [uN]':>15}",
        f"  {'single stage: K2 x2 / L^2 (TP2 alone)':<44} "
        f"{s['correlation_single_stage']:11.3f} {s['rms_error_single_stage_n'] * 1e6:15.4f}",
        f"  {'two-stage: (y2 - kappa b) / ((1 - kappa) L)':<44} "
        f"{s['correlation_two_stage']:11.3f} {s['rms_error_two_stage_n'] * 1e6:15.4f}",
        f"  (b: TP1's null-control torque, low-passed at {s['null_lowpass_hz']:g} Hz; "
        "paper Fig. 17: the decoupled signal recovers the square wave)",
        *([f"  plot: {s['plot']}"] if "plot" in s else []),
    ])


def plot(r: TwoStageResult, path: str) -> None:
    """Three panels on one time axis: base tilt, TP1's null-control torque, thrust estimates."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from leveler.procedures.two_stage import NULL_LOWPASS_HZ

    fig = Figure(figsize=(9, 7), layout="constrained")
    FigureCanvasAgg(fig)
    ax1, ax2, ax3 = fig.subplots(3, 1, sharex=True)
    t = r.run.t_s
    ax1.plot(t, r.run.tilt_rad * 1e6, color="C0")
    ax1.set_ylabel("Base pitch [urad]")
    ax1.set_title("Two-stage torsion pendulum under base tilt (cf. paper Fig. 17)")
    ax2.plot(t, -r.run.null_torque_nm * 1e6, color="0.7", linewidth=0.6, label="-u, raw")
    ax2.plot(t, r.balance_torque_nm * 1e6, color="C1",
             label=f"b: -u low-passed\nat {NULL_LOWPASS_HZ:g} Hz")
    ax2.set_ylabel("TP1 balance torque [uN m]")
    # legends right of the panels: inside, they would hide the waves' crests
    ax2.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)
    ax3.plot(t, r.single_stage_n * 1e6, color="C3", linewidth=1,
             label=f"single stage\n(TP2 alone),\ncorr. {r.correlation_single:.3f}")
    ax3.plot(t, r.decoupled_n * 1e6, color="C2", linewidth=1,
             label=f"two-stage\ndecoupled,\ncorr. {r.correlation_decoupled:.3f}")
    ax3.plot(t, r.run.thrust_n * 1e6, color="k", linestyle="--", linewidth=1, label="true thrust")
    ax3.set_ylabel("Thrust [uN]")
    ax3.set_xlabel("Time [s]")
    ax3.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)
    for ax in (ax1, ax2, ax3):
        ax.grid(True, alpha=0.3)
    fig.savefig(path, dpi=120)


def run(args: argparse.Namespace) -> int:
    from leveler.procedures.two_stage import run_two_stage

    drive = {"tilt_amplitude_rad": args.tilt_amplitude_rad,
             "tilt_frequency_hz": args.tilt_frequency_hz, "thrust_n": args.thrust_n,
             "thrust_period_s": args.thrust_period_s, "duration_s": args.duration_s,
             "fs_hz": args.fs_hz}
    try:
        result = run_two_stage(seed=args.seed, **drive)
    except ValueError as exc:
        print(f"leveler analyze two-stage: error: {exc}", file=sys.stderr)
        return 2
    out = summary(result, drive)
    out["seed"] = args.seed
    if args.plot:
        plot(result, args.plot)
        out["plot"] = args.plot
    print(json.dumps(out) if args.json else report(out))
    return 0
