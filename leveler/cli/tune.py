"""`leveler tune`: live changes through the daemon, or gains suggested from the model."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from leveler.cli.common import add_socket
from leveler.cli.tune_model import retrack, running_config, suggest_boost, suggest_from_model
from leveler.daemon.client import Client, ClientError
from leveler.daemon.protocol import TUNE_INF_OK

FLAG_KEYS = {"kp": "kp_v_per_m", "ki": "ki_v_per_m_s", "kd": "kd_v_s_per_m",
             "ki2": "ki2_v_per_m_s2",
             "setpoint": "setpoint_m", "min_v": "output_min_v", "max_v": "output_max_v",
             "slew": "slew_v_per_s", "notch_hz": "notch_frequency_hz", "notch_q": "notch_q",
             "notch_depth": "notch_depth"}


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
        "`leveler diagnose` writes), answer what the model names, on top of the running "
        "controller: a mode (extra_resonance) gets a notch on the reading, with the PID's "
        "gains scaled down if its phase lag needs room, or the reason none is needed; a "
        "periodic disturbance (a fitted periodic_disturbance, else its [plant.cooler]) gets "
        "resonant terms that cancel it. Each comes with its margins over the model's "
        "tolerances and the true tilt a simulated day predicts; --apply switches it on "
        "bumplessly, --persist also writes it to the config file. A fitted temperature "
        "coupling gets the most a temperature feedforward could buy against the sensor floor "
        "(told, not applied: the daemon reads no temperature).")
    p.add_argument("--kp", type=float, help="proportional gain [V/m]")
    p.add_argument("--ki", type=float, help="integral gain [V/(m s)]")
    p.add_argument("--kd", type=float, help="derivative gain [V s/m]")
    p.add_argument("--ki2", type=float, help="double-integral gain [V/(m s^2)]: loop gain "
                   "rising as 1/f^2 below ki2 / (2 pi ki) Hz; 0: none")
    p.add_argument("--setpoint", type=float, help="setpoint of the sensor reading [m] (SI: "
                   "1e-6 is 1 um; refused beyond +-1 mm)")
    p.add_argument("--min-v", type=float, help="lower output limit [V]; a range that excludes "
                   "the present output moves the piezo into it at once, at the actuator's own "
                   "slew limit, not the controller's (--slew): limits protect the hardware, "
                   "the slew only smooths")
    p.add_argument("--max-v", type=float, help="upper output limit [V] (as --min-v)")
    p.add_argument("--slew", type=float, help="output slew limit [V/s]; inf: no limit")
    p.add_argument("--notch-hz", type=float, help="notch on the reading at this frequency "
                   "[Hz], below the loop's Nyquist frequency; 0: no notch")
    p.add_argument("--notch-q", type=float, help="the notch's Q: its width is frequency / Q")
    p.add_argument("--notch-depth", type=float, help="the notch's gain at its centre, in "
                   "[0, 1) (0: a full notch)")
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
                   help="with --suggest: a model naming a mode, a periodic disturbance or a "
                   "temperature coupling (`leveler diagnose LOG` writes LOG.fitted.toml): "
                   "suggest a notch or resonant terms against it, or tell what feedforward "
                   "could buy")
    p.add_argument("--log", default=None, metavar="LOG",
                   help="with --suggest --model: also replay this log's run with the terms "
                   "added (the replay what-if; typically the log the model was diagnosed from)")
    p.add_argument("--boost", action="store_true",
                   help="with --suggest: a double integral and the PID moved to keep the "
                   "margins, for more loop gain in 1-10 mHz, searched over the model's "
                   "tolerances (--model, else the config's plant); with its predicted tilt")
    p.add_argument("--retrack", default=None, metavar="LOG",
                   help="re-estimate the period of the running resonant terms from a recent "
                   "log's command (the loop drives the piezo against the disturbance at its "
                   "true period) and re-design them there if it drifted by more than 0.2 %%; "
                   "with --apply / --persist as for --suggest")
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
    if args.model is not None and not (args.suggest or args.retrack):
        raise ClientError("--model goes with --suggest (or --retrack)")
    if args.suggest and args.retrack:
        raise ClientError("--retrack LOG re-designs the running terms; give it without --suggest")
    if args.boost and not args.suggest:
        raise ClientError("--boost goes with --suggest")
    if args.suggest or args.retrack:
        values.update(retrack(args) if args.retrack else suggest_boost(args) if args.boost
                      else suggest_from_model(args) if args.model is not None else _suggest(args))
        if not args.apply:
            return 0
        if not values:
            print("nothing to apply")
            return 0
    if not values:
        raise ClientError("nothing to change: give --kp, --ki, --kd, --setpoint, --min-v, "
                          "--max-v, --slew or --notch-hz/-q/-depth (or --suggest)")
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


def _suggest(args: argparse.Namespace) -> dict[str, float]:
    """Print a proposal from the plant model; returns it as tune values."""
    from leveler.analysis import suggest
    from leveler.settings import load_config

    config = running_config(args)
    cfg, _ = load_config(Path(config))
    c = cfg.controller
    current = suggest.loop_margins(cfg.plant, cfg.loop.rate_hz, c.kp_v_per_m, c.ki_v_per_m_s,
                                   c.kd_v_s_per_m, c.d_filter_tau_s, c.ki2_v_per_m_s2)
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
