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
        "coupling gets a temperature feedforward through its lags (on a daemon with a "
        "[thermometer]), told beside what a perfect one and one off by the model's tolerance "
        "would buy against the sensor floor, and none when the loop already holds the "
        "temperature's tilt under that floor.")
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
    p.add_argument("--ff-gain", type=float, action="append", default=None, metavar="V_PER_K",
                   help="a temperature feedforward path's gain [V/K]: the thermometer's "
                   "reading through --ff-lag (and --ff-lag2) times it is added to the command. "
                   "One --ff-gain and one --ff-lag per path, repeated for several (e.g. "
                   "--ff-gain -50 --ff-lag 1800 --ff-gain -25 --ff-lag 600); they replace the "
                   "running paths, bumplessly. Needs a daemon with a [thermometer]")
    p.add_argument("--ff-lag", type=float, action="append", default=None, metavar="S",
                   help="a feedforward path's lag [s] (0: none), one per --ff-gain")
    p.add_argument("--ff-lag2", type=float, action="append", default=None, metavar="S",
                   help="a second lag in series [s], one per --ff-gain if given at all")
    p.add_argument("--ff-off", action="store_true", help="remove the temperature "
                   "feedforward (bumplessly: what it added moves into the integral)")
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
                   "suggest a notch, resonant terms or a temperature feedforward against it")
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


def feedforward_values(args: argparse.Namespace) -> dict[str, list[float]]:
    """--ff-gain/--ff-lag/--ff-lag2 (a path each) or --ff-off as tune values ({}: none)."""
    gains, lags, lags2 = args.ff_gain or [], args.ff_lag or [], args.ff_lag2 or []
    if args.ff_off:
        if gains or lags or lags2:
            raise ClientError("--ff-off removes the feedforward: give it without --ff-gain, "
                              "--ff-lag or --ff-lag2")
        return {"feedforward_gains_v_per_k": [], "feedforward_lags_s": [],
                "feedforward_lags2_s": []}
    if not (gains or lags or lags2):
        return {}
    if len(lags) != len(gains) or (lags2 and len(lags2) != len(gains)):
        raise ClientError(f"a feedforward path is one --ff-gain with one --ff-lag (and one "
                          f"--ff-lag2, if any path has one): got {len(gains)} gain(s), "
                          f"{len(lags)} lag(s), {len(lags2)} second lag(s)")
    for flag, xs in (("--ff-gain", gains), ("--ff-lag", lags), ("--ff-lag2", lags2)):
        for x in xs:
            if not math.isfinite(x) or (flag != "--ff-gain" and x < 0):
                raise ClientError(f"{flag} {x!r}: must be a finite number"
                                  + (" >= 0 [s]" if flag != "--ff-gain" else " [V/K]"))
    return {"feedforward_gains_v_per_k": gains, "feedforward_lags_s": lags,
            "feedforward_lags2_s": lags2 or [0.0] * len(gains)}


def _shown(value: float | None) -> str:
    return "inf" if value is None else f"{value:g}"  # JSON carries infinity as null


def run(args: argparse.Namespace) -> int:
    values = {key: _checked(flag, key, getattr(args, flag)) for flag, key in FLAG_KEYS.items()
              if getattr(args, flag) is not None}
    values |= feedforward_values(args)
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
                          "--max-v, --slew, --notch-hz/-q/-depth, --ff-gain/--ff-lag or "
                          "--ff-off (or --suggest)")
    with Client(args.socket) as client:
        reply = client.request("tune", persist=args.persist, force=args.force, **values)
        with client.reading():
            c = reply["controller"]
            parts = [", ".join(f"{k} = {_shown(c[k])}" for k in values
                               if not isinstance(c[k], list))]
            if "periodic_gains_v_per_m_s" in values:
                parts.append(f"resonant terms at {len(c['periodic_gains_v_per_m_s'])} "
                             f"harmonics of {c['periodic_period_s']:g} s")
            if "feedforward_gains_v_per_k" in values:
                ff = c["feedforward_gains_v_per_k"]
                parts.append(f"temperature feedforward over {len(ff)} path(s)" if ff
                             else "temperature feedforward off")
            if reply["persisted"]:
                parts.append("written to the config file")
            print("applied: " + "; ".join(p for p in parts if p))
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
