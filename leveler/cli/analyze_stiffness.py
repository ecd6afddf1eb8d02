"""`leveler analyze stiffness`: the paper's Figs. 3-6, the three regimes and the tilt budget."""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING

from leveler.cli import analyze_stiffness_log

if TYPE_CHECKING:
    import numpy as np

    from leveler.procedures.stiffness import TiltPoint
    from leveler.sim.torsion import TorsionParams


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "stiffness", help="thrust stiffness and compliance against base tilt; regimes; tilt "
        "budget (paper Figs. 3-6)",
        description="For each pivot stiffness K0 and thrust F, and each pitch tilt of a "
        "symmetric sweep, a square-wave thrust (0/F, 5 x 400 s at 5 Hz, 1 nm/rtHz sensor noise) "
        "drives the simulated pendulum, and a second-order thrust -> displacement transfer "
        "function is identified by least squares. Its 0 Hz value, with the sensor zeroed at "
        "the level rest position (the paper's definition), gives the compliance S = theta / "
        "(F L) and the stiffness K = 1 / S. The gravity torque does not change the pendulum's "
        "dynamics, it shifts its rest point; attributing that shift to the thrust makes "
        "S = (1 + r) / K0 with r = M g sin(tilt) l_cm / (F L): compliance linear in tilt "
        "(Fig. 6), stiffness close to a two-term exponential (Fig. 5). 'K incr.' is the "
        "stiffness fitted with a free offset: K0 at every tilt. Regimes: r > 0 softening, "
        "-1 < r < 0 stiffening, r < -1 negative stiffness (unstable as a balance). Tilt budget: "
        "the largest |tilt| with gravity torque <= 1/4 of F L, from the measured compliance "
        "slope. Fits and the regime table use the first K0; takes some seconds per K0 and F. "
        "With LOG, the same quantities come from a thrust stand's recording instead (thrust, "
        "displacement and, for the coupling, tilt channels; import-csv imports them): the "
        "equation of motion with both torques is fitted to the whole record (f0, Q, the "
        "start's ringing, the sensor's drift), giving K0 = L^2 / G and M g l_cm = B L / G "
        "(the displacement sensor's gain cancels, as in the paper's dual-frequency "
        "calibration), 1-sigma from a block jackknife plus the stated calibrations; r, K and "
        "the regime on every tilt plateau; the tilt budget.",
        epilog="Examples: leveler analyze stiffness --plot-dir out/ (transfer_1uN.png and "
        "transfer_0.1uN.png like Figs. 3, 4; stiffness.png, compliance.png, regimes.png). "
        "leveler analyze stiffness stand.mcap --arm-m 0.25 --arm-sigma-m 0.001 "
        "--thrust-sigma-rel 0.02 --plot-dir out/ (stiffness_log.png). "
        "Units are SI; the tables show urad and uN.")
    p.add_argument("log", nargs="?", metavar="LOG",
                   help="a thrust stand's recording (MCAP, e.g. from import-csv) to analyse "
                   "instead of the simulated sweep")
    p.add_argument("--stiffness-nm-per-rad", type=float, nargs="+", default=None,
                   metavar="K0", help="pivot stiffnesses K0 [N m/rad] (default: 0.2 0.02, "
                   "the paper's); the first gets the fits")
    p.add_argument("--thrust-n", type=float, nargs="+", default=None, metavar="F",
                   help="square-wave thrust amplitudes [N] (default: 1e-6 1e-7, the paper's); "
                   "the first gets the Fig. 5/6 fits. With LOG: the one F that r refers to "
                   "(default: the thrust channel's step, 98th minus 2nd percentile)")
    p.add_argument("--max-tilt-rad", type=float, default=None,
                   help="sweep pitch from -this to +this [rad] (default: "
                   f"{_SWEEP['max_tilt_rad']:g})")
    p.add_argument("--tilt-step-rad", type=float, default=None,
                   help=f"sweep step [rad] (default: {_SWEEP['tilt_step_rad']:g})")
    p.add_argument("--seed", type=int, default=None, help="sensor-noise seed (default: 0)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (model, identification, sweeps with points, "
                   "fits, regimes_seen, tilt_budget_rad)")
    p.add_argument("--plot-dir", default=None, metavar="DIR",
                   help="write the figures (PNG) into DIR")
    analyze_stiffness_log.add_arguments(p)
    p.set_defaults(func=run)


#: The simulated sweep's defaults; None on the command line, so that LOG can refuse them.
_SWEEP: dict = {"stiffness_nm_per_rad": [0.2, 0.02], "thrust_n": [1e-6, 1e-7],
                "max_tilt_rad": 20e-6, "tilt_step_rad": 2.5e-6, "seed": 0}


def _num(x: float) -> float | None:
    """JSON has no inf: a diverged stiffness is null."""
    return x if math.isfinite(x) else None


def analyze(base: TorsionParams, stiffnesses: list[float], thrusts: list[float],
            tilts: np.ndarray, seed: int) -> dict:
    """Every (K0, F) sweep; fits on the first K0; regimes and budgets for every F."""
    from leveler.procedures import stiffness as st
    from leveler.sim.torsion import DEFAULT_COUNTERWEIGHT_KG, DEFAULT_COUNTERWEIGHT_OFFSET_M

    regimes = (st.SOFTENING, st.LEVEL, st.STIFFENING, st.NEGATIVE)
    sweeps = []
    for i, k0 in enumerate(stiffnesses):
        p = replace(base, stiffness_nm_per_rad=k0)
        for j, thrust in enumerate(thrusts):
            points = st.tilt_sweep(p, thrust, tilts, seed=seed + 100 * i + j)
            lin = st.fit_compliance(points)
            sweep: dict = {"stiffness_nm_per_rad": k0, "thrust_n": thrust,
                           "points": [_point(pt) for pt in points],
                           "compliance_fit": asdict(lin)}
            try:
                sweep["stiffness_fit"] = asdict(st.fit_stiffness(points))
            except ValueError as exc:  # K <= 0 somewhere: a negative-stiffness sweep
                sweep["stiffness_fit"] = None
                sweep["stiffness_fit_skipped"] = str(exc)
            sens = st.tilt_sensitivity_nm_per_rad(lin, thrust, p.arm_m)
            sweep["measured_tilt_sensitivity_nm_per_rad"] = sens
            sweep["tilt_budget_rad"] = st.tilt_budget_rad(sens, thrust, p.arm_m)
            sweep["negative_stiffness_below_rad"] = st.negative_stiffness_tilt_rad(
                sens, thrust, p.arm_m)
            sweep["regimes_seen"] = {
                name: [pt.tilt_rad for pt in points if pt.regime == name] for name in regimes}
            sweeps.append(sweep)
    return {
        "model": {**asdict(base), "natural_frequency_hz": base.natural_frequency_hz,
                  "quality_factor": base.quality_factor,
                  "tilt_sensitivity_nm_per_rad": base.tilt_sensitivity_nm_per_rad,
                  "counterweight_kg": DEFAULT_COUNTERWEIGHT_KG,
                  "counterweight_offset_m": DEFAULT_COUNTERWEIGHT_OFFSET_M},
        "identification": {"fs_hz": st.RUN_FS_HZ, "square_wave_period_s": st.RUN_PERIOD_S,
                           "cycles": st.RUN_CYCLES,
                           "sensor_noise_m_per_rthz": st.SENSOR_NOISE_M_PER_RTHZ,
                           "seed": seed},
        "budget_fraction": st.BUDGET_FRACTION,
        "sweeps": sweeps,
    }


def _point(pt: TiltPoint) -> dict:
    return {"tilt_rad": pt.tilt_rad, "compliance_rad_per_nm": pt.compliance_rad_per_nm,
            "stiffness_nm_per_rad": _num(pt.stiffness_nm_per_rad),
            "incremental_stiffness_nm_per_rad": pt.incremental_stiffness_nm_per_rad,
            "coupling_ratio": pt.coupling_ratio,
            "model_coupling_ratio": pt.model_coupling_ratio, "regime": pt.regime,
            "dc_gain_m_per_n": pt.fit.dc_gain_m_per_n,
            "natural_frequency_hz": pt.fit.natural_frequency_hz,
            "quality_factor": pt.fit.quality_factor,
            "rms_residual_m": pt.fit.rms_residual_m}


def report(r: dict) -> str:
    m, ident = r["model"], r["identification"]
    lines = [
        f"Torsion pendulum (simulated): K0 = {m['stiffness_nm_per_rad']:g} N m/rad, "
        f"J = {m['inertia_kgm2']:g} kg m^2 (f0 {m['natural_frequency_hz']:.3f} Hz, "
        f"Q {m['quality_factor']:.3g}), L = {m['arm_m']:g} m, M = {m['mass_kg']:g} kg,",
        f"  l_cm,y = {m['com_y_m'] * 1e3:.3f} mm ({m['counterweight_kg']:g} kg counterweight at "
        f"{m['counterweight_offset_m'] * 1e3:g} mm): M g l_cm = "
        f"{m['tilt_sensitivity_nm_per_rad']:.4g} uN m/urad",
        f"Identification per tilt: square-wave thrust 0/F, {ident['cycles']} x "
        f"{ident['square_wave_period_s']:g} s at {ident['fs_hz']:g} Hz, sensor noise "
        f"{ident['sensor_noise_m_per_rthz'] * 1e9:g} nm/rtHz; least-squares 2nd-order thrust ->",
        "  displacement model; S = H(0) / L^2 with the sensor zeroed at level, K = 1 / S, "
        "r = S / S(level) - 1",
        "",
        "Figs. 3/4: identified transfer function, 0 Hz value H(0) [m/N] per tilt",
    ]
    sweeps = r["sweeps"]
    shown = _shown_tilts([pt["tilt_rad"] for pt in sweeps[0]["points"]])
    lines.append(f"  {'K0 [N m/rad]':>12} {'F [uN]':>7} {'f0 [Hz]':>8} {'Q':>6}  "
                 + " ".join(f"{t * 1e6:+8.0f}urad" for t in shown))
    for sw in sweeps:
        pts = {pt["tilt_rad"]: pt for pt in sw["points"]}
        level = pts[0.0]
        lines.append(f"  {sw['stiffness_nm_per_rad']:12g} {sw['thrust_n'] * 1e6:7g} "
                     f"{level['natural_frequency_hz']:8.3f} {level['quality_factor']:6.2f}  "
                     + " ".join(f"{pts[t]['dc_gain_m_per_n']:12.4g}" for t in shown))
    main = [s for s in sweeps if s["stiffness_nm_per_rad"] == sweeps[0]["stiffness_nm_per_rad"]]
    for i, sw in enumerate(main):
        lines += ["", *_sweep_table(sw, " (cf. paper Figs. 5, 6)" if i == 0 else "")]
    lines += ["", f"Tilt budget (gravity torque at the largest tilt <= {r['budget_fraction']:g} "
              "F L), from the measured compliance slope:"]
    for sw in main:
        lines.append(f"  F = {sw['thrust_n'] * 1e6:g} uN: |tilt| <= "
                     f"{sw['tilt_budget_rad'] * 1e6:.3g} urad  (measured M g l_cm = "
                     f"{sw['measured_tilt_sensitivity_nm_per_rad']:.4g} uN m/urad, model "
                     f"{m['tilt_sensitivity_nm_per_rad']:.4g})")
    lines.append("  the paper's thermal tilt of +-20 urad exceeds these: level the base "
                 "(leveler run) or calibrate l_cm (leveler calibrate-com)")
    return "\n".join(lines)


def _shown_tilts(tilts: list[float]) -> list[float]:
    """-max, -max/2, 0, +max/2, +max (or the nearest swept tilts)."""
    import numpy as np

    arr = np.array(tilts)
    top = float(arr.max())
    return sorted({float(arr[np.argmin(np.abs(arr - t))]) for t in
                   (-top, -top / 2, 0.0, top / 2, top)})


def _sweep_table(sw: dict, note: str) -> list[str]:
    from leveler.procedures.stiffness import LEVEL

    k0, thrust = sw["stiffness_nm_per_rad"], sw["thrust_n"]
    lines = [f"Tilt sweep: K0 = {k0:g} N m/rad, F = {thrust * 1e6:g} uN{note}",
             f"  {'tilt [urad]':>11} {'S [rad/(N m)]':>14} {'K [N m/rad]':>12} "
             f"{'K incr. [N m/rad]':>17} {'r (identified)':>15} {'r (model)':>10}  regime"]
    for pt in sw["points"]:
        k = pt["stiffness_nm_per_rad"]
        lines.append(f"  {pt['tilt_rad'] * 1e6:11.1f} {pt['compliance_rad_per_nm']:14.4g} "
                     f"{'inf' if k is None else f'{k:.4g}':>12} "
                     f"{pt['incremental_stiffness_nm_per_rad']:17.4f} "
                     f"{pt['coupling_ratio']:15.3f} {pt['model_coupling_ratio']:10.3f}  "
                     f"{pt['regime']}")
    lin = sw["compliance_fit"]
    lines.append(f"  compliance (Fig. 6, linear): S = S0 + s1 sin(tilt), S0 = "
                 f"{lin['intercept_rad_per_nm']:.4f} rad/(N m), s1 = "
                 f"{lin['slope_rad_per_nm_per_rad'] * 1e-6:.4g} rad/(N m) per urad, "
                 f"R^2 = {lin['r_squared']:.6f}")
    fit = sw["stiffness_fit"]
    if fit is None:
        lines.append("  stiffness (Fig. 5): no two-term exponential fit, K changes sign "
                     "(negative-stiffness points)")
    else:
        lines.append(f"  stiffness (Fig. 5, two-term exponential, a in urad): K = "
                     f"{fit['a_nm_per_rad']:.4g} exp({fit['b_per_urad']:+.4g} a) + "
                     f"{fit['c_nm_per_rad']:.4g} exp({fit['d_per_urad']:+.4g} a) N m/rad, "
                     f"R^2 = {fit['r_squared']:.6f}, max error {fit['max_rel_error']:.2%}")
    neg = sw["negative_stiffness_below_rad"]
    bound = ("never (|r| < 1 at any tilt)" if neg is None else
             f"{'below' if neg < 0 else 'above'} {neg * 1e6:.3g} urad")
    up, down = (("above", "below") if sw["measured_tilt_sensitivity_nm_per_rad"] >= 0
                else ("below", "above"))
    lines.append(f"  regimes: softening (r > 0) {up} level; stiffening (-1 < r < 0) {down} "
                 f"level; negative stiffness (r < -1, unstable) {bound}")
    for name, seen in sw["regimes_seen"].items():
        if seen and name != LEVEL:
            span = (f"{seen[0] * 1e6:+.1f}" if len(seen) == 1 else
                    f"{min(seen) * 1e6:+.1f} .. {max(seen) * 1e6:+.1f}")
            lines.append(f"    {name}: seen at {span} urad ({len(seen)} of the swept tilts)")
    return lines


def plot(r: dict, out_dir: Path) -> list[Path]:
    """transfer_<F>uN.png (Figs. 3, 4), stiffness.png (5), compliance.png (6), regimes.png."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    from leveler.procedures import stiffness as st

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    sweeps = r["sweeps"]
    main_k0 = sweeps[0]["stiffness_nm_per_rad"]
    freq = np.logspace(-3, math.log10(0.4 * r["identification"]["fs_hz"]), 600)

    def new() -> tuple[Figure, object]:
        fig = Figure(figsize=(8, 5), layout="constrained")
        FigureCanvasAgg(fig)
        return fig, fig.add_subplot()

    for thrust in dict.fromkeys(sw["thrust_n"] for sw in sweeps):
        fig, ax = new()
        # colour: K0, line: tilt; one legend for each, so no entry repeats the other's words
        k0_handles, styles, negative = [], {}, {}
        for c, sw in enumerate(s for s in sweeps if s["thrust_n"] == thrust):
            pts = {pt["tilt_rad"]: pt for pt in sw["points"]}
            for t in _shown_tilts(list(pts)):
                pt = pts[t]
                fit = st.TransferFit(dc_gain_m_per_n=pt["dc_gain_m_per_n"],
                                     incremental_gain_m_per_n=0.0, offset_m=0.0,
                                     natural_frequency_hz=pt["natural_frequency_hz"],
                                     quality_factor=pt["quality_factor"], rms_residual_m=0.0)
                style = {"linestyle": "--" if t < 0 else "-",
                         "alpha": 0.35 + 0.65 * (1 - abs(t) / max(abs(k) for k in pts))}
                ax.loglog(freq, fit.magnitude_m_per_n(freq), color=f"C{c}", **style)
                key = round(t * 1e6)
                styles.setdefault(key, style)
                if pt["dc_gain_m_per_n"] < 0:
                    negative.setdefault(key, []).append(f"{sw['stiffness_nm_per_rad']:g}")
            k0_handles.append(Line2D([], [], color=f"C{c}",
                                     label=f"K0 = {sw['stiffness_nm_per_rad']:g} N m/rad"))
        n_k0 = len(k0_handles)
        tilt_handles = [
            Line2D([], [], color="0.2", **style, label=f"{key:+d} urad" + (
                "" if key not in negative else " (H(0) < 0)" if len(negative[key]) == n_k0
                else f" (H(0) < 0 at K0 = {', '.join(negative[key])})"))
            for key, style in sorted(styles.items())]
        ax.set_xlabel("Frequency [Hz]")
        ax.set_ylabel("|H| thrust -> end displacement [m/N]")
        ax.set_title(f"Identified transfer function, F = {thrust * 1e6:g} uN square wave "
                     "(cf. paper Figs. 3, 4)")
        ax.grid(True, which="both", alpha=0.3)
        ax.add_artist(ax.legend(handles=k0_handles, loc="upper right", fontsize=8))
        ax.legend(handles=tilt_handles, loc="lower left", fontsize=8, title="base tilt",
                  title_fontsize=8)
        path = out_dir / f"transfer_{thrust * 1e6:g}uN.png"
        fig.savefig(path, dpi=120)
        written.append(path)

    main = [sw for sw in sweeps if sw["stiffness_nm_per_rad"] == main_k0]
    first = main[0]
    tilt_urad = np.array([pt["tilt_rad"] * 1e6 for pt in first["points"]])
    dense = np.linspace(tilt_urad.min(), tilt_urad.max(), 400)
    budget = first["tilt_budget_rad"] * 1e6

    fig, ax = new()
    k = np.array([pt["stiffness_nm_per_rad"] for pt in first["points"]], dtype=float)
    ax.plot(tilt_urad, k, "o", label="identified K = F L / theta")
    if first["stiffness_fit"] is not None:
        f = first["stiffness_fit"]
        ax.plot(dense, st.TwoExpFit(**f)(dense), "-", label="two-term exponential fit")
    r_model = np.array([pt["model_coupling_ratio"] for pt in first["points"]])
    ax.plot(tilt_urad, main_k0 / (1 + r_model), "k--", linewidth=0.8,
            label="paper eq. 6, K0 / (1 + r), simulator's r")
    ax.axhline(main_k0, color="0.4", linestyle=":", label=f"K0 = {main_k0:g} N m/rad")
    ax.axvspan(-budget, budget, color="C2", alpha=0.1, label="tilt budget (|r| <= 1/4)")
    ax.set_xlabel("Pitch tilt [urad]")
    ax.set_ylabel("Thrust stiffness K [N m/rad]")
    ax.set_title(f"Stiffness vs tilt, K0 = {main_k0:g} N m/rad, F = "
                 f"{first['thrust_n'] * 1e6:g} uN (cf. paper Fig. 5)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    written.append(out_dir / "stiffness.png")
    fig.savefig(written[-1], dpi=120)

    fig, ax = new()
    s = np.array([pt["compliance_rad_per_nm"] for pt in first["points"]])
    lin = first["compliance_fit"]
    ax.plot(tilt_urad, s, "o", label="identified S = theta / (F L)")
    ax.plot(dense, lin["intercept_rad_per_nm"] + lin["slope_rad_per_nm_per_rad"]
            * np.sin(dense * 1e-6), "-", label=f"linear fit, R^2 = {lin['r_squared']:.6f}")
    ax.plot(tilt_urad, (1 + r_model) / main_k0, "k--", linewidth=0.8,
            label="paper eq. 5, (1 + r) / K0, simulator's r")
    ax.set_xlabel("Pitch tilt [urad]")
    ax.set_ylabel("Thrust compliance S [rad/(N m)]")
    ax.set_title(f"Compliance vs tilt, K0 = {main_k0:g} N m/rad, F = "
                 f"{first['thrust_n'] * 1e6:g} uN (cf. paper Fig. 6)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    written.append(out_dir / "compliance.png")
    fig.savefig(written[-1], dpi=120)

    fig, ax = new()
    for sw in main:
        ax.plot([pt["tilt_rad"] * 1e6 for pt in sw["points"]],
                [pt["coupling_ratio"] for pt in sw["points"]], "o-",
                label=f"F = {sw['thrust_n'] * 1e6:g} uN")
    lo, hi = ax.get_ylim()
    ax.axhspan(0, max(hi, 0.5), color="C8", alpha=0.1, label="softening, r > 0")
    ax.axhspan(-1, 0, color="C9", alpha=0.1, label="stiffening, -1 < r < 0")
    ax.axhspan(min(lo, -1.5), -1, color="C3", alpha=0.1,
               label="negative stiffness (unstable), r < -1")
    ax.set_ylim(min(lo, -1.5), max(hi, 0.5))
    ax.set_xlabel("Pitch tilt [urad]")
    ax.set_ylabel("r = M g sin(tilt) l_cm / (F L), identified")
    ax.set_title(f"The paper's three regimes, K0 = {main_k0:g} N m/rad")
    ax.grid(True, alpha=0.3)
    ax.legend()
    written.append(out_dir / "regimes.png")
    fig.savefig(written[-1], dpi=120)
    return written


def run(args: argparse.Namespace) -> int:
    from leveler.procedures import stiffness as st
    from leveler.sim.torsion import TorsionParams

    if args.log is not None:
        return analyze_stiffness_log.run(args)
    for key, default in _SWEEP.items():
        if getattr(args, key) is None:
            setattr(args, key, default)
    log_only = analyze_stiffness_log.given_without_log(args)
    try:
        if log_only:
            raise ValueError(f"{', '.join(log_only)}: only with a LOG (a thrust stand's "
                             "recording)")
        tilts = st.sweep_tilts(args.max_tilt_rad, args.tilt_step_rad)
        base = TorsionParams(stiffness_nm_per_rad=args.stiffness_nm_per_rad[0])
        result = analyze(base, args.stiffness_nm_per_rad, args.thrust_n, tilts, args.seed)
    except ValueError as exc:
        print(f"leveler analyze stiffness: error: {exc}", file=sys.stderr)
        return 2
    if args.plot_dir:
        result["plots"] = [str(p) for p in plot(result, Path(args.plot_dir))]
    if args.json:
        print(json.dumps(result))
    else:
        print(report(result))
        if args.plot_dir:
            print("\nplots: " + ", ".join(result["plots"]))
    return 0
