"""`leveler design ip`: the paper's counterweight sweep for the inverted-pendulum tilt amplifier.

The physics and the model live in leveler.procedures.design_ip; this module turns options into a
sweep, a pick and a report (text, JSON, PNG).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from leveler.procedures.design_ip import IpModel, Pick, Point


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    design = sub.add_parser(
        "design", help="the paper's design procedures (ip: inverted-pendulum counterweight)",
        description="Design calculations from the paper, each a subcommand.")
    dsub = design.add_subparsers(dest="design_command", required=True, metavar="DESIGN")
    p = dsub.add_parser(
        "ip", help="inverted-pendulum tilt amplifier: amplification N against counterweight",
        description="The paper's counterweight sweep (its Figure 8) with our geometry, not its "
        "Simscape model: a flexure of stiffness k (config [plant.pendulum]) carries a frame "
        "(mass m_f, centre of mass L_f above the pivot; default none) and a counterweight "
        "m_cw at height h_cw, so m g L_cm = g (m_f L_f + m_cw h_cw). For each counterweight "
        "mass it prints m g L_cm, the small-angle amplification N = 1 / (k / (m g L_cm) - 1) "
        "and the N = theta / phi of the full balance m g L_cm sin(theta + phi) = k theta "
        "solved at the reference tilt phi, with the equilibrium angle theta. The stability "
        "limit m g L_cm = k (small-angle N -> infinity) is marked; heavier counterweights are "
        "reported unstable. --target-n picks the mass for a requested N at phi (exactly, by "
        "the balance's closed-form inverse). The default stand is a 185 g mass 49.6 mm above "
        "a 0.1 N m/rad flexure: m g L_cm = 0.09 N m/rad, N = 9, the paper's example.",
        epilog="Example: leveler design ip --target-n 10 --plot ip.png. Units are SI; the "
        "table shows theta in mrad, the plot masses in g.")
    p.add_argument("--config", default="config/sim.toml",
                   help="config whose [plant.pendulum] gives k and g; its com_length_m is "
                   "the default counterweight height (default: %(default)s)")
    p.add_argument("--target-n", type=float, default=None, metavar="N",
                   help="pick the counterweight giving amplification N at the reference tilt")
    p.add_argument("--tilt-rad", type=float, default=1e-3,
                   help="reference tilt phi for the non-linear N [rad] (default: %(default)g, "
                   "as in the paper)")
    p.add_argument("--cw-height-m", type=float, default=None,
                   help="height of the counterweight's centre of mass above the pivot [m] "
                   "(default: the config's com_length_m)")
    p.add_argument("--frame-mass-kg", type=float, default=0.0,
                   help="mass of the rest of the pendulum [kg] (default: 0)")
    p.add_argument("--frame-com-m", type=float, default=0.0,
                   help="height of the frame's centre of mass above the pivot [m] "
                   "(default: 0)")
    p.add_argument("--mass-kg", type=float, nargs=2, default=None, metavar=("MIN", "MAX"),
                   help="counterweight masses to sweep [kg] (default: 0.5 to 1.05 times the "
                   "stability limit; a range across the limit is fine)")
    p.add_argument("--step-kg", type=float, default=None,
                   help="table step [kg] (default: a round step giving 6 to 15 rows)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (model, sweep, stability_limit, pick, plot)")
    p.add_argument("--plot", default=None, metavar="FILE.png",
                   help="save N against counterweight mass, limit marked (PNG)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from leveler.procedures.design_ip import (
        DesignError,
        IpModel,
        check_tilt,
        default_range,
        evaluate,
        pick,
        plot_design,
        table_masses,
    )
    from leveler.settings import load_config

    cfg, _ = load_config(args.config)
    base = cfg.plant.pendulum
    try:
        check_tilt(args.tilt_rad)
        model = IpModel(base, base.com_length_m if args.cw_height_m is None else args.cw_height_m,
                        args.frame_mass_kg, args.frame_com_m)
        chosen = None if args.target_n is None else pick(model, args.target_n, args.tilt_rad)
        if args.mass_kg is None:
            lo, hi = default_range(model, None if chosen is None else chosen.cw_mass_kg)
        else:
            lo, hi = args.mass_kg
        rows = [evaluate(model, m, args.tilt_rad) for m in table_masses(lo, hi, args.step_kg)]
    except DesignError as exc:
        print(f"leveler design ip: error: {exc}", file=sys.stderr)
        return 2
    result = _result(args, model, rows, chosen)
    if args.plot:
        plot_design(args.plot, model, args.tilt_rad, lo, hi, chosen,
                    title=f"Inverted-pendulum tilt amplifier: k = "
                    f"{base.flexure_stiffness_nm_per_rad:g} N m/rad, counterweight at "
                    f"{model.cw_height_m * 1e3:g} mm")
        result["plot"] = args.plot
    print(json.dumps(result) if args.json else report(result))
    return 0


def _point(p: Point) -> dict[str, Any]:
    return {"cw_mass_kg": p.cw_mass_kg,
            "gravity_stiffness_nm_per_rad": p.gravity_stiffness_nm_per_rad,
            "n_small_angle": p.n_small_angle, "n_at_tilt": p.n_at_tilt,
            "theta_rad": p.theta_rad, "stable": p.stable}


def _result(args: argparse.Namespace, model: IpModel, rows: list[Point],
            chosen: Pick | None) -> dict[str, Any]:
    from leveler.procedures.design_ip import max_amplification_at

    base = model.base
    return {
        "config": str(args.config),
        "model": {"flexure_stiffness_nm_per_rad": base.flexure_stiffness_nm_per_rad,
                  "gravity_m_per_s2": base.gravity_m_per_s2,
                  "cw_height_m": model.cw_height_m, "frame_mass_kg": model.frame_mass_kg,
                  "frame_com_m": model.frame_com_m},
        "configured": {"mass_kg": base.mass_kg, "com_length_m": base.com_length_m,
                       "gravity_stiffness_nm_per_rad": base.gravity_stiffness_nm_per_rad,
                       "n_small_angle": base.amplification},
        "tilt_rad": args.tilt_rad,
        "stability_limit": {"cw_mass_kg": model.stability_limit_kg,
                            "gravity_stiffness_nm_per_rad": base.flexure_stiffness_nm_per_rad,
                            "n_at_tilt": max_amplification_at(args.tilt_rad)},
        "sweep": [_point(p) for p in rows],
        "pick": None if chosen is None else {
            "target_n": chosen.target_n, "cw_mass_kg": chosen.cw_mass_kg,
            "cw_mass_small_angle_kg": chosen.cw_mass_small_angle_kg,
            "dn_dm_per_kg": chosen.dn_dm_per_kg, **_point(chosen.point)},
        "plot": None,
    }


def report(r: dict[str, Any]) -> str:
    """The sweep as a table, the stability limit drawn across it, then the pick."""
    m, c, lim = r["model"], r["configured"], r["stability_limit"]
    tilt_mrad = r["tilt_rad"] * 1e3
    frame = ("no frame" if m["frame_mass_kg"] == 0 else
             f"frame {m['frame_mass_kg']:g} kg at {m['frame_com_m']:g} m")
    lines = [
        f"inverted pendulum from {r['config']}: k = {m['flexure_stiffness_nm_per_rad']:g} N m/rad, "
        f"g = {m['gravity_m_per_s2']:g} m/s^2 (configured: {c['mass_kg']:g} kg at "
        f"{c['com_length_m']:g} m, m g L_cm = {c['gravity_stiffness_nm_per_rad']:.4g} N m/rad, "
        f"N = {c['n_small_angle']:.4g})",
        f"counterweight at h_cw = {m['cw_height_m']:g} m above the pivot, {frame}; "
        f"reference tilt phi = {tilt_mrad:g} mrad",
        "",
        f"{'cw mass':>8}  {'m g L_cm':>9}  {'N':>11}  {'N':>11}  {'theta':>11}",
        f"{'[kg]':>8}  {'[N m/rad]':>9}  {'small-angle':>11}  {f'at {tilt_mrad:g} mrad':>11}  "
        f"{'[mrad]':>11}",
    ]
    limit_drawn = False
    for p in r["sweep"]:
        if not p["stable"] and not limit_drawn:
            lines.append(f"{'-' * 10} stability limit {lim['cw_mass_kg']:.4f} kg {'-' * 10}")
            limit_drawn = True
        if p["stable"]:
            lines.append(f"{p['cw_mass_kg']:8.4f}  {p['gravity_stiffness_nm_per_rad']:9.5f}  "
                         f"{p['n_small_angle']:11.4g}  {p['n_at_tilt']:11.4g}  "
                         f"{p['theta_rad'] * 1e3:11.4g}")
        else:
            lines.append(f"{p['cw_mass_kg']:8.4f}  {p['gravity_stiffness_nm_per_rad']:9.5f}  "
                         "   unstable (m g L_cm >= k)")
    lines += [
        "",
        f"stability limit: m_cw = {lim['cw_mass_kg']:.4f} kg, where m g L_cm = k = "
        f"{lim['gravity_stiffness_nm_per_rad']:g} N m/rad: small-angle N -> infinity, "
        f"N at {tilt_mrad:g} mrad -> {lim['n_at_tilt']:.4g} (theta = "
        f"{lim['n_at_tilt'] * tilt_mrad:.3g} mrad)",
    ]
    pk = r["pick"]
    if pk is not None:
        lines.append(
            f"pick for N = {pk['target_n']:g} at {tilt_mrad:g} mrad: m_cw = "
            f"{pk['cw_mass_kg']:.4f} kg (m g L_cm = {pk['gravity_stiffness_nm_per_rad']:.4g} "
            f"N m/rad; small-angle formula: {pk['cw_mass_small_angle_kg']:.4f} kg); "
            f"dN/dm = {pk['dn_dm_per_kg'] * 1e-3:.3g} per gram")
    lines.append("paper (Figure 8): 180-190 g of counterweight gives N around 10 at 1 mrad; "
                 "k = 0.1 and m g L_cm = 0.09 N m/rad give N = 9")
    if r["plot"]:
        lines.append(f"plot: {r['plot']}")
    return "\n".join(lines)

