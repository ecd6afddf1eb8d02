"""`leveler tune`: live changes through the daemon, or gains suggested from the model."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from leveler.daemon.client import Client, ClientError
from leveler.daemon.protocol import TUNE_INF_OK

FLAG_KEYS = {"kp": "kp_v_per_m", "ki": "ki_v_per_m_s", "kd": "kd_v_s_per_m",
             "setpoint": "setpoint_m", "min_v": "output_min_v", "max_v": "output_max_v",
             "slew": "slew_v_per_s"}


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


def run_tune_command(args: argparse.Namespace) -> int:
    values = {key: _checked(flag, key, getattr(args, flag)) for flag, key in FLAG_KEYS.items()
              if getattr(args, flag) is not None}
    if args.suggest:
        values.update(_suggest(args))
        if not args.apply:
            return 0
    if not values:
        raise ClientError("nothing to change: give --kp, --ki, --kd, --setpoint, --min-v, "
                          "--max-v or --slew (or --suggest)")
    # the first gain change loads python-control into the daemon: seconds on a busy machine
    with Client(args.socket, timeout_s=60.0) as client:
        reply = client.request("tune", persist=args.persist, force=args.force, **values)
        with client.reading():
            c = reply["controller"]
            print("applied: " + ", ".join(f"{k} = {_shown(c[k])}" for k in values)
                  + ("; written to the config file" if reply["persisted"] else ""))
    return 0


def _suggest(args: argparse.Namespace) -> dict[str, float]:
    """Print a proposal from the plant model; returns it as tune values."""
    from leveler.analysis import suggest
    from leveler.settings import load_config

    config = args.config
    if config is None:
        try:
            with Client(args.socket) as client, client.reading():
                config = client.request("status")["status"]["config_path"]
        except ClientError:
            config = "config/sim.toml"
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
