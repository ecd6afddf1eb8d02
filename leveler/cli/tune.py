"""`leveler tune`: live changes through the daemon, or gains suggested from the model."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import Any

from leveler.cli.common import add_socket
from leveler.daemon.client import Client, ClientError
from leveler.daemon.protocol import TUNE_INF_OK
from leveler.loop.resonant import PeriodicTerms

FLAG_KEYS = {"kp": "kp_v_per_m", "ki": "ki_v_per_m_s", "kd": "kd_v_s_per_m",
             "setpoint": "setpoint_m", "min_v": "output_min_v", "max_v": "output_max_v",
             "slew": "slew_v_per_s"}


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "tune", help="change gains, setpoint, limits or slew live; or suggest gains",
        description="Change controller settings of the running daemon. Values are checked "
        "before they are applied; gain changes are bumpless (the piezo command does not jump). "
        "--persist also writes them into the daemon's config file (atomically, comments kept). "
        "New gains that the plant model predicts make the loop unstable (closed-loop poles) are "
        "refused unless --force. "
        "With --suggest, propose gains from the configured plant model (python-control) and "
        "print margins; --apply sends them. With --suggest --model FITTED.toml (what "
        "`leveler diagnose` writes), propose resonant terms that cancel the periodic "
        "disturbance the model names (a fitted periodic_disturbance, else its [plant.cooler]) "
        "on top of the running PID, with their margins over the model's tolerances and the "
        "true tilt a simulated day predicts; --apply switches them on bumplessly, --persist "
        "also writes them to the config file.")
    p.add_argument("--kp", type=float, help="proportional gain [V/m]")
    p.add_argument("--ki", type=float, help="integral gain [V/(m s)]")
    p.add_argument("--kd", type=float, help="derivative gain [V s/m]")
    p.add_argument("--setpoint", type=float, help="setpoint of the sensor reading [m] (SI: "
                   "1e-6 is 1 um; refused beyond +-1 mm)")
    p.add_argument("--min-v", type=float, help="lower output limit [V]; a range that excludes "
                   "the present output moves the piezo into it at once, at the actuator's own "
                   "slew limit, not the controller's (--slew): limits protect the hardware, "
                   "the slew only smooths")
    p.add_argument("--max-v", type=float, help="upper output limit [V] (as --min-v)")
    p.add_argument("--slew", type=float, help="output slew limit [V/s]; inf: no limit")
    p.add_argument("--persist", action="store_true", help="also write the values to the "
                   "daemon's config file")
    p.add_argument("--force", action="store_true", help="apply gains even if the plant model "
                   "predicts an unstable loop (refused otherwise)")
    p.add_argument("--suggest", action="store_true", help="propose gains from the plant model")
    p.add_argument("--bandwidth", type=float, default=None,
                   help="with --suggest: wanted unity-gain frequency [Hz] (default: the highest "
                   "the margins allow)")
    p.add_argument("--phase-margin", type=float, default=60.0,
                   help="with --suggest: wanted phase margin [deg] (default: 60)")
    p.add_argument("--plot", default=None, help="with --suggest: Bode/Nyquist plot (PNG)")
    p.add_argument("--config", default=None, help="with --suggest: plant model config "
                   "(default: the running daemon's, else config/sim.toml)")
    p.add_argument("--apply", action="store_true", help="with --suggest: send the proposal to "
                   "the daemon")
    p.add_argument("--model", default=None, metavar="FITTED.toml",
                   help="with --suggest: a model naming a periodic disturbance (`leveler "
                   "diagnose LOG` writes LOG.fitted.toml): suggest resonant terms against it")
    p.add_argument("--log", default=None, metavar="LOG",
                   help="with --suggest --model: also replay this log's run with the terms "
                   "added (the replay what-if; typically the log the model was diagnosed from)")
    p.add_argument("--predict-hours", type=float, default=24.0,
                   help="with --suggest --model: hours of the model simulated for the "
                   "predicted tilt (default: %(default)s; 0: none)")
    add_socket(p)
    p.set_defaults(func=run)


def _checked(flag: str, key: str, value: float) -> float | str:
    """A flag's value as the request carries it; NaN and infinity are refused here (JSON
    has neither), except an infinite slew, which means no limit and goes as "inf"."""
    if key in TUNE_INF_OK and value == math.inf:
        return "inf"
    if not math.isfinite(value):
        extra = " (inf, for no limit, is allowed)" if key in TUNE_INF_OK else ""
        raise ClientError(f"--{flag.replace('_', '-')}: {value!r} is not a finite "
                          f"number{extra}")
    return value


def _shown(value: float | None) -> str:
    return "inf" if value is None else f"{value:g}"  # JSON carries infinity as null


def run(args: argparse.Namespace) -> int:
    values = {key: _checked(flag, key, getattr(args, flag)) for flag, key in FLAG_KEYS.items()
              if getattr(args, flag) is not None}
    if args.model is not None and not args.suggest:
        raise ClientError("--model goes with --suggest")
    if args.suggest:
        values.update(_suggest_periodic(args) if args.model is not None else _suggest(args))
        if not args.apply:
            return 0
    if not values:
        raise ClientError("nothing to change: give --kp, --ki, --kd, --setpoint, --min-v, "
                          "--max-v or --slew (or --suggest)")
    with Client(args.socket) as client:
        reply = client.request("tune", persist=args.persist, force=args.force, **values)
        with client.reading():
            c = reply["controller"]
            print("applied: " + ", ".join(f"{k} = {_shown(c[k])}" for k in values
                                          if not isinstance(c[k], list))
                  + ("; resonant terms at " + str(len(c["periodic_gains_v_per_m_s"]))
                     + f" harmonics of {c['periodic_period_s']:g} s"
                     if "periodic_gains_v_per_m_s" in values else "")
                  + ("; written to the config file" if reply["persisted"] else ""))
    return 0


def _running_config(args: argparse.Namespace) -> str:
    """--config, else the running daemon's config file, else config/sim.toml."""
    if args.config is not None:
        return str(args.config)
    try:
        with Client(args.socket) as client, client.reading():
            return str(client.request("status")["status"]["config_path"])
    except ClientError:
        return "config/sim.toml"


def _suggest_periodic(args: argparse.Namespace) -> dict[str, Any]:
    """Print resonant terms against the model's periodic disturbance; returns them as tune
    values (on top of the running config's PID and at its loop rate)."""
    from leveler.analysis import periodic
    from leveler.settings import load_config

    config = _running_config(args)
    cfg, _ = load_config(Path(config))
    model, _ = load_config(Path(args.model))
    d = periodic.named_disturbance(model.plant)
    if d is None:
        raise ClientError(f"--model {args.model}: it names no periodic disturbance (no "
                          "[plant.effects.periodic_disturbance] and no [plant.cooler] with a "
                          "peak_to_peak_rad); `leveler diagnose LOG` writes one when it finds it")
    rate = cfg.loop.rate_hz
    try:
        terms = periodic.design(model.plant, rate, cfg.controller, d.period_s)
    except ValueError as exc:
        raise ClientError(f"--suggest --model: {exc}") from None
    values = {"periodic_period_s": terms.period_s,
              "periodic_gains_v_per_m_s": list(terms.gains_v_per_m_s),
              "periodic_phases_rad": list(terms.phases_rad),
              "periodic_radius": terms.radius}
    new = dataclasses.replace(cfg.controller, **{k: tuple(v) if isinstance(v, list) else v
                                                 for k, v in values.items()})
    ours = periodic.check(model.plant, rate, new)
    theirs = periodic.check(model.plant, rate, cfg.controller)
    pred = None
    if args.predict_hours > 0:
        at_rate = dataclasses.replace(model, loop=cfg.loop)
        pred = periodic.predict(at_rate, cfg.controller, new, d.period_s,
                                args.predict_hours * 3600.0)
    print(f"plant model from {args.model}; controller and loop rate from {config}")
    print(periodic.report(d, terms, cfg.controller, ours, theirs, pred))
    if args.log is not None:
        print(_replayed(args.log, args.model, terms))
    if not theirs.ok:
        print(f"note: the current loop itself misses {periodic.MIN_GAIN_MARGIN_DB:g} dB / "
              f"{periodic.MIN_PHASE_MARGIN_DEG:g} deg on this model; the terms are judged "
              "against it (check the PID with `leveler tune --suggest`)")
    why = periodic.refusal(ours, theirs)
    if why:
        raise ClientError(f"the suggested terms are refused: {why}")
    return values


def _replayed(log: str, model: str, terms: PeriodicTerms) -> str:
    """The replay what-if of `log` with the terms added to its logged controller: the
    reading at the disturbance's first lines, as logged and as predicted."""
    from leveler.analysis.diagnose import warmup_samples
    from leveler.analysis.predict import Predictor, load_measured
    from leveler.analysis.replay import what_if
    from leveler.analysis.spectral import asd_at
    from leveler.errors import LogError

    try:
        meas = load_measured(log, model=model)
    except LogError as exc:
        raise ClientError(f"--log: {exc}") from None
    if meas.controller is None:
        raise ClientError(f"--log {log}: it does not say what its controller was (not a "
                          "leveler log), so there is nothing to add the terms to")
    pred = Predictor(meas.config.plant, meas, ringing=True)
    span = slice(warmup_samples(meas, pred), len(meas.y_m))
    with_terms = dataclasses.replace(
        meas.controller, periodic_period_s=terms.period_s,
        periodic_gains_v_per_m_s=terms.gains_v_per_m_s, periodic_phases_rad=terms.phases_rad,
        periodic_radius=terms.radius)
    fs = 1.0 / meas.dt_s
    y = meas.y_m[span]
    lines = [h / terms.period_s for h in range(1, 6) if h / terms.period_s * len(y) / fs >= 20]
    if not lines:
        return f"(--log {log}: too short to resolve the disturbance's lines)"
    logged = asd_at(y, fs, lines)
    replayed = asd_at(what_if(meas, pred, with_terms)[span], fs, lines)
    out = [f"\nOn {log}'s own run (the replay what-if: its logged controller plus the terms; "
           "the reading) [nm/rtHz]:", f"{'':<34}{'suggested':<22}as logged"]
    out += [f"{'ASD at ' + f'{f * 1e3:.3g} mHz (line {j + 1})':<34}{a * 1e9:<22.3g}{b * 1e9:.3g}"
            for j, (f, a, b) in enumerate(zip(lines, replayed, logged, strict=True))]
    return "\n".join(out)


def _suggest(args: argparse.Namespace) -> dict[str, float]:
    """Print a proposal from the plant model; returns it as tune values."""
    from leveler.analysis import suggest
    from leveler.settings import load_config

    config = _running_config(args)
    cfg, _ = load_config(Path(config))
    c = cfg.controller
    current = suggest.loop_margins(cfg.plant, cfg.loop.rate_hz, c.kp_v_per_m, c.ki_v_per_m_s,
                                   c.kd_v_s_per_m, c.d_filter_tau_s)
    try:
        proposal = suggest.suggest(cfg.plant, cfg.loop.rate_hz, bandwidth_hz=args.bandwidth,
                                   phase_margin_deg=args.phase_margin)
    except ValueError as exc:
        raise ClientError(f"--suggest: {exc}") from None
    print(f"plant model from {config}")
    print(suggest.report(proposal, current))
    if args.plot:
        print(f"plot: {suggest.plot(cfg.plant, cfg.loop.rate_hz, proposal, args.plot)}")
    return {"kp_v_per_m": proposal.kp_v_per_m, "ki_v_per_m_s": proposal.ki_v_per_m_s,
            "kd_v_s_per_m": proposal.kd_v_s_per_m}
