"""`leveler calibrate-com LOG`: a pendulum's centre of mass from a recorded drive of its table."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from leveler.procedures.pendulum_fit import PendulumFit, response


def _line_row(line: Any, predicted: complex) -> dict[str, Any]:
    h = line.transfer_m_per_v
    return {"frequency_hz": line.frequency_hz, "waveform": line.waveform,
            "harmonic": line.harmonic, "start_s": line.start_s, "end_s": line.end_s,
            "command_amplitude_v": abs(line.command_v),
            "transfer_m_per_v": [h.real, h.imag],
            "transfer_sigma_m_per_v": line.transfer_sigma_m_per_v,
            "magnitude_m_per_v": abs(h), "phase_rad": math.atan2(h.imag, h.real),
            "snr": line.snr, "model_m_per_v": [predicted.real, predicted.imag],
            "pull": abs(h - predicted) / line.transfer_sigma_m_per_v}


def result(fit: PendulumFit, log: str, model_source: str) -> dict[str, Any]:
    """Everything the report prints, in SI, for --json."""
    return {
        "log": log, "model": model_source, "kind": fit.kind,
        "com_length_m": fit.com_length_m, "com_length_sigma_m": fit.com_length_sigma_m,
        "zero_frequency_hz": fit.zero_frequency_hz if fit.g_per_s2 < 0 else None,
        "zero_frequency_sigma_hz": fit.zero_frequency_sigma if fit.g_per_s2 < 0 else None,
        "natural_frequency_hz": fit.natural_frequency_hz,
        "natural_frequency_sigma_hz": fit.natural_frequency_sigma,
        "q": fit.q, "q_sigma": fit.q_sigma,
        "stiffness_nm_per_rad": fit.stiffness_nm_per_rad,
        "static_response": fit.amplification,
        "scale_m_per_v": fit.scale_m_per_v, "scale_sigma_m_per_v": fit.scale_sigma,
        "scale_stated_m_per_v": fit.scale_stated_m_per_v,
        "scale_pull": None if math.isnan(fit.scale_pull) else fit.scale_pull,
        "delay_s": fit.delay_s, "delay_sigma_s": fit.delay_sigma_s,
        "mass_kg": fit.mass_kg, "inertia_kgm2": fit.inertia_kgm2,
        "chi2": fit.chi2, "dof": fit.dof,
        "lines": [_line_row(line, p) for line, p in zip(fit.lines, fit.predicted_m_per_v,
                                                         strict=True)],
    }


def report(r: dict[str, Any]) -> str:
    """The table a physicist reads: each line's response, then the fit and the offset."""
    out = [f"centre of mass from the drive lines of {r['log']} (model: {r['model']}; "
           f"m {r['mass_kg']:g} kg, J {r['inertia_kgm2']:g} kg m^2)", "",
           f"  {'f':>9} {'wave':>9} {'drive':>8} {'|H|':>10} {'phase':>7} {'SNR':>7} "
           f"{'model |H|':>10} {'pull':>5}",
           f"  {'[mHz]':>9} {'':>9} {'[V]':>8} {'[nm/V]':>10} {'[deg]':>7} {'':>7} "
           f"{'[nm/V]':>10} {'[sd]':>5}"]
    for row in r["lines"]:
        wave = row["waveform"] + (f"/{row['harmonic']}" if row["harmonic"] > 1 else "")
        model = complex(*row["model_m_per_v"])
        out.append(f"  {row['frequency_hz'] * 1e3:9.4f} {wave:>9} "
                   f"{row['command_amplitude_v']:8.3g} {row['magnitude_m_per_v'] * 1e9:10.4g} "
                   f"{math.degrees(row['phase_rad']):7.1f} {row['snr']:7.1f} "
                   f"{abs(model) * 1e9:10.4g} {row['pull']:5.1f}")
    sign = "above" if r["kind"] == "inverted" else "below"
    out += ["",
            f"  centre of mass: L = {r['com_length_m'] * 1e6:+.4g} +- "
            f"{r['com_length_sigma_m'] * 1e6:.2g} um ({r['kind']}: "
            f"{abs(r['com_length_m']) * 1e6:.4g} um {sign} the pivot; config key "
            "[plant.pendulum] com_length_m = "
            f"{r['com_length_m']:.4g})"]
    if r["zero_frequency_hz"] is not None:
        out.append(f"  zero of the response: {r['zero_frequency_hz'] * 1e3:.4g} +- "
                   f"{r['zero_frequency_sigma_hz'] * 1e3:.2g} mHz (m g d / J)")
    out += [f"  resonance: {r['natural_frequency_hz'] * 1e3:.4g} +- "
            f"{r['natural_frequency_sigma_hz'] * 1e3:.2g} mHz, Q {r['q']:.3g} +- "
            f"{r['q_sigma']:.2g}; flexure k = {r['stiffness_nm_per_rad']:.4g} N m/rad; static "
            f"response theta/phi = {r['static_response']:+.4g}",
            f"  scale (reading per volt above the resonance): "
            f"{r['scale_m_per_v'] * 1e9:.4g} +- {r['scale_sigma_m_per_v'] * 1e9:.2g} nm/V, "
            f"stated {r['scale_stated_m_per_v'] * 1e9:.4g} nm/V"
            + (f" (pull {r['scale_pull']:+.2f} sd)" if r["scale_pull"] is not None
               else " (no tolerance stated)"),
            f"  command lag {r['delay_s']:+.3g} +- {r['delay_sigma_s']:.2g} s; chi-square "
            f"{r['chi2']:.1f} for {r['dof']} degrees of freedom"
            + (" (uncertainties scaled up by sqrt of its ratio)" if r["chi2"] > r["dof"] else "")]
    if "plot" in r:
        out.append(f"  plot: {r['plot']}")
    return "\n".join(out)


def plot(fit: PendulumFit, path: str, title: str) -> None:
    """Bode plot: measured lines with 1-sigma bars, the fitted response, the zero marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    f = np.array([line.frequency_hz for line in fit.lines])
    h = np.array([line.transfer_m_per_v for line in fit.lines])
    s = np.array([line.transfer_sigma_m_per_v for line in fit.lines])
    ff = np.geomspace(f.min() / 1.5, f.max() * 1.5, 600)
    def model_at(f_hz: np.ndarray) -> np.ndarray:
        return response(math.tau * f_hz, fit.scale_m_per_v, fit.g_per_s2,
                        math.tau * fit.natural_frequency_hz, fit.q, fit.delay_s)

    model = model_at(ff)
    # each line's phase on the model's branch (-173 deg next to a model at +180 is +187):
    # wrapped on its own it lands a full turn from a fit that goes through it
    phase_h = np.angle(model_at(f)) + np.angle(h / model_at(f))
    fig = Figure(figsize=(8, 6.5), layout="constrained")
    FigureCanvasAgg(fig)
    mag, ph = fig.subplots(2, 1, sharex=True, height_ratios=(3, 2))
    mag.errorbar(f, np.abs(h) * 1e9, yerr=s * 1e9, fmt="o", ms=4, label="drive lines (1 sd)")
    mag.loglog(ff, np.abs(model) * 1e9, label=f"fit: L = {fit.com_length_m * 1e6:+.3g} um")
    ph.errorbar(f, np.degrees(phase_h), yerr=np.degrees(s / np.abs(h)), fmt="o", ms=4)
    ph.semilogx(ff, np.degrees(np.angle(model)))
    for ax in (mag, ph):
        if fit.g_per_s2 < 0:
            ax.axvline(fit.zero_frequency_hz, color="0.3", linestyle=":", linewidth=1)
        ax.axvline(fit.natural_frequency_hz, color="0.6", linestyle="--", linewidth=1)
        ax.grid(True, which="both", alpha=0.3)
    if fit.g_per_s2 < 0:
        mag.annotate(f"zero {fit.zero_frequency_hz * 1e3:.3g} mHz", (fit.zero_frequency_hz, 1),
                     xycoords=("data", "axes fraction"), xytext=(3, -3),
                     textcoords="offset points", va="top", fontsize=8, color="0.3")
    mag.annotate(f"resonance {fit.natural_frequency_hz * 1e3:.3g} mHz",
                 (fit.natural_frequency_hz, 0), xycoords=("data", "axes fraction"),
                 xytext=(3, 3), textcoords="offset points", va="bottom", fontsize=8, color="0.3")
    mag.set_ylabel("|reading / command| [nm/V]")
    mag.legend()
    mag.set_title(title)
    ph.set_ylabel("phase [deg]")
    ph.set_xlabel("Frequency [Hz]")
    fig.savefig(Path(path), dpi=120, format="png")


def fitted_pendulum(fit: PendulumFit) -> dict[str, float]:
    """[plant.pendulum] as the fit says: L, the flexure k = J (w0^2 + g) and the damping
    that gives the fitted Q at the fitted resonance, c = J w0 / Q."""
    w0 = math.tau * fit.natural_frequency_hz
    return {"com_length_m": fit.com_length_m,
            "flexure_stiffness_nm_per_rad": fit.stiffness_nm_per_rad,
            "damping_nms_per_rad": fit.inertia_kgm2 * w0 / fit.q}


def write_model(args: argparse.Namespace, base_text: str, fit: PendulumFit) -> None:
    """The model with the fitted pendulum, for `leveler replay --model` and the daemon; the
    log and the input model are never overwritten, and the file is checked before it lands."""
    from leveler.daemon.persist import set_keys, write_atomic
    from leveler.errors import LogError
    from leveler.settings import load_config

    out = Path(args.model_out)
    if out.resolve() == Path(args.log).resolve() or (
            args.model and out.resolve() == Path(args.model).resolve()):
        raise LogError(f"{out}: refusing to overwrite the log or the input model; choose "
                       "another --model-out")
    text = set_keys(base_text, "plant.pendulum", fitted_pendulum(fit))
    text += (f"\n# [plant.pendulum] com_length_m, flexure_stiffness_nm_per_rad and "
             f"damping_nms_per_rad fitted by `leveler calibrate-com` from "
             f"{Path(args.log).name}: L = {fit.com_length_m:.4g} +- "
             f"{fit.com_length_sigma_m:.2g} m\n")
    write_atomic(out, text, load_config)


def run(args: argparse.Namespace) -> int:
    """Find the drive lines where the loop was open, fit the pendulum, print or --json."""
    from leveler.analysis.predict import load_measured
    from leveler.cli.progress import fraction, reading
    from leveler.errors import LogError
    from leveler.procedures.drive_lines import drive_spans, measure
    from leveler.procedures.pendulum_fit import fit_pendulum

    with reading(args.log, quiet=args.json) as b:
        meas = load_measured(args.log, args.model, fraction(b))
    if not meas.model_text:
        raise LogError(f"{args.log}: the log carries no config (imported?): give --model "
                       "CONFIG with the pendulum's mass and inertia, which turn its response "
                       "into a distance")
    usable = None if meas.engaged is None else ~meas.engaged
    if usable is not None and not usable.any():
        raise LogError(f"{args.log}: the loop was closed throughout; a drive line is read "
                       "where the loop was open (the command is the controller's otherwise)")
    spans = drive_spans(meas.t_s, meas.u_v, usable)
    try:
        # first with each step's start left to ring down; then with the ringing that fit
        # found fitted in every step, which uses the steps whole
        first = fit_pendulum(measure(meas.t_s, meas.u_v, meas.y_m, spans, args.settle_fraction),
                             meas.config.plant, meas.dt_s)
        ring = (first.natural_frequency_hz, first.q)
        fit = fit_pendulum(measure(meas.t_s, meas.u_v, meas.y_m, spans, 0.0, ring),
                           meas.config.plant, meas.dt_s)
    except ValueError as exc:
        where = ("" if usable is None or usable.all() else
                 f" in the {usable.sum() * meas.dt_s:.6g} s where the loop was open")
        raise LogError(f"{args.log}: {str(exc).replace(' found', ' found' + where, 1)}") from None
    out = result(fit, args.log, meas.model_source)
    if args.model_out:
        write_model(args, meas.model_text, fit)
        out["model_out"] = args.model_out
    if args.plot:
        plot(fit, args.plot, f"{Path(args.log).name}: response to the drive lines")
        out["plot"] = args.plot
    print(json.dumps(out) if args.json else report(out))
    return 0
