"""`leveler modulate`: square or triangle tilt modulation by the piezo, run by the daemon (a logged
procedure of the loop) or on the simulated stand in virtual time (--sim); what the pendulums
made of it is leveler.procedures.tilt_modulation."""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from leveler.cli.common import add_socket, duration
from leveler.daemon.client import Client, ClientError

if TYPE_CHECKING:
    import numpy as np

    from leveler.loop.modulation import Wave
    from leveler.sim.torsion import TorsionParams


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "modulate", help="square or triangle tilt modulation by the piezo; the pendulum's "
        "response",
        description="Drive the piezo in a square or triangle wave about the voltage it "
        "holds, with the loop open, and measure the inverted pendulum's response: peak to "
        "peak, per piezo volt, as "
        "platform tilt, and against what the config's piezo geometry (stroke / support spacing)"
        " predicts. A square's steps are read where the pendulum has settled. A triangle sweeps"
        " the piezo at a steady rate, and the reading is fitted against the model pendulum's "
        "response plus a term for the direction of travel: the opening between the up and the "
        "down sweeps at the same voltage, which a square cannot show. An opening is a piezo's "
        "hysteresis when it stays the same at another --period, a lag (an actuator delay) when "
        "it grows with the sweep rate. The running daemon executes it as a logged procedure "
        "(state `modulating`, `procedure` events, every sample in the log); it refuses while "
        "the loop is engaged unless --force, which opens the loop for the wave and closes it "
        "again afterwards. `leveler stop` aborts a wave; a fault ends it with the piezo safe. "
        "With --sim the same procedure runs on the simulated stand in virtual time. With LOG, a"
        " recording is analysed instead: every square or triangle modulation of the piezo found"
        " in it where the loop was open (leveler's own `modulate` procedures, or another "
        "system's, imported with `leveler import-csv`), each measured the same way against the "
        "config stored in the log or --model; its shape is the one that fits the recorded "
        "command.")
    p.add_argument("log", nargs="?", default=None,
                   help="a recording to analyse instead of running a wave")
    p.add_argument("--model", default=None, metavar="CONFIG",
                   help="with LOG: the config whose piezo geometry and pendulum are the model "
                   "(default: the config stored in the log)")
    p.add_argument("--amplitude-v", type=float, default=None,
                   help="piezo swing about the held voltage [V] (peak to peak = 2 x amplitude)")
    p.add_argument("--period", type=duration, default=None,
                   help="wave period, e.g. 60s or 5min (at least 4 loop periods; a triangle "
                   "well above the pendulum's ring-down, a few minutes)")
    p.add_argument("--shape", choices=("square", "triangle"), default="square",
                   help="square: +amplitude, then -amplitude (the step per volt); triangle: "
                   "centre, up to +amplitude, down to -amplitude, back (the step per volt and "
                   "the opening between the sweeps: hysteresis) (default: %(default)s)")
    p.add_argument("--cycles", type=int, default=3, help="number of periods (default: 3)")
    p.add_argument("--force", action="store_true",
                   help="modulate even if the loop is engaged (it closes again afterwards)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.add_argument("--sim", action="store_true",
                   help="run on the simulated stand in virtual time instead of the daemon")
    p.add_argument("--config", default=None,
                   help="with --sim: the stand's config (default: config/sim.toml)")
    p.add_argument("--settle", type=duration, default=0.0,
                   help="with --sim: idle time before the wave, e.g. 30s (default: none)")
    p.add_argument("--seed", type=int, default=None,
                   help="with --sim: disturbance and noise seed (default: [sim] seed)")
    p.add_argument("--plot", default=None, help="with --sim: time-series plot (PNG)")
    p.add_argument("--tp-peak-to-peak-m", type=float, default=None,
                   help="the torsion pendulum's step under the same wave, read off the thrust "
                   "stand [m]: gives the inverted/torsion ratio and the roll/pitch split "
                   "(with --sim it is simulated)")
    p.add_argument("--tp-com-x-m", type=float, default=1e-4,
                   help="torsion pendulum's centre-of-mass offset along x, coupling roll [m] "
                   "(default: %(default)g; measure yours with calibrate-com)")
    p.add_argument("--tp-com-y-m", type=float, default=None,
                   help="its offset along y, coupling pitch [m] (default: the model's, "
                   "0.27 mm)")
    p.add_argument("--tilt-axis-deg", type=float, default=30.0,
                   help="with --sim: the piezo tilts the platform along this angle from the "
                   "torsion pendulum's pitch axis (default: %(default)g)")
    add_socket(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.log is not None:
        return _recorded(args)
    missing = [o for o, v in (("--amplitude-v", args.amplitude_v), ("--period", args.period))
               if v is None]
    if missing:
        raise ClientError(f"{' and '.join(missing)} needed to run a wave (or give a LOG to "
                          "analyse a recorded one)")
    if args.sim:
        result = _simulated(args)
    else:
        if args.config is not None:
            raise ClientError("--config goes with --sim (the daemon uses its own config)")
        result = _on_daemon(args)
    tp_pp = result.pop("tp_simulated_peak_to_peak_m", args.tp_peak_to_peak_m)
    if tp_pp is not None:
        from leveler.procedures.tilt_modulation import torsion_split

        result["tp"] = torsion_split(result, tp_pp, _tp_params(args))
    if args.json:
        print(json.dumps(result))
    else:
        print(_report(result))
    return 0


def _tp_params(args: argparse.Namespace) -> TorsionParams:
    from leveler.sim.torsion import TorsionParams

    base = TorsionParams()
    return replace(base, com_x_m=args.tp_com_x_m,
                   com_y_m=base.com_y_m if args.tp_com_y_m is None else args.tp_com_y_m)


def _on_daemon(args: argparse.Namespace) -> dict[str, Any]:
    """Ask the daemon to run the wave, follow it on the watch stream, then measure."""
    import numpy as np

    from leveler.loop.modulation import Wave

    with Client(args.socket) as client:
        reply = client.request("modulate", amplitude_v=args.amplitude_v, period_s=args.period,
                               cycles=args.cycles, shape=args.shape, force=args.force)
    wave = Wave(**reply["wave"])
    print(f"modulating: {wave.cycles} x {wave.period_s:g} s {wave.shape}, piezo "
          f"{wave.center_v:.3f} V "
          f"+- {wave.amplitude_v:g} V; ends in {wave.end_t_s - wave.start_t_s:.0f} s "
          "(Ctrl-C leaves it running; `leveler stop` aborts it)", file=sys.stderr, flush=True)
    t, y, v = [], [], []
    with Client(args.socket) as client:
        for s in client.watch(reply["rate_hz"]):
            if s["t_s"] < wave.start_t_s:
                continue
            if s["state"] != "modulating":
                if s["t_s"] < wave.end_t_s - 1.5 / reply["rate_hz"]:
                    raise ClientError(f"the modulation ended early: the daemon is {s['state']} "
                                      "(`leveler status` says why)")
                break
            t.append(s["t_s"])
            y.append(np.nan if s["sensor_m"] is None else s["sensor_m"])
            v.append(np.nan if s["applied_v"] is None else s["applied_v"])
    from leveler.procedures.tilt_modulation import analyze

    return analyze(wave, np.array(t), np.array(y), np.array(v), reply["model"], "daemon")


def _recorded(args: argparse.Namespace) -> int:
    """Every square or triangle wave found in the log where the loop was open, measured as a
    run is."""
    from leveler.analysis.predict import load_measured
    from leveler.cli.progress import fraction, reading
    from leveler.errors import LogError
    from leveler.procedures.tilt_modulation import analyze, model_of, waves

    with reading(args.log, quiet=args.json) as b:
        meas = load_measured(args.log, args.model, fraction(b))
    usable = None if meas.engaged is None else ~meas.engaged
    found = waves(meas.t_s, meas.u_v, usable)
    if not found:
        raise LogError(f"{args.log}: no square or triangle modulation of the piezo found where "
                       "the loop was open (a sine sweep is read by `leveler calibrate-com LOG`)")
    model = model_of(meas.config.plant)
    results = []
    for wave in found:
        sel = (meas.t_s >= wave.start_t_s) & (meas.t_s < wave.end_t_s)
        r = analyze(wave, meas.t_s[sel], meas.y_m[sel], meas.u_v[sel], model,
                    f"recording {args.log}")
        if args.tp_peak_to_peak_m is not None:
            from leveler.procedures.tilt_modulation import torsion_split

            r["tp"] = torsion_split(r, args.tp_peak_to_peak_m, _tp_params(args))
        results.append(r)
    print(json.dumps({"log": args.log, "model_source": meas.model_source, "waves": results})
          if args.json else "\n\n".join(_report(r) for r in results))
    return 0


def _simulated(args: argparse.Namespace) -> dict[str, Any]:
    """The same procedure on the simulated stand in virtual time: idle for --settle, then
    the wave, with the true platform tilt (known only here) next to the reading."""

    from leveler.loop.cycle import IDLE
    from leveler.procedures.tilt_modulation import analyze, model_of, peak_to_peak
    from leveler.settings import load_config
    from leveler.sim.torsion import simulate as simulate_tp
    from leveler.virtual import VirtualStand

    cfg, _ = load_config(args.config or "config/sim.toml")
    if cfg.sensor.backend != "sim":
        raise ClientError(f"{args.config}: --sim needs the simulated backend; to modulate "
                          "hardware, run the daemon and leave out --sim")
    seed = cfg.sim.seed if args.seed is None else args.seed
    with VirtualStand(cfg, seed, start_wall_ns=0) as vs:
        vs.cycle()
        while vs.t_s < args.settle:
            vs.step()
        vs.tick()
        try:
            wave = vs.loop.modulate(vs.t_s, args.amplitude_v, args.period, args.cycles,
                                    shape=args.shape)
        except ValueError as exc:
            raise ClientError(f"modulate: {exc}") from None
        first = len(vs.recorder.t_s)
        vs.cycle()
        while vs.loop.state != IDLE:
            vs.step()
        run = vs.recorded(first)
    t, y, v = run.t_s, run.sensor_m, run.applied_v
    pz = cfg.plant.piezo
    model = model_of(cfg.plant)
    result = analyze(wave, t, y, v, model, "simulated stand")
    result["true_tilt_peak_to_peak_rad"] = peak_to_peak(wave, t, run.tilt_rad)
    # The torsion pendulum on the same platform: the piezo tilts it along an axis at
    # --tilt-axis-deg from its pitch axis, so its roll is pitch x tan(angle) of the piezo's part.
    piezo_pitch = (v - pz.ref_v) * model["tilt_rad_per_v"]
    roll = piezo_pitch * math.tan(math.radians(args.tilt_axis_deg))
    tp = _tp_params(args)
    theta = simulate_tp(tp, vs.dt_s, 0.0, run.tilt_rad, roll)
    result["tp_simulated_peak_to_peak_m"] = peak_to_peak(wave, t, theta * tp.arm_m)
    result["tilt_axis_deg_simulated"] = args.tilt_axis_deg
    if args.plot:
        _plot(args.plot, wave, t, y, v)
        result["plot"] = args.plot
    return result


def _report(r: dict[str, Any]) -> str:
    w = r["wave"]
    triangle = w["shape"] == "triangle"
    over = "cycles" if triangle else "steps"
    scatter = ("one cycle: no scatter" if r["ip_scatter_m"] is None else
               f"+- {r['ip_scatter_m'] * 1e6:.2g} um over {r['ip_steps']} {over}")
    lines = [
        f"tilt modulation on the {r['where']}: {w['cycles']} x {w['period_s']:g} s {w['shape']} "
        f"wave, piezo {w['center_v']:.3f} V +- {w['amplitude_v']:g} V ({r['samples']} samples)",
        f"inverted pendulum  {r['ip_peak_to_peak_m'] * 1e6:.4g} um peak to peak "
        f"({scatter}) for "
        f"{r['piezo_peak_to_peak_v']:.4g} V on the piezo: {r['ip_m_per_v'] * 1e6:.4g} um/V",
        f"platform tilt      {r['tilt_peak_to_peak_rad'] * 1e6:.4g} urad peak to peak through "
        f"the model's {r['model']['sensor_m_per_rad']:.4g} m/rad (amplification x arm)",
        f"piezo geometry     predicts {r['model_tilt_peak_to_peak_rad'] * 1e6:.4g} urad "
        f"(stroke / support spacing): measured / model = {r['measured_over_model']:.3f}",
    ]
    if triangle:
        lines.append(_opening(r))
    lines += [f"warning            {c}" for c in r["coherent"]]
    if "true_tilt_peak_to_peak_rad" in r:
        lines.append(f"true tilt          {r['true_tilt_peak_to_peak_rad'] * 1e6:.4g} urad peak "
                     "to peak (simulation only, out of loop)")
    if "tp" in r:
        tp = r["tp"]
        lines.append(f"torsion pendulum   {tp['peak_to_peak_m'] * 1e6:.4g} um peak to peak: "
                     f"inverted / torsion = {tp['ip_over_tp']:.3g} (paper: about 3 / 0.4 = 7.5); "
                     f"pitch alone would give {tp['pitch_only_peak_to_peak_m'] * 1e6:.4g} um "
                     f"(l_cm,y {tp['com_y_m'] * 1e3:.3g} mm)")
        if "roll_over_pitch" in tp:
            lines.append(f"roll/pitch split   roll {tp['roll_peak_to_peak_rad'] * 1e6:.4g} urad "
                         f"with the pitch: roll/pitch = {tp['roll_over_pitch']:.3g}, tilt axis "
                         f"{tp['tilt_axis_deg']:.1f} deg from pitch (l_cm,x "
                         f"{tp['com_x_m'] * 1e3:.3g} mm)"
                         + (f"; simulated {r['tilt_axis_deg_simulated']:g} deg"
                            if "tilt_axis_deg_simulated" in r else ""))
        else:
            lines.append("roll/pitch split   needs l_cm,x (--tp-com-x-m, from calibrate-com)")
    if "plot" in r:
        lines.append(f"plot               {r['plot']}")
    return "\n".join(lines)


def _opening(r: dict[str, Any]) -> str:
    """The sweeps' opening, what it is in piezo volts and as a lag, and whether it stands
    out of its scatter over the cycles."""
    size = (f"the down sweep reads {r['opening_m'] * 1e9:+.3g} nm against the up sweep at the "
            f"same voltage")
    if r["opening_sigma_m"] is None:
        size += " (one cycle: no uncertainty; run 2 or more)"
    else:
        size += f" (+- {r['opening_sigma_m'] * 1e9:.2g} nm, {r['opening_z']:+.1f} sigma)"
    what = (f": {r['opening_v'] * 1e3:+.3g} mV of piezo ({r['opening_of_swing'] * 100:+.2g} % "
            f"of the swing), or a lag of {r['opening_as_lag_s'] * 1e3:+.3g} ms")
    if r["opening_z"] is not None and abs(r["opening_z"]) < 3:
        what += "; no opening beyond its scatter"
    return f"sweep direction    {size}{what}"


def _plot(path: str, wave: Wave, t: np.ndarray, y: np.ndarray, v: np.ndarray) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5), layout="constrained")
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t - wave.start_t_s, y * 1e6, lw=0.8)
    ax1.set_ylabel("inverted pendulum reading [µm]", fontsize=9)
    ax1.set_title(f"Tilt modulation on the simulated stand: {wave.cycles} × {wave.period_s:g} s "
                  f"{wave.shape} wave, piezo {wave.center_v:g} V ± {wave.amplitude_v:g} V")
    ax2.plot(t - wave.start_t_s, v, lw=0.8, color="C1")
    ax2.set_ylabel("piezo voltage [V]", fontsize=9)
    ax2.set_xlabel("time since the wave started [s]")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
    fig.savefig(path, dpi=120)
